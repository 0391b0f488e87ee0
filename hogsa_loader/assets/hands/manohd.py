"""MANO-HD: edge-midpoint subdivision of a MANO-schema model (HandAvatar, CVPR 2023).

:func:`subdivide_model` builds the model; :func:`subdivide_mesh` the mesh step.
"""

from __future__ import annotations

from typing import Optional

import numpy as np
import scipy.sparse as sp

from hogsa_loader.assets.hands.mano_io import ManoModelData

__all__ = ["unique_edges", "subdivide_mesh", "subdivide_model"]


def unique_edges(faces: np.ndarray) -> np.ndarray:
    """(E, 2) undirected edges of a triangle mesh, each sorted (a < b), rows sorted."""
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    return np.unique(np.sort(e, axis=1), axis=0)


def subdivide_mesh(faces: np.ndarray, num_verts: int) -> tuple[np.ndarray, sp.csr_matrix]:
    """One level of midpoint subdivision, as topology plus an interpolation operator.

    Args:
        faces: (F, 3) triangles.
        num_verts: V, number of vertices of the input mesh.

    Returns:
        new_faces: (4F, 3) triangles, orientation preserved.
        interp: (V + E, V) sparse matrix; ``interp @ attr`` gives any per-vertex attribute
            of the subdivided mesh (identity rows for old vertices, 1/2-1/2 for midpoints).
    """
    edges = unique_edges(faces)
    E = edges.shape[0]
    # midpoint id of each face edge: lookup via a sorted key
    key_all = edges[:, 0] * num_verts + edges[:, 1]

    def mid(a: np.ndarray, b: np.ndarray) -> np.ndarray:
        k = np.minimum(a, b) * num_verts + np.maximum(a, b)
        return num_verts + np.searchsorted(key_all, k)

    a, b, c = faces[:, 0], faces[:, 1], faces[:, 2]
    ab, bc, ca = mid(a, b), mid(b, c), mid(c, a)
    new_faces = np.concatenate([np.stack(t, 1) for t in ((a, ab, ca), (ab, b, bc), (ca, bc, c), (ab, bc, ca))])
    rows = np.concatenate([np.arange(num_verts), num_verts + np.repeat(np.arange(E), 2)])
    cols = np.concatenate([np.arange(num_verts), edges.reshape(-1)])
    vals = np.concatenate([np.ones(num_verts), np.full(2 * E, 0.5)])
    interp = sp.csr_matrix((vals, (rows, cols)), shape=(num_verts + E, num_verts))
    return new_faces.astype(np.int64), interp


def _laplacian_smooth(v: np.ndarray, faces: np.ndarray, passes: int) -> np.ndarray:
    V = v.shape[0]
    e = unique_edges(faces)
    A = sp.coo_matrix((np.ones(2 * len(e)), (e.reshape(-1), e[:, ::-1].reshape(-1))), shape=(V, V)).tocsr()
    deg = np.asarray(A.sum(1)).ravel()
    for _ in range(passes):
        v = (A @ v) / np.maximum(deg, 1)[:, None]
    return v


def subdivide_model(
    model: ManoModelData, levels: int = 1, lbs_weights: Optional[np.ndarray] = None, laplacian_passes: int = 0
) -> ManoModelData:
    """MANO-HD model by ``levels`` rounds of midpoint subdivision.

    Each level adds one vertex at the midpoint of every edge (old vertices keep their indices,
    new ones are appended in sorted-edge order) and splits every triangle into four, so
    ``V' = V + E`` and ``F' = 4 F`` (778 -> 3093 -> 12337 vertices on the official MANO mesh).
    Blend shapes, pose correctives, skinning weights and vertex colours of a new vertex are the
    mean of its edge's endpoints; ``J_regressor`` gets zero columns, so joints are unchanged
    (with the default ``laplacian_passes=0``; smoothing moves the old vertices too, so the
    21 joints shift slightly: up to 0.57 mm, at a fingertip, at level 1 with 3 passes on the
    synthetic hand).
    Fingertips and contact vertices keep their (old) indices; a new vertex joins a contact set
    when both endpoints are in it.

    Skinning weights may be refined later (HandAvatar optimises them): pass ``lbs_weights`` to
    use refined ones instead of the interpolated ones.

    Args:
        model: any MANO-schema model.
        levels: 1 or 2 (HandAvatar ships 2).
        lbs_weights: optional (V', 16) refined skinning weights for the final mesh; rows are
            clamped to [0, 1] and renormalised. Default: interpolated weights.
        laplacian_passes: one-ring averaging passes applied to the final template (HandAvatar
            uses 3; default 0 keeps the surface exactly on the original mesh's midpoints
            and the joints exactly where the original model puts them).

    Returns:
        A new :class:`ManoModelData` with ``meta["manohd"] = {"levels", "parent_num_verts",
        "laplacian_passes"}``.
    """
    if levels not in (1, 2):
        raise ValueError(f"levels must be 1 or 2, got {levels}")
    faces = model.faces
    op = sp.identity(model.num_verts, format="csr")
    contact = {k: v.copy() for k, v in model.contact_vertex_ids.items()}
    for _ in range(levels):
        n = op.shape[0]
        faces, step = subdivide_mesh(faces, n)
        for k, ids in contact.items():
            member = np.zeros(n, bool)
            member[ids] = True
            extra = np.flatnonzero(np.asarray(step[n:] @ member.astype(float)).ravel() > 0.99) + n
            contact[k] = np.concatenate([ids, extra])
        op = step @ op
    V1 = op.shape[0]

    def lift(arr: np.ndarray) -> np.ndarray:
        flat = arr.reshape(arr.shape[0], -1)
        return np.asarray(op @ flat).reshape((V1,) + arr.shape[1:])

    v = lift(model.v_template)
    if laplacian_passes:
        v = _laplacian_smooth(v, faces, laplacian_passes)
    if lbs_weights is None:
        weights = lift(model.weights)
    else:
        if lbs_weights.shape != (V1, model.num_joints):
            raise ValueError(f"lbs_weights must be ({V1}, {model.num_joints}), got {lbs_weights.shape}")
        weights = np.clip(lbs_weights, 0.0, 1.0)
    weights = weights / weights.sum(1, keepdims=True)
    J_reg = np.zeros((model.num_joints, V1))
    J_reg[:, : model.num_verts] = model.J_regressor
    meta = dict(model.meta)
    meta["manohd"] = {"levels": levels, "parent_num_verts": model.num_verts, "laplacian_passes": laplacian_passes}
    return model.replace(
        v_template=v,
        shapedirs=lift(model.shapedirs),
        posedirs=lift(model.posedirs),
        J_regressor=J_reg,
        weights=weights,
        faces=faces,
        vertex_colors=None if model.vertex_colors is None else lift(model.vertex_colors),
        contact_vertex_ids=contact,
        meta=meta,
    )
