"""The ArcticNet-SF sample builder, ARCTIC augmentation and ``ArcticDataset``.

Reference: ``/work/shared/reference/arctic_format.md`` §1.3, §1.7–1.9, §3.

* unit tests of :func:`make_arctic_sample` on synthetic posed scenes built here (camera,
  hand joints, object keypoints and an image where keypoints are drawn as coloured
  Gaussian dots), checked against exact geometry;
* a hard-coded copy of the §3.4 sample table (before and after default collate);
* ``ArcticDataset`` on a miniature ARCTIC-format folder written by this file;
* end-to-end on the generated ``tiny_world`` when the world generator and the ARCTIC
  processing are available.
"""

from __future__ import annotations

import json
import math
import random
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
import torch
from torch.utils.data import DataLoader, default_collate

from hogsa_loader.assets.conventions import (
    allocentric_bbox,
    cropped_bbox,
    cropped_intrinsics,
    distort_points,
    ego_bbox,
    full_to_cropped,
    project,
    transform,
    validity_flags,
)
from hogsa_loader.errors import AssetError
from hogsa_loader.geometry.rotations import axis_angle_to_matrix, matrix_to_axis_angle
from hogsa_loader.sample.arctic_dataset import (
    SUBSAMPLE_COUNTS,
    ArcticDataset,
    parse_imgname,
    rewrite_imgname,
    subsample_imgnames,
)
from hogsa_loader.sample.augment import (
    ArcticConfig,
    AugParams,
    hmr_transform_matrix,
    patch_intrinsics,
    patch_warp_matrix,
    process_image,
    rot_aa,
    rotation_z,
    sample_aug_params,
    transform_keypoints,
    unnormalize_kp2d,
)
from hogsa_loader.sample.targets import (
    SAMPLE_META_KEYS,
    SAMPLE_TARGET_KEYS,
    HandLabels,
    ObjectLabels,
    make_arctic_sample,
    solve_rigid_rotation,
)

CFG = ArcticConfig()
MEAN = np.array(CFG.img_norm_mean)
STD = np.array(CFG.img_norm_std)

# --------------------------------------------------------------------------------------
# §3.4 table (hard-coded copy): key -> (kind, dtype, shape)
# kinds: "torch", "numpy", "float" (python float), "int" (python int), "str",
#        "np.float32" (numpy scalar)
# --------------------------------------------------------------------------------------

F32, F64, I64 = "float32", "float64", "int64"
TABLE_INPUTS = {"img": ("torch", F32, (3, 224, 224))}
TABLE_TARGETS = {
    "mano.pose.r": ("torch", F32, (48,)),
    "mano.pose.l": ("torch", F32, (48,)),
    "mano.beta.r": ("torch", F32, (10,)),
    "mano.beta.l": ("torch", F32, (10,)),
    "mano.j2d.norm.r": ("torch", F32, (21, 2)),
    "mano.j2d.norm.l": ("torch", F32, (21, 2)),
    "mano.j3d.full.r": ("torch", F32, (21, 3)),
    "mano.j3d.full.l": ("torch", F32, (21, 3)),
    "object.kp3d.full.t": ("torch", F32, (16, 3)),
    "object.kp3d.full.b": ("torch", F32, (16, 3)),
    "object.kp2d.norm.t": ("torch", F32, (16, 2)),
    "object.kp2d.norm.b": ("torch", F32, (16, 2)),
    "object.kp2d.norm": ("torch", F32, (32, 2)),
    "object.bbox3d.full.t": ("torch", F32, (8, 3)),
    "object.bbox3d.full.b": ("torch", F32, (8, 3)),
    "object.bbox2d.norm.t": ("torch", F32, (8, 2)),
    "object.bbox2d.norm.b": ("torch", F32, (8, 2)),
    "object.bbox2d.norm": ("torch", F32, (16, 2)),
    "object.radian": ("torch", F32, ()),
    "object.rot": ("torch", F32, (1, 3)),
    "is_valid": ("float", None, None),
    "left_valid": ("float", None, None),
    "right_valid": ("float", None, None),
    "joints_valid_r": ("numpy", F64, (21,)),
    "joints_valid_l": ("numpy", F64, (21,)),
}
TABLE_META = {
    "imgname": ("str", None, None),
    "query_names": ("str", None, None),
    "window_size": ("torch", I64, (1,)),
    "intrinsics": ("torch", F32, (3, 3)),
    "dist": ("torch", F32, (8,)),
    "center": ("numpy", F32, (2,)),
    "is_flipped": ("int", None, None),
    "rot_angle": ("np.float32", None, None),
    "kp3d.cano": ("torch", F32, (16, 3)),
}
#: After default collate: python float -> float64 (B,), int -> int64 (B,),
#: np.float32 -> float32 (B,), numpy arrays -> tensors of their dtype, str -> list[str].
COLLATED = {"float": (F64, ()), "int": (I64, ()), "np.float32": (F32, ())}


def _check_sample_types(sample: tuple[dict, dict, dict]) -> None:
    for d, table in zip(sample, (TABLE_INPUTS, TABLE_TARGETS, TABLE_META)):
        assert set(d) == set(table), set(d) ^ set(table)
        for key, (kind, dtype, shape) in table.items():
            v = d[key]
            if kind == "torch":
                assert isinstance(v, torch.Tensor), key
                assert str(v.dtype) == f"torch.{dtype}", (key, v.dtype)
                assert tuple(v.shape) == shape, (key, v.shape)
            elif kind == "numpy":
                assert isinstance(v, np.ndarray), key
                assert v.dtype == np.dtype(dtype) and v.shape == shape, (key, v.dtype, v.shape)
            elif kind == "float":
                assert type(v) is float, (key, type(v))
            elif kind == "int":
                assert type(v) is int, (key, type(v))
            elif kind == "str":
                assert type(v) is str, (key, type(v))
            elif kind == "np.float32":
                assert type(v) is np.float32, (key, type(v))
            else:  # pragma: no cover
                raise AssertionError(kind)


def _check_collated_types(batch: Any, B: int) -> None:
    for d, table in zip(batch, (TABLE_INPUTS, TABLE_TARGETS, TABLE_META)):
        assert set(d) == set(table)
        for key, (kind, dtype, shape) in table.items():
            v = d[key]
            if kind == "str":
                assert isinstance(v, list) and len(v) == B and all(type(s) is str for s in v), key
                continue
            assert isinstance(v, torch.Tensor), key
            if kind in COLLATED:
                dtype, shape = COLLATED[kind]
            assert str(v.dtype) == f"torch.{dtype}", (key, v.dtype)
            assert tuple(v.shape) == (B,) + shape, (key, v.shape)


# --------------------------------------------------------------------------------------
# Synthetic posed scenes
# --------------------------------------------------------------------------------------


def _rand_rot(rng: np.random.Generator, max_angle: float = math.pi) -> np.ndarray:
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    return axis * rng.uniform(0.2, max_angle)


def _aa2mat(aa: np.ndarray) -> np.ndarray:
    return axis_angle_to_matrix(torch.as_tensor(aa, dtype=torch.float64)).numpy()


@dataclass
class Scene:
    image: np.ndarray
    bbox: np.ndarray  # image pixels
    K_full: np.ndarray
    image_size: tuple[int, int]
    right: HandLabels
    left: HandLabels
    obj: ObjectLabels
    egocentric: bool
    dist: np.ndarray
    # ground truth used to build it
    local: dict[str, np.ndarray]  # hand joints in the hand frame
    trans: dict[str, np.ndarray]  # hand translation (camera frame)
    rotm: dict[str, np.ndarray]  # hand global orientation (camera frame)
    kp_cano: np.ndarray  # (32, 3) object keypoints, canonical
    R_obj: np.ndarray
    t_obj: np.ndarray
    dots: list[tuple[np.ndarray, int]]  # (image pixel, colour channel)


