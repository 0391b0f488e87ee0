"""World-frame posing of ARCTIC's ``process_seq`` in ARCTIC's own float32 arithmetic.

The processed splits (:mod:`hogsa_loader.assets.arctic_processing`) must match ARCTIC's
bit for bit: a float64 computation rounded to float32 (what the shared MANO and object
layers give) differs in the last bits, which the projection to ~1000 px turns into ~5e-4
px. Equality needs the same torch operations on tensors of the same shapes and memory
layouts, so the batch is the whole chunk of frames, as ARCTIC's ``DataLoader`` batch is,
and every function names the ARCTIC operation it reproduces.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Optional

import numpy as np
import torch
import torch.nn.functional as nnf
from torch import Tensor

from hogsa_loader.assets.objects.articulated import TOP_ID
from hogsa_loader.geometry.quaternion import quat_multiply

__all__ = ["ObjectTensors32", "mano_forward", "object_forward", "rot_to_camera"]

_EPS_SMALL_ANGLE = 1e-6  # common/rot.py: below it sin(θ/2)/θ is its Taylor expansion


# ----------------------------------------------------------------------------------------
# MANO (smplx lbs, float32)
# ----------------------------------------------------------------------------------------
def _rodrigues(rotvec: Tensor) -> Tensor:
    """(N, 3) axis-angle → (N, 3, 3): ``I + sin θ K + (1 − cos θ) K²`` with ``θ = |v + 1e-8|``."""
    n = rotvec.shape[0]
    theta = torch.norm(rotvec + 1e-8, dim=1, keepdim=True)
    axis = rotvec / theta
    cos = torch.cos(theta)[:, None]
    sin = torch.sin(theta)[:, None]
    ax, ay, az = axis[:, 0:1], axis[:, 1:2], axis[:, 2:3]
    zero = torch.zeros((n, 1), dtype=rotvec.dtype, device=rotvec.device)
    skew = torch.cat([zero, -az, ay, az, zero, -ax, -ay, ax, zero], dim=1).view(n, 3, 3)
    eye = torch.eye(3, dtype=rotvec.dtype, device=rotvec.device)[None]
    return eye + sin * skew + (1 - cos) * torch.bmm(skew, skew)


def _chain(rot_mats: Tensor, joints: Tensor, parents: list[int]) -> tuple[Tensor, Tensor]:
    """Posed joints (B, J, 3) and rest-relative transforms (B, J, 4, 4) along the tree."""
    B, J = joints.shape[:2]
    j = joints[..., None]  # (B, J, 3, 1)
    offsets = j.clone()
    offsets[:, 1:] = offsets[:, 1:] - j[:, parents[1:]]
    local = torch.cat(
        [nnf.pad(rot_mats.reshape(-1, 3, 3), [0, 0, 0, 1]), nnf.pad(offsets.reshape(-1, 3, 1), [0, 0, 0, 1], value=1)],
        dim=2,
    ).reshape(B, J, 4, 4)
    world = [local[:, 0]]
    for i in range(1, J):
        world.append(torch.matmul(world[parents[i]], local[:, i]))
    G = torch.stack(world, dim=1)
    shift = torch.matmul(G, nnf.pad(j, [0, 0, 0, 1]))  # G · [j_rest, 0]
    return G[:, :, :3, 3], G - nnf.pad(shift, [3, 0])


def mano_forward(
    layer: Any, global_orient: Tensor, hand_pose: Tensor, betas: Tensor, transl: Tensor
) -> tuple[Tensor, Tensor]:
    """smplx ``MANO`` (as ARCTIC builds it) in float32 on a :class:`MANOLayer`'s buffers.

    Args:
        layer: a float32 :class:`~hogsa_loader.assets.hands.mano.MANOLayer` with ``use_pca=False``
            (its buffers hold the model file's values rounded to float32, as smplx's do).
        global_orient: (B, 3); hand_pose: (B, 45) (offsets from ``hands_mean`` unless the
            layer is flat); betas: (B, S); transl: (B, 3); all float32.

    Returns:
        vertices (B, V, 3) and joints (B, 21, 3) (16 MANO joints, then the fingertip
        vertices), float32, metres.
    """
    if layer.use_pca or layer.v_template.dtype != torch.float32:
        raise ValueError("mano_forward needs a float32 MANOLayer without PCA (ARCTIC's layer)")
    B = betas.shape[0]
    J = int(layer.parents.shape[0])
    V = int(layer.v_template.shape[0])
    parents = layer.parents.tolist()
    zeros3 = torch.zeros(3, dtype=layer.hand_mean.dtype, device=layer.hand_mean.device)
    pose = torch.cat([global_orient, hand_pose], dim=1) + torch.cat([zeros3, layer.hand_mean])
    # smplx keeps J_regressor and posedirs as transposed views (column-major); the products
    # below see the same layouts.
    j_regressor = layer.J_regressor.t().contiguous().t()
    posedirs = layer.posedirs.reshape(V * 3, -1).t()
    v_shaped = layer.v_template + torch.einsum("bl,mkl->bmk", betas, layer.shapedirs[..., : betas.shape[1]])
    rest_joints = torch.einsum("bik,ji->bjk", v_shaped, j_regressor)
    rot_mats = _rodrigues(pose.view(-1, 3)).view(B, -1, 3, 3)
    eye = torch.eye(3, dtype=pose.dtype, device=pose.device)
    v_posed = torch.matmul((rot_mats[:, 1:] - eye).view(B, -1), posedirs).view(B, -1, 3) + v_shaped
    joints, G = _chain(rot_mats, rest_joints, parents)
    weights = layer.lbs_weights[None].expand(B, -1, -1)
    T = torch.matmul(weights, G.view(B, J, 16)).view(B, -1, 4, 4)
    ones = torch.ones((B, V, 1), dtype=pose.dtype, device=pose.device)
    verts = torch.matmul(T, torch.cat([v_posed, ones], dim=2)[..., None])[:, :, :3, 0]
    joints = joints + transl[:, None]
    verts = verts + transl[:, None]
    return verts, torch.cat([joints, verts[:, layer.tip_ids]], dim=1)


# ----------------------------------------------------------------------------------------
# Quaternions (common/rot.py conversions, float32)
# ----------------------------------------------------------------------------------------
def _quat_from_rotvec(rotvec: Tensor) -> Tensor:
    """(..., 3) axis-angle → (..., 4) ``(cos θ/2, v · sin(θ/2)/θ)`` (Taylor for θ < 1e-6)."""
    theta = torch.norm(rotvec, p=2, dim=-1, keepdim=True)
    half = theta * 0.5
    small = theta.abs() < _EPS_SMALL_ANGLE
    ratio = torch.empty_like(theta)
    ratio[~small] = torch.sin(half[~small]) / theta[~small]
    ratio[small] = 0.5 - (theta[small] * theta[small]) / 48
    return torch.cat([torch.cos(half), rotvec * ratio], dim=-1)


def _quat_rotate(q: Tensor, points: Tensor) -> Tensor:
    """``q ⊗ (0, p) ⊗ q*`` → (..., 3)."""
    pq = torch.cat((points.new_zeros(points.shape[:-1] + (1,)), points), -1)
    conj = q * q.new_tensor([1, -1, -1, -1])
    return quat_multiply(quat_multiply(q, pq), conj)[..., 1:]


def _quat_from_matrix(R: Tensor) -> Tensor:
    """(..., 3, 3) → (..., 4): the best-conditioned of the four candidate quaternions."""
    lead = R.shape[:-2]
    m00, m01, m02, m10, m11, m12, m20, m21, m22 = R.reshape(lead + (9,)).unbind(-1)
    diag = torch.stack(
        [1.0 + m00 + m11 + m22, 1.0 + m00 - m11 - m22, 1.0 - m00 + m11 - m22, 1.0 - m00 - m11 + m22], dim=-1
    )
    q_abs = torch.zeros_like(diag)
    pos = diag > 0
    q_abs[pos] = torch.sqrt(diag[pos])
    cand = torch.stack(
        [
            torch.stack([q_abs[..., 0] ** 2, m21 - m12, m02 - m20, m10 - m01], dim=-1),
            torch.stack([m21 - m12, q_abs[..., 1] ** 2, m10 + m01, m02 + m20], dim=-1),
            torch.stack([m02 - m20, m10 + m01, q_abs[..., 2] ** 2, m12 + m21], dim=-1),
            torch.stack([m10 - m01, m20 + m02, m21 + m12, q_abs[..., 3] ** 2], dim=-1),
        ],
        dim=-2,
    )
    floor = torch.tensor(0.1, dtype=q_abs.dtype, device=q_abs.device)
    cand = cand / (2.0 * q_abs[..., None].max(floor))
    pick = nnf.one_hot(q_abs.argmax(dim=-1), num_classes=4) > 0.5
    return cand[pick, :].reshape(lead + (4,))


def _rotvec_from_quat(q: Tensor) -> Tensor:
    """(..., 4) → (..., 3) axis-angle ``v / (sin(θ/2)/θ)``, ``θ = 2 atan2(|v|, w)``."""
    norm = torch.norm(q[..., 1:], p=2, dim=-1, keepdim=True)
    half = torch.atan2(norm, q[..., :1])
    theta = 2 * half
    small = theta.abs() < _EPS_SMALL_ANGLE
    ratio = torch.empty_like(theta)
    ratio[~small] = torch.sin(half[~small]) / theta[~small]
    ratio[small] = 0.5 - (theta[small] * theta[small]) / 48
    return q[..., 1:] / ratio


def rot_to_camera(rotvec: Tensor, world2cam: Tensor) -> Tensor:
    """Axis-angle of ``R_world2cam · R(rotvec)`` as ARCTIC's ``transform_mano_rot_cam``.

    Args:
        rotvec: (B, 3) float32 world-frame axis-angle; world2cam: (B, 4, 4) float32.

    Returns:
        (B, 3) float32 camera-frame axis-angle (the product quaternion is taken with a
        non-negative real part, so the angle is in [0, π]).
    """
    q = quat_multiply(_quat_from_matrix(world2cam[:, :3, :3]), _quat_from_rotvec(rotvec))
    q = torch.where(q[..., 0:1] < 0, -q, q)
    return _rotvec_from_quat(q)


# ----------------------------------------------------------------------------------------
# Object (ObjectTensors, float32)
# ----------------------------------------------------------------------------------------
@dataclass(frozen=True)
class ObjectTensors32:
    """One object's template as ARCTIC's ``ObjectTensors`` holds it (float32, metres).

    Attributes:
        v: (V, 3) vertices ``float32(mm) / 1000``; v_top: (V,) bool, top-part vertices.
        kp3d: (32, 3) keypoints (top 16, bottom 16); kp_top: (32,) bool.
        bbox3d: (16, 3) box corners (top 8, bottom 8); bbox_top: (16,) bool.
        exact: True when built from the template files' millimetres (bit-equal to ARCTIC);
            False when taken from a layer's metres (ARCTIC's arithmetic on templates that
            may differ from ARCTIC's by a rounding).
    """

    v: Tensor
    v_top: Tensor
    kp3d: Tensor
    kp_top: Tensor
    bbox3d: Tensor
    bbox_top: Tensor
    exact: bool

    @staticmethod
    def _masks(layer: Any, name: str) -> tuple[Tensor, Tensor, Tensor, int]:
        i = layer.name_to_index[name]
        n = int(layer.v_len[i])
        return layer.parts_ids[i, :n] == TOP_ID, layer.kp_is_top, layer.bbox_is_top, n

    @classmethod
    def from_layer(cls, layer: Any, name: str) -> "ObjectTensors32":
        """The layer's float32 metres as they are (``exact=False``)."""
        v_top, kp_top, bbox_top, n = cls._masks(layer, name)
        i = layer.name_to_index[name]
        f = torch.float32
        return cls(layer.v[i, :n].to(f), v_top, layer.kp[i].to(f), kp_top, layer.bbox[i].to(f), bbox_top, False)

    @classmethod
    def from_mm(
        cls, layer: Any, name: str, verts_mm: np.ndarray, kp_mm: np.ndarray, bbox_mm: np.ndarray
    ) -> Optional["ObjectTensors32"]:
        """ARCTIC's tensors ``float32(mm) / 1000`` from the template files' millimetres.

        Args:
            layer: the object layer the sequence is posed with (part masks, and the check).
            name: the object.
            verts_mm: (V, 3) ``mesh.obj`` vertices; kp_mm: (32, 3) ``keypoints_top`` then
                ``keypoints_bottom``; bbox_mm: (16, 3) ``bbox_top`` then ``bbox_bottom``
                (float64 as parsed from the files).

        Returns:
            ``exact=True`` tensors, or None when these millimetres are not the layer's
            template (shapes differ, or ``float32(mm · 0.001)``, the metres the project's
            reader derives from the files, differ from the layer's).
        """
        v_top, kp_top, bbox_top, n = cls._masks(layer, name)
        i = layer.name_to_index[name]
        pairs = ((verts_mm, layer.v[i, :n]), (kp_mm, layer.kp[i]), (bbox_mm, layer.bbox[i]))
        for mm, metres in pairs:
            ref = metres.detach().cpu().numpy()
            if mm.shape != ref.shape or not np.array_equal(
                (mm * (1.0 / 1000.0)).astype(np.float32), ref.astype(np.float32)
            ):
                return None

        def arctic(a: np.ndarray) -> Tensor:  # torch.FloatTensor(mm) / 1000
            return torch.from_numpy(np.ascontiguousarray(a, dtype=np.float32)) / 1000

        return cls(arctic(verts_mm), v_top, arctic(kp_mm), kp_top, arctic(bbox_mm), bbox_top, True)


