"""A small classical triangle-mesh rasteriser (z-buffer, textures, Blinn-Phong shading).

Two backends with the same conventions: vectorised PyTorch over triangle-pixel pairs in
memory-bounded chunks (any device), and compiled CPU kernels that loop over pixels
(:mod:`hogsa_loader.render.raster_kernels`, numba; same fragments bit for bit, shading within
float rounding), chosen by ``backend``. It never uses Gaussian splatting.

Start with :func:`render_meshes` (shaded, textured meshes of a scene) or :func:`rasterize`
(fragments of one camera-space mesh); :func:`rasterize` lists the camera, pixel and coverage
conventions, :func:`render_meshes` those of textures and supersampling.
"""

from __future__ import annotations

import math
import operator
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal, Sequence

import cv2
import numpy as np
import torch
import torch.nn.functional as F_nn
from torch import Tensor

from hogsa_loader.geometry.cameras import LOOK_AT_PARALLEL, look_at
from hogsa_loader.geometry.meshes import NORMAL_EPS, face_normals, normalize, vertex_normals
from hogsa_loader.geometry.texture import sample_texture
from hogsa_loader.render import raster_kernels

__all__ = [
    "Fragments",
    "MeshPart",
    "Light",
    "MeshRender",
    "rasterize",
    "render_meshes",
    "warm_up_kernels",
    "project_points",
    "scale_intrinsics",
    "transform_points",
    "shade_blinn_phong",
    "camera_look_at",
    "intrinsics_from_fov",
    "save_png",
]

_INT64_MAX = torch.iinfo(torch.int64).max
_BBOX_EPS = 1e-3  # px; pixel bounding boxes are grown by this much, the edge test decides
_SHADE_CHUNK = 1 << 20  # covered samples shaded at a time in render_meshes

Backend = Literal["auto", "torch", "numba"]


# --------------------------------------------------------------------------------------
# Data types
# --------------------------------------------------------------------------------------


@dataclass
class Fragments:
    """Per-pixel result of :func:`rasterize`.

    Attributes:
        face_idx: (H, W) int64 index of the visible face, -1 on background.
        bary: (H, W, 3) perspective-correct barycentrics of the visible face, 0 on
            background.
        depth: (H, W) camera-space z (metres) of the visible surface, +inf on background.
    """

    face_idx: Tensor
    bary: Tensor
    depth: Tensor


@dataclass
class MeshPart:
    """One mesh of a scene (a hand, an object).

    Exactly one colour source: ``vertex_colors``, or ``uv`` together with ``texture``.

    Attributes:
        verts: (V, 3) world coordinates, metres.
        faces: (F, 3) int64 vertex indices.
        part_id: written into :attr:`MeshRender.part_id`; must be >= 1 (0 = background).
        vertex_colors: (V, 3) float in [0, 1], or None.
        uv: (V, 2) texture coordinates (OBJ convention, v = 0 is the image bottom), or None.
        texture: (Ht, Wt, 3) float in [0, 1] (uint8 is accepted and divided by 255), or None.
    """

    verts: Tensor
    faces: Tensor
    part_id: int
    vertex_colors: Tensor | None = None
    uv: Tensor | None = None
    texture: Tensor | None = None

    def __post_init__(self) -> None:
        _validate_part(self, name="MeshPart")


@dataclass(frozen=True)
class Light:
    """A directional light with Blinn-Phong shading, in camera coordinates.

    ``colour = albedo (ambient + diffuse max(0, n.l)) + specular max(0, n.h)^shininess``
    (white specular, only where ``n.l > 0``), clamped to [0, 1]; ``l = -direction``
    points toward the light, ``h`` is the half vector of ``l`` and the view vector.

    Attributes:
        direction: direction the light travels, camera coordinates. The default
            (0, 0, 1) shines forward from the camera (a head light).
        ambient, diffuse, specular: weights of the three terms.
        shininess: Blinn-Phong exponent.
    """

    direction: tuple[float, float, float] = (0.0, 0.0, 1.0)
    ambient: float = 0.35
    diffuse: float = 0.65
    specular: float = 0.1
    shininess: float = 20.0


@dataclass
class MeshRender:
    """Output of :func:`render_meshes` (all at the output resolution H x W).

    Attributes:
        rgb: (H, W, 3) float in [0, 1], composited over the background.
        alpha: (H, W) coverage in [0, 1] (fractional on edges when supersampled).
        depth: (H, W) nearest camera-space depth of the block, +inf on background.
        part_id: (H, W) int64, 0 on background, else the ``part_id`` of the nearest sample.
        normal: (H, W, 3) camera-space unit shading normal of the nearest sample, facing
            the camera; 0 on background.
    """

    rgb: Tensor
    alpha: Tensor
    depth: Tensor
    part_id: Tensor
    normal: Tensor


@dataclass
class _FaceTables:
    """Per-face data of the faces that survive setup (Fk of them), for pair evaluation.

    Attributes:
        face_ids: (Fk,) int64 original face index of each kept face (increasing).
        edge_a: (3, Fk) coefficient multiplying ``px - ex`` in the oriented edge function.
        edge_b: (3, Fk) coefficient multiplying ``py - ey``.
        edge_x, edge_y: (3, Fk) canonical first endpoint of each edge.
        edge_tl: (3, Fk) bool, True when the edge is a top-left edge (ties are inside).
        inv_z: (3, Fk) ``1 / z`` of the vertex opposite each edge.
        row0, col0: (Fk,) int64 first row / column of the clipped pixel bounding box.
        nrows, ncols: (Fk,) int64 size of that box (>= 1).
    """

    face_ids: Tensor
    edge_a: Tensor
    edge_b: Tensor
    edge_x: Tensor
    edge_y: Tensor
    edge_tl: Tensor
    inv_z: Tensor
    row0: Tensor
    col0: Tensor
    nrows: Tensor
    ncols: Tensor


@dataclass
class _PixelTiles:
    """Pixel rectangles to test, at most ``max_pairs`` pixels each when possible.

    Attributes:
        face: (T,) int64 index into the kept faces (non-decreasing).
        row0, col0: (T,) int64 top-left pixel of the tile.
        ncols: (T,) int64 tile width.
        count: (T,) int64 number of pixels of the tile.
    """

    face: Tensor
    row0: Tensor
    col0: Tensor
    ncols: Tensor
    count: Tensor


# --------------------------------------------------------------------------------------
# Geometry helpers
# --------------------------------------------------------------------------------------


def transform_points(points: Tensor, world2cam: Tensor) -> Tensor:
    """Rigid transform to camera space.

    Args:
        points: (..., 3) world points.
        world2cam: (4, 4) matrix ``[[R, t], [0, 1]]``.

    Returns:
        (..., 3) ``R @ p + t``.
    """
    R = world2cam[:3, :3].to(points)
    t = world2cam[:3, 3].to(points)
    return points @ R.T + t


def project_points(points_cam: Tensor, K: Tensor) -> Tensor:
    """Pinhole projection with the full intrinsics (elementwise, hence bit-reproducible).

    Args:
        points_cam: (..., 3) camera-space points, z > 0.
        K: (3, 3) intrinsics ``[[fx, s, cx], [0, fy, cy], [0, 0, 1]]``.

    Returns:
        (..., 2) continuous pixel coordinates ``(u, v)``; pixel (i, j) has its centre at
        ``(j + 0.5, i + 0.5)``.
    """
    K = K.to(points_cam)
    xn = points_cam[..., 0] / points_cam[..., 2]
    yn = points_cam[..., 1] / points_cam[..., 2]
    u = K[0, 0] * xn + K[0, 1] * yn + K[0, 2]
    v = K[1, 0] * xn + K[1, 1] * yn + K[1, 2]
    return torch.stack([u, v], dim=-1)