def _blob(img: np.ndarray, p: np.ndarray, channel: int, sigma: float = 3.0) -> None:
    """Add a Gaussian dot of colour ``channel`` centred exactly on pixel coordinate ``p``."""
    h, w = img.shape[:2]
    r = int(4 * sigma) + 1
    x0, x1 = max(int(p[0]) - r, 0), min(int(p[0]) + r + 1, w)
    y0, y1 = max(int(p[1]) - r, 0), min(int(p[1]) + r + 1, h)
    if x0 >= x1 or y0 >= y1:
        return
    xs, ys = np.meshgrid(np.arange(x0, x1), np.arange(y0, y1))
    g = np.exp(-((xs - p[0]) ** 2 + (ys - p[1]) ** 2) / (2 * sigma**2))
    img[y0:y1, x0:x1, channel] = np.maximum(img[y0:y1, x0:x1, channel], 255.0 * g)


DOT_JOINTS = (0, 4, 8, 12, 16, 20)
DOT_KP = (0, 5, 10, 16, 21, 26)


def make_scene(egocentric: bool, seed: int = 0, cropped_size: int = 1000, ego_scale: float = 0.3) -> Scene:
    """A camera, two hands (21 joints), an object (32 keypoints, 16 box corners) and an
    image in the pixels ARCTIC's cropped images use, with coloured dots on keypoints."""
    rng = np.random.default_rng(seed)
    W, H = 2800, 2000
    if egocentric:
        K = np.array([[1500.0, 0, 1400.0], [0, 1500.0, 1000.0], [0, 0, 1]])
    else:
        K = np.array([[2400.0, 0, 1420.0], [0, 2380.0, 980.0], [0, 0, 1]])
    # the ego patch shows the whole frame: bring the scene closer and spread it out
    z, g = (0.5, 2.0) if egocentric else (1.0, 1.0)
    t_obj = np.array([rng.uniform(-0.05, 0.05), rng.uniform(-0.05, 0.05), rng.uniform(z - 0.1, z + 0.1)])
    R_obj = _aa2mat(_rand_rot(rng))
    kp_cano = rng.uniform(-0.09, 0.09, (32, 3)) * g
    kp3d = kp_cano @ R_obj.T + t_obj
    bb3d = (rng.uniform(-0.1, 0.1, (16, 3)) * g) @ R_obj.T + t_obj
    local, trans, rotm, hands = {}, {}, {}, {}
    for side, dx in (("right", 0.09 * g), ("left", -0.09 * g)):
        loc = rng.normal(0, 0.035 * g, (21, 3))
        loc[0] = 0.0
        aa = _rand_rot(rng)
        Rg = _aa2mat(aa)
        t = t_obj + np.array([dx, rng.uniform(-0.04, 0.04), rng.uniform(-0.05, 0.0)])
        j3d = loc @ Rg.T + t
        local[side], trans[side], rotm[side] = loc, t, Rg
        hands[side] = (aa, j3d)
    kp2d_full = project(kp3d, K)
    if egocentric:
        bbox_full = ego_bbox((W, H))

        def to_img(p: np.ndarray) -> np.ndarray:
            return p * ego_scale

        bbox = bbox_full * ego_scale
        shape = (int(round(H * ego_scale)), int(round(W * ego_scale)), 3)
    else:
        bbox_full = allocentric_bbox(kp2d_full)

        def to_img(p: np.ndarray) -> np.ndarray:
            return full_to_cropped(p, bbox_full, cropped_size)

        bbox = cropped_bbox(bbox_full, cropped_size)
        shape = (cropped_size, cropped_size, 3)
    labels = {}
    for side, (aa, j3d) in hands.items():
        pose48 = np.concatenate([aa, rng.normal(0, 0.3, 45)]).astype(np.float32)
        labels[side] = HandLabels(
            pose48=pose48,
            betas=rng.normal(0, 1, 10).astype(np.float32),
            j3d_full=j3d,
            j2d=to_img(project(j3d, K)),
            valid=1.0,
        )
    obj = ObjectLabels(
        name="box",
        radian=0.3,
        kp3d_full=kp3d,
        bbox3d_full=bb3d,
        kp2d=to_img(kp2d_full),
        bbox2d=to_img(project(bb3d, K)),
        valid=1.0,
        kp_bottom_cano=kp_cano[16:].astype(np.float32),
    )
    img = np.zeros(shape, dtype=np.float32)
    dots = []
    for c, side in enumerate(("right", "left")):
        for j in DOT_JOINTS:
            dots.append((labels[side].j2d[j], c))
    for k in DOT_KP:
        dots.append((obj.kp2d[k], 2))
    for p, c in dots:
        _blob(img, p, c)
    return Scene(
        image=img.round().astype(np.uint8),
        bbox=bbox,
        K_full=K,
        image_size=(W, H),
        right=labels["right"],
        left=labels["left"],
        obj=obj,
        egocentric=egocentric,
        dist=rng.normal(0, 0.01, 8),
        local=local,
        trans=trans,
        rotm=rotm,
        kp_cano=kp_cano,
        R_obj=R_obj,
        t_obj=t_obj,
        dots=dots,
    )


def build(scene: Scene, aug: AugParams, cfg: ArcticConfig = CFG, **kw: Any):
    return make_arctic_sample(
        image=scene.image,
        bbox=scene.bbox,
        K_full=scene.K_full,
        image_size=scene.image_size,
        right=scene.right,
        left=scene.left,
        obj=scene.obj,
        egocentric=scene.egocentric,
        dist=scene.dist,
        aug=aug,
        imgname="./data/arctic_data/data/cropped_images/s01/box_use_01/1/00010.jpg",
        cfg=cfg,
        **kw,
    )


def _patch_rgb(img: torch.Tensor) -> np.ndarray:
    """Undo the normalisation: (224, 224, 3) in [0, 255]."""
    x = img.numpy().transpose(1, 2, 0) * STD + MEAN
    return x * 255.0


def _dot_errors(scene: Scene, aug: AugParams) -> list[float]:
    """For every well-separated dot inside the patch: |label − measured dot centre| (px)."""
    _, targets, _ = build(scene, aug)
    rgb = _patch_rgb(build(scene, aug)[0]["img"])
    sc = 1.0 if scene.egocentric else aug.sc
    T = hmr_transform_matrix(scene.bbox[:2], sc * scene.bbox[2], aug.rot, 224)
    exact = [T[:2, :2] @ p + T[:2, 2] for p, _ in scene.dots]
    labels = []
    for key in ("mano.j2d.norm.r", "mano.j2d.norm.l"):
        lab = unnormalize_kp2d(targets[key].numpy(), 224)
        labels += [lab[j] for j in DOT_JOINTS]
    lab = unnormalize_kp2d(targets["object.kp2d.norm"].numpy(), 224)
    labels += [lab[k] for k in DOT_KP]
    errors = []
    img_h, img_w = scene.image.shape[:2]
    for i, ((p, ch), q, lab) in enumerate(zip(scene.dots, exact, labels)):
        others = [np.linalg.norm(q - e) for k, e in enumerate(exact) if k != i]
        if min(others) < 12 or not (8 <= q[0] <= 215 and 8 <= q[1] <= 215):
            continue
        if not (15 <= p[0] <= img_w - 16 and 15 <= p[1] <= img_h - 16):
            continue  # drawn (partly) outside the source image
        c = np.round(q).astype(int)
        win = rgb[c[1] - 5 : c[1] + 6, c[0] - 5 : c[0] + 6]
        # the dot has the expected colour
        assert win.reshape(-1, 3).sum(0).argmax() == ch
        w = np.clip(win[..., ch], 0, None)
        ys, xs = np.mgrid[c[1] - 5 : c[1] + 6, c[0] - 5 : c[0] + 6]
        centre = np.array([(w * xs).sum(), (w * ys).sum()]) / w.sum()
        # HMR labels are trunc(exact) + 1: between 0 and 1 px right/below the dot
        d = lab - centre
        assert np.all(d > -0.35) and np.all(d < 1.35), (lab, centre, q)
        errors.append(float(np.abs(d).max()))
    return errors


