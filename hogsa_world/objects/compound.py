"""Parts built from several closed pieces: rounded boxes and surfaces of revolution.

A piece is one closed, outward-oriented mesh with its texture charts and the painters of
those charts; a part is the union of its pieces (concatenated, not welded: pieces may
overlap, each stays a closed solid). Rounded boxes come from
:func:`hogsa_world.objects.procedural.rounded_box` (six charts ``"+x"`` ...); a lathe
(:func:`lathe`) revolves a profile about a coordinate axis and is one chart ``"side"``
(u around the axis, v along the profile).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Mapping, Optional, Sequence

import numpy as np

from hogsa_world.objects.procedural import Painter, PartMesh, rounded_box

__all__ = ["Piece", "CompoundSpec", "box_piece", "lathe", "disc_profile", "merge_pieces"]


@dataclass
class Piece:
    """One closed component of a part.

    Attributes:
        mesh: its welded mesh and charts (mm).
        painters: chart key -> painter.
        default: painter of the charts not in ``painters``.
    """

    mesh: PartMesh
    default: Painter
    painters: Mapping[str, Painter] = field(default_factory=dict)


@dataclass
class CompoundSpec:
    """An object whose parts are lists of pieces.

    Attributes:
        name: ARCTIC object name.
        parts: ``{TOP: [...], BOTTOM: [...]}``.
    """

    name: str
    parts: dict[int, list[Piece]]


def box_piece(
    lo: Sequence[float],
    hi: Sequence[float],
    radius: float,
    default: Painter,
    painters: Optional[Mapping[str, Painter]] = None,
    spacing: float = 6.0,
    band: int = 2,
    up: Optional[dict[str, str]] = None,
) -> Piece:
    """A rounded box piece (see :func:`~hogsa_world.objects.procedural.rounded_box`)."""
    return Piece(rounded_box(lo, hi, radius, spacing, band, up=up), default, dict(painters or {}))


def disc_profile(radius: float, h0: float, h1: float, edge: float, rings: int = 6, edge_steps: int = 3) -> np.ndarray:
    """Profile of a flat cylinder with rounded rims, from the pole at ``h0`` to the one at ``h1``.

    Args:
        radius: outer radius; h0, h1: heights of the two flat faces (h0 < h1).
        edge: rim rounding radius (clamped to half the height and to the radius).
        rings: samples on each flat face between the pole and the rim.
        edge_steps: samples on each rounded rim.

    Returns:
        (n, 2) ``(r, h)`` points, radius 0 at both ends.
    """
    e = min(edge, 0.5 * (h1 - h0) - 1e-6, radius - 1e-6)
    flat = np.linspace(0.0, radius - e, rings + 1)
    ang = np.linspace(0.0, 0.5 * math.pi, edge_steps + 2)[1:-1]
    low_rim = np.stack([radius - e + e * np.sin(ang), h0 + e - e * np.cos(ang)], 1)
    high_rim = np.stack([radius - e + e * np.cos(ang), h1 - e + e * np.sin(ang)], 1)
    side = np.array([[radius, h0 + e], [radius, h1 - e]])
    return np.concatenate(
        [
            np.stack([flat, np.full_like(flat, h0)], 1),
            low_rim,
            side,
            high_rim,
            np.stack([flat[::-1], np.full_like(flat, h1)], 1),
        ]
    )


def _lathe_ids(segments: int, rows: int, radii: np.ndarray, loop: bool) -> np.ndarray:
    """(segments + 1, rows) welded vertex id of every chart grid point.

    The seam column wraps to column 0; a pole row (radius 0) is one vertex; with ``loop``
    the last row wraps to row 0.
    """
    ids = np.empty((segments + 1, rows), dtype=np.int64)
    nxt = 0
    for j in range(rows):
        if loop and j == rows - 1:
            ids[:, j] = ids[:, 0]
        elif radii[j] <= 0.0:
            ids[:, j] = nxt
            nxt += 1
        else:
            ids[:segments, j] = nxt + np.arange(segments)
            ids[segments, j] = nxt
            nxt += segments
    return ids


def _lathe_grid(
    prof: np.ndarray, axis: int, centre: Sequence[float], scale: Sequence[float], segments: int
) -> np.ndarray:
    """Points of the profile swept around the axis (see :func:`lathe`).

    Args:
        prof: (rows, 2) ``(r, h)`` samples.
        axis, centre, scale, segments: as in :func:`lathe`.

    Returns:
        (segments + 1, rows, 3) points (mm); the last angle repeats the first exactly.
    """
    a, b, c = axis, (axis + 1) % 3, (axis + 2) % 3
    phi = 2.0 * math.pi * np.arange(segments + 1) / segments
    cos, sin = np.cos(phi), np.sin(phi)
    cos[-1], sin[-1] = 1.0, 0.0
    grid = np.zeros((segments + 1, prof.shape[0], 3))
    grid[..., a] = prof[None, :, 1]
    grid[..., b] = scale[0] * cos[:, None] * prof[None, :, 0]
    grid[..., c] = scale[1] * sin[:, None] * prof[None, :, 0]
    grid += np.asarray(centre, dtype=np.float64)
    return grid


def lathe(
    profile: np.ndarray,
    axis: int = 1,
    centre: Sequence[float] = (0.0, 0.0, 0.0),
    scale: Sequence[float] = (1.0, 1.0),
    segments: int = 32,
    loop: bool = False,
    key: str = "side",
) -> PartMesh:
    """Closed surface of revolution about a coordinate axis through ``centre``.

    The point ``(r, h)`` of the profile at angle φ is
    ``centre + h e_a + r (scale[0] cos φ e_b + scale[1] sin φ e_c)`` with ``a = axis``,
    ``b = a + 1``, ``c = a + 2`` (mod 3). Normals point outward when the profile runs from
    the low pole up the outside (or, with ``loop``, counter-clockwise in the (r, h) plane).

    Args:
        profile: (n, 2) ``(r, h)`` samples; without ``loop`` the first and last have r = 0
            (poles); with ``loop`` it is a closed curve (first point not repeated).
        axis: 0, 1 or 2.
        centre: (3,) a point of the axis (mm).
        scale: radial scale along ``e_b`` and ``e_c`` (oval cross-sections).
        segments: samples around the axis.
        loop: the profile is closed (a ring); otherwise it ends on the axis.
        key: the chart's name.

    Returns:
        the welded mesh and its single chart.
    """
    prof = np.asarray(profile, dtype=np.float64)
    if loop:
        prof = np.concatenate([prof, prof[:1]])
    elif prof[0, 0] != 0.0 or prof[-1, 0] != 0.0:
        raise ValueError("an open lathe profile must start and end on the axis (r = 0)")
    rows = prof.shape[0]
    grid = _lathe_grid(prof, axis, centre, scale, segments)
    ids = _lathe_ids(segments, rows, prof[:, 0], loop)

    g = np.arange((segments + 1) * rows).reshape(segments + 1, rows)
    v00, v10 = g[:-1, :-1].ravel(), g[1:, :-1].ravel()
    v11, v01 = g[1:, 1:].ravel(), g[:-1, 1:].ravel()
    tris = np.concatenate([np.stack([v00, v10, v11], 1), np.stack([v00, v11, v01], 1)])
    flat_ids = ids.ravel()
    welded_tris = flat_ids[tris]
    keep = (
        (welded_tris[:, 0] != welded_tris[:, 1])
        & (welded_tris[:, 1] != welded_tris[:, 2])
        & (welded_tris[:, 0] != welded_tris[:, 2])
    )
    tris = tris[keep]

    pts = grid.reshape(-1, 3)
    verts = np.zeros((int(flat_ids.max()) + 1, 3))
    verts[flat_ids] = pts  # duplicates carry the same position
    mean_scale = 0.5 * (abs(scale[0]) + abs(scale[1]))
    seg_len = np.linalg.norm(np.diff(prof, axis=0) * [mean_scale, 1.0], axis=1)
    arc = np.concatenate([[0.0], np.cumsum(seg_len)])
    uv = np.stack(
        [np.repeat(np.arange(segments + 1) / segments, rows), np.tile(arc / max(arc[-1], 1e-9), segments + 1)], 1
    )
    used = np.unique(tris)  # a pole keeps one chart vertex per triangle fan
    remap = np.full(pts.shape[0], -1, dtype=np.int64)
    remap[used] = np.arange(used.size)
    return PartMesh(
        verts=verts,
        faces=flat_ids[tris],
        chart_verts=[pts[used]],
        chart_faces=[remap[tris]],
        chart_param=[uv[used]],
        chart_keys=[key],
        chart_size=[(2.0 * math.pi * float(prof[:, 0].max()) * mean_scale, float(arc[-1]))],
        chart_to_welded=[flat_ids[used]],
    )


def merge_pieces(pieces: Sequence[Piece]) -> PartMesh:
    """One part from its pieces: meshes concatenated, charts listed with their painters."""
    out = PartMesh(verts=np.zeros((0, 3)), faces=np.zeros((0, 3), dtype=np.int64))
    verts, faces, offset = [], [], 0
    for piece in pieces:
        m = piece.mesh
        verts.append(m.verts)
        faces.append(m.faces + offset)
        for k, key in enumerate(m.chart_keys):
            out.chart_verts.append(m.chart_verts[k])
            out.chart_faces.append(m.chart_faces[k])
            out.chart_param.append(m.chart_param[k])
            out.chart_keys.append(key)
            out.chart_size.append(m.chart_size[k])
            out.chart_to_welded.append(m.chart_to_welded[k] + offset)
            out.chart_painters.append(piece.painters.get(key, piece.default))
        offset += m.verts.shape[0]
    out.verts = np.concatenate(verts)
    out.faces = np.concatenate(faces).astype(np.int64)
    return out
