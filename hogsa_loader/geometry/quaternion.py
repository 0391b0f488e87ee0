"""Quaternion helpers (Gaussian rotations): matrices <-> wxyz quaternions, frames, orthonormalising.

Quaternions are (w, x, y, z) like gsplat and GaMeS (``rot_to_quat_batch``); the ones this
module returns are unit length with ``w >= 0``. Every function is batched over leading
dimensions and differentiable.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

__all__ = ["matrix_to_quat", "quat_to_matrix", "quat_multiply", "orthonormalize", "identity_quats"]


def quat_to_matrix(quats: Tensor) -> Tensor:
    """(..., 4) wxyz quaternions (normalised here) -> (..., 3, 3) rotation matrices."""
    w, x, y, z = F.normalize(quats, p=2, dim=-1).unbind(-1)
    rows = [
        1 - 2 * (y * y + z * z),
        2 * (x * y - w * z),
        2 * (x * z + w * y),
        2 * (x * y + w * z),
        1 - 2 * (x * x + z * z),
        2 * (y * z - w * x),
        2 * (x * z - w * y),
        2 * (y * z + w * x),
        1 - 2 * (x * x + y * y),
    ]
    return torch.stack(rows, -1).unflatten(-1, (3, 3))


def matrix_to_quat(rot: Tensor) -> Tensor:
    """Rotation matrices to unit wxyz quaternions with ``w >= 0``.

    Each of the four classic candidates (divide by ``4w``, ``4x``, ``4y`` or ``4z``) is
    formed, and per matrix the one with the largest divisor is kept, so the result is
    well conditioned for every rotation (also near 180 degrees).

    Args:
        rot: (..., 3, 3) rotation matrices.

    Returns:
        (..., 4) quaternions.
    """
    m = rot
    m00, m01, m02 = m[..., 0, 0], m[..., 0, 1], m[..., 0, 2]
    m10, m11, m12 = m[..., 1, 0], m[..., 1, 1], m[..., 1, 2]
    m20, m21, m22 = m[..., 2, 0], m[..., 2, 1], m[..., 2, 2]
    # 4 q_i^2 for i = w, x, y, z
    sq = torch.stack([1 + m00 + m11 + m22, 1 + m00 - m11 - m22, 1 - m00 + m11 - m22, 1 - m00 - m11 + m22], -1)
    two_q = torch.sqrt(sq.clamp(min=1e-12))  # 2 |q_i|
    cand = torch.stack(
        [
            torch.stack([two_q[..., 0] ** 2, m21 - m12, m02 - m20, m10 - m01], -1),
            torch.stack([m21 - m12, two_q[..., 1] ** 2, m10 + m01, m02 + m20], -1),
            torch.stack([m02 - m20, m10 + m01, two_q[..., 2] ** 2, m12 + m21], -1),
            torch.stack([m10 - m01, m20 + m02, m21 + m12, two_q[..., 3] ** 2], -1),
        ],
        -2,
    ) / (2.0 * two_q[..., None])  # row i = 4 q_i q / (4 |q_i|)
    best = sq.argmax(-1)
    q = torch.gather(cand, -2, best[..., None, None].expand(*best.shape, 1, 4)).squeeze(-2)
    q = F.normalize(q, p=2, dim=-1)
    return torch.where(q[..., :1] < 0, -q, q)


def quat_multiply(a: Tensor, b: Tensor) -> Tensor:
    """Hamilton product ``a b`` of wxyz quaternions (rotation ``R(a) R(b)``), (..., 4).

    Every term is evaluated in the written order (pytorch3d's ``quaternion_raw_multiply``),
    which ARCTIC's float32 posing in :mod:`hogsa_loader.assets.arctic_float32` relies on.
    """
    aw, ax, ay, az = a.unbind(-1)
    bw, bx, by, bz = b.unbind(-1)
    return torch.stack(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ],
        -1,
    )


def orthonormalize(mat: Tensor, eps: float = 1e-12) -> Tensor:
    """Nearest-rotation surrogate of a linear map by Gram-Schmidt on its first two columns.

    Used for linear-blend-skinning matrices ``sum_j w_j R_j``, which are rotations times a
    small symmetric shrink; for an exact rotation the result is the rotation itself.
    (SVD-based polar decomposition is avoided: its gradient is undefined when singular
    values coincide, e.g. at the rest pose where the blend is exactly a rotation.)

    Args:
        mat: (..., 3, 3).

    Returns:
        (..., 3, 3) proper rotation matrices.
    """
    a, b = mat[..., :, 0], mat[..., :, 1]
    x = a / a.norm(dim=-1, keepdim=True).clamp(min=eps)
    b = b - (x * b).sum(-1, keepdim=True) * x
    y = b / b.norm(dim=-1, keepdim=True).clamp(min=eps)
    z = torch.linalg.cross(x, y, dim=-1)
    return torch.stack([x, y, z], -1)


def identity_quats(*shape: int, dtype: torch.dtype = torch.float32, device: torch.device | None = None) -> Tensor:
    """(*shape, 4) identity quaternions (1, 0, 0, 0)."""
    q = torch.zeros(*shape, 4, dtype=dtype, device=device)
    q[..., 0] = 1.0
    return q