# --------------------------------------------------------------------------------------
# Sample table and collate
# --------------------------------------------------------------------------------------


@pytest.mark.parametrize("ego", [False, True])
@pytest.mark.parametrize("train", [False, True])
def test_sample_keys_shapes_dtypes(ego: bool, train: bool) -> None:
    scene = make_scene(ego, seed=1)
    aug = sample_aug_params(np.random.default_rng(3), train, ego, CFG)
    sample = build(scene, aug)
    _check_sample_types(sample)
    inputs, targets, meta = sample
    assert tuple(targets) == SAMPLE_TARGET_KEYS and tuple(meta) == SAMPLE_META_KEYS
    assert meta["query_names"] == "box" and meta["is_flipped"] == 0
    assert meta["window_size"].tolist() == [11]
    assert np.allclose(meta["center"], scene.bbox[:2])
    if ego:
        assert torch.allclose(meta["dist"], torch.as_tensor(scene.dist, dtype=torch.float32))
    else:
        assert torch.isnan(meta["dist"]).all()
        assert torch.equal(meta["intrinsics"], torch.tensor([[1000.0, 0, 112], [0, 1000.0, 112], [0, 0, 1]]))
    # concatenations and splits agree
    assert torch.equal(
        targets["object.kp2d.norm"], torch.cat([targets["object.kp2d.norm.t"], targets["object.kp2d.norm.b"]])
    )
    assert torch.equal(
        targets["object.bbox2d.norm"], torch.cat([targets["object.bbox2d.norm.t"], targets["object.bbox2d.norm.b"]])
    )
    # 3D targets are the un-augmented full-image camera frame
    assert np.allclose(targets["mano.j3d.full.r"].numpy(), scene.right.j3d_full, atol=1e-6)
    assert np.allclose(targets["object.kp3d.full.t"].numpy(), scene.obj.kp3d_full[:16], atol=1e-6)
    assert np.allclose(targets["object.bbox3d.full.b"].numpy(), scene.obj.bbox3d_full[8:], atol=1e-6)
    assert math.isclose(float(targets["object.radian"]), 0.3, rel_tol=1e-6)


def test_validity_flags_combine_with_object() -> None:
    scene = make_scene(False, seed=2)
    scene.right.valid = 1.0
    scene.left.valid = 0.0
    _, t, _ = build(scene, AugParams.identity())
    assert (t["is_valid"], t["right_valid"], t["left_valid"]) == (1.0, 1.0, 0.0)
    assert np.array_equal(t["joints_valid_r"], np.ones(21))
    assert np.array_equal(t["joints_valid_l"], np.zeros(21))
    scene.obj.valid = 0.0
    _, t, _ = build(scene, AugParams.identity())
    assert (t["is_valid"], t["right_valid"], t["left_valid"]) == (0.0, 0.0, 0.0)


def test_default_collate_batch_of_four() -> None:
    rng = np.random.default_rng(0)
    samples = [build(make_scene(i % 2 == 1, seed=i), sample_aug_params(rng, True, i % 2 == 1)) for i in range(4)]
    batch = default_collate(samples)
    _check_collated_types(batch, 4)
    assert torch.isnan(batch[2]["dist"][0]).all() and not torch.isnan(batch[2]["dist"][1]).any()


# --------------------------------------------------------------------------------------
# Image and 2D labels
# --------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "ego,aug",
    [
        (False, AugParams.identity()),
        (False, AugParams(rot=27.0, sc=1.2, pn=np.array([0.7, 1.3, 1.1]))),
        (False, AugParams(rot=-48.0, sc=0.8, pn=np.array([1.2, 0.9, 0.65]))),
        (True, AugParams.identity()),
        (True, AugParams(rot=35.0, sc=1.0, pn=np.array([1.3, 0.8, 1.0]))),
    ],
)
def test_dots_land_on_labels(ego: bool, aug: AugParams) -> None:
    errors = []
    for seed in range(3):
        errors += _dot_errors(make_scene(ego, seed=10 + seed), aug)
    assert len(errors) >= 12, len(errors)
    assert max(errors) <= 1.35


def test_image_normalisation_and_colour_noise() -> None:
    img = np.full((600, 600, 3), 100, np.uint8)
    img[..., 1] = 200
    scene = make_scene(False, seed=3)
    scene.image = img
    scene.bbox = np.array([300.0, 300.0, 1.0])
    aug = AugParams(rot=0.0, sc=1.0, pn=np.array([0.5, 1.5, 1.0]))
    x = _patch_rgb(build(scene, aug)[0]["img"])
    centre = x[100:124, 100:124]
    assert np.allclose(centre[..., 0], 50.0, atol=1e-3)
    assert np.allclose(centre[..., 1], 255.0, atol=1e-3)  # 300 clipped to 255
    assert np.allclose(centre[..., 2], 100.0, atol=1e-3)
    # ImageNet normalisation is torchvision's float32 (x/255 − mean) / std, bit for bit
    raw = cv2.warpAffine(
        cv2.GaussianBlur(img.astype(np.float32), (5, 5), 8.0),
        patch_warp_matrix((300.0, 300.0), 200, 0.0, 224),
        (224, 224),
        flags=cv2.INTER_CUBIC,
    )
    raw = np.clip(raw * aug.pn.astype(np.float32), 0, 255).astype(np.float32)
    ref = torch.from_numpy(raw.transpose(2, 0, 1) / np.float32(255.0))
    ref = ref.sub(torch.tensor(CFG.img_norm_mean)[:, None, None]).div(torch.tensor(CFG.img_norm_std)[:, None, None])
    assert torch.equal(build(scene, aug)[0]["img"], ref)
    # outside the source: zero border, normalised to -mean/std
    scene.bbox = np.array([0.0, 0.0, 1.0])
    patch = build(scene, AugParams.identity())[0]["img"]
    assert torch.allclose(patch[:, 0, 0], torch.tensor(-MEAN / STD, dtype=torch.float32), atol=1e-6)


def test_blur_footprint_follows_source_scale() -> None:
    """A 3× smaller source with ``source_scale = 1/3`` gives the patch the full-size source
    gives with ARCTIC's own blur; ARCTIC's 5-px kernel on the small source blurs it more."""
    rng = np.random.default_rng(0)
    big = cv2.resize(rng.uniform(0, 255, (100, 100, 3)).astype(np.float32), (900, 900), interpolation=cv2.INTER_CUBIC)
    big = cv2.GaussianBlur(big, (0, 0), 2.0)  # texture with detail at the patch's scale
    small = cv2.resize(big, (300, 300), interpolation=cv2.INTER_AREA)
    aug = AugParams(rot=20.0, sc=1.0, pn=np.ones(3))
    ref = process_image(big, (450.0, 450.0), 600 / 200, aug, CFG)  # 600-px box -> 224
    same = process_image(small, (150.0, 150.0), 200 / 200, aug, CFG, source_scale=1 / 3)
    arctic = process_image(small, (150.0, 150.0), 200 / 200, aug, CFG)
    assert torch.equal(process_image(big, (450.0, 450.0), 3.0, aug, CFG, source_scale=1.0), ref)

    def err(x):
        return float((x - ref)[:, 20:-20, 20:-20].pow(2).mean())

    # measured: 0.045 (scaled blur), 0.166 (ARCTIC's kernel on the small source), 0.051 (no blur)
    unblurred = process_image(small, (150.0, 150.0), 1.0, aug, CFG, source_scale=1e-3)
    assert err(same) < 0.35 * err(arctic) and err(same) < err(unblurred), (err(same), err(arctic), err(unblurred))
    with pytest.raises(ValueError, match="source_scale"):
        process_image(small, (150.0, 150.0), 1.0, aug, CFG, source_scale=0.0)