def scale_intrinsics(K: Tensor, scale: float) -> Tensor:
    """Intrinsics of the same camera on an image ``scale`` times larger.

    With pixel centres at ``j + 0.5`` the continuous coordinates simply scale
    (``u' = scale u``), so ``K' = diag(scale, scale, 1) @ K``: fx, skew, cx, fy and cy
    are all multiplied by ``scale``.

    Args:
        K: (3, 3) intrinsics.
        scale: positive factor.

    Returns:
        (3, 3) scaled intrinsics.
    """
    S = torch.diag(torch.tensor([scale, scale, 1.0], dtype=K.dtype, device=K.device))
    return S @ K


def _interpolate(values: Tensor, tri_vidx: Tensor, bary: Tensor) -> Tensor:
    """Barycentric interpolation of a per-vertex attribute.

    Args:
        values: (V, C) attribute.
        tri_vidx: (N, 3) int64 vertex indices of the face seen at each sample.
        bary: (N, 3) barycentrics.

    Returns:
        (N, C).
    """
    return (values[tri_vidx] * bary[..., None]).sum(dim=1)


# --------------------------------------------------------------------------------------
# Rasterisation
# --------------------------------------------------------------------------------------


def _check_raster_inputs(
    verts_cam: Tensor, faces: Tensor, K: Tensor, height: int, width: int, near: float, max_pairs: int
) -> None:
    """Raise ValueError with a clear message on malformed :func:`rasterize` inputs."""
    if not isinstance(verts_cam, Tensor) or verts_cam.ndim != 2 or verts_cam.shape[1] != 3:
        raise ValueError(f"verts_cam must be a (V, 3) tensor, got {_shape(verts_cam)}")
    if not verts_cam.is_floating_point():
        raise ValueError(f"verts_cam must be floating point, got {verts_cam.dtype}")
    _check_faces(faces, verts_cam.shape[0], "faces")
    _check_K(K)
    for name, val in (("height", height), ("width", width)):
        if not isinstance(val, int) or isinstance(val, bool) or val < 1:
            raise ValueError(f"{name} must be a positive int, got {val!r}")
    if not (near > 0 and math.isfinite(near)):
        raise ValueError(f"near must be a positive finite number, got {near!r}")
    if not isinstance(max_pairs, int) or max_pairs < 1:
        raise ValueError(f"max_pairs must be a positive int, got {max_pairs!r}")


def _shape(x: object) -> str:
    """Shape of a tensor for error messages, or its type name."""
    return str(tuple(x.shape)) if isinstance(x, Tensor) else type(x).__name__


def _check_faces(faces: Tensor, num_verts: int, name: str) -> None:
    """Faces must be an integer (F, 3) tensor indexing [0, num_verts)."""
    if not isinstance(faces, Tensor) or faces.ndim != 2 or faces.shape[1] != 3:
        raise ValueError(f"{name} must be a (F, 3) tensor, got {_shape(faces)}")
    if faces.is_floating_point() or faces.dtype == torch.bool or faces.is_complex():
        raise ValueError(f"{name} must hold integer vertex indices, got {faces.dtype}")
    if faces.numel() and (int(faces.min()) < 0 or int(faces.max()) >= num_verts):
        raise ValueError(f"{name} index out of range [0, {num_verts}): min {int(faces.min())}, max {int(faces.max())}")


def _check_K(K: Tensor) -> None:
    """K must be a (3, 3) upper-triangular pinhole matrix with last row (0, 0, 1)."""
    if not isinstance(K, Tensor) or K.shape != (3, 3):
        raise ValueError(f"K must be a (3, 3) tensor, got {_shape(K)}")
    last = K[2].detach().to("cpu", torch.float64)
    if not torch.equal(last, torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)):
        raise ValueError(f"K's last row must be (0, 0, 1), got {last.tolist()}")


def _front_facing(tri_cam: Tensor) -> Tensor:
    """Whether each triangle is counter-clockwise seen from the camera.

    Args:
        tri_cam: (F, 3, 3) camera-space triangles.

    Returns:
        (F,) bool, True when ``cross(v1 - v0, v2 - v0) . v0 < 0`` (normal toward camera).
    """
    n = torch.linalg.cross(tri_cam[:, 1] - tri_cam[:, 0], tri_cam[:, 2] - tri_cam[:, 0], dim=-1)
    return (n * tri_cam[:, 0]).sum(-1) < 0


def _oriented_edges(tri_uv: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor, Tensor]:
    """Edge functions of each triangle, canonically ordered and oriented inward.

    Edge k is opposite vertex k. Its endpoints are sorted lexicographically by (u, v), so
    two triangles sharing an edge compute bit-identical coefficients; the sign is then
    flipped (exactly) so that the opposite vertex is on the positive side. Inside-ness of a
    pixel centre p for edge k is ``a (p.u - x) + b (p.v - y) > 0`` (``>= 0`` on top-left
    edges, whose inward normal (a, b) has a > 0, or a == 0 and b > 0).

    Args:
        tri_uv: (F, 3, 2) projected triangles.

    Returns:
        a, b, x, y: (3, F) coefficients and canonical first endpoint.
        top_left: (3, F) bool.
        nondegenerate: (F,) bool, False when a vertex lies on its opposite edge's line.
    """
    a_l, b_l, x_l, y_l, s_l = [], [], [], [], []
    for k in range(3):
        p = tri_uv[:, (k + 1) % 3]
        q = tri_uv[:, (k + 2) % 3]
        c = tri_uv[:, k]
        swap = (q[:, 0] < p[:, 0]) | ((q[:, 0] == p[:, 0]) & (q[:, 1] < p[:, 1]))
        e0 = torch.where(swap[:, None], q, p)
        e1 = torch.where(swap[:, None], p, q)
        a = -(e1[:, 1] - e0[:, 1])
        b = e1[:, 0] - e0[:, 0]
        # Side of the opposite vertex, in float64 for a robust sign.
        side = a.double() * (c[:, 0].double() - e0[:, 0].double()) + b.double() * (c[:, 1].double() - e0[:, 1].double())
        sign = torch.sign(side).to(tri_uv.dtype)
        a_l.append(a * sign)
        b_l.append(b * sign)
        x_l.append(e0[:, 0])
        y_l.append(e0[:, 1])
        s_l.append(sign)
    a, b = torch.stack(a_l), torch.stack(b_l)
    top_left = (a > 0) | ((a == 0) & (b > 0))
    nondegenerate = (torch.stack(s_l) != 0).all(dim=0)
    return a, b, torch.stack(x_l), torch.stack(y_l), top_left, nondegenerate