def object_forward(obj: ObjectTensors32, angles: Tensor, global_orient: Tensor, transl_mm: Tensor) -> dict[str, Tensor]:
    """Pose one object over B frames as ARCTIC's ``ObjectTensors.forward``.

    Args:
        obj: the template; angles: (B,) float32 articulation; global_orient: (B, 3)
            float32 axis-angle; transl_mm: (B, 3) float32 translation in mm (ARCTIC passes
            ``obj_trans / 1000``, divided in float32).

    Returns:
        ``{"v": (B, V, 3), "kp3d": (B, 32, 3), "bbox3d": (B, 16, 3)}`` float32 metres.
    """
    B = angles.shape[0]
    z_axis = torch.tensor([[0.0, 0.0, -1.0]], dtype=torch.float32)
    q_arti = _quat_from_rotvec(z_axis * angles.reshape(B, 1))[:, None, :]
    q_glob = _quat_from_rotvec(global_orient.view(-1, 3))[:, None, :]
    t = (transl_mm / 1000)[:, None, :]
    out = {}
    for key, pts, top in (
        ("v", obj.v, obj.v_top),
        ("kp3d", obj.kp3d, obj.kp_top),
        ("bbox3d", obj.bbox3d, obj.bbox_top),
    ):
        pts = pts[None].expand(B, -1, -1)
        top_pts = _quat_rotate(q_glob, _quat_rotate(q_arti, pts)) + t
        bottom_pts = _quat_rotate(q_glob, pts) + t
        out[key] = torch.where(top[None, :, None], top_pts, bottom_pts)
    return out