def test_missing_image_is_zero_patch() -> None:
    scene = make_scene(False, seed=4)
    scene.image = None  # type: ignore[assignment]
    img = build(scene, AugParams(rot=10.0, sc=1.1, pn=np.array([1.2, 1.2, 1.2])))[0]["img"]
    expect = torch.tensor(-MEAN / STD, dtype=torch.float32)[:, None, None].expand(3, 224, 224)
    assert torch.allclose(img, expect)


def test_hmr_truncation_semantics() -> None:
    # centre (100, 100), side 200, res 200 -> patch = source exactly
    kp = np.array([[10.7, 12.0], [-0.3, -1.5], [42.0, 42.99], [0.0, 312.0], [-2.5, 0.5]])
    out = transform_keypoints(kp, (100.0, 100.0), 1.0, 0.0, 200)
    # trunc towards zero, then + 1
    assert out.tolist() == [[11.0, 13.0], [1.0, 0.0], [43.0, 43.0], [1.0, 313.0], [-1.0, 1.0]]
    # float edge cases behave like ARCTIC's float arithmetic: 224/(200·1.12) < 1
    assert transform_keypoints(np.array([[300.0, 0.0]]), (100.0, 100.0), 224 / 200, 0.0, 224)[0, 0] == 312.0
    assert np.isnan(transform_keypoints(np.array([[np.nan, 1.0]]), (0, 0), 1, 0, 224)[0, 0])


@pytest.mark.parametrize("sc", [1.0, 1.17, 0.8])
def test_identity_rotation_labels_are_patch_projection(sc: float) -> None:
    """Without rotation, labels = trunc(project(j3d, K_patch)) + 1 with the exact camera of
    the object-centred patch: K_patch = HMR crop ∘ cropped-image map ∘ K_full."""
    for seed in range(3):
        scene = make_scene(False, seed=20 + seed)
        _, t, _ = build(scene, AugParams(rot=0.0, sc=sc, pn=np.ones(3)))
        bbox_full = allocentric_bbox(project(scene.obj.kp3d_full, scene.K_full))
        Kc = cropped_intrinsics(scene.K_full, bbox_full, 1000)
        Kp = hmr_transform_matrix(scene.bbox[:2], sc * scene.bbox[2], 0.0, 224) @ Kc
        for key, pts in (
            ("mano.j2d.norm.r", scene.right.j3d_full),
            ("mano.j2d.norm.l", scene.left.j3d_full),
            ("object.kp2d.norm", scene.obj.kp3d_full),
            ("object.bbox2d.norm", scene.obj.bbox3d_full),
        ):
            u = project(pts, Kp)
            lab = unnormalize_kp2d(t[key].numpy(), 224)
            assert np.allclose(lab, np.trunc(u) + 1, atol=2e-3), key


# --------------------------------------------------------------------------------------
# Intrinsics
# --------------------------------------------------------------------------------------


def test_ego_gt_k_rule_numbers() -> None:
    K = np.array([[1500.0, 0, 1390.0], [0, 1510.0, 1005.0], [0, 0, 1]])
    Kp = patch_intrinsics(K, (2800, 2000), 1.0, True)
    assert np.allclose(Kp, [[120.0, 0, 111.2], [0, 120.8, 112.4], [0, 0, 1]])
    # d = sc·max(W, H) = 3500, k = 0.064
    Kp = patch_intrinsics(K, (2800, 2000), 1.25, True)
    assert np.allclose(Kp, [[96.0, 0, 0.064 * 1740], [0, 96.64, 0.064 * 1755], [0, 0, 1]])
    assert np.array_equal(
        patch_intrinsics(K, (2800, 2000), 1.2, False), [[1000.0, 0, 112], [0, 1000.0, 112], [0, 0, 1]]
    )
    # the builder forces sc = 1 and GT-K for egocentric samples
    scene = make_scene(True, seed=5)
    _, t, meta = build(scene, AugParams(rot=0.0, sc=1.2, pn=np.ones(3)))
    assert np.allclose(meta["intrinsics"].numpy(), patch_intrinsics(scene.K_full, (2800, 2000), 1.0, True))
    # and the GT-K patch camera is the exact camera of the ego patch
    u = project(scene.right.j3d_full, meta["intrinsics"].numpy().astype(np.float64))
    lab = unnormalize_kp2d(t["mano.j2d.norm.r"].numpy(), 224)
    assert np.all(lab - u > -0.01) and np.all(lab - u < 1.01)
    # use_gt_k for allocentric: the whole-image rule with the aug scale (ARCTIC's quirk)
    scene = make_scene(False, seed=5)
    _, _, meta = build(scene, AugParams(rot=0.0, sc=1.2, pn=np.ones(3)), cfg=ArcticConfig(use_gt_k=True))
    assert np.allclose(meta["intrinsics"].numpy(), patch_intrinsics(scene.K_full, (2800, 2000), 1.2, True), rtol=1e-6)


def test_ego_patch_k_cache_override() -> None:
    scene = make_scene(True, seed=6)
    cached = np.diag([7.0, 8.0, 1.0])
    _, _, meta = build(scene, AugParams.identity(), ego_patch_k=cached)
    assert np.array_equal(meta["intrinsics"].numpy(), cached)
    scene = make_scene(False, seed=6)
    _, _, meta = build(scene, AugParams.identity(), ego_patch_k=cached)
    assert meta["intrinsics"][0, 0] == 1000.0  # not used for allocentric samples


# --------------------------------------------------------------------------------------
# 3D rotations
# --------------------------------------------------------------------------------------


def test_rot_aa_is_left_multiplied_rz_minus_rot() -> None:
    rng = np.random.default_rng(0)
    for _ in range(20):
        aa = _rand_rot(rng, 3.0)
        rot = rng.uniform(-60, 60)
        out = rot_aa(aa, rot)
        assert np.allclose(_aa2mat(out), rotation_z(-rot) @ _aa2mat(aa), atol=1e-9)


@pytest.mark.parametrize("rot", [30.0, -55.0, 12.5])
def test_rotation_augmentation_consistent_with_2d(rot: float) -> None:
    """Egocentric patch (principal point = patch centre): re-posing the hands and object
    with the augmented global orientations and translations rotated by R_z(−rot), then
    projecting with the sample's intrinsics, lands on the augmented 2D labels."""
    scene = make_scene(True, seed=7)
    inp, t, meta = build(scene, AugParams(rot=rot, sc=1.0, pn=np.ones(3)))
    K = meta["intrinsics"].numpy().astype(np.float64)
    assert np.allclose(K[:2, 2], 112.0)
    Rz = rotation_z(-rot)
    for side, s in (("right", "r"), ("left", "l")):
        Rg = _aa2mat(t[f"mano.pose.{s}"].numpy()[:3].astype(np.float64))
        assert np.allclose(Rg, Rz @ scene.rotm[side], atol=1e-5)
        j3d = scene.local[side] @ Rg.T + Rz @ scene.trans[side]
        lab = unnormalize_kp2d(t[f"mano.j2d.norm.{s}"].numpy(), 224)
        d = lab - project(j3d, K)
        assert np.all(d > -1.05) and np.all(d < 2.05), d
        # the opposite sign convention would be far off
        wrong = scene.local[side] @ (rotation_z(rot) @ scene.rotm[side]).T + rotation_z(rot) @ scene.trans[side]
        assert np.abs(lab - project(wrong, K)).max() > 10
    # object: canonical bottom keypoints posed with object.rot
    Ro = _aa2mat(t["object.rot"].numpy()[0].astype(np.float64))
    kp = scene.kp_cano[16:] @ Ro.T + Rz @ scene.t_obj
    lab = unnormalize_kp2d(t["object.kp2d.norm.b"].numpy(), 224)
    d = lab - project(kp, K)
    assert np.all(d > -1.05) and np.all(d < 2.05)
    # finger pose untouched
    assert np.allclose(t["mano.pose.r"].numpy()[3:], scene.right.pose48[3:])
    assert meta["rot_angle"] == np.float32(rot)


