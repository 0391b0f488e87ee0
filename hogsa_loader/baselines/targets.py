"""Training targets of ArcticNet-SF from dataset samples (ARCTIC's pre-loss processing).

:func:`prepare_targets` is the entry point; the steps are listed there.
"""

from __future__ import annotations

import math
from typing import Any, Literal, Mapping, Optional

import numpy as np
import torch
from scipy.spatial import cKDTree
from torch import Tensor

from hogsa_loader.assets.hands.mano import MANOLayer
from hogsa_loader.assets.objects.articulated import ArticulatedObjectLayer
from hogsa_loader.baselines.arcticnet_sf import mean_focal, perspective_to_weak_perspective
from hogsa_loader.sample.augment import unnormalize_kp2d

__all__ = ["estimate_translation_k", "nearest_distances", "prepare_targets", "solve_rigid_transform"]


def solve_rigid_transform(src: Tensor, dst: Tensor) -> tuple[Tensor, Tensor]:
    """Batched least-squares rotation and translation (Arun / Kabsch), ``dst ≈ R src + t``.

    Reflections are corrected (the last singular direction is flipped when det < 0).
    Computed in float64.

    Args:
        src, dst: (B, N, 3) corresponding points.

    Returns:
        R (B, 3, 3) and t (B, 3) in ``src``'s dtype.
    """
    if src.shape != dst.shape or src.dim() != 3 or src.shape[-1] != 3:
        raise ValueError(f"need two (B, N, 3) point sets, got {tuple(src.shape)} and {tuple(dst.shape)}")
    a, b = src.double(), dst.double()
    ca, cb = a.mean(dim=1, keepdim=True), b.mean(dim=1, keepdim=True)
    H = (a - ca).transpose(1, 2) @ (b - cb)
    U, _, Vh = torch.linalg.svd(H)
    d = torch.sign(torch.linalg.det(Vh.transpose(1, 2) @ U.transpose(1, 2)))
    D = torch.diag_embed(torch.stack([torch.ones_like(d), torch.ones_like(d), d], dim=-1))
    R = Vh.transpose(1, 2) @ D @ U.transpose(1, 2)
    t = cb[:, 0] - (R @ ca[:, 0, :, None])[..., 0]
    return R.to(src.dtype), t.to(src.dtype)


def estimate_translation_k(points3d: Tensor, points2d: Tensor, K: Tensor, weights: Optional[Tensor] = None) -> Tensor:
    """Translation t with ``project(K, X + t) ≈ uv``, by weighted linear least squares.

    Each point gives two equations linear in t (from ``u = fx (X + tx)/(Z + tz) + cx``):
    ``fx tx + (cx − u) tz = (u − cx) Z − fx X`` and the same for y; they are weighted by
    ``sqrt(w)`` and solved through the normal equations (float64). The skew of K is ignored.

    Args:
        points3d: (B, N, 3) points (without translation).
        points2d: (B, N, 2) their pixels.
        K: (B, 3, 3) intrinsics.
        weights: (B, N) confidences, or None for all ones.

    Returns:
        (B, 3) translations in ``points3d``'s dtype.
    """
    X, uv, Kd = points3d.double(), points2d.double(), K.double()
    B, N = X.shape[:2]
    f = torch.stack([Kd[:, 0, 0], Kd[:, 1, 1]], dim=-1)[:, None]  # (B, 1, 2)
    c = torch.stack([Kd[:, 0, 2], Kd[:, 1, 2]], dim=-1)[:, None]
    A = X.new_zeros(B, N, 2, 3)
    A[..., 0, 0] = f[..., 0]
    A[..., 1, 1] = f[..., 1]
    A[..., 2] = c - uv
    rhs = (uv - c) * X[..., 2:3] - f * X[..., :2]  # (B, N, 2)
    if weights is not None:
        w = weights.double().clamp(min=0).sqrt()[..., None]
        A, rhs = A * w[..., None], rhs * w
    A, rhs = A.reshape(B, 2 * N, 3), rhs.reshape(B, 2 * N, 1)
    At = A.transpose(1, 2)
    return torch.linalg.solve(At @ A, At @ rhs)[..., 0].to(points3d.dtype)


