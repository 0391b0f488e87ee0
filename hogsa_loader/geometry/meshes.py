"""Triangle-mesh normals, batched and differentiable: the one implementation every stage uses."""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

__all__ = ["NORMAL_EPS", "face_normals", "normalize", "vertex_normals", "vertex_normals_np"]

#: Vectors shorter than this are left (near) zero by :func:`normalize`.
NORMAL_EPS = 1e-12


def face_normals(verts: Tensor, faces: Tensor) -> Tensor:
    """Unnormalised face normals ``cross(v1 - v0, v2 - v0)`` (length = 2 x area).

    Args:
        verts: (..., V, 3).
        faces: (F, 3) int64, on ``verts``' device.

    Returns:
        (..., F, 3).
    """
    v0, v1, v2 = (verts.index_select(-2, faces[:, k]) for k in range(3))  # (..., F, 3) each
    return torch.linalg.cross(v1 - v0, v2 - v0, dim=-1)


def normalize(x: Tensor) -> Tensor:
    """Unit vectors along the last axis; zero vectors stay zero.

    Args:
        x: (..., 3).

    Returns:
        (..., 3).
    """
    return x / x.norm(dim=-1, keepdim=True).clamp_min(NORMAL_EPS)


def vertex_normals(verts: Tensor, faces: Tensor) -> Tensor:
    """Area-weighted unit vertex normals (zero for vertices used by no face).

    Each vertex sums the unnormalised normals of its faces, first over the faces' first
    corners, then their second and third (on the CPU a fixed order, so the result is
    reproducible bit for bit; CUDA adds atomically).

    Args:
        verts: (..., V, 3).
        faces: (F, 3) int64.

    Returns:
        (..., V, 3).
    """
    fn = face_normals(verts, faces)
    acc = torch.zeros_like(verts)
    for k in range(3):
        acc = acc.index_add(-2, faces[:, k], fn)
    return normalize(acc)


def vertex_normals_np(verts: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """:func:`vertex_normals` of NumPy arrays.

    Args:
        verts: (V, 3) float.
        faces: (F, 3) int.

    Returns:
        (V, 3), the dtype of ``verts``.
    """
    out = vertex_normals(torch.from_numpy(np.ascontiguousarray(verts)), torch.from_numpy(np.asarray(faces, np.int64)))
    return out.numpy()