def test_kabsch_object_rotation() -> None:
    rng = np.random.default_rng(8)
    for i in range(10):
        scene = make_scene(False, seed=30 + i)
        _, t, meta = build(scene, AugParams.identity())
        R = _aa2mat(t["object.rot"].numpy()[0].astype(np.float64))
        assert np.allclose(R, scene.R_obj, atol=1e-5)
    # scale invariance and proper rotations
    A = rng.normal(size=(16, 3))
    R = _aa2mat(_rand_rot(rng))
    assert np.allclose(solve_rigid_rotation(A * 1e-3, A @ R.T + 5.0), R, atol=1e-9)
    Rr = solve_rigid_rotation(A, A * np.array([1, 1, -1]))  # a reflection: best proper rotation
    assert np.isclose(np.linalg.det(Rr), 1.0)
    # near pi the axis-angle stays exact
    aa = np.array([0.0, 1.0, 0.0]) * (math.pi - 1e-4)
    back = matrix_to_axis_angle(torch.as_tensor(_aa2mat(aa))).numpy()
    assert np.allclose(_aa2mat(back), _aa2mat(aa), atol=1e-9)


def test_kp3d_cano_scale_quirk() -> None:
    scene = make_scene(False, seed=9)
    _, _, meta = build(scene, AugParams.identity())
    expect = torch.from_numpy(scene.obj.kp_bottom_cano.astype(np.float32)) / 1000
    assert torch.equal(meta["kp3d.cano"], expect)
    assert meta["kp3d.cano"].abs().max() < 1e-3  # 1e-3 of metres


# --------------------------------------------------------------------------------------
# Augmentation parameters
# --------------------------------------------------------------------------------------


def test_aug_param_distributions() -> None:
    rng = np.random.default_rng(123)
    n = 20000
    draws = [sample_aug_params(rng, True, False, CFG) for _ in range(n)]
    rot = np.array([a.rot for a in draws])
    sc = np.array([a.sc for a in draws])
    pn = np.stack([a.pn for a in draws])
    assert abs((rot == 0).mean() - 0.6) < 0.015
    assert rot.min() >= -60 and rot.max() <= 60
    nz = rot[rot != 0]
    # clipped at ±2·30: P(|N| > 2) = 0.0455
    assert abs((np.abs(nz) == 60).mean() - 0.0455) < 0.008
    assert abs(nz[np.abs(nz) < 60].std() - 30 * 0.8796) < 1.5  # std of N(0,1)·30 truncated at ±2σ
    assert sc.min() >= 0.75 and sc.max() <= 1.25
    assert abs(((sc == 0.75) | (sc == 1.25)).mean() - 0.3173) < 0.015
    assert pn.min() >= 0.6 and pn.max() <= 1.4 and abs(pn.mean() - 1.0) < 0.01
    assert all(a.flip == 0 for a in draws)
    ego = [sample_aug_params(rng, True, True, CFG) for _ in range(200)]
    assert all(a.sc == 1.0 for a in ego) and any(a.rot != 0 for a in ego)
    ident = sample_aug_params(rng, False, False, CFG)
    assert ident.rot == 0 and ident.sc == 1 and np.array_equal(ident.pn, np.ones(3))
    with pytest.raises(ValueError):
        ArcticConfig(flip_prob=0.5)


def test_aug_draw_order_and_determinism() -> None:
    a = sample_aug_params(np.random.default_rng(5), True, False, CFG)
    g = np.random.default_rng(5)
    g.uniform()
    pn = g.uniform(0.6, 1.4, 3)
    r = float(np.clip(g.standard_normal() * 30, -60, 60))
    s = float(np.clip(g.standard_normal() * 0.25 + 1, 0.75, 1.25))
    zero = g.uniform() <= 0.6
    assert np.array_equal(a.pn, pn) and a.sc == s and a.rot == (0.0 if zero else r)
    s1 = build(make_scene(False, 1), sample_aug_params(np.random.default_rng(9), True))
    s2 = build(make_scene(False, 1), sample_aug_params(np.random.default_rng(9), True))
    for d1, d2 in zip(s1, s2):
        for k in d1:
            v1, v2 = d1[k], d2[k]
            if isinstance(v1, torch.Tensor):
                assert torch.equal(torch.nan_to_num(v1), torch.nan_to_num(v2)), k
            elif isinstance(v1, np.ndarray):
                assert np.array_equal(v1, v2), k
            else:
                assert v1 == v2, k


# --------------------------------------------------------------------------------------
# ArcticDataset on a miniature ARCTIC-format folder written here
# --------------------------------------------------------------------------------------

MINI_F = 8
MINI_OFFSET = 2
MINI_VIEWS = (0, 1, 2)


def _look_at(eye: np.ndarray, target: np.ndarray) -> np.ndarray:
    z = target - eye
    z /= np.linalg.norm(z)
    x = np.cross(np.array([0.0, -1.0, 0.0]), z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z])
    M = np.eye(4)
    M[:3, :3] = R
    M[:3, 3] = -R @ eye
    return M


def _write_box_template(meta: Path, kp_bottom: np.ndarray, kp_top: np.ndarray) -> None:
    from hogsa_loader.assets.objects.template import ObjectTemplate, bbox_corners
    from hogsa_world.object_files import write_object_template

    rng = np.random.default_rng(0)
    verts = rng.uniform(-0.08, 0.08, (40, 3)).astype(np.float32)
    faces = np.array([[i, i + 1, i + 2] for i in range(0, 38)], dtype=np.int64)
    parts = (np.arange(40) >= 20).astype(np.int64)
    t = ObjectTemplate(
        name="box",
        verts=verts,
        faces=faces,
        parts=parts,
        kp_top=kp_top,
        kp_bottom=kp_bottom,
        bbox_top=bbox_corners(verts[:20]),
        bbox_bottom=bbox_corners(verts[20:]),
        mocap_top=np.zeros((0, 3)),
        mocap_bottom=np.zeros((0, 3)),
        sub_top=rng.uniform(-0.08, 0.08, (300, 3)),
        sub_bottom=rng.uniform(-0.08, 0.08, (300, 3)),
        diameter=0.25,
    )
    write_object_template(t, meta / "object_vtemplates" / "box")