def nearest_distances(
    src: Tensor, dst: Tensor, src_len: Optional[Tensor] = None, dst_len: Optional[Tensor] = None
) -> tuple[Tensor, Tensor]:
    """For every valid point of ``src``: distance to and index of its nearest valid ``dst`` point.

    On a CPU: exact nearest neighbours from a k-d tree (scipy) per frame, in float64 (a
    brute-force search costs O(N·M) per frame, more than the model's whole training step
    for a few thousand object vertices); on a GPU: brute-force distances there.

    Args:
        src: (B, N, 3); dst: (B, M, 3) points (zero-padded).
        src_len, dst_len: (B,) numbers of valid points (None = all).

    Returns:
        dist (B, N) and idx (B, N) int64 on ``src``'s device; entries of padded ``src``
        points are 0. Non-finite input gives NaN distances: a non-finite ``src`` point's,
        and on a CPU every distance of a frame whose ``dst`` has a non-finite point.
    """
    B, N = src.shape[:2]
    ns = [N] * B if src_len is None else src_len.tolist()
    ms = [dst.shape[1]] * B if dst_len is None else dst_len.tolist()
    if src.device.type != "cpu":
        dist_t = src.new_zeros(B, N)
        idx_t = torch.zeros(B, N, dtype=torch.long, device=src.device)
        for k in range(B):
            n, m = int(ns[k]), int(ms[k])
            if n and m:
                d = torch.cdist(src[k, :n], dst[k, :m], compute_mode="donot_use_mm_for_euclid_dist")
                dist_t[k, :n], idx_t[k, :n] = d.min(dim=1)
        return dist_t, idx_t
    dist = np.zeros((B, N), dtype=np.float64)
    idx = np.zeros((B, N), dtype=np.int64)
    a = src.detach().to(torch.float64).numpy()
    b = dst.detach().to(torch.float64).numpy()
    for k in range(B):
        n, m = int(ns[k]), int(ms[k])
        if n == 0 or m == 0:
            continue
        ok = np.isfinite(a[k, :n]).all(axis=1)
        if not (ok.all() and np.isfinite(b[k, :m]).all()):  # non-finite in, NaN out
            dist[k, :n] = np.nan
            if not np.isfinite(b[k, :m]).all():
                continue
        dist[k, :n][ok], idx[k, :n][ok] = cKDTree(b[k, :m]).query(a[k, :n][ok], k=1)
    return torch.from_numpy(dist).to(src.dtype), torch.from_numpy(idx)


def _interfield(t: dict[str, Tensor], max_dist: float, both: bool = True) -> None:
    """Add ``dist.{ro,lo}`` (with ``both`` also ``dist.{or,ol}``) and ``idx.*`` to ``t`` (clamped to [0, max_dist])."""
    v_o, v_len = t["object.v.cam"], t["object.v_len"]
    for s in ("r", "l"):
        v_h = t[f"mano.v3d.cam.{s}"]
        d, i = nearest_distances(v_h, v_o, None, v_len)
        t[f"dist.{s}o"], t[f"idx.{s}o"] = d.clamp(0.0, max_dist), i
        if not both:
            continue
        d, i = nearest_distances(v_o, v_h, v_len, None)
        t[f"dist.o{s}"], t[f"idx.o{s}"] = d.clamp(0.0, max_dist), i


