"""Backgrounds (COCO through pycocotools, folder, procedural) and alpha compositing."""

from __future__ import annotations

import json
import pickle
import warnings
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from conftest import _IMAGES
from conftest import write_coco as _write_coco

from hogsa_loader.compose import (
    AlphaComposite,
    CocoBackgrounds,
    FolderBackgrounds,
    Harmonize,
    ImageCache,
    ProceduralBackgrounds,
    composite,
    harmonize,
    make_backgrounds,
)
from hogsa_loader.compose import backgrounds as bg_mod
from hogsa_loader.compose import coco as coco_mod
from hogsa_loader.errors import AssetError


@pytest.fixture(scope="module")
def coco_root(tmp_path_factory) -> Path:
    return _write_coco(tmp_path_factory.mktemp("coco"))


@pytest.fixture(autouse=True)
def _cache_in_tmp(tmp_path_factory, monkeypatch):
    """The COCO selection cache goes to a temporary folder, never to ~/.cache."""
    monkeypatch.setenv("HOGSA_CACHE", str(tmp_path_factory.getbasetemp() / "hogsa_cache"))


def _gen(seed: int = 0) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


def _dominant(img: torch.Tensor) -> int:
    """Image id whose colour the (flat-coloured) crop is closest to."""
    mean = img.reshape(-1, 3).mean(0).numpy() * 255
    return min(_IMAGES, key=lambda i: np.abs(mean - np.array(_IMAGES[i][0])).sum())


# --------------------------------------------------------------------------------------


def test_coco_all_images_shapes_range_determinism(coco_root):
    src = make_backgrounds(coco_root=coco_root)
    assert isinstance(src, CocoBackgrounds) and len(src) == 5
    a = src.sample(12, 40, 56, _gen(3))
    assert a.shape == (12, 40, 56, 3) and a.dtype == torch.float32
    assert float(a.min()) >= 0.0 and float(a.max()) <= 1.0
    b = src.sample(12, 40, 56, _gen(3))
    assert torch.equal(a, b)
    # a fresh source (empty cache) gives the same images
    c = CocoBackgrounds(coco_root).sample(12, 40, 56, _gen(3))
    assert torch.equal(a, c)
    assert not torch.equal(a, src.sample(12, 40, 56, _gen(4)))
    seen = {_dominant(x) for x in src.sample(40, 16, 16, _gen(0))}
    assert seen == set(_IMAGES)


def test_coco_category_filter_and_person_exclusion(coco_root):
    src = CocoBackgrounds(coco_root, categories=["dining table"])
    assert sorted(src.image_ids) == [1, 2]
    assert {_dominant(x) for x in src.sample(20, 16, 16, _gen(1))} == {1, 2}
    src = CocoBackgrounds(coco_root, categories=["dining table", "cup"], exclude_person=True)
    assert sorted(src.image_ids) == [1, 3]
    assert {_dominant(x) for x in src.sample(20, 16, 16, _gen(1))} == {1, 3}
    src = make_backgrounds(coco_root=coco_root, exclude_person=True)
    assert sorted(src.image_ids) == [1, 3, 5]
    with pytest.raises(AssetError, match="unknown COCO categories"):
        CocoBackgrounds(coco_root, categories=["giraffe"])


def test_coco_alternative_layout_and_explicit_ann(tmp_path):
    root = _write_coco(tmp_path / "c2", layout="flat")
    src = make_backgrounds(coco_root=root)
    assert src.image_dir == root / "train2017"
    src2 = make_backgrounds(coco_ann=root / "annotations" / "instances_train2017.json", image_dir=root / "train2017")
    assert torch.equal(src.sample(3, 8, 8, _gen()), src2.sample(3, 8, 8, _gen()))