@pytest.fixture(scope="module")
def mini_arctic(tmp_path_factory) -> Path:
    """One subject, one sequence (``box_grab_01``), views 0 (ego), 1, 2; F = 8 frames;
    processed split files p1_{train,val}.npy / p2_train.npy in ARCTIC's format, cropped
    images with dots at the keypoints, a 'box' template."""
    data_root = tmp_path_factory.mktemp("mini_arctic") / "data"
    root = data_root / "arctic_data" / "data"
    rng = np.random.default_rng(42)
    kp_cano = rng.uniform(-0.08, 0.08, (32, 3))
    bb_cano = rng.uniform(-0.09, 0.09, (16, 3))
    loc = {s: np.vstack([np.zeros(3), rng.normal(0, 0.035, (20, 3)) + [0, 0, 0.05]]) for s in "rl"}
    K_allo = [
        np.array([[2400.0, 0, 1400], [0, 2400, 1000], [0, 0, 1]]),
        np.array([[2300.0, 0, 1380], [0, 2310, 1010], [0, 0, 1]]),
    ]
    w2c_allo = [_look_at(np.array([0.3, -0.4, -0.9]), np.zeros(3)), _look_at(np.array([-0.5, -0.3, -0.8]), np.zeros(3))]
    K_ego = np.array([[1500.0, 0, 1400], [0, 1500, 1000], [0, 0, 1]])
    dist = np.array([-0.05, 0.01, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0])
    F, V = MINI_F, 10
    cam = {
        k: np.zeros((F, V, n, 3)) for k, n in (("joints.right", 21), ("joints.left", 21), ("kp3d", 32), ("bbox3d", 16))
    }
    d2 = {
        k: np.zeros((F, V, n, 2)) for k, n in (("joints.right", 21), ("joints.left", 21), ("kp3d", 32), ("bbox3d", 16))
    }
    for k in ("rot_r_cam", "rot_l_cam", "obj_rot_cam"):
        cam[k] = np.zeros((F, 9, 3))
    for k in ("is_valid", "right_valid", "left_valid"):
        cam[k] = np.zeros((F, 9))
    bbox = np.zeros((F, 9, 3))
    params = {
        "pose_r": rng.normal(0, 0.3, (F, 45)),
        "pose_l": rng.normal(0, 0.3, (F, 45)),
        "shape_r": np.tile(rng.normal(0, 1, 10), (F, 1)),
        "shape_l": np.tile(rng.normal(0, 1, 10), (F, 1)),
        "obj_arti": np.linspace(0, 0.5, F),
        "dist": np.tile(dist, (F, 1)),
        "K_ego": np.tile(K_ego, (F, 1, 1)),
        "world2ego": np.zeros((F, 4, 4)),
    }
    imgnames = {0: [], 1: []}
    for f in range(F):
        R_o = _aa2mat(np.array([0.1 * f, 0.3, -0.2]))
        t_o = np.array([0.01 * f, 0.0, 0.0])
        w = {"kp3d": kp_cano @ R_o.T + t_o, "bbox3d": bb_cano @ R_o.T + t_o}
        rots = {}
        for s, side, dx in (("r", "right", 0.1), ("l", "left", -0.1)):
            Rg = _aa2mat(np.array([0.2 * f, 1.0 + 0.1 * s.count("r"), 0.5]))
            rots[s] = Rg
            w[f"joints.{side}"] = loc[s] @ Rg.T + np.array([dx, 0.02 * f, -0.03])
        w2e = _look_at(np.array([0.02 * f, -0.5, -0.5]), np.zeros(3))
        params["world2ego"][f] = w2e
        cams = {0: (w2e, K_ego)}
        for v in (1, 2):
            cams[v] = (w2c_allo[v - 1], K_allo[v - 1])
        for v in range(1, 9):
            cams.setdefault(v, (w2c_allo[0], K_allo[0]))
        for v, (M, K) in cams.items():
            for key, pts in w.items():
                pc = transform(M, pts)
                cam[key][f, v] = pc
                d2[key][f, v] = project(pc, K)
            for s in "rl":
                cam[f"rot_{s}_cam"][f, v] = matrix_to_axis_angle(torch.as_tensor(M[:3, :3] @ rots[s])).numpy()
            cam["obj_rot_cam"][f, v] = matrix_to_axis_angle(torch.as_tensor(M[:3, :3] @ R_o)).numpy()
        for key, pts in w.items():  # view 9: distorted ego
            pc = distort_points(transform(w2e, pts), dist)
            cam[key][f, 9] = pc
            d2[key][f, 9] = project(pc, K_ego)
        for v in range(9):
            bbox[f, v] = ego_bbox() if v == 0 else allocentric_bbox(d2["kp3d"][f, v])
            src = 9 if v == 0 else v
            iv, rv, lv = validity_flags(
                d2["kp3d"][f, src],
                d2["joints.right"][f, src],
                d2["joints.left"][f, src],
                bbox[f, v],
                np.array([2800, 2000]),
            )
            cam["is_valid"][f, v], cam["right_valid"][f, v], cam["left_valid"][f, v] = iv, rv, lv
        for v in MINI_VIEWS:
            name = f"./data/arctic_data/data/images/s01/box_grab_01/{v}/{f + MINI_OFFSET:05d}.jpg"
            imgnames[0 if v == 0 else 1].append(name)
            if v == 0:
                img = np.zeros((600, 840, 3), np.float32)
                tf = lambda p: p * 0.3  # noqa: E731
            else:
                img = np.zeros((1000, 1000, 3), np.float32)
                tf = lambda p, b=bbox[f, v]: full_to_cropped(p, b, 1000)  # noqa: E731
            for c, key in enumerate(("joints.right", "joints.left", "kp3d")):
                for p in tf(d2[key][f, v]):
                    _blob(img, p, c)
            out = root / "cropped_images" / "s01" / "box_grab_01" / str(v) / f"{f + MINI_OFFSET:05d}.jpg"
            out.parent.mkdir(parents=True, exist_ok=True)
            cv2.imwrite(str(out), np.ascontiguousarray(img.round().astype(np.uint8)[..., ::-1]))
    seq = {"cam_coord": cam, "2d": d2, "bbox": bbox, "params": params}
    (root / "splits").mkdir(parents=True)
    for name, names in (("p1_train", imgnames[1]), ("p1_val", imgnames[1]), ("p2_train", imgnames[0])):
        np.save(
            root / "splits" / f"{name}.npy",
            {"data_dict": {"s01/box_grab_01": seq}, "imgnames": names},
            allow_pickle=True,
        )
    (root / "meta").mkdir(parents=True)
    misc = {
        "s01": {
            "world2cam": [w2c_allo[0].tolist(), w2c_allo[1].tolist()] + [w2c_allo[0].tolist()] * 6,
            "intris_mat": [K_allo[0].tolist(), K_allo[1].tolist()] + [K_allo[0].tolist()] * 6,
            "image_size": [[2800, 2000]] * 9,
            "ioi_offset": MINI_OFFSET,
            "gender": "male",
        }
    }
    (root / "meta" / "misc.json").write_text(json.dumps(misc))
    _write_box_template(root / "meta", kp_cano[16:], kp_cano[:16])
    return data_root


def _same(a: Any, b: Any) -> bool:
    if isinstance(a, dict):
        return a.keys() == b.keys() and all(_same(a[k], b[k]) for k in a)
    if isinstance(a, (list, tuple)):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b))
    if isinstance(a, torch.Tensor):
        return torch.equal(torch.nan_to_num(a), torch.nan_to_num(b))
    if isinstance(a, np.ndarray):
        return np.array_equal(np.nan_to_num(a), np.nan_to_num(b))
    return a == b


def test_dataset_arctic_sizes_refuses_other_image_sizes(mini_arctic: Path, tmp_path: Path) -> None:
    import shutil

    assert len(ArcticDataset(mini_arctic, "p1_val", arctic_sizes=True)) == MINI_F * 2  # ARCTIC's sizes
    copy = Path(shutil.copytree(mini_arctic, tmp_path / "data"))
    doc = {
        "schema_version": 1,
        "cropped_size": 256,
        "ego_image_scale": 0.1,
        "ego_image_size": [2800, 2000],
        "mask_ids": {},
    }
    meta = copy / "arctic_data" / "data" / "meta" / "hogsa_world.json"
    meta.write_text(json.dumps(doc))
    assert ArcticDataset(copy, "p1_val").cropped_size == 256  # the world's own sizes are fine by default
    with pytest.raises(AssetError, match=r"256-px allocentric crops .* hard-codes 1000-px crops") as info:
        ArcticDataset(copy, "p1_val", arctic_sizes=True)
    assert info.value.path == str(meta)


