"""Rotation conversions used by the hand and object layers.

All functions are batched over leading dimensions, differentiable (also at the zero
rotation), and keep the dtype and device of their input.
"""

from __future__ import annotations

import torch
from torch import Tensor

__all__ = ["axis_angle_to_matrix", "matrix_to_axis_angle", "rotation_about_axis", "skew"]


def skew(v: Tensor) -> Tensor:
    """Cross-product matrices.

    Args:
        v: (..., 3) vectors.

    Returns:
        (..., 3, 3) matrices ``[v]_x`` with ``[v]_x @ w == cross(v, w)``.
    """
    zero = torch.zeros_like(v[..., 0])
    x, y, z = v.unbind(-1)
    return torch.stack([zero, -z, y, z, zero, -x, -y, x, zero], dim=-1).reshape(v.shape[:-1] + (3, 3))


def axis_angle_to_matrix(rotvec: Tensor) -> Tensor:
    """Rodrigues' formula: axis-angle (rotation vector) to rotation matrix.

    ``R = I + a [k]_x + b [k]_x^2`` with ``a = sin(t)/t``, ``b = (1 - cos(t))/t^2`` on the
    unnormalised cross matrix; both coefficients switch to their Taylor series near
    ``t = 0`` so values and gradients stay finite at the identity.

    Args:
        rotvec: (..., 3) rotation vectors (radians).

    Returns:
        (..., 3, 3) rotation matrices.
    """
    theta2 = (rotvec * rotvec).sum(-1, keepdim=True)
    small = theta2 < 1e-8
    safe2 = torch.where(small, torch.ones_like(theta2), theta2)
    theta = safe2.sqrt()
    a = torch.where(small, 1.0 - theta2 / 6.0, torch.sin(theta) / theta)
    b = torch.where(small, 0.5 - theta2 / 24.0, (1.0 - torch.cos(theta)) / safe2)
    k = skew(rotvec)
    eye = torch.eye(3, dtype=rotvec.dtype, device=rotvec.device).expand_as(k)
    return eye + a[..., None] * k + b[..., None] * (k @ k)


def matrix_to_axis_angle(rot: Tensor) -> Tensor:
    """Inverse of :func:`axis_angle_to_matrix` (angles in [0, pi]).

    Args:
        rot: (..., 3, 3) rotation matrices.

    Returns:
        (..., 3) rotation vectors.
    """
    # Quaternion route (Shepperd) is stable for every angle including pi.
    m = rot
    t = m[..., 0, 0] + m[..., 1, 1] + m[..., 2, 2]
    q = torch.stack(
        [
            1 + t,
            1 + m[..., 0, 0] - m[..., 1, 1] - m[..., 2, 2],
            1 - m[..., 0, 0] + m[..., 1, 1] - m[..., 2, 2],
            1 - m[..., 0, 0] - m[..., 1, 1] + m[..., 2, 2],
        ],
        dim=-1,
    )
    best = q.argmax(-1, keepdim=True)
    w_x = m[..., 2, 1] - m[..., 1, 2]
    w_y = m[..., 0, 2] - m[..., 2, 0]
    w_z = m[..., 1, 0] - m[..., 0, 1]
    xy = m[..., 0, 1] + m[..., 1, 0]
    xz = m[..., 0, 2] + m[..., 2, 0]
    yz = m[..., 1, 2] + m[..., 2, 1]
    cands = torch.stack(
        [
            torch.stack([q[..., 0], w_x, w_y, w_z], -1),
            torch.stack([w_x, q[..., 1], xy, xz], -1),
            torch.stack([w_y, xy, q[..., 2], yz], -1),
            torch.stack([w_z, xz, yz, q[..., 3]], -1),
        ],
        dim=-2,
    )
    quat = torch.gather(cands, -2, best[..., None].expand(best.shape[:-1] + (1, 4))).squeeze(-2)
    quat = quat / quat.norm(dim=-1, keepdim=True)
    quat = torch.where(quat[..., :1] < 0, -quat, quat)
    w, xyz = quat[..., 0], quat[..., 1:]
    s = xyz.norm(dim=-1)
    angle = 2.0 * torch.atan2(s, w)
    small = s < 1e-7
    scale = torch.where(small, 2.0 / w.clamp_min(1e-12), angle / torch.where(small, torch.ones_like(s), s))
    return xyz * scale[..., None]


def rotation_about_axis(angle: Tensor, axis: tuple[float, float, float]) -> Tensor:
    """Rotation by ``angle`` about a fixed unit ``axis``.

    Args:
        angle: (...) angles in radians.
        axis: a fixed 3-vector (normalised here).

    Returns:
        (..., 3, 3) rotation matrices.
    """
    ax = torch.tensor(axis, dtype=angle.dtype, device=angle.device)
    ax = ax / ax.norm()
    return axis_angle_to_matrix(angle[..., None] * ax)