def test_coco_missing_and_malformed_files(tmp_path, coco_root):
    with pytest.raises(AssetError, match="COCO root folder is missing"):
        make_backgrounds(coco_root=tmp_path / "nope")
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(AssetError) as ei:
        make_backgrounds(coco_root=empty)
    assert "instances_train2017.json" in str(ei.value) and "missing" in str(ei.value)
    bad = tmp_path / "bad"
    (bad / "annotations").mkdir(parents=True)
    (bad / "annotations" / "instances_train2017.json").write_text("{ not json")
    with pytest.raises(AssetError, match="malformed JSON") as ei:
        make_backgrounds(coco_root=bad)
    assert ei.value.path.endswith("instances_train2017.json")
    (bad / "annotations" / "instances_train2017.json").write_text(json.dumps({"images": []}))
    with pytest.raises(AssetError, match="categories"):
        make_backgrounds(coco_root=bad)
    # annotation fine, image folder absent
    (bad / "annotations" / "instances_train2017.json").write_text(
        (coco_root / "annotations" / "instances_train2017.json").read_text()
    )
    with pytest.raises(AssetError, match="no COCO image folder"):
        make_backgrounds(coco_root=bad)
    # an unreadable image is skipped with a warning, the draw goes on
    root = _write_coco(tmp_path / "c3")
    (root / "images" / "train2017" / f"{2:012d}.jpg").write_bytes(b"not a jpeg")
    src = make_backgrounds(coco_root=root)
    with pytest.warns(RuntimeWarning, match="unreadable"):
        out = src.sample(30, 8, 8, _gen(0))
    assert out.shape == (30, 8, 8, 3)


def test_coco_without_sizes_is_deterministic_and_annotation_ids_checked(tmp_path):
    """An annotation file without image sizes: every draw decodes at full size, so the same
    generator gives the same image whatever was drawn before (the size is never learnt from
    a decode). An annotation without 'id' is refused naming the file."""
    root = tmp_path / "c"
    (root / "images" / "train2017").mkdir(parents=True)
    (root / "annotations").mkdir()
    rng = np.random.default_rng(0)
    img = cv2.GaussianBlur((rng.random((900, 1200, 3)) * 255).astype(np.uint8), (0, 0), 3)
    cv2.imwrite(str(root / "images" / "train2017" / "a.jpg"), img)
    ann = {"images": [{"id": 1, "file_name": "a.jpg"}], "categories": [{"id": 1, "name": "cup"}], "annotations": []}
    (root / "annotations" / "instances_train2017.json").write_text(json.dumps(ann))
    src = CocoBackgrounds(root, index_cache=False)
    for seed in range(6):
        first = src.sample(1, 224, 224, _gen(seed))
        assert torch.equal(first, src.sample(1, 224, 224, _gen(seed))), seed
        assert torch.equal(first, CocoBackgrounds(root, index_cache=False).sample(1, 224, 224, _gen(seed)))
    assert src.sizes == [None]
    ann["annotations"] = [{"image_id": 1, "category_id": 1, "bbox": [0, 0, 1, 1]}]
    (root / "annotations" / "instances_train2017.json").write_text(json.dumps(ann))
    with pytest.raises(AssetError, match="lacks 'id'") as ei:
        CocoBackgrounds(root, index_cache=False)
    assert ei.value.path.endswith("instances_train2017.json")
    ann["annotations"] = [{"id": [7], "image_id": 1, "category_id": 1, "bbox": [0, 0, 1, 1]}]  # passes the key checks
    (root / "annotations" / "instances_train2017.json").write_text(json.dumps(ann))
    with pytest.raises(AssetError, match="not a valid COCO instances file") as ei:  # pycocotools' own error, named
        CocoBackgrounds(root, index_cache=False)
    assert ei.value.path.endswith("instances_train2017.json")
    assert CocoBackgrounds(_write_coco(tmp_path / "c2"), categories="cup", index_cache=False).categories == ["cup"]


def test_unreadable_backgrounds_skip_to_the_next_and_never_fail_at_random(tmp_path):
    """With 1 good image among 8, every draw succeeds (the next readable image in list
    order); draws that land on good images are unchanged; only an all-bad list raises,
    naming the folder."""
    d = tmp_path / "bg"
    d.mkdir()
    cv2.imwrite(str(d / "a_good.png"), np.full((40, 50, 3), (0, 0, 200), np.uint8))
    for i in range(7):
        (d / f"b_junk{i}.jpg").write_bytes(b"not an image")
    src = FolderBackgrounds(d)
    with pytest.warns(RuntimeWarning, match="unreadable"):
        out = torch.cat([src.sample(1, 8, 8, _gen(s)) for s in range(60)])
    assert torch.allclose(out[..., 0], torch.full_like(out[..., 0], 200 / 255), atol=1 / 255)
    assert len(src._bad) == 7
    # a draw that lands on a good image is the same with or without the bad files around
    clean = tmp_path / "clean"
    clean.mkdir()
    for k in range(3):
        cv2.imwrite(str(clean / f"g{k}.png"), np.full((40, 50, 3), 60 * (k + 1), np.uint8))
    a = FolderBackgrounds(clean).sample(1, 8, 8, _gen(3))
    first = int(torch.randint(3, (1,), generator=_gen(3)).item())  # the image this draw lands on
    (clean / f"g{(first + 1) % 3}.png").write_bytes(b"broken")
    b = FolderBackgrounds(clean).sample(1, 8, 8, _gen(3))  # (no warning: the bad file is never touched)
    assert torch.equal(a, b)
    for i in range(3):
        (clean / f"g{i}.png").write_bytes(b"broken")
    with pytest.warns(RuntimeWarning), pytest.raises(AssetError, match="none of the 3 background images") as ei:
        FolderBackgrounds(clean).sample(1, 8, 8, _gen(0))
    assert ei.value.path == str(clean)