def test_dataset_basic(mini_arctic: Path) -> None:
    ds = ArcticDataset(mini_arctic, "p1_train", seed=3)
    assert ds.augment and len(ds) == 2 * MINI_F
    assert not ArcticDataset(mini_arctic, "p1_val").augment
    assert not ArcticDataset(mini_arctic, "p1_train", seq="box_grab_01").augment
    s = ds[5]
    _check_sample_types(s)
    name = ds.imgnames[5]
    assert s[2]["imgname"] == name.replace("/images/", "/cropped_images/")
    assert s[2]["query_names"] == "box"
    # targets come from the right frame/view: vidx = frame − ioi_offset
    sid, seqn, view, frame = parse_imgname(name)
    seq = ds.data["s01/box_grab_01"]
    assert np.allclose(
        s[1]["mano.j3d.full.r"].numpy(), seq["cam_coord"]["joints.right"][frame - MINI_OFFSET, view], atol=1e-6
    )
    assert s[1]["is_valid"] == float(seq["cam_coord"]["is_valid"][frame - MINI_OFFSET, view])
    assert ds.missing_images == 0


def test_dataset_labels_match_image_dots(mini_arctic: Path) -> None:
    """No augmentation: every blob drawn at a keypoint in the cropped image shows up at
    the sample's 2D label in the patch."""
    for split in ("p1_val", "p2_train"):
        ds = ArcticDataset(mini_arctic, split, augment=False)
        ego = split.startswith("p2")
        for i in range(0, len(ds), 3):
            inp, t, meta = ds[i]
            rgb = _patch_rgb(inp["img"])
            for c, key in enumerate(("mano.j2d.norm.r", "mano.j2d.norm.l", "object.kp2d.norm")):
                lab = unnormalize_kp2d(t[key].numpy(), 224)
                inside = np.all((lab > 4) & (lab < 220), axis=1)
                vals = [rgb[int(v) - 1 : int(v) + 1, int(u) - 1 : int(u) + 1, c].max() for u, v in lab[inside]]
                assert len(vals) > 0
                # the dot's colour is bright right at (or within 1 px of) the label
                assert np.mean(np.array(vals) > 40) > 0.9, (split, i, key, vals)
            if ego:
                assert np.allclose(meta["intrinsics"].numpy(), ds.ego_patch_k, atol=1e-4)


def test_dataset_collate_workers_and_determinism(mini_arctic: Path) -> None:
    ds = ArcticDataset(mini_arctic, "p1_train", seed=11)
    loader = DataLoader(ds, batch_size=4, num_workers=2, shuffle=False)
    batches = list(loader)
    assert len(batches) == len(ds) // 4
    _check_collated_types(batches[0], 4)
    # the same items in the main process, any order
    ref = default_collate([ds[i] for i in (3, 2, 1, 0)])
    got = default_collate([ds[i] for i in (0, 1, 2, 3)])
    assert _same(default_collate([ds[i] for i in range(4)]), batches[0])
    assert _same(ref[1]["mano.pose.r"].flip(0), got[1]["mano.pose.r"])
    # another dataset object with the same seed gives the same samples
    ds2 = ArcticDataset(mini_arctic, "p1_train", seed=11)
    assert _same(ds2[7], ds[7])
    # epochs and seeds change the augmentation, the un-augmented labels do not change
    rots = [float(ds[i][2]["rot_angle"]) for i in range(len(ds))]
    ds.set_epoch(1)
    rots1 = [float(ds[i][2]["rot_angle"]) for i in range(len(ds))]
    assert rots != rots1
    assert _same(ds[7][1]["mano.j3d.full.r"], ds2[7][1]["mano.j3d.full.r"])
    assert any(r != 0 for r in rots)


def test_dataset_missing_images_counted(mini_arctic: Path) -> None:
    ds = ArcticDataset(mini_arctic, "p1_val", speedup=False)  # images/ was never written
    s = ds[0]
    assert ds.missing_images == 1 and ds.missing_image_paths[0].endswith("00002.jpg")
    assert torch.allclose(s[0]["img"][:, 5, 5], torch.tensor(-MEAN / STD, dtype=torch.float32))
    assert s[2]["imgname"] == ds.imgnames[0]  # no /cropped_images/ rewrite without speed-up
    ds[1]
    assert ds.missing_images == 2


def test_dataset_index_range_and_image_size(mini_arctic: Path, tmp_path: Path) -> None:
    """Negative indices count from the end (as for a list); out of range is an IndexError;
    an image whose size is not the one its labels are in is refused, naming the file."""
    import shutil

    ds = ArcticDataset(mini_arctic, "p1_train", seed=2)
    assert _same(ds[-1], ds[len(ds) - 1])
    for bad in (len(ds), -len(ds) - 1):
        with pytest.raises(IndexError):
            ds[bad]
    root = tmp_path / "copy"
    shutil.copytree(mini_arctic, root, symlinks=True)
    ds = ArcticDataset(root, "p1_val", augment=False)
    path = ds.image_path(ds.imgnames[0])
    img = cv2.imread(str(path))
    assert img.shape[:2] == (1000, 1000) and ds.expected_image_size("s01", 1) == (1000, 1000)
    cv2.imwrite(str(path), cv2.resize(img, (500, 500)))  # e.g. a re-cropped image at another size
    with pytest.raises(AssetError, match=r"00002.jpg.*500x500 px, but its labels are in 1000x1000"):
        ds[0]
    ds[1]  # the others are fine
    ego = ArcticDataset(root, "p2_train", augment=False)
    assert ego.expected_image_size("s01", 0) == (840, 600)
    ego[0]
    path = ego.image_path(ego.imgnames[0])
    cv2.imwrite(str(path), cv2.resize(cv2.imread(str(path)), (2800, 2000)))  # the full-size ego image
    with pytest.raises(AssetError, match=r"2800x2000 px, but its labels are in 840x600"):
        ego[0]


def test_dataset_ego_cache(mini_arctic: Path) -> None:
    ds = ArcticDataset(mini_arctic, "p2_train", seed=1)
    assert ds.augment
    expect = patch_intrinsics(np.array([[1500.0, 0, 1400], [0, 1500, 1000], [0, 0, 1]]), (2800, 2000), 1.0, True)
    assert np.allclose(ds.ego_patch_k, expect)
    for i in range(len(ds)):
        assert np.allclose(ds[i][2]["intrinsics"].numpy(), expect, atol=1e-4)
    assert ArcticDataset(mini_arctic, "p2_train", cache_ego_k=False).ego_patch_k is None


def test_subsampling_matches_random_seed_1() -> None:
    names = [f"./x/images/s01/seq/1/{i:05d}.jpg" for i in range(1000)]
    random.seed(1)
    assert random.randint(0, 100) == 17
    expect = random.sample(names, 300)
    state = random.getstate()
    assert subsample_imgnames(names, "minitrain") == expect
    assert random.getstate() == state  # global state untouched
    assert subsample_imgnames(names, "train") == names
    assert len(subsample_imgnames(names, "minival")) == SUBSAMPLE_COUNTS["minival"] == 80
    assert sorted(subsample_imgnames(names[:50], "minival")) == sorted(names[:50])
    with pytest.raises(ValueError):
        subsample_imgnames(names, "hugetrain")


def test_imgname_rewrite() -> None:
    n = "./data/arctic_data/data/images/s05/box_use_01/3/00123.jpg"
    assert rewrite_imgname(n, True) == "./data/arctic_data/data/cropped_images/s05/box_use_01/3/00123.jpg"
    assert rewrite_imgname(n, False) == n
    assert parse_imgname(n) == ("s05", "box_use_01", 3, 123)


# --------------------------------------------------------------------------------------
# End-to-end on the generated tiny world (hogsa world --preset tiny)
# --------------------------------------------------------------------------------------

