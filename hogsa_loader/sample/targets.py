"""The one ArcticNet-SF sample builder.

:func:`make_arctic_sample` turns one posed frame (image, crop box, camera, two hands and
the object, all expressed in that image) into the ``(inputs, targets, meta_info)`` triple
that ARCTIC's ``ArcticDataset.getitem`` returns. The real-data ``ArcticDataset`` and the
synthetic loader both call it, so real and synthetic samples share one code path.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any, Optional, Sequence

import numpy as np
import torch

from hogsa_loader.geometry.rotations import matrix_to_axis_angle
from hogsa_loader.sample.augment import ArcticConfig, AugParams, j2d_processing, patch_intrinsics, process_image, rot_aa

__all__ = [
    "ArcticConfig",
    "HandLabels",
    "ObjectLabels",
    "SAMPLE_INPUT_KEYS",
    "SAMPLE_TARGET_KEYS",
    "SAMPLE_META_KEYS",
    "make_arctic_sample",
    "solve_rigid_rotation",
]

#: Keys of the three dicts, in ARCTIC's insertion order.
#:
#: Value types follow ARCTIC exactly, because PyTorch's default collate turns them into
#: different batch types (float → float64 tensor, ``np.float32`` → float32 tensor,
#: int → int64 tensor, str → list of str):
#:
#: * ``inputs["img"]``: torch float32 (3, 224, 224);
#: * every other array target is a torch float32 tensor, except ``joints_valid_r/l``
#:   which are numpy float64 (21,) arrays; ``is_valid``, ``left_valid``,
#:   ``right_valid`` are python floats; ``object.radian`` is a 0-dim float32 tensor;
#: * ``meta_info``: ``imgname``/``query_names`` str, ``window_size`` int64 tensor (1,),
#:   ``intrinsics`` float32 tensor (3, 3), ``dist`` float32 tensor (8,), ``center``
#:   numpy float32 (2,), ``is_flipped`` int, ``rot_angle`` ``np.float32``, ``kp3d.cano``
#:   float32 tensor (16, 3) (see ``_object_rotation``).
SAMPLE_INPUT_KEYS: tuple[str, ...] = ("img",)
SAMPLE_TARGET_KEYS: tuple[str, ...] = (
    "mano.pose.r",
    "mano.pose.l",
    "mano.beta.r",
    "mano.beta.l",
    "mano.j2d.norm.r",
    "mano.j2d.norm.l",
    "object.kp3d.full.b",
    "object.kp2d.norm.b",
    "object.kp3d.full.t",
    "object.kp2d.norm.t",
    "object.bbox3d.full.b",
    "object.bbox2d.norm.b",
    "object.bbox3d.full.t",
    "object.bbox2d.norm.t",
    "object.radian",
    "object.kp2d.norm",
    "object.bbox2d.norm",
    "object.rot",
    "mano.j3d.full.r",
    "mano.j3d.full.l",
    "is_valid",
    "left_valid",
    "right_valid",
    "joints_valid_r",
    "joints_valid_l",
)
SAMPLE_META_KEYS: tuple[str, ...] = (
    "imgname",
    "kp3d.cano",
    "query_names",
    "window_size",
    "intrinsics",
    "dist",
    "center",
    "is_flipped",
    "rot_angle",
)


@dataclass
class HandLabels:
    """One hand of a posed frame.

    Attributes:
        pose48: (48,) axis-angle: global orientation **in the camera frame of the image**
            followed by the 45 finger values relative to the MANO mean pose.
        betas: (10,) MANO shape.
        j3d_full: (21, 3) joints in the camera frame of the full image (m).
        j2d: (21, 2) joints in pixels of the image passed to the builder.
        valid: raw hand flag (0/1); the sample multiplies it by the object's ``valid``.
    """

    pose48: np.ndarray
    betas: np.ndarray
    j3d_full: np.ndarray
    j2d: np.ndarray
    valid: float


@dataclass
class ObjectLabels:
    """The object of a posed frame.

    Attributes:
        name: object name (``query_names``).
        radian: articulation angle θ (rad).
        kp3d_full: (32, 3) keypoints [top 16, bottom 16], full-image camera frame (m).
        bbox3d_full: (16, 3) box corners [top 8, bottom 8], full-image camera frame (m).
        kp2d: (32, 2) keypoints in pixels of the builder's image.
        bbox2d: (16, 2) corners in pixels of the builder's image.
        valid: ARCTIC ``is_valid`` (0/1).
        kp_bottom_cano: (16, 3) canonical bottom keypoints of the template (m).
    """

    name: str
    radian: float
    kp3d_full: np.ndarray
    bbox3d_full: np.ndarray
    kp2d: np.ndarray
    bbox2d: np.ndarray
    valid: float
    kp_bottom_cano: np.ndarray


def solve_rigid_rotation(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """Kabsch/Arun least-squares rotation taking point set ``A`` to ``B``.

    Centroids removed, ``H = Aᵀ_c B_c``, ``R = V Uᵀ`` from the SVD of H, with the last
    singular direction flipped when ``det(R) < 0`` (a proper rotation is returned).
    A uniform scale difference between A and B does not change R.

    Args:
        A, B: (N, 3) corresponding points.

    Returns:
        (3, 3) float64 rotation with ``B − b̄ ≈ R (A − ā)``.
    """
    A = np.asarray(A, dtype=np.float64)
    B = np.asarray(B, dtype=np.float64)
    if A.shape != B.shape or A.ndim != 2 or A.shape[1] != 3:
        raise ValueError(f"need two (N, 3) point sets, got {A.shape} and {B.shape}")
    Ac = A - A.mean(axis=0)
    Bc = B - B.mean(axis=0)
    H = Ac.T @ Bc
    U, _, Vt = np.linalg.svd(H)
    R = Vt.T @ U.T
    if np.linalg.det(R) < 0:
        Vt[2, :] *= -1
        R = Vt.T @ U.T
    return R


def _f32(x: Any) -> torch.Tensor:
    return torch.as_tensor(np.asarray(x, dtype=np.float32).copy())


def _check(name: str, arr: np.ndarray, shape: tuple[int, ...]) -> np.ndarray:
    arr = np.asarray(arr)
    if arr.shape != shape:
        raise ValueError(f"{name}: expected shape {shape}, got {arr.shape}")
    return arr


def _checked_points(right: HandLabels, left: HandLabels, obj: ObjectLabels) -> dict[str, np.ndarray]:
    """The 2D and 3D point labels of a frame, each checked for its shape."""
    return {
        "j2d_r": _check("right.j2d", right.j2d, (21, 2)),
        "j2d_l": _check("left.j2d", left.j2d, (21, 2)),
        "kp2d": _check("obj.kp2d", obj.kp2d, (32, 2)),
        "bb2d": _check("obj.bbox2d", obj.bbox2d, (16, 2)),
        "kp3d": _check("obj.kp3d_full", obj.kp3d_full, (32, 3)),
        "bb3d": _check("obj.bbox3d_full", obj.bbox3d_full, (16, 3)),
        "cano": _check("obj.kp_bottom_cano", obj.kp_bottom_cano, (16, 3)),
    }


def _rotated_pose(h: HandLabels, side: str, rot: float) -> torch.Tensor:
    """(48,) float32 hand pose with its global orientation turned by the in-plane ``rot`` (deg)."""
    p = np.array(_check(f"{side}.pose48", h.pose48, (48,)), dtype=np.float32)
    p[:3] = rot_aa(p[:3].astype(np.float64), rot)
    return torch.from_numpy(p.astype(np.float32))


def _hand_targets(
    right: HandLabels, left: HandLabels, j2d_r: np.ndarray, j2d_l: np.ndarray, rot: float
) -> dict[str, torch.Tensor]:
    """MANO pose (48,), shape (10,) and normalised patch joints (21, 2) of both hands."""
    return {
        "mano.pose.r": _rotated_pose(right, "right", rot),
        "mano.pose.l": _rotated_pose(left, "left", rot),
        "mano.beta.r": _f32(_check("right.betas", right.betas, (10,))),
        "mano.beta.l": _f32(_check("left.betas", left.betas, (10,))),
        "mano.j2d.norm.r": _f32(j2d_r),
        "mano.j2d.norm.l": _f32(j2d_l),
    }


def _object_targets(
    obj: ObjectLabels, pts: dict[str, np.ndarray], center: list[float], scale: float, aug: AugParams, res: int
) -> dict[str, torch.Tensor]:
    """Object keypoints and box corners split into top (first half) and bottom parts.

    3D values are float32 tensors in the full-image camera frame (m): keypoints (16, 3),
    corners (8, 3). 2D values are normalised patch coordinates: keypoints (16, 2) per
    part and (32, 2) [top, bottom] together; corners (8, 2) per part and (16, 2) together.
    """
    kp2d, bb2d, kp3d, bb3d = pts["kp2d"], pts["bb2d"], pts["kp3d"], pts["bb3d"]
    kp2d_t, kp2d_b = (
        j2d_processing(kp2d[:16], center, scale, aug, res),
        j2d_processing(kp2d[16:], center, scale, aug, res),
    )
    bbox2d_t, bbox2d_b = (
        j2d_processing(bb2d[:8], center, scale, aug, res),
        j2d_processing(bb2d[8:], center, scale, aug, res),
    )
    return {
        "object.kp3d.full.b": _f32(kp3d[16:]),
        "object.kp2d.norm.b": _f32(kp2d_b),
        "object.kp3d.full.t": _f32(kp3d[:16]),
        "object.kp2d.norm.t": _f32(kp2d_t),
        "object.bbox3d.full.b": _f32(bb3d[8:]),
        "object.bbox2d.norm.b": _f32(bbox2d_b),
        "object.bbox3d.full.t": _f32(bb3d[:8]),
        "object.bbox2d.norm.t": _f32(bbox2d_t),
        "object.radian": torch.tensor(float(obj.radian), dtype=torch.float32),
        "object.kp2d.norm": _f32(np.concatenate([kp2d_t, kp2d_b], axis=0)),
        "object.bbox2d.norm": _f32(np.concatenate([bbox2d_t, bbox2d_b], axis=0)),
    }


def _object_rotation(cano: np.ndarray, kp3d_bottom: torch.Tensor, rot: float) -> tuple[torch.Tensor, torch.Tensor]:
    """ARCTIC's ``kp3d.cano`` and ``object.rot`` of a frame.

    ``kp3d.cano`` is the (16, 3) float32 canonical bottom keypoints divided by 1000
    *again* (ARCTIC's quirk; only the rotation is ever used). ``object.rot`` (1, 3) is the
    Kabsch/Arun rotation from ``kp3d.cano`` to the camera-frame bottom keypoints
    ``kp3d_bottom`` (16, 3), turned into axis-angle with the quaternion-based
    :func:`~hogsa_loader.geometry.rotations.matrix_to_axis_angle` (ARCTIC uses ``acos``
    of the trace, which loses precision near π; the rotation is the same), then
    left-multiplied by ``R_z(−rot)``.
    """
    kp3d_cano = torch.from_numpy(np.asarray(cano, dtype=np.float32).copy()) / 1000
    R = solve_rigid_rotation(kp3d_cano.numpy(), kp3d_bottom.numpy())
    obj_rot = matrix_to_axis_angle(torch.from_numpy(R).float().view(1, 3, 3)).view(3).numpy()
    return kp3d_cano, _f32(rot_aa(obj_rot.astype(np.float64), rot)).view(1, 3)


def _camera_meta(
    K_full: np.ndarray,
    image_size: Sequence[float],
    aug: AugParams,
    egocentric: bool,
    dist: Optional[np.ndarray],
    ego_patch_k: Optional[np.ndarray],
    cfg: ArcticConfig,
) -> dict[str, torch.Tensor]:
    """Patch intrinsics (3, 3) and lens distortion (8,) (all NaN for allocentric views)."""
    use_gt_k = bool(cfg.use_gt_k or egocentric)
    K = patch_intrinsics(K_full, image_size, aug.sc, use_gt_k, cfg)
    if egocentric and ego_patch_k is not None:
        K = np.asarray(ego_patch_k, dtype=np.float64)
    if egocentric:
        d = np.zeros(8) if dist is None else np.asarray(dist, dtype=np.float64).reshape(8)
    else:
        d = np.full(8, np.nan)
    return {"intrinsics": _f32(K), "dist": _f32(d)}


def _validity_targets(right: HandLabels, left: HandLabels, obj: ObjectLabels) -> dict[str, Any]:
    """Frame and hand validity: python floats, per-joint flags as float64 (21,) arrays."""
    is_valid = float(obj.valid)
    left_valid = float(left.valid) * is_valid
    right_valid = float(right.valid) * is_valid
    return {
        "is_valid": is_valid,
        "left_valid": left_valid,
        "right_valid": right_valid,
        "joints_valid_r": np.ones(21) * right_valid,
        "joints_valid_l": np.ones(21) * left_valid,
    }


def make_arctic_sample(
    image: Optional[np.ndarray],
    bbox: Sequence[float],
    K_full: np.ndarray,
    image_size: Sequence[float],
    right: HandLabels,
    left: HandLabels,
    obj: ObjectLabels,
    egocentric: bool,
    dist: Optional[np.ndarray],
    aug: AugParams,
    imgname: str,
    query_name: Optional[str] = None,
    cfg: ArcticConfig = ArcticConfig(),
    ego_patch_k: Optional[np.ndarray] = None,
    source_scale: float = 1.0,
) -> tuple[dict[str, Any], dict[str, Any], dict[str, Any]]:
    """Build ARCTIC's ``(inputs, targets, meta_info)`` for one posed frame.

    The steps follow ARCTIC's ``getitem``: augment the patch (egocentric views keep
    ``sc = 1``), map the 2D labels into it, rotate the global orientations, solve the
    object rotation, set the patch camera and the validity flags.

    Dict keys come in ARCTIC's insertion order and values have ARCTIC's types (both listed
    with :data:`SAMPLE_TARGET_KEYS`).

    Args:
        image: (H, W, 3) RGB uint8 (or float in [0, 255]) — the image the 2D labels and
            the box refer to (for real ARCTIC data the cropped image); None = missing
            image (ARCTIC's zero stand-in).
        bbox: ``(cx, cy, scale)`` crop box in ``image`` pixels, side ``200·scale``.
        K_full: (3, 3) intrinsics of the full-resolution image (used by the GT-K rule of
            :func:`~hogsa_loader.sample.augment.patch_intrinsics`).
        image_size: (W, H) of the full-resolution image (GT-K rule).
        right, left: hand labels (2D in ``image`` pixels).
        obj: object labels.
        egocentric: egocentric view: ``sc`` forced to 1, GT-K intrinsics, ``dist`` kept.
        dist: (8,) lens distortion; None = zeros (egocentric) — for allocentric views the
            output is all NaN either way.
        aug: augmentation (see :func:`~hogsa_loader.sample.augment.sample_aug_params`).
        imgname: ``meta_info["imgname"]``.
        query_name: ``meta_info["query_names"]``; default ``obj.name``.
        cfg: settings (``img_res``, focal, normalisation, window size, ``use_gt_k``).
        ego_patch_k: (3, 3) cached egocentric patch K (ARCTIC's ``egocam_k``); used
            instead of the computed one for egocentric samples when given.
        source_scale: ``image`` pixels per pixel of ARCTIC's source for this view (1 for
            real data); scales the blur footprint (see
            :func:`~hogsa_loader.sample.augment.process_image`).

    Returns:
        ``(inputs, targets, meta_info)`` dicts with the types listed above.
    """
    if egocentric and aug.sc != 1.0:
        aug = replace(aug, sc=1.0)
    res = cfg.img_res
    center = [float(bbox[0]), float(bbox[1])]
    scale = float(bbox[2])
    pts = _checked_points(right, left, obj)
    j2d_r = j2d_processing(pts["j2d_r"], center, scale, aug, res)
    j2d_l = j2d_processing(pts["j2d_l"], center, scale, aug, res)
    inputs: dict[str, Any] = {"img": process_image(image, center, scale, aug, cfg, source_scale=source_scale)}

    targets: dict[str, Any] = _hand_targets(right, left, j2d_r, j2d_l, aug.rot)
    targets.update(_object_targets(obj, pts, center, scale, aug, res))
    kp3d_cano, targets["object.rot"] = _object_rotation(pts["cano"], targets["object.kp3d.full.b"], aug.rot)
    targets["mano.j3d.full.r"] = _f32(_check("right.j3d_full", right.j3d_full, (21, 3)))
    targets["mano.j3d.full.l"] = _f32(_check("left.j3d_full", left.j3d_full, (21, 3)))
    targets.update(_validity_targets(right, left, obj))

    meta: dict[str, Any] = {
        "imgname": imgname,
        "kp3d.cano": kp3d_cano,
        "query_names": obj.name if query_name is None else query_name,
        "window_size": torch.tensor([int(cfg.window_size)], dtype=torch.int64),
    }
    meta.update(_camera_meta(K_full, image_size, aug, egocentric, dist, ego_patch_k, cfg))
    meta["center"] = np.array(center, dtype=np.float32)
    meta["is_flipped"] = int(aug.flip)
    meta["rot_angle"] = np.float32(aug.rot)
    return inputs, targets, meta