def test_folder_backgrounds(tmp_path):
    d = tmp_path / "bg"
    (d / "sub").mkdir(parents=True)
    cv2.imwrite(str(d / "a.jpg"), np.full((50, 70, 3), (0, 0, 200), np.uint8))
    cv2.imwrite(str(d / "sub" / "b.PNG"), np.full((60, 40, 3), (200, 0, 0), np.uint8))
    (d / "notes.txt").write_text("x")
    src = make_backgrounds(folder=d)
    assert isinstance(src, FolderBackgrounds) and len(src) == 2
    out = src.sample(10, 32, 24, _gen(2))
    assert out.shape == (10, 32, 24, 3)
    assert torch.equal(out, FolderBackgrounds(d).sample(10, 32, 24, _gen(2)))
    reds = (out[..., 0].mean((1, 2)) > 0.6).sum().item()
    assert 0 < reds < 10
    with pytest.raises(AssetError, match="missing"):
        FolderBackgrounds(tmp_path / "none")
    (tmp_path / "empty").mkdir()
    with pytest.raises(AssetError, match="no background images"):
        FolderBackgrounds(tmp_path / "empty")
    with pytest.raises(ValueError):
        make_backgrounds(coco_root=tmp_path, folder=d)


def test_procedural_fallback_warns_once_and_is_deterministic(monkeypatch):
    monkeypatch.setattr(bg_mod, "_FALLBACK_WARNED", False)
    with pytest.warns(UserWarning, match="procedural"):
        src = make_backgrounds()
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        make_backgrounds()
    assert isinstance(src, ProceduralBackgrounds)
    assert src.sample(2, 24, 32, _gen(5)).shape == (2, 24, 32, 3)
    small = ProceduralBackgrounds(pool_size=6, tile=64)
    a = small.sample(10, 48, 64, _gen(5))
    assert a.shape == (10, 48, 64, 3) and a.dtype == torch.float32
    assert float(a.min()) >= 0 and float(a.max()) <= 1
    # same generator -> same images, in a fresh instance and after pickling (pool rebuilt)
    assert torch.equal(a, ProceduralBackgrounds(pool_size=6, tile=64).sample(10, 48, 64, _gen(5)))
    assert torch.equal(a, pickle.loads(pickle.dumps(small)).sample(10, 48, 64, _gen(5)))
    assert not torch.equal(a, small.sample(10, 48, 64, _gen(6)))
    # varied: images differ from each other and are not all flat
    assert float(a.std(dim=(1, 2)).mean()) > 0.01
    assert float((a[1:] - a[:-1]).abs().mean()) > 0.05
    # every family renders, without a pool too
    direct = ProceduralBackgrounds(pool_size=0)
    fams = set()
    g = _gen(0)
    for _ in range(12):
        state = g.get_state()
        fams.add(int(torch.randint(5, (1,), generator=g)))
        g.set_state(state)
        img = direct.sample(1, 20, 24, g)
        assert img.shape == (1, 20, 24, 3) and bool(torch.isfinite(img).all())
    assert len(fams) >= 4


def test_image_cache_lru():
    c = ImageCache(max_bytes=300)
    for k in range(4):
        c.put(k, np.zeros(100, np.uint8))
    assert len(c) == 3 and c.get(0) is None and c.get(3) is not None
    c.get(1)
    c.put(9, np.zeros(100, np.uint8))
    assert c.get(2) is None and c.get(1) is not None and c.nbytes == 300
    c.put(10, np.zeros(1000, np.uint8))  # larger than capacity: not kept
    assert c.get(10) is None


# --------------------------------------------------------------------------------------