WORLD_SPLITS = ("p1_train", "p1_val", "p2_train", "p2_val")
HAND_IDS = {"right": 1, "left": 2}  # hogsa_world.json mask_ids
INTERIOR_JOINTS = np.arange(16)  # MANO skeleton joints; 16..20 are fingertip surface vertices


def _world_path(tiny_world: Path) -> Path:
    """The world's ``./data`` folder (the ``tiny_world`` session fixture of conftest)."""
    return Path(tiny_world)


@pytest.fixture(scope="module")
def world_sets(tiny_world) -> dict[str, ArcticDataset]:
    root = _world_path(tiny_world)
    return {sp: ArcticDataset(root, sp, augment=False, seed=0) for sp in WORLD_SPLITS}


def _frame(ds: ArcticDataset, i: int) -> tuple[int, int, Any, np.ndarray]:
    sid, seq, view, frame = parse_imgname(ds.imgnames[i])
    sd = ds.data[f"{sid}/{seq}"]
    vidx = frame - ds.root.subject_misc(sid).ioi_offset
    return view, vidx, sd, np.asarray(sd["bbox"][vidx, view], dtype=np.float64)


def test_world_every_sample_matches_table(tiny_world) -> None:
    root = _world_path(tiny_world)
    meta = ArcticDataset(root, "p2_val").root.world_meta()
    assert meta.present and meta.cropped_size != 1000 and meta.ego_image_scale != 0.3  # tiny sizes
    for sp in WORLD_SPLITS:
        ds = ArcticDataset(root, sp, seed=5)
        assert ds.augment == sp.endswith("train") and len(ds) > 0
        assert ds.cropped_size == meta.cropped_size and ds.cfg.ego_image_scale == meta.ego_image_scale
        for i in range(len(ds)):
            _check_sample_types(ds[i])
        assert ds.missing_images == 0
        batch = next(iter(DataLoader(ds, batch_size=4, shuffle=True, generator=torch.Generator().manual_seed(0))))
        _check_collated_types(batch, 4)


def test_world_projections_land_on_labels(world_sets: dict[str, ArcticDataset]) -> None:
    """No augmentation: projecting the full-image 3D targets with the patch camera gives the
    2D targets up to the HMR truncation (label − exact ∈ [0, 1] px). Allocentric: the patch
    camera is K_full composed with the cropped-image map and the HMR crop (the fixed
    f=1000 meta intrinsics are not a real camera); egocentric: the meta (GT-K) intrinsics."""
    pairs = (
        ("mano.j2d.norm.r", "mano.j3d.full.r"),
        ("mano.j2d.norm.l", "mano.j3d.full.l"),
        ("object.kp2d.norm.t", "object.kp3d.full.t"),
        ("object.kp2d.norm.b", "object.kp3d.full.b"),
        ("object.bbox2d.norm.t", "object.bbox3d.full.t"),
        ("object.bbox2d.norm.b", "object.bbox3d.full.b"),
    )
    for sp, ds in world_sets.items():
        lo, hi, n = np.inf, -np.inf, 0
        for i in range(len(ds)):
            _, t, meta = ds[i]
            view, _, sd, bbf = _frame(ds, i)
            if view == 0:
                Kp = meta["intrinsics"].numpy().astype(np.float64)
            else:
                assert np.array_equal(meta["intrinsics"].numpy(), np.array([[1000, 0, 112], [0, 1000, 112], [0, 0, 1]]))
                b = ds.image_bbox(bbf, view)
                Kc = cropped_intrinsics(
                    ds.root.subject_misc(parse_imgname(ds.imgnames[i])[0]).intris_mat[view - 1], bbf, ds.cropped_size
                )
                Kp = hmr_transform_matrix(b[:2], b[2], 0.0, 224) @ Kc
            for k2, k3 in pairs:
                u = project(t[k3].numpy().astype(np.float64), Kp)
                d = (unnormalize_kp2d(t[k2].numpy(), 224) - u)[u > 0]
                lo, hi, n = min(lo, d.min()), max(hi, d.max()), n + d.size
        assert n > 1000
        assert lo > -2e-3 and hi < 1 + 2e-3, (sp, lo, hi)


def _mask_hits(ds: ArcticDataset, distorted_ego: bool = True) -> dict[str, float]:
    """Warp each mask with the sample's own crop (its augmentation included, nearest
    neighbour) and look up the hand labels.

    A label u = trunc(exact) + 1 stands for an exact position in [u − 1, u]: the 2×2
    pixel block {u − 1, u}² is looked up. Returns the fractions of valid-hand interior
    joints (0..15) on their own hand's pixels (``own``), on any foreground (``fg``: own
    hand or an occluder in front of it, the other hand or the object), and of fingertips
    (16..20, surface vertices on the silhouette) on foreground (``tips_fg``).
    """
    own = fg = tips = n = nt = 0
    for i in range(len(ds)):
        view, vidx, sd, bbf = _frame(ds, i)
        aug = ds.aug_params(i)
        _, t, meta = ds[i]
        assert meta["rot_angle"] == np.float32(aug.rot)
        mask = cv2.imread(str(ds.mask_path(ds.imgnames[i])), cv2.IMREAD_UNCHANGED)
        assert mask is not None and mask.ndim == 2
        b = ds.image_bbox(bbf, view)
        M = patch_warp_matrix(b[:2], int(aug.sc * b[2] * 200), aug.rot, 224)
        pm = cv2.warpAffine(mask, M, (224, 224), flags=cv2.INTER_NEAREST)
        for side, s in (("right", "r"), ("left", "l")):
            if t[f"{side}_valid"] != 1.0:
                continue
            if view == 0 and distorted_ego:
                # ego images are distorted, the targets are not (spec §1.7): check the
                # distorted projections (view 9) through the very same crop
                j2 = ds.to_image_pixels(sd["2d"][f"joints.{side}"][vidx, 9], bbf, 0)
                lab = transform_keypoints(j2, b[:2], aug.sc * b[2], aug.rot, 224)
            else:
                lab = unnormalize_kp2d(t[f"mano.j2d.norm.{s}"].numpy(), 224)
            for j, (u, v) in enumerate(np.round(lab).astype(int)):
                if not (1 <= u <= 223 and 1 <= v <= 223):
                    continue
                blk = pm[v - 1 : v + 1, u - 1 : u + 1]
                if j < 16:
                    n += 1
                    own += bool((blk == HAND_IDS[side]).any())
                    fg += bool((blk > 0).any())
                else:
                    nt += 1
                    tips += bool((blk > 0).any())
    return {"n": n, "own": own / n, "fg": fg / n, "tips_fg": tips / max(nt, 1)}


def test_world_hand_labels_inside_masks(world_sets: dict[str, ArcticDataset]) -> None:
    results = {sp: _mask_hits(ds) for sp, ds in world_sets.items()}
    print("mask hits (no augmentation):", results)
    for sp, r in results.items():
        assert r["n"] > 300
        # every interior joint of a valid hand is on the hand or on something in front of it
        assert r["fg"] >= 0.99, (sp, r)
        # most of them on their own hand's pixels (the rest are occluded)
        assert r["own"] >= 0.6, (sp, r)


def test_world_augmented_labels_follow_augmented_masks(tiny_world) -> None:
    """Augmentation on: the rotated/scaled crop of the mask still has the hands under the
    (rotated/scaled) labels."""
    for sp in ("p1_train", "p2_train"):
        ds = ArcticDataset(_world_path(tiny_world), sp, seed=2)
        assert ds.augment and any(ds.aug_params(i).rot != 0 for i in range(len(ds)))
        r = _mask_hits(ds)
        print(sp, "mask hits (augmented):", r)
        assert r["fg"] >= 0.99 and r["own"] >= 0.6, (sp, r)
