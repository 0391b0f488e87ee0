"""Image files read with their size checked before decoding, and written atomically.

:func:`read_image` refuses, before any pixel is decoded, a PNG or JPEG whose header announces
more than :data:`MAX_IMAGE_PIXELS` pixels (a small file can announce a 30000² image that
decodes to gigabytes), and a JPEG cut short (no end-of-image marker: OpenCV would decode the
part that is there and fill the rest). :func:`write_image` encodes in memory and writes
through :func:`~hogsa_loader.io.atomic.atomic_write`, so a failed write (a full disk) raises
an error naming the file and leaves no partial image.
"""

from __future__ import annotations

import struct
from pathlib import Path
from typing import Optional, Sequence

import cv2
import numpy as np

from hogsa_loader.errors import AssetError, PathLike
from hogsa_loader.io.atomic import atomic_write

__all__ = ["MAX_IMAGE_PIXELS", "announced_size", "decode_image", "read_image", "write_image"]

#: Largest image (width × height) read from a file: 8 times a 2800 × 2000 ARCTIC frame and
#: larger than a 40-megapixel photograph.
MAX_IMAGE_PIXELS = 48_000_000

_JPEG_SOF = {0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF}


def announced_size(data: bytes) -> Optional[tuple[int, int]]:
    """``(width, height)`` a PNG or JPEG header announces; None for other formats or a header
    that cannot be read."""
    if data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) >= 24 and data[12:16] == b"IHDR":
        return struct.unpack(">II", data[16:24])
    if data[:2] != b"\xff\xd8":
        return None
    i = 2
    while i + 9 < len(data):
        if data[i] != 0xFF:
            return None
        marker = data[i + 1]
        if marker == 0xFF:  # fill byte
            i += 1
            continue
        if marker in (0xD8, 0x01) or 0xD0 <= marker <= 0xD7:  # markers without a length
            i += 2
            continue
        (length,) = struct.unpack(">H", data[i + 2 : i + 4])
        if marker in _JPEG_SOF:
            h, w = struct.unpack(">HH", data[i + 5 : i + 9])
            return int(w), int(h)
        i += 2 + length
    return None


def read_image(path: PathLike, flags: int = cv2.IMREAD_COLOR, max_pixels: int = MAX_IMAGE_PIXELS) -> np.ndarray:
    """Decode an image file (as ``cv2.imread``: BGR for colour) after checking its header.

    Args:
        path: the file.
        flags: OpenCV read flags.
        max_pixels: the largest ``width × height`` accepted.

    Returns:
        the decoded array.

    Raises:
        AssetError: missing or unreadable, an announced size past ``max_pixels``, a JPEG
            without its end-of-image marker (truncated), or data OpenCV cannot decode.
    """
    p = Path(path)
    try:
        data = p.read_bytes()
    except OSError as exc:
        raise AssetError(p, f"cannot read the image ({exc.strerror or exc})") from None
    return decode_image(data, p, flags, max_pixels)


def decode_image(
    data: bytes, where: PathLike, flags: int = cv2.IMREAD_COLOR, max_pixels: int = MAX_IMAGE_PIXELS
) -> np.ndarray:
    """Decode the bytes of an image file (as ``cv2.imdecode``) after the checks of
    :func:`read_image`; ``where`` names the file (or archive member) in errors."""
    size = announced_size(data)
    if size is not None and size[0] * size[1] > max_pixels:
        raise AssetError(where, f"the image announces {size[0]}x{size[1]} pixels, more than {max_pixels}")
    if data[:2] == b"\xff\xd8" and b"\xff\xd9" not in data[-64:]:
        raise AssetError(where, f"truncated JPEG ({len(data)} bytes, no end-of-image marker)")
    img = cv2.imdecode(np.frombuffer(data, np.uint8), flags)
    if img is None:
        raise AssetError(where, "not an image OpenCV can decode")
    return img


def write_image(path: PathLike, image: np.ndarray, params: Sequence[int] = (), durable: bool = True) -> None:
    """Encode ``image`` (as ``cv2.imwrite``: BGR for colour) in the format of ``path``'s suffix
    and write it atomically (``durable``: fsynced, see :func:`~hogsa_loader.io.atomic.atomic_open`).

    Raises:
        OSError: the encoding or the write failed (the message names the file).
    """
    p = Path(path)
    ok, buf = cv2.imencode(p.suffix or ".png", image, list(params))
    if not ok:
        raise OSError(f"{p}: cannot encode the image as {p.suffix}")
    try:
        atomic_write(p, buf.tobytes(), durable=durable)
    except OSError as exc:
        raise OSError(exc.errno, f"{p}: cannot write the image ({exc.strerror or exc})") from None