def _hand_in_object_space(mano: MANOLayer, pose: Tensor, beta: Tensor, j3d: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Pose MANO (no translation) and move its vertices onto the given joints.

    Args:
        mano: MANO layer; pose: (B, 48) axis-angle; beta: (B, 10); j3d: (B, J, 3) joints
            in object canonical space.

    Returns:
        vertices (B, V, 3) shifted by the mean joint offset, joints ``j3d``, and the
        canonical root (B, 3) of the untranslated MANO.
    """
    dt = mano.v_template.dtype
    out = mano(global_orient=pose[:, :3].to(dt), hand_pose=pose[:, 3:].to(dt), betas=beta.to(dt))
    joints, verts = out.joints.to(j3d.dtype), out.vertices.to(j3d.dtype)
    if joints.shape != j3d.shape:
        raise ValueError(f"MANO gives joints {tuple(joints.shape)}, labels are {tuple(j3d.shape)}")
    shift = (j3d - joints).mean(dim=1, keepdim=True)
    return verts + shift, j3d, joints[:, 0]


def _object_canonical(
    t: Mapping[str, Any],
    meta: Mapping[str, Any],
    object_layer: ArticulatedObjectLayer,
    dev: torch.device,
    dtype: torch.dtype,
) -> dict[str, Tensor]:
    """The object posed with its GT rotation and angle, no translation ("object canonical space")."""
    names = [meta["query_names"]] if isinstance(meta["query_names"], str) else list(meta["query_names"])
    return object_layer(
        angles=torch.as_tensor(t["object.radian"]).to(dev, dtype).reshape(-1, 1),
        global_orient=torch.as_tensor(t["object.rot"]).to(dev, dtype).reshape(-1, 3),
        transl=None,
        names=names,
    )


def _hand_cam_targets(
    t: Mapping[str, Any],
    s: str,
    mano: MANOLayer,
    R0: Tensor,
    T0: Tensor,
    transl: Tensor,
    dev: torch.device,
    dtype: torch.dtype,
) -> dict[str, Tensor]:
    """Patch-camera vertices (B, V, 3), joints (B, J, 3) and root translation (B, 3) of hand ``s``.

    ``R0``, ``T0`` take full-camera points into object canonical space; ``transl`` (B, 3)
    takes that space into the patch camera.
    """
    j_full = torch.as_tensor(t[f"mano.j3d.full.{s}"]).to(dev, dtype)
    j0 = j_full @ R0.transpose(1, 2) + T0[:, None]
    pose, beta = (torch.as_tensor(t[f"mano.{k}.{s}"]).to(dev, dtype) for k in ("pose", "beta"))
    verts, joints, root_cano = _hand_in_object_space(mano, pose, beta, j0)
    j3d = joints + transl[:, None]
    return {
        f"mano.v3d.cam.{s}": verts + transl[:, None],
        f"mano.j3d.cam.{s}": j3d,
        f"mano.cam_t.{s}": j3d[:, 0] - root_cano,
    }


def _object_cam_targets(
    t: Mapping[str, Any], obj: Mapping[str, Tensor], transl: Tensor, focal: Tensor, img_res: int, dtype: torch.dtype
) -> dict[str, Any]:
    """Translations (perspective and weak-perspective) and the patch-camera object points."""
    out: dict[str, Any] = {"object.cam_t": transl}
    for s in ("r", "l"):
        out[f"mano.cam_t.wp.{s}"] = perspective_to_weak_perspective(t[f"mano.cam_t.{s}"], focal, img_res)
    out["object.cam_t.wp"] = perspective_to_weak_perspective(transl, focal, img_res)
    out["object.cam_t.kp3d.b"] = transl
    out["object.kp3d.cam"] = obj["kp3d"].to(dtype) + transl[:, None]
    out["object.bbox3d.cam"] = obj["bbox3d"].to(dtype) + transl[:, None]
    out["object.v.cam"] = obj["v"].to(dtype) + transl[:, None]
    for key in ("v_len", "f", "f_len", "parts_ids"):
        out[f"object.{key}"] = obj[key]
    return out


def prepare_targets(
    targets: Mapping[str, Any],
    meta_info: Mapping[str, Any],
    mano_r: MANOLayer,
    mano_l: MANOLayer,
    object_layer: ArticulatedObjectLayer,
    img_res: int = 224,
    max_dist: float = math.inf,
    field: Literal["both", "hands"] = "both",
) -> tuple[dict[str, Any], dict[str, Any]]:
    """Add ArcticNet-SF's patch-camera 3D targets to a collated batch.

    A batch of :class:`~hogsa_loader.sample.arctic_dataset.ArcticDataset` (or synthetic)
    samples holds MANO and object parameters plus 3D labels in the camera of the *full*
    image and 2D labels in the patch. :func:`prepare_targets` turns them into the 3D labels
    the loss compares with the network outputs, in the patch camera:

    1. pose the object with its GT rotation and angle, no translation ("object canonical
       space"); solve the rigid transform taking the full-camera bottom keypoints onto it
       (Kabsch) and apply it to the GT hand joints;
    2. pose MANO without translation and shift its vertices by the mean joint offset to
       those joints;
    3. estimate the translation bringing the posed bottom keypoints onto their 2D labels
       (linear least squares with the patch intrinsics) and add it to everything;
    4. derive the hand / object translations (and weak-perspective cameras) and the
       hand↔object nearest-vertex distances.

    Args:
        targets: batch targets with ``mano.pose.{r,l}`` (B, 48), ``mano.beta.{r,l}``
            (B, 10), ``mano.j3d.full.{r,l}`` (B, J, 3), ``object.radian`` (B,) or (B, 1),
            ``object.rot`` (B, 1, 3) or (B, 3), ``object.kp3d.full.b`` (B, 16, 3),
            ``object.kp2d.norm.b`` (B, 16, 2).
        meta_info: ``intrinsics`` (B, 3, 3) patch intrinsics, ``query_names`` (B names).
        mano_r, mano_l: the MANO layers of the data; object_layer: its
            :class:`~hogsa_loader.assets.objects.articulated.ArticulatedObjectLayer`.
        img_res: patch side (px) of the normalised 2D labels.
        max_dist: clamp of the ``dist.*`` targets (ArcticNet-SF: none).
        field: which nearest-vertex targets to add: ``"both"`` directions (as ARCTIC
            prepares for every model) or only ``"hands"`` (``dist.{ro,lo}`` and
            ``idx.{ro,lo}``, all that ArcticNet-SF's contact-deviation loss reads; the
            object-to-hand half is the larger cost on a CPU).

    Returns:
        new ``(targets, meta_info)`` dicts: targets gain ``mano.cam_t.{r,l}``,
        ``object.cam_t``, ``mano.cam_t.wp.{r,l}``, ``object.cam_t.wp``,
        ``object.cam_t.kp3d.b``, ``mano.v3d.cam.{r,l}`` (B, V, 3), ``mano.j3d.cam.{r,l}``,
        ``object.kp3d.cam`` (B, 32, 3), ``object.bbox3d.cam`` (B, 16, 3), ``object.v.cam``
        (B, L, 3), ``object.v_len`` (B,), ``object.f``, ``object.f_len``,
        ``object.parts_ids`` (B, L), ``dist.{ro,lo}`` (B, V), ``dist.{or,ol}`` (B, L; only
        with ``field="both"``) and the matching ``idx.*``; meta_info gains ``part_ids`` (B, L) and ``diameter`` (B,).
    """
    t, meta = dict(targets), dict(meta_info)
    with torch.no_grad():
        kp3d_b = torch.as_tensor(t["object.kp3d.full.b"])
        dtype, dev = kp3d_b.dtype, kp3d_b.device
        K = torch.as_tensor(meta["intrinsics"]).to(dev, dtype)
        obj = _object_canonical(t, meta, object_layer, dev, dtype)
        meta["part_ids"], meta["diameter"] = obj["parts_ids"], obj["diameter"]
        kp_b_cano = obj["kp3d"][:, obj["kp3d"].shape[1] // 2 :].to(dtype)
        R0, T0 = solve_rigid_transform(kp3d_b, kp_b_cano)
        kp2d_b = unnormalize_kp2d(torch.as_tensor(t["object.kp2d.norm.b"]).to(dev, dtype), img_res)
        transl = estimate_translation_k(kp_b_cano, kp2d_b, K)
        for s, mano in (("r", mano_r), ("l", mano_l)):
            t.update(_hand_cam_targets(t, s, mano, R0, T0, transl, dev, dtype))
        t.update(_object_cam_targets(t, obj, transl, mean_focal(K), img_res, dtype))
        _interfield(t, max_dist, both=field == "both")
    return t, meta