def _pixel_bbox(tri_uv: Tensor, height: int, width: int) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Clipped, inclusive range of pixels whose centres may lie in each triangle.

    Args:
        tri_uv: (F, 3, 2) projected triangles (finite).

    Returns:
        row0, row1, col0, col1: (F,) int64 (empty when row1 < row0 or col1 < col0).
    """
    lo = tri_uv.amin(dim=1) - 0.5 - _BBOX_EPS
    hi = tri_uv.amax(dim=1) - 0.5 + _BBOX_EPS
    lo = lo.clamp(-1.0, float(max(height, width)) + 1.0)
    hi = hi.clamp(-1.0, float(max(height, width)) + 1.0)
    col0 = torch.ceil(lo[:, 0]).long().clamp_min(0)
    row0 = torch.ceil(lo[:, 1]).long().clamp_min(0)
    col1 = torch.floor(hi[:, 0]).long().clamp_max(width - 1)
    row1 = torch.floor(hi[:, 1]).long().clamp_max(height - 1)
    return row0, row1, col0, col1


def _setup_faces(
    verts_cam: Tensor, faces: Tensor, K: Tensor, height: int, width: int, near: float, cull_backfaces: bool
) -> _FaceTables:
    """Project, drop (near plane, degenerate, off-screen, culled) and tabulate faces.

    Args:
        verts_cam: (V, 3) camera-space vertices.
        faces: (F, 3) int64.
        K: (3, 3) intrinsics (same dtype/device as verts_cam).

    Returns:
        The tables of the Fk kept faces.
    """
    tri_cam = verts_cam[faces]  # (F, 3, 3)
    z = tri_cam[..., 2]
    keep = (z > near).all(dim=1) & torch.isfinite(tri_cam).all(dim=2).all(dim=1)
    safe_cam = torch.where(keep[:, None, None], tri_cam, torch.ones_like(tri_cam))
    tri_uv = project_points(safe_cam, K)  # (F, 3, 2)
    keep &= torch.isfinite(tri_uv).all(dim=2).all(dim=1)
    tri_uv = torch.where(keep[:, None, None], tri_uv, torch.zeros_like(tri_uv))
    if cull_backfaces:
        keep &= _front_facing(safe_cam)
    a, b, x, y, top_left, nondegenerate = _oriented_edges(tri_uv)
    keep &= nondegenerate
    row0, row1, col0, col1 = _pixel_bbox(tri_uv, height, width)
    keep &= (row1 >= row0) & (col1 >= col0)
    ids = keep.nonzero().squeeze(1)
    inv_z = (1.0 / z[ids]).T.contiguous()  # (3, Fk); column k = vertex k
    return _FaceTables(
        face_ids=ids,
        edge_a=a[:, ids].contiguous(),
        edge_b=b[:, ids].contiguous(),
        edge_x=x[:, ids].contiguous(),
        edge_y=y[:, ids].contiguous(),
        edge_tl=top_left[:, ids].contiguous(),
        inv_z=inv_z,
        row0=row0[ids],
        col0=col0[ids],
        nrows=(row1 - row0 + 1)[ids],
        ncols=(col1 - col0 + 1)[ids],
    )


def _make_tiles(tables: _FaceTables, max_pairs: int) -> _PixelTiles:
    """Split each face's pixel box into row bands of at most ``max_pairs`` pixels.

    A band is at least one row, so a single row wider than ``max_pairs`` still forms one
    tile.

    Returns:
        The tiles, ordered by face.
    """
    ncols = tables.ncols
    band_rows = (max_pairs // ncols).clamp_min(1)  # (Fk,)
    nbands = (tables.nrows + band_rows - 1) // band_rows
    face = torch.repeat_interleave(torch.arange(ncols.shape[0], device=ncols.device), nbands)
    first = torch.cumsum(nbands, 0) - nbands
    band = torch.arange(face.shape[0], device=ncols.device) - first[face]
    row0 = tables.row0[face] + band * band_rows[face]
    row_end = tables.row0[face] + tables.nrows[face]
    nrows = torch.minimum(band_rows[face], row_end - row0)
    return _PixelTiles(face=face, row0=row0, col0=tables.col0[face], ncols=ncols[face], count=nrows * ncols[face])


def _chunk_bounds(counts: Tensor, max_pairs: int) -> list[tuple[int, int, int]]:
    """Greedy split of consecutive tiles into chunks of at most ``max_pairs`` pairs.

    Args:
        counts: (T,) int64 pixels per tile.

    Returns:
        ``(start, end, pairs)`` per chunk; a chunk holds at least one tile.
    """
    cum = torch.cumsum(counts.cpu(), 0)
    total = cum.shape[0]
    bounds: list[tuple[int, int, int]] = []
    start = 0
    while start < total:
        before = int(cum[start - 1]) if start > 0 else 0
        end = int(torch.searchsorted(cum, torch.tensor(before + max_pairs), right=True))
        end = max(end, start + 1)
        bounds.append((start, end, int(cum[end - 1]) - before))
        start = end
    return bounds


def _enumerate_pairs(tiles: _PixelTiles, start: int, end: int, pairs: int) -> tuple[Tensor, Tensor, Tensor]:
    """All (face, pixel) candidate pairs of tiles ``start:end``.

    Returns:
        face: (P,) int64 kept-face index.
        row, col: (P,) int64 pixel coordinates.
    """
    counts = tiles.count[start:end]
    device = counts.device
    tile = torch.repeat_interleave(torch.arange(end - start, device=device), counts, output_size=pairs)
    first = torch.cumsum(counts, 0) - counts
    local = torch.arange(pairs, device=device) - first[tile]
    ncols = tiles.ncols[start:end][tile]
    drow = torch.div(local, ncols, rounding_mode="floor")
    row = tiles.row0[start:end][tile] + drow
    col = tiles.col0[start:end][tile] + (local - drow * ncols)
    return tiles.face[start:end][tile], row, col


def _coverage(tables: _FaceTables, face: Tensor, px: Tensor, py: Tensor) -> tuple[Tensor, list[Tensor]]:
    """Inside test of pixel centres against their triangle (top-left tie rule).

    Args:
        face: (P,) kept-face index per pair.
        px, py: (P,) pixel centre coordinates.

    Returns:
        inside: (P,) bool.
        edges: three (P,) oriented edge values (>= 0 inside; proportional to the
            screen-space barycentrics of the opposite vertices).
    """
    inside = torch.ones_like(px, dtype=torch.bool)
    edges = []
    for k in range(3):
        e = tables.edge_a[k][face] * (px - tables.edge_x[k][face]) + tables.edge_b[k][face] * (
            py - tables.edge_y[k][face]
        )
        inside &= torch.where(tables.edge_tl[k][face], e >= 0, e > 0)
        edges.append(e)
    return inside, edges


def _pair_depth(tables: _FaceTables, face: Tensor, edges: list[Tensor]) -> Tensor:
    """Perspective-correct depth of covered pairs.

    ``1/z`` is affine in screen space; it is the mean of the vertices' ``1/z`` weighted by
    the (non-negative) edge values, so it stays within the triangle's range.

    Args:
        face: (P,) kept-face index.
        edges: three (P,) non-negative edge values.

    Returns:
        (P,) depth (+inf where the weights vanish).
    """
    num = sum(e * tables.inv_z[k][face] for k, e in enumerate(edges))
    den = edges[0] + edges[1] + edges[2]
    return torch.where(den > 0, den / num, torch.full_like(den, math.inf))


def _depth_keys(depth: Tensor, face: Tensor) -> Tensor:
    """Pack (depth, face) into int64 keys ordered by depth, then face index.

    Positive float32 bit patterns sort like the floats, so ``min`` over keys gives the
    nearest surface with ties to the lowest face index.

    Args:
        depth: (P,) positive depths.
        face: (P,) int64 kept-face index (< 2^31).

    Returns:
        (P,) int64 keys.
    """
    bits = depth.float().view(torch.int32).to(torch.int64)
    return (bits << 32) | face


def _zbuffer(tables: _FaceTables, height: int, width: int, max_pairs: int) -> Tensor:
    """Z-buffer over all kept faces, processed in chunks of at most ``max_pairs`` pairs.

    Returns:
        (H W,) int64 keys (see :func:`_depth_keys`), ``INT64_MAX`` on background.
    """
    device = tables.row0.device
    dtype = tables.edge_a.dtype
    zkey = torch.full((height * width,), _INT64_MAX, dtype=torch.int64, device=device)
    if tables.face_ids.numel() == 0:
        return zkey
    tiles = _make_tiles(tables, max_pairs)
    for start, end, pairs in _chunk_bounds(tiles.count, max_pairs):
        face, row, col = _enumerate_pairs(tiles, start, end, pairs)
        px = col.to(dtype) + 0.5
        py = row.to(dtype) + 0.5
        inside, edges = _coverage(tables, face, px, py)
        sel = inside.nonzero().squeeze(1)
        face = face[sel]
        depth = _pair_depth(tables, face, [e[sel] for e in edges])
        ok = torch.isfinite(depth) & (depth > 0)
        pix = row[sel] * width + col[sel]
        keys = _depth_keys(depth, face)
        keys = torch.where(ok, keys, torch.full_like(keys, _INT64_MAX))
        zkey.scatter_reduce_(0, pix, keys, reduce="amin", include_self=True)
    return zkey


def _cross2(a: Tensor, b: Tensor) -> Tensor:
    """2D cross product ``a.x b.y - a.y b.x`` of (N, 2) vectors, (N,)."""
    return a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]


def _perspective_barycentrics(pix_uv: Tensor, tri_uv: Tensor, tri_z: Tensor) -> tuple[Tensor, Tensor]:
    """Perspective-correct barycentrics and depth at given pixel centres.

    Args:
        pix_uv: (N, 2) pixel centres.
        tri_uv: (N, 3, 2) projected triangle per pixel.
        tri_z: (N, 3) camera-space z of its vertices.

    Returns:
        bary: (N, 3) non-negative, summing to 1.
        depth: (N,) camera-space z.
    """
    d = tri_uv - pix_uv[:, None, :]  # (N, 3, 2) vertices relative to the pixel centre
    lam = torch.stack([_cross2(d[:, 1], d[:, 2]), _cross2(d[:, 2], d[:, 0]), _cross2(d[:, 0], d[:, 1])], dim=-1)
    lam = lam / lam.sum(dim=-1, keepdim=True)
    lam = lam.clamp_min(0.0)
    lam = lam / lam.sum(dim=-1, keepdim=True).clamp_min(torch.finfo(lam.dtype).tiny)
    w = lam / tri_z
    inv_depth = w.sum(dim=-1, keepdim=True)
    return w / inv_depth, 1.0 / inv_depth.squeeze(-1)


def _resolve_fragments(
    zkey: Tensor, tables: _FaceTables, verts_cam: Tensor, faces: Tensor, K: Tensor, height: int, width: int, chunk: int
) -> Fragments:
    """Decode the z-buffer and compute barycentrics / depth of the visible faces.

    Covered pixels are processed in chunks of ``chunk`` to bound temporary memory.

    Returns:
        Fragments at (H, W).
    """
    dtype, device = verts_cam.dtype, verts_cam.device
    face_idx = torch.full((height * width,), -1, dtype=torch.int64, device=device)
    bary = torch.zeros((height * width, 3), dtype=dtype, device=device)
    depth = torch.full((height * width,), math.inf, dtype=dtype, device=device)
    covered = (zkey != _INT64_MAX).nonzero().squeeze(1)
    for pix in covered.split(chunk):
        fid = tables.face_ids[zkey[pix] & 0xFFFFFFFF]
        tri = verts_cam[faces[fid]]  # (n, 3, 3)
        pix_uv = torch.stack([(pix % width).to(dtype) + 0.5, (pix // width).to(dtype) + 0.5], -1)
        b, z = _perspective_barycentrics(pix_uv, project_points(tri, K), tri[..., 2])
        face_idx[pix] = fid
        bary[pix] = b
        depth[pix] = z
    return Fragments(
        face_idx=face_idx.view(height, width), bary=bary.view(height, width, 3), depth=depth.view(height, width)
    )


def _use_kernels(backend: str, tensors: Sequence[Tensor]) -> bool:
    """Whether the compiled CPU kernels run (see ``backend`` of :func:`rasterize`).

    Raises:
        ValueError: unknown backend, or ``"numba"`` where the kernels cannot run.
    """
    return raster_kernels.use_kernels("backend", backend, tensors, differentiable=False)


def _setup_faces_kernel(
    verts_cam: Tensor, faces: Tensor, K: Tensor, height: int, width: int, near: float, cull_backfaces: bool
) -> _FaceTables:
    """:func:`_setup_faces` by the compiled kernel (bit-identical tables)."""
    dtype, num_f = verts_cam.dtype, faces.shape[0]
    face_ids, row0, col0, nrows, ncols = (torch.empty(num_f, dtype=torch.int64) for _ in range(5))
    a, b, x, y, inv_z = (torch.empty((3, num_f), dtype=dtype) for _ in range(5))
    tl = torch.empty((3, num_f), dtype=torch.bool)
    consts = torch.tensor([0.5, _BBOX_EPS, -1.0, float(max(height, width)) + 1.0], dtype=dtype)
    if cull_backfaces:
        tri_cam = verts_cam.detach()[faces]
        finite = (tri_cam[..., 2] > near).all(dim=1) & torch.isfinite(tri_cam).all(dim=2).all(dim=1)
        front = _front_facing(torch.where(finite[:, None, None], tri_cam, torch.ones_like(tri_cam)))
    else:
        front = torch.ones(num_f, dtype=torch.bool)
    kept = raster_kernels.setup_faces(
        verts_cam.detach().contiguous().numpy(),
        faces.contiguous().numpy(),
        K.detach().contiguous().numpy(),
        height,
        width,
        torch.tensor([near], dtype=dtype).numpy(),
        front.numpy(),
        consts.numpy(),
        face_ids.numpy(),
        a.numpy(),
        b.numpy(),
        x.numpy(),
        y.numpy(),
        tl.numpy(),
        inv_z.numpy(),
        row0.numpy(),
        col0.numpy(),
        nrows.numpy(),
        ncols.numpy(),
    )
    return _FaceTables(  # contiguous copies: one compiled signature per dtype downstream
        face_ids=face_ids[:kept],
        edge_a=a[:, :kept].contiguous(),
        edge_b=b[:, :kept].contiguous(),
        edge_x=x[:, :kept].contiguous(),
        edge_y=y[:, :kept].contiguous(),
        edge_tl=tl[:, :kept].contiguous(),
        inv_z=inv_z[:, :kept].contiguous(),
        row0=row0[:kept],
        col0=col0[:kept],
        nrows=nrows[:kept],
        ncols=ncols[:kept],
    )


def warm_up_kernels() -> None:
    """Compile (or load from numba's cache) the CPU kernels for float32 scenes now, e.g. in a
    parent process before it forks renderers, so that they do not each compile them."""
    if not raster_kernels.AVAILABLE:
        return
    verts = torch.tensor([[-0.1, -0.1, 1.0], [0.1, -0.1, 1.0], [0.0, 0.1, 1.0], [0.0, 0.0, -1.0]])
    faces = torch.tensor([[0, 1, 2], [0, 1, 3]])
    parts = [
        MeshPart(verts, faces, 1, vertex_colors=torch.ones(4, 3)),
        MeshPart(verts, faces, 2, uv=torch.zeros(4, 2), texture=torch.ones(1, 1, 3)),
    ]
    render_meshes(parts, torch.eye(4), intrinsics_from_fov(60.0, 4, 4), 4, 4, backend="numba")


def _zbuffer_kernel(tables: _FaceTables, pxs: Tensor, pys: Tensor) -> Tensor:
    """:func:`_zbuffer` by the compiled kernel (bit-identical keys); ``pxs`` (W,), ``pys`` (H,)
    are the pixel centres (:func:`~hogsa_loader.render.raster_kernels.pixel_centres`)."""
    height, width = pys.shape[0], pxs.shape[0]
    zkey = torch.full((height * width,), _INT64_MAX, dtype=torch.int64)
    if tables.face_ids.numel() == 0:
        return zkey
    raster_kernels.zbuffer(
        tables.edge_a.numpy(),
        tables.edge_b.numpy(),
        tables.edge_x.numpy(),
        tables.edge_y.numpy(),
        tables.edge_tl.numpy(),
        tables.inv_z.numpy(),
        tables.row0.numpy(),
        tables.col0.numpy(),
        tables.nrows.numpy(),
        tables.ncols.numpy(),
        pxs.numpy(),
        pys.numpy(),
        width,
        zkey.numpy(),
    )
    return zkey


def _resolve_kernel(
    zkey: Tensor, tables: _FaceTables, verts_cam: Tensor, faces: Tensor, K: Tensor, pxs: Tensor, pys: Tensor
) -> Fragments:
    """:func:`_resolve_fragments` by the compiled kernel (bit-identical fragments)."""
    dtype = verts_cam.dtype
    height, width = pys.shape[0], pxs.shape[0]
    face_idx = torch.empty((height * width,), dtype=torch.int64)
    bary = torch.empty((height * width, 3), dtype=dtype)
    depth = torch.empty((height * width,), dtype=dtype)
    consts = torch.tensor([torch.finfo(dtype).tiny, 1.0], dtype=dtype)
    raster_kernels.resolve(
        zkey.numpy(),
        tables.face_ids.numpy(),
        verts_cam.detach().contiguous().numpy(),
        faces.contiguous().numpy(),
        K.detach().contiguous().numpy(),
        pxs.numpy(),
        pys.numpy(),
        width,
        consts.numpy(),
        face_idx.numpy(),
        bary.numpy(),
        depth.numpy(),
    )
    return Fragments(
        face_idx=face_idx.view(height, width), bary=bary.view(height, width, 3), depth=depth.view(height, width)
    )


def rasterize(
    verts_cam: Tensor,
    faces: Tensor,
    K: Tensor,
    height: int,
    width: int,
    near: float = 1e-3,
    cull_backfaces: bool = False,
    max_pairs: int = 4_000_000,
    backend: Backend = "auto",
) -> Fragments:
    """Rasterise a camera-space triangle mesh with a z-buffer.

    Notation: V vertices, F faces, H x W image, N covered pixels, P triangle-pixel pairs.

    Conventions (shared by both backends and by :func:`render_meshes`):

    * Camera: OpenCV. ``p_cam = R @ p_world + t`` with ``world2cam = [[R, t], [0, 1]]`` (4, 4);
      x right, y down, z forward (metres).
    * Projection: pinhole with the full intrinsics ``K = [[fx, s, cx], [0, fy, cy], [0, 0, 1]]``
      (skew ``s`` allowed): ``u = fx x/z + s y/z + cx``, ``v = fy y/z + cy``.
    * Pixels: pixel (row i, col j) has its centre at ``(u, v) = (j + 0.5, i + 0.5)``; the image
      spans ``[0, W] x [0, H]`` in continuous coordinates.
    * Coverage: a pixel is covered by a triangle when its centre is inside the projected
      triangle. Centres exactly on an edge follow the top-left rule (in the y-down image:
      the pixel belongs to the triangle lying to the right of the edge, or below it for a
      horizontal edge), evaluated on canonically ordered edges so that the two triangles
      sharing an edge see bit-identical edge functions: a mesh has no cracks and no pixel
      drawn twice, whatever the winding of its triangles.
    * Near plane: a triangle with any vertex at ``z <= near`` is dropped entirely (no
      clipping). Degenerate (zero screen area) and non-finite triangles are dropped too.
    * Culling: off by default. With ``cull_backfaces`` a triangle is drawn only when it is
      counter-clockwise seen from the camera, i.e. ``cross(v1 - v0, v2 - v0)`` points toward
      the camera (OpenGL's front face).
    * Barycentrics are perspective correct: ``bary`` interpolates camera-space attributes, and
      ``depth`` is the camera-space z (metres) of the visible surface, ``+inf`` on background.
    * Z-buffer: the nearest surface wins; exact ties go to the lowest face index (depths are
      compared at float32 precision, also for float64 input).

    Args:
        verts_cam: (V, 3) camera-space vertices (float32 or float64; sets the dtype).
        faces: (F, 3) integer vertex indices.
        K: (3, 3) intrinsics.
        height, width: image size in pixels.
        near: triangles with any vertex at ``z <= near`` are dropped.
        cull_backfaces: drop triangles that are clockwise seen from the camera.
        max_pairs: triangle-pixel candidate pairs evaluated per chunk (memory bound;
            a single bounding-box row wider than this is still one chunk) by the
            vectorised PyTorch path.
        backend: ``"torch"``, the vectorised PyTorch path (any device, differentiable
            barycentrics); ``"numba"``, compiled CPU kernels that loop over pixels
            (bit-identical fragments, tens of times faster on CPU); ``"auto"``, numba
            when it is installed, the tensors are float32/float64 on the CPU and no input
            requires grad, else torch.

    Returns:
        Fragments with face_idx (H, W), bary (H, W, 3) and depth (H, W).
    """
    _check_raster_inputs(verts_cam, faces, K, height, width, near, max_pairs)
    K = K.to(verts_cam)
    faces = faces.to(device=verts_cam.device, dtype=torch.int64)
    if _use_kernels(backend, (verts_cam, K)):
        tables = _setup_faces_kernel(verts_cam, faces, K, height, width, near, cull_backfaces)
        pxs, pys = (raster_kernels.pixel_centres(n, verts_cam.dtype) for n in (width, height))
        return _resolve_kernel(_zbuffer_kernel(tables, pxs, pys), tables, verts_cam, faces, K, pxs, pys)
    tables = _setup_faces(verts_cam, faces, K, height, width, near, cull_backfaces)
    zkey = _zbuffer(tables, height, width, max_pairs)
    return _resolve_fragments(zkey, tables, verts_cam, faces, K, height, width, chunk=max(max_pairs // 4, 1))


# --------------------------------------------------------------------------------------
# Shading and rendering
# --------------------------------------------------------------------------------------


def _validate_part(part: MeshPart, name: str) -> None:
    """Raise ValueError when a MeshPart is malformed; converts a uint8 texture in place."""
    verts = part.verts
    if not isinstance(verts, Tensor) or verts.ndim != 2 or verts.shape[1] != 3:
        raise ValueError(f"{name}.verts must be a (V, 3) tensor, got {_shape(verts)}")
    if not verts.is_floating_point():
        raise ValueError(f"{name}.verts must be floating point, got {verts.dtype}")
    num_verts = verts.shape[0]
    _check_faces(part.faces, num_verts, f"{name}.faces")
    if isinstance(part.part_id, bool) or not hasattr(part.part_id, "__index__") or operator.index(part.part_id) < 1:
        raise ValueError(f"{name}.part_id must be an int >= 1 (0 is background), got {part.part_id!r}")
    has_vc = part.vertex_colors is not None
    has_uv, has_tex = part.uv is not None, part.texture is not None
    if has_vc and (has_uv or has_tex):
        raise ValueError(f"{name}: give either vertex_colors or uv + texture, not both")
    if not has_vc and not (has_uv and has_tex):
        if has_uv or has_tex:
            missing = "texture" if has_uv else "uv"
            raise ValueError(f"{name}: uv and texture go together, {missing} is missing")
        raise ValueError(f"{name}: no colour source, give vertex_colors or uv + texture")
    if has_vc:
        vc = part.vertex_colors
        if not isinstance(vc, Tensor) or vc.shape != (num_verts, 3):
            raise ValueError(f"{name}.vertex_colors must be ({num_verts}, 3), got {_shape(vc)}")
        if not vc.is_floating_point():
            raise ValueError(f"{name}.vertex_colors must be float in [0, 1], got {vc.dtype}")
        return
    if not isinstance(part.uv, Tensor) or part.uv.shape != (num_verts, 2):
        raise ValueError(f"{name}.uv must be ({num_verts}, 2), got {_shape(part.uv)}")
    tex = part.texture
    if not isinstance(tex, Tensor) or tex.ndim != 3 or tex.shape[2] != 3 or tex.shape[0] < 1 or tex.shape[1] < 1:
        raise ValueError(f"{name}.texture must be a (Ht, Wt, 3) tensor, got {_shape(tex)}")
    if tex.dtype == torch.uint8:
        part.texture = tex.float() / 255.0


def _check_render_inputs(
    parts: Sequence[MeshPart], world2cam: Tensor, K: Tensor, height: int, width: int, supersample: int
) -> None:
    """Raise ValueError with a clear message on malformed :func:`render_meshes` inputs."""
    if len(parts) == 0:
        raise ValueError("render_meshes needs at least one MeshPart")
    for i, part in enumerate(parts):
        if not isinstance(part, MeshPart):
            raise ValueError(f"parts[{i}] must be a MeshPart, got {type(part).__name__}")
        _validate_part(part, name=f"parts[{i}]")
    if not isinstance(world2cam, Tensor) or world2cam.shape != (4, 4):
        raise ValueError(f"world2cam must be a (4, 4) tensor, got {_shape(world2cam)}")
    _check_K(K)
    for name, val in (("height", height), ("width", width), ("supersample", supersample)):
        if not isinstance(val, int) or isinstance(val, bool) or val < 1:
            raise ValueError(f"{name} must be a positive int, got {val!r}")


@dataclass
class _Scene:
    """All parts concatenated into one mesh.

    Attributes:
        verts: (V, 3) world vertices.
        faces: (F, 3) int64 faces into ``verts``.
        face_part: (F,) int64 index of the part each face belongs to.
        vert_start: python list of the num_parts + 1 vertex offsets of the parts.
    """

    verts: Tensor
    faces: Tensor
    face_part: Tensor
    vert_start: list[int] = field(default_factory=list)


def _concat_parts(parts: Sequence[MeshPart], dtype: torch.dtype, device: torch.device) -> _Scene:
    """Concatenate parts into one mesh with offset faces."""
    verts, faces, face_part = [], [], []
    vert_start = [0]
    for i, part in enumerate(parts):
        verts.append(part.verts.to(device=device, dtype=dtype))
        faces.append(part.faces.to(device=device, dtype=torch.int64) + vert_start[-1])
        face_part.append(torch.full((part.faces.shape[0],), i, dtype=torch.int64, device=device))
        vert_start.append(vert_start[-1] + part.verts.shape[0])
    return _Scene(verts=torch.cat(verts), faces=torch.cat(faces), face_part=torch.cat(face_part), vert_start=vert_start)


def _albedo(parts: Sequence[MeshPart], scene: _Scene, face: Tensor, bary: Tensor) -> Tensor:
    """Surface colour of each covered sample, from vertex colours or textures.

    Args:
        face: (N,) int64 visible face per sample.
        bary: (N, 3) barycentrics.

    Returns:
        (N, 3).
    """
    albedo = torch.zeros((face.shape[0], 3), dtype=bary.dtype, device=bary.device)
    part_of = scene.face_part[face]
    for i, part in enumerate(parts):
        sel = (part_of == i).nonzero().squeeze(1)
        if sel.numel() == 0:
            continue
        tri = scene.faces[face[sel]] - scene.vert_start[i]  # (n, 3) local vertex ids
        if part.vertex_colors is not None:
            vc = part.vertex_colors.to(bary)
            albedo[sel] = _interpolate(vc, tri, bary[sel])
        else:
            uv = _interpolate(part.uv.to(bary), tri, bary[sel])
            albedo[sel] = sample_texture(part.texture, uv)
    return albedo


def _shading_normals(
    unit_fn: Tensor, vert_n: Tensor | None, faces: Tensor, face: Tensor, bary: Tensor, points: Tensor
) -> Tensor:
    """Unit camera-space shading normals facing the camera (two-sided lighting).

    The normal is flipped where the triangle's geometric normal faces away from the
    camera. Smooth normals interpolate the vertex normals (face normal where they cancel
    out); without vertex normals the flat face normal is used.

    Args:
        unit_fn: (F, 3) unit camera-space face normals.
        vert_n: (V, 3) unit camera-space vertex normals, or None for flat shading.
        faces: (F, 3) int64.
        face: (N,) visible face per sample.
        bary: (N, 3) barycentrics.
        points: (N, 3) camera-space surface points.

    Returns:
        (N, 3).
    """
    fn = unit_fn[face]
    facing = torch.where((fn * points).sum(-1, keepdim=True) > 0, -1.0, 1.0).to(fn)
    if vert_n is None:
        return fn * facing
    n = _interpolate(vert_n, faces[face], bary)
    norm = n.norm(dim=-1, keepdim=True)
    n = torch.where(norm > 1e-6, n / norm.clamp_min(1e-6), fn)
    return n * facing


def _to_light(light: Light, dtype: torch.dtype, device: torch.device | str = "cpu") -> Tensor:
    """(3,) unit vector toward the light (``-direction``, normalised)."""
    direction = torch.tensor(light.direction, dtype=dtype, device=device)
    if direction.norm() == 0:
        raise ValueError("Light.direction must be non-zero")
    return -direction / direction.norm()


def shade_blinn_phong(albedo: Tensor, normal: Tensor, points: Tensor, light: Light) -> Tensor:
    """Ambient + Lambert + Blinn-Phong shading (see :class:`Light`).

    Args:
        albedo: (N, 3) surface colours in [0, 1].
        normal: (N, 3) unit camera-space normals.
        points: (N, 3) camera-space surface points (the camera is at the origin).
        light: the light.

    Returns:
        (N, 3) colours clamped to [0, 1].
    """
    to_light = _to_light(light, albedo.dtype, albedo.device)
    view = normalize(-points)
    n_dot_l = (normal * to_light).sum(-1).clamp_min(0.0)
    half = normalize(to_light + view)
    n_dot_h = (normal * half).sum(-1).clamp_min(0.0)
    spec = torch.where(n_dot_l > 0, n_dot_h.pow(light.shininess), torch.zeros_like(n_dot_h))
    rgb = albedo * (light.ambient + light.diffuse * n_dot_l)[:, None] + light.specular * spec[:, None]
    return rgb.clamp(0.0, 1.0)


def _background(
    background: tuple[float, float, float] | Tensor, height: int, width: int, dtype: torch.dtype, device: torch.device
) -> Tensor:
    """Background as a (3,) colour or (H, W, 3) image tensor."""
    bg = torch.as_tensor(background, dtype=dtype, device=device)
    if bg.shape != (3,) and bg.shape != (height, width, 3):
        raise ValueError(
            f"background must be an RGB triple or a ({height}, {width}, 3) image, got shape {tuple(bg.shape)}"
        )
    return bg


def _downsample(
    color: Tensor, coverage: Tensor, depth: Tensor, part_id: Tensor, normal: Tensor, s: int
) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """Reduce supersampled buffers over s x s blocks.

    Args:
        color: (sH, sW, 3) premultiplied colour (0 on background samples).
        coverage: (sH, sW) 0/1.
        depth: (sH, sW), +inf on background.
        part_id: (sH, sW) int64.
        normal: (sH, sW, 3).

    Returns:
        Premultiplied rgb (H, W, 3) and alpha (H, W) (block means), depth (H, W) (block
        min), part_id (H, W) and normal (H, W, 3) of the block's nearest sample.
    """
    if s == 1:
        return color, coverage, depth, part_id, normal
    rgb = F_nn.avg_pool2d(color.permute(2, 0, 1)[None], s)[0].permute(1, 2, 0)
    alpha = F_nn.avg_pool2d(coverage[None, None], s)[0, 0]
    neg, idx = F_nn.max_pool2d(-depth[None, None], s, return_indices=True)
    idx = idx[0, 0]
    h, w = idx.shape
    pid = part_id.reshape(-1)[idx.reshape(-1)].view(h, w)
    nrm = normal.reshape(-1, 3)[idx.reshape(-1)].view(h, w, 3)
    return rgb, alpha, -neg[0, 0], pid, nrm


def _shade_samples(
    parts: Sequence[MeshPart],
    scene: _Scene,
    verts_cam: Tensor,
    frags: Fragments,
    light: Light,
    smooth_normals: bool,
    chunk: int,
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Shade every covered sample, ``chunk`` samples at a time (bounded memory).

    Args:
        verts_cam: (V, 3) camera-space vertices of the concatenated scene.
        frags: fragments at the sampling resolution (sH, sW).

    Returns:
        colour (sH, sW, 3) (0 on background), normal (sH, sW, 3), part id (sH, sW) int64
        and coverage (sH, sW) in {0, 1}.
    """
    sh, sw = frags.face_idx.shape
    dtype, device = verts_cam.dtype, verts_cam.device
    unit_fn = normalize(face_normals(verts_cam, scene.faces))
    vert_n = vertex_normals(verts_cam, scene.faces) if smooth_normals else None
    part_ids = torch.tensor([operator.index(p.part_id) for p in parts], dtype=torch.int64, device=device)
    color = torch.zeros((sh * sw, 3), dtype=dtype, device=device)
    normal = torch.zeros((sh * sw, 3), dtype=dtype, device=device)
    pid = torch.zeros((sh * sw,), dtype=torch.int64, device=device)
    flat_face = frags.face_idx.reshape(-1)
    flat_bary = frags.bary.reshape(-1, 3)
    for pix in (flat_face >= 0).nonzero().squeeze(1).split(chunk):
        face = flat_face[pix]
        bary = flat_bary[pix]
        points = _interpolate(verts_cam, scene.faces[face], bary)
        n = _shading_normals(unit_fn, vert_n, scene.faces, face, bary, points)
        albedo = _albedo(parts, scene, face, bary)
        color[pix] = shade_blinn_phong(albedo, n, points, light)
        normal[pix] = n
        pid[pix] = part_ids[scene.face_part[face]]
    coverage = (flat_face >= 0).to(dtype)
    return (color.view(sh, sw, 3), normal.view(sh, sw, 3), pid.view(sh, sw), coverage.view(sh, sw))


def _shade_kernel(
    parts: Sequence[MeshPart], scene: _Scene, verts_cam: Tensor, frags: Fragments, light: Light, smooth_normals: bool
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """:func:`_shade_samples` by the compiled kernel (colours within a few float ulps)."""
    sh, sw = frags.face_idx.shape
    dtype = verts_cam.dtype
    to_light = _to_light(light, dtype)
    num_v = scene.verts.shape[0]
    colors = torch.zeros((num_v, 3), dtype=dtype)
    uv = torch.zeros((num_v, 2), dtype=dtype)
    part_tex = torch.full((len(parts),), -1, dtype=torch.int64)
    textures, tex_off, tex_h, tex_w, offset = [], [], [], [], 0
    slots: dict[int, int] = {}  # parts sharing one texture tensor share its slot
    for i, part in enumerate(parts):
        lo, hi = scene.vert_start[i], scene.vert_start[i + 1]
        if part.vertex_colors is not None:
            colors[lo:hi] = part.vertex_colors.to(dtype)
            continue
        uv[lo:hi] = part.uv.to(dtype)
        if id(part.texture) not in slots:
            tex = part.texture.to(dtype).contiguous()
            slots[id(part.texture)] = len(textures)
            textures.append(tex.reshape(-1))
            tex_off.append(offset)
            tex_h.append(tex.shape[0])
            tex_w.append(tex.shape[1])
            offset += tex.numel()
        part_tex[i] = slots[id(part.texture)]
    if not textures:
        flat_tex = torch.zeros(1, dtype=dtype)
    else:
        flat_tex = textures[0] if len(textures) == 1 else torch.cat(textures)
    tex_hw = torch.tensor([[h, w] for h, w in zip(tex_h, tex_w, strict=True)] or [[1, 1]], dtype=dtype)
    light_vec = torch.cat(
        [
            to_light,
            torch.tensor(
                [light.ambient, light.diffuse, light.specular, light.shininess, 1e-6, NORMAL_EPS], dtype=dtype
            ),
        ]
    )
    unit_fn = normalize(face_normals(verts_cam, scene.faces))
    vert_n = vertex_normals(verts_cam, scene.faces) if smooth_normals else unit_fn[:1]
    part_ids = torch.tensor([operator.index(p.part_id) for p in parts], dtype=torch.int64)
    color = torch.empty((sh * sw, 3), dtype=dtype)
    normal = torch.empty((sh * sw, 3), dtype=dtype)
    pid = torch.empty((sh * sw,), dtype=torch.int64)
    flat_face = frags.face_idx.reshape(-1).contiguous()
    raster_kernels.shade(
        flat_face.numpy(),
        frags.bary.reshape(-1, 3).contiguous().numpy(),
        verts_cam.detach().contiguous().numpy(),
        scene.faces.contiguous().numpy(),
        unit_fn.detach().contiguous().numpy(),
        vert_n.detach().contiguous().numpy(),
        bool(smooth_normals),
        scene.face_part.numpy(),
        part_ids.numpy(),
        part_tex.numpy(),
        colors.numpy(),
        uv.numpy(),
        flat_tex.numpy(),
        torch.tensor(tex_off or [0], dtype=torch.int64).numpy(),
        torch.tensor(tex_h or [1], dtype=torch.int64).numpy(),
        torch.tensor(tex_w or [1], dtype=torch.int64).numpy(),
        tex_hw.numpy(),
        light_vec.numpy(),
        torch.ones(1, dtype=dtype).numpy(),
        color.numpy(),
        normal.numpy(),
        pid.numpy(),
    )
    coverage = (flat_face >= 0).to(dtype)
    return (color.view(sh, sw, 3), normal.view(sh, sw, 3), pid.view(sh, sw), coverage.view(sh, sw))


def render_meshes(
    parts: Sequence[MeshPart],
    world2cam: Tensor,
    K: Tensor,
    height: int,
    width: int,
    light: Light = Light(),
    background: tuple[float, float, float] | Tensor = (0.0, 0.0, 0.0),
    supersample: int = 1,
    near: float = 1e-3,
    smooth_normals: bool = True,
    backend: Backend = "auto",
) -> MeshRender:
    """Render shaded, coloured / textured meshes.

    The parts are concatenated and rasterised once (no back-face culling), colours come
    from interpolated vertex colours or bilinear texture lookups, normals are flipped to
    face the camera, shading is ambient + Lambert + Blinn-Phong, and the result is
    composited over the background with the (supersampled) coverage.

    Args:
        parts: the meshes (world coordinates); dtype and device follow ``parts[0].verts``.
        world2cam: (4, 4) OpenCV world-to-camera matrix.
        K: (3, 3) intrinsics for the (height, width) output image.
        height, width: output size.
        light: directional light in camera coordinates.
        background: RGB triple, (3,) tensor or (H, W, 3) image in [0, 1].
        supersample: s >= 1; rasterise at (s H, s W) and reduce (see below).
        near: near plane (triangles with a vertex at ``z <= near`` are dropped).
        smooth_normals: interpolate vertex normals (else flat face normals).
        backend: as in :func:`rasterize`; the compiled shading agrees with the PyTorch
            path to a few float ulps (``pow`` and the bilinear texture filter round
            differently), coverage, depth and part ids exactly.

    Returns:
        MeshRender at (height, width).

    Conventions besides those of :func:`rasterize`:

    * Textures: OBJ convention, ``uv = (0, 0)`` is the bottom-left corner of the texture image,
      sampled bilinearly (``grid_sample``, ``align_corners=False``); coordinates outside
      ``[0, 1]`` are clamped to the border.
    * Supersampling by ``s``: the image is rasterised at ``(s H, s W)`` with
      ``K' = diag(s, s, 1) @ K`` (so ``u' = s u``: a point lands in the same place in
      continuous image coordinates) and reduced over ``s x s`` blocks: ``rgb`` and ``alpha``
      are averaged; ``depth``, ``part_id`` and ``normal`` come from the block's nearest sample
      (first in raster order on exact ties, deterministic on CPU).
    """
    _check_render_inputs(parts, world2cam, K, height, width, supersample)
    dtype, device = parts[0].verts.dtype, parts[0].verts.device
    bg = _background(background, height, width, dtype, device)
    scene = _concat_parts(parts, dtype, device)
    verts_cam = transform_points(scene.verts, world2cam.to(device=device, dtype=dtype))
    s = supersample
    sh, sw = s * height, s * width
    Ks = scale_intrinsics(K.to(device, dtype), s)
    kernels = _use_kernels(
        backend, [verts_cam, Ks] + [t for p in parts for t in (p.vertex_colors, p.uv, p.texture) if t is not None]
    )
    frags = rasterize(verts_cam, scene.faces, Ks, sh, sw, near=near, backend="numba" if kernels else "torch")
    if kernels:
        color_s, normal_s, pid_s, cov_s = _shade_kernel(parts, scene, verts_cam, frags, light, smooth_normals)
    else:
        color_s, normal_s, pid_s, cov_s = _shade_samples(
            parts, scene, verts_cam, frags, light, smooth_normals, _SHADE_CHUNK
        )
    rgb, alpha, depth, part_id, nrm = _downsample(color_s, cov_s, frags.depth, pid_s, normal_s, s)
    rgb = (rgb + (1.0 - alpha)[..., None] * bg).clamp(0.0, 1.0)
    return MeshRender(rgb=rgb, alpha=alpha, depth=depth, part_id=part_id, normal=nrm)


# --------------------------------------------------------------------------------------
# Cameras and output
# --------------------------------------------------------------------------------------


def _as_vec3(x: Sequence[float] | Tensor, name: str, dtype: torch.dtype) -> Tensor:
    """A (3,) CPU tensor of the given dtype from a sequence or tensor."""
    t = torch.as_tensor(x, dtype=dtype).detach().cpu() if isinstance(x, Tensor) else torch.tensor(x, dtype=dtype)
    if t.shape != (3,):
        raise ValueError(f"{name} must have 3 components, got shape {tuple(t.shape)}")
    return t


def camera_look_at(
    eye: Sequence[float] | Tensor, target: Sequence[float] | Tensor, up: Sequence[float] | Tensor = (0.0, 1.0, 0.0)
) -> Tensor:
    """OpenCV world-to-camera matrix of a camera at ``eye`` looking at ``target``.

    The camera z axis points from eye to target, y points along ``-up`` (projected
    orthogonal to z), so ``up`` appears toward the top of the image (image -v); x = y x z.

    Args:
        eye, target, up: (3,) world vectors.

    Returns:
        (4, 4) world2cam, float32 (the dtype of ``eye`` when it is a floating tensor).
    """
    out_dtype = eye.dtype if isinstance(eye, Tensor) and eye.is_floating_point() else torch.float32
    e = _as_vec3(eye, "eye", torch.float64)
    t = _as_vec3(target, "target", torch.float64)
    u = _as_vec3(up, "up", torch.float64)
    z = t - e
    if z.norm() < 1e-12:
        raise ValueError("camera_look_at: eye and target coincide")
    z = z / z.norm()
    if u.norm() < 1e-300 or (u - (u @ z) * z).norm() < LOOK_AT_PARALLEL * u.norm():
        raise ValueError("camera_look_at: up is parallel to the viewing direction")
    return torch.from_numpy(look_at(e.numpy(), t.numpy(), (u / u.norm()).numpy())[0]).to(out_dtype)


def intrinsics_from_fov(fov_y_deg: float, width: int, height: int, dtype: torch.dtype = torch.float32) -> Tensor:
    """Pinhole intrinsics with square pixels and the principal point at the image centre.

    Args:
        fov_y_deg: vertical field of view in degrees, in (0, 180).
        width, height: image size in pixels.

    Returns:
        (3, 3) K with ``fy = fx = (H / 2) / tan(fov_y / 2)``, ``cx = W / 2``, ``cy = H / 2``.
    """
    if not 0.0 < fov_y_deg < 180.0:
        raise ValueError(f"fov_y_deg must be in (0, 180), got {fov_y_deg!r}")
    if width < 1 or height < 1:
        raise ValueError(f"width and height must be positive, got {width}x{height}")
    f = 0.5 * height / math.tan(math.radians(fov_y_deg) / 2.0)
    return torch.tensor([[f, 0.0, width / 2.0], [0.0, f, height / 2.0], [0.0, 0.0, 1.0]], dtype=dtype)


def save_png(path: str | os.PathLike[str], rgb_or_rgba: Tensor) -> None:
    """Write an RGB(A) image as an 8-bit PNG (parent folders are created).

    Args:
        path: output file.
        rgb_or_rgba: (H, W, 3), (H, W, 4) or (H, W); float in [0, 1] (clamped, rounded)
            or uint8.
    """
    img = rgb_or_rgba
    ok = isinstance(img, Tensor) and (img.ndim == 2 or (img.ndim == 3 and img.shape[2] in (3, 4)))
    if not ok:
        raise ValueError(f"image must be (H, W), (H, W, 3) or (H, W, 4), got {_shape(img)}")
    img = img.detach().cpu()
    if img.dtype != torch.uint8:
        img = (img.float().clamp(0.0, 1.0) * 255.0).round().to(torch.uint8)
    arr = np.ascontiguousarray(img.numpy())
    if arr.ndim == 3:
        code = cv2.COLOR_RGB2BGR if arr.shape[2] == 3 else cv2.COLOR_RGBA2BGRA
        arr = cv2.cvtColor(arr, code)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(path), arr):
        raise OSError(f"{path}: cv2.imwrite failed")


# --------------------------------------------------------------------------------------
# Timing
# --------------------------------------------------------------------------------------


def _timing_demo(repeats: int = 5) -> None:
    """Render a textured icosphere (20480 faces) at 1000 x 1000 and print the time."""
    import trimesh  # deferred: slow to import, and only this timing demo uses it

    sphere = trimesh.creation.icosphere(subdivisions=5, radius=1.0)
    verts = torch.tensor(sphere.vertices, dtype=torch.float32)
    faces = torch.tensor(sphere.faces, dtype=torch.int64)
    uv = torch.stack(
        [
            0.5 + torch.atan2(verts[:, 0], verts[:, 2]) / (2 * math.pi),
            0.5 + torch.asin(verts[:, 1].clamp(-1, 1)) / math.pi,
        ],
        dim=-1,
    )
    ii, jj = torch.meshgrid(torch.arange(512), torch.arange(1024), indexing="ij")
    checker = ((ii // 32 + jj // 32) % 2).float()
    texture = torch.stack([checker, 0.5 * checker + 0.25, 1.0 - checker], dim=-1)
    part = MeshPart(verts=verts, faces=faces, part_id=1, uv=uv, texture=texture)
    K = intrinsics_from_fov(40.0, 1000, 1000)
    w2c = camera_look_at((0.0, 0.5, 3.0), (0.0, 0.0, 0.0), (0.0, 1.0, 0.0))
    out = render_meshes([part], w2c, K, 1000, 1000)  # warm-up
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = render_meshes([part], w2c, K, 1000, 1000)
        times.append((time.perf_counter() - t0) * 1e3)
    print(
        f"render_meshes icosphere(5) {faces.shape[0]} faces textured 1000x1000 "
        f"(threads={torch.get_num_threads()}): median {sorted(times)[len(times) // 2]:.0f} ms, "
        f"min {min(times):.0f} ms, coverage {out.alpha.mean().item():.2f}"
    )


if __name__ == "__main__":
    _timing_demo()