def test_composite_exact():
    g = _gen(0)
    B, H, W = 2, 5, 7
    colour = torch.rand(B, H, W, 3, generator=g)
    bg = torch.rand(B, H, W, 3, generator=g)
    alpha = torch.rand(B, H, W, generator=g)
    alpha[:, 0] = 1.0
    alpha[:, 1] = 0.0
    rgb = colour * alpha[..., None]  # premultiplied
    out = composite(rgb, alpha, bg)
    assert out.shape == (B, H, W, 3)
    assert torch.equal(out[:, 0], rgb[:, 0])  # alpha = 1 -> foreground exactly
    assert torch.equal(out[:, 1], bg[:, 1])  # alpha = 0 -> background exactly
    ref = colour * alpha[..., None] + (1 - alpha[..., None]) * bg
    assert torch.allclose(out, ref, atol=1e-6)
    assert torch.equal(composite(rgb, alpha[..., None], bg), out)
    mod = AlphaComposite()
    assert torch.allclose(mod(rgb, alpha, bg), out.clamp(0, 1))
    # broadcast background colour
    out2 = composite(rgb, alpha, torch.tensor([0.0, 0.5, 1.0]))
    assert torch.allclose(out2[:, 1], torch.tensor([0.0, 0.5, 1.0]).expand(B, W, 3))
    with pytest.raises(ValueError):
        composite(rgb, alpha[..., None].expand(B, H, W, 3), bg)  # wrong alpha shape


def test_harmonize_mild_and_safe():
    g = _gen(1)
    B, H, W = 3, 16, 16
    alpha = torch.zeros(B, H, W, 1)
    alpha[:, 4:12, 4:12] = 1.0
    alpha[:, 3, 4:12] = 0.5
    fg = torch.full((B, H, W, 3), 0.8) + 0.05 * torch.rand(B, H, W, 3, generator=g)
    rgb = fg * alpha
    bg = 0.2 * torch.rand(B, H, W, 3, generator=g)
    out = harmonize(rgb, alpha, bg, strength=0.3)
    assert torch.equal(out[alpha.expand_as(out) == 0], torch.zeros_like(out[alpha.expand_as(out) == 0]))
    assert bool((out <= alpha + 1e-6).all()) and bool((out >= 0).all())
    mask = alpha[..., 0] == 1
    before, after = rgb[mask].mean(), out[mask].mean()
    assert after < before  # moved towards the darker background
    assert after > 0.8 * 0.6  # but only mildly
    assert torch.equal(harmonize(rgb, alpha, bg, strength=0.0), rgb)
    assert AlphaComposite().harmonizer is None
    comp = AlphaComposite(harmonize=0.3)
    assert isinstance(comp.harmonizer, Harmonize)
    assert torch.allclose(comp(rgb, alpha, bg), composite(out, alpha, bg).clamp(0, 1))


def test_coco_selection_cache_and_pickle(coco_root, tmp_path, monkeypatch):
    cache = tmp_path / "cache"
    a = CocoBackgrounds(coco_root, categories=["cup"], index_cache=cache)
    assert len(list(cache.glob("coco_selection_*.json"))) == 1
    coco_mod._COCO_MEMO.clear()

    def boom(path):
        raise AssertionError("annotation file parsed again")

    monkeypatch.setattr(coco_mod, "_load_coco", boom)
    b = CocoBackgrounds(coco_root, categories=["cup"], index_cache=cache)  # from the disk cache
    assert b.image_ids == a.image_ids == [3] and b.sizes == a.sizes
    c = pickle.loads(pickle.dumps(a))  # what a DataLoader worker gets (empty image cache)
    assert len(c.cache) == 0
    assert torch.equal(c.sample(4, 16, 24, _gen(9)), a.sample(4, 16, 24, _gen(9)))


def test_sample_many_matches_sequential(coco_root):
    sources = [
        CocoBackgrounds(coco_root),
        ProceduralBackgrounds(pool_size=5, tile=48),
        ProceduralBackgrounds(pool_size=0),
    ]
    for src in sources:
        src.threads = 3
        n = 2 if getattr(src, "pool_size", 1) == 0 else 9
        gens = [_gen(100 + i) for i in range(n)]
        many = src.sample_many(gens, 20, 28, device="cpu")
        seq = torch.cat([src.sample(1, 20, 28, _gen(100 + i)) for i in range(n)])
        assert many.shape == (n, 20, 28, 3) and torch.equal(many, seq), type(src).__name__
