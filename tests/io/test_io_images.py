"""Image files: sizes checked before decoding, truncated JPEGs refused, atomic writes that name
the file when they fail; the readers that use them (ARCTIC images, shard members)."""

from __future__ import annotations

import struct
import zlib

import cv2
import numpy as np
import pytest

from hogsa_loader.errors import AssetError
from hogsa_loader.io.images import MAX_IMAGE_PIXELS, announced_size, decode_image, read_image, write_image


def _png_bomb(width: int, height: int) -> bytes:
    """A valid small PNG whose header announces ``width × height`` (one compressed row of zeros
    repeated: decoding it would allocate the whole image)."""
    raw = zlib.compress(b"\x00" * (1 + width) * 8)  # a few rows; a decoder would expect `height` of them

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)

    ihdr = struct.pack(">IIBBBBB", width, height, 8, 0, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", raw) + chunk(b"IEND", b"")


def test_announced_sizes_of_png_and_jpeg():
    img = np.zeros((37, 53, 3), np.uint8)
    for ext in (".png", ".jpg"):
        ok, buf = cv2.imencode(ext, img)
        assert ok and announced_size(buf.tobytes()) == (53, 37)
    assert announced_size(b"GIF89a....") is None
    assert announced_size(_png_bomb(30000, 30000)) == (30000, 30000)


def test_bombs_and_truncated_jpegs_are_refused_before_decoding(tmp_path):
    bomb = tmp_path / "bomb.png"
    bomb.write_bytes(_png_bomb(30000, 30000))
    assert bomb.stat().st_size < 100_000 and 30000 * 30000 > MAX_IMAGE_PIXELS
    with pytest.raises(AssetError, match=r"announces 30000x30000 pixels") as info:
        read_image(bomb)
    assert str(bomb) in str(info.value)
    ok, buf = cv2.imencode(".jpg", np.random.default_rng(0).integers(0, 255, (120, 160, 3), dtype=np.uint8))
    whole = buf.tobytes()
    cut = tmp_path / "cut.jpg"
    cut.write_bytes(whole[:2048])
    assert cv2.imread(str(cut)) is not None  # OpenCV alone decodes what is there
    with pytest.raises(AssetError, match="truncated JPEG"):
        read_image(cut)
    assert decode_image(whole, "x.jpg").shape == (120, 160, 3)
    with pytest.raises(AssetError, match="not an image"):
        decode_image(b"\x00" * 100, "junk.png")


def test_write_image_is_atomic_and_names_the_file(tmp_path):
    img = np.full((8, 8, 3), 200, np.uint8)
    out = tmp_path / "a.png"
    write_image(out, img)
    np.testing.assert_array_equal(read_image(out), img)
    assert [p.name for p in tmp_path.iterdir()] == ["a.png"]  # no temporary file left
    with pytest.raises(OSError, match=str(tmp_path / "missing" / "b.jpg")):
        write_image(tmp_path / "missing" / "b.jpg", img)


def test_arctic_dataset_counts_a_truncated_image_as_missing(tiny_world, tmp_path):
    from hogsa_loader.sample.arctic_dataset import ArcticDataset
    from hogsa_loader.sample.augment import ArcticConfig

    ds = ArcticDataset(tiny_world, split="p1_train", config=ArcticConfig(img_res=64), seed=0)
    src = next((tiny_world / "arctic_data" / "data" / "cropped_images").rglob("*.jpg"))
    cut = tmp_path / "cut.jpg"
    cut.write_bytes(src.read_bytes()[:2048])
    before = ds.missing_images
    assert ds._read_image(src) is not None and ds._read_image(cut) is None
    assert ds.missing_images == before + 1 and ds.missing_image_paths[-1] == str(cut)


def test_a_shard_member_of_another_size_is_refused():
    from conftest import make_frame

    from hogsa_loader.sample.export.codec import decode_frame, encode_frame

    members = encode_frame(make_frame(0), "k")
    files = {name.split(".", 1)[1]: data for name, data in members.items()}
    decode_frame(files, "shard/k")
    ok, big = cv2.imencode(".png", np.zeros((480, 640), np.uint8))
    with pytest.raises(ValueError, match="announces 640x480 pixels, more than 2304"):
        decode_frame({**files, "alpha.png": big.tobytes()}, "shard/k")
    with pytest.raises(AssetError, match="announces 30000x30000"):
        decode_frame({**files, "alpha.png": _png_bomb(30000, 30000)}, "shard/k")
