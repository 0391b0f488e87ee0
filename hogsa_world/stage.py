"""The static set: a textured table in a simple room, and the world light.

World frame (metres): z up, the floor at z = 0, the table top at z = ``TABLE_Z``; the
subject sits at the table edge y = ``TABLE_Y[0]`` facing +y, x to the subject's right.

Meshes are returned as lists of :class:`~hogsa_loader.render.mesh_raster.MeshPart` with
part ids >= ``STAGE_PART_ID`` (the foreground masks map them to background). Large
surfaces are split into grids so that the rasteriser's near-plane rule (it drops whole
triangles that cross it) only removes small pieces when a wall passes behind a camera.
"""

from __future__ import annotations

import numpy as np
import torch

from hogsa_loader.render.mesh_raster import Light, MeshPart

__all__ = [
    "TABLE_Z",
    "TABLE_X",
    "TABLE_Y",
    "WORKSPACE",
    "STAGE_PART_ID",
    "build_stage",
    "wood_texture",
    "world_light",
    "light_for_camera",
]

TABLE_Z = 0.75
TABLE_X = (-0.8, 0.8)
TABLE_Y = (-0.35, 0.65)
#: Where the object rests (x, y) and what the cameras look at.
WORKSPACE = np.array([0.0, -0.06, TABLE_Z + 0.08])
ROOM_HALF = 2.6
ROOM_HEIGHT = 2.7
STAGE_PART_ID = 10
TABLE_TILE = 0.2


def wood_texture(rng: np.random.Generator, size: int = 512) -> np.ndarray:
    """A seamless (periodic) wood-plank texture: grain along u, a seam at the tile border.

    Built only from sinusoids with integer frequencies over the tile, so tiles repeat
    without visible discontinuities.

    Returns:
        (size, size, 3) float32 RGB in [0, 1].
    """
    u = (np.arange(size) + 0.5) / size
    U, V = np.meshgrid(u, u)
    warp = np.zeros_like(U)
    for _ in range(5):
        fu, fv = rng.integers(1, 3), rng.integers(0, 2)
        warp += rng.uniform(0.0008, 0.0025) * np.sin(2 * np.pi * (fu * U + fv * V) + rng.uniform(0, 2 * np.pi))
    grain = np.zeros_like(U)
    for _ in range(4):
        f = int(rng.integers(3, 14))
        grain += rng.uniform(0.4, 1.0) * np.sin(2 * np.pi * f * (V + warp) + rng.uniform(0, 2 * np.pi))
    for _ in range(2):
        f = int(rng.integers(18, 30))
        grain += rng.uniform(0.1, 0.2) * np.sin(2 * np.pi * f * (V + 2 * warp) + rng.uniform(0, 2 * np.pi))
    grain = 0.5 + 0.5 * np.tanh(0.5 * grain)
    fleck = np.zeros_like(U)
    for _ in range(4):
        fu, fv = int(rng.integers(20, 60)), int(rng.integers(60, 140))
        fleck += np.sin(2 * np.pi * (fu * U + fv * (V + warp)) + rng.uniform(0, 2 * np.pi))
    seam = np.exp(-((np.minimum(V, 1 - V) * size / 2.0) ** 2))  # dark line between planks
    palettes = np.array(
        [[0.78, 0.64, 0.46], [0.62, 0.60, 0.56], [0.86, 0.84, 0.80], [0.45, 0.30, 0.20], [0.70, 0.52, 0.36]]
    )  # oak, grey laminate, white, walnut, pine
    base = palettes[int(rng.integers(0, len(palettes)))] * rng.uniform(0.92, 1.05, size=3)
    shade = 0.86 + 0.14 * grain + 0.02 * fleck / 4 - 0.4 * seam
    img = base[None, None] * shade[..., None]
    return np.clip(img, 0.0, 1.0).astype(np.float32)


def _grid_quads(
    origin: np.ndarray, du: np.ndarray, dv: np.ndarray, nu: int, nv: int, unweld: bool
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """A planar grid of nu x nv quads (2 triangles each).

    Args:
        origin: (3,) corner; du, dv: (3,) full edge vectors of the grid.
        unweld: give every quad its own 4 vertices (per-quad UV [0,1]^2 / flat colours).

    Returns:
        verts (V,3), faces (F,3), uv (V,2) and quad index per vertex (V,).
    """
    if unweld:
        verts, uv, faces, qid = [], [], [], []
        for i in range(nu):
            for j in range(nv):
                p0 = origin + du * (i / nu) + dv * (j / nv)
                a, b = du / nu, dv / nv
                base = len(verts)
                verts += [p0, p0 + a, p0 + a + b, p0 + b]
                uv += [(0, 0), (1, 0), (1, 1), (0, 1)]
                faces += [(base, base + 1, base + 2), (base, base + 2, base + 3)]
                qid += [i * nv + j] * 4
        return np.array(verts), np.array(faces), np.array(uv, dtype=np.float64), np.array(qid)
    s = np.linspace(0, 1, nu + 1)
    t = np.linspace(0, 1, nv + 1)
    S, T = np.meshgrid(s, t, indexing="ij")
    verts = origin + S[..., None] * du + T[..., None] * dv
    idx = np.arange((nu + 1) * (nv + 1)).reshape(nu + 1, nv + 1)
    a, b, c, d = idx[:-1, :-1], idx[1:, :-1], idx[1:, 1:], idx[:-1, 1:]
    faces = np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3), np.stack([a, c, d], -1).reshape(-1, 3)])
    uv = np.stack([S, T], -1).reshape(-1, 2)
    return verts.reshape(-1, 3), faces, uv, np.zeros(len(uv), dtype=np.int64)


def _t(x: np.ndarray, dtype=torch.float32) -> torch.Tensor:
    return torch.as_tensor(np.ascontiguousarray(x), dtype=dtype)


#: A flat-coloured mesh piece: verts (V, 3), faces (F, 3) local to the piece, colours (V, 3).
_Piece = tuple[np.ndarray, np.ndarray, np.ndarray]


def _flat(verts: np.ndarray, faces: np.ndarray, col: np.ndarray) -> _Piece:
    """A piece with one colour (3,) on every vertex."""
    return verts, faces, np.tile(col, (len(verts), 1))


def _table_top(rng: np.random.Generator) -> tuple[MeshPart, np.ndarray]:
    """Table top of 0.2 m tiles, each mapping the whole periodic wood texture.

    Returns:
        the textured MeshPart (part id ``STAGE_PART_ID``) and its (512, 512, 3) texture.
    """
    x0, x1 = TABLE_X
    y0, y1 = TABLE_Y
    nu, nv = int(round((x1 - x0) / TABLE_TILE)), int(round((y1 - y0) / TABLE_TILE))
    v, f, uv, _ = _grid_quads(
        np.array([x0, y0, TABLE_Z]), np.array([x1 - x0, 0, 0]), np.array([0, y1 - y0, 0]), nu, nv, unweld=True
    )
    tex = wood_texture(rng)
    return MeshPart(_t(v), torch.as_tensor(f), STAGE_PART_ID, uv=_t(uv), texture=_t(tex)), tex


def _table_frame(edge_col: np.ndarray) -> list[_Piece]:
    """The table's four edge aprons (0.04 m high) and four square legs, flat coloured."""
    x0, x1 = TABLE_X
    y0, y1 = TABLE_Y
    h = 0.04
    pieces = []
    for o, du in (
        ((x0, y0), (x1 - x0, 0)),
        ((x1, y0), (0, y1 - y0)),
        ((x1, y1), (x0 - x1, 0)),
        ((x0, y1), (0, y0 - y1)),
    ):
        gv, gf, _, _ = _grid_quads(
            np.array([o[0], o[1], TABLE_Z - h]), np.array([du[0], du[1], 0.0]), np.array([0, 0, h]), 8, 1, unweld=False
        )
        pieces.append(_flat(gv, gf, edge_col))
    for lx in (x0 + 0.05, x1 - 0.09):
        for ly in (y0 + 0.05, y1 - 0.09):
            for o, du in (
                ((0, 0), (0.04, 0)),
                ((0.04, 0), (0, 0.04)),
                ((0.04, 0.04), (-0.04, 0)),
                ((0, 0.04), (0, -0.04)),
            ):
                gv, gf, _, _ = _grid_quads(
                    np.array([lx + o[0], ly + o[1], 0.0]),
                    np.array([du[0], du[1], 0.0]),
                    np.array([0, 0, TABLE_Z - h]),
                    1,
                    4,
                    unweld=False,
                )
                pieces.append(_flat(gv, gf, edge_col * 0.8))
    return pieces


def _room_floor(rng: np.random.Generator) -> _Piece:
    """The room's floor: 12 x 12 checkered tiles of two random grey shades."""
    floor_a = np.array([0.55, 0.55, 0.53]) * rng.uniform(0.8, 1.1)
    floor_b = floor_a * 0.82
    n = 12
    gv, gf, _, q = _grid_quads(
        np.array([-ROOM_HALF, -ROOM_HALF, 0.0]),
        np.array([2 * ROOM_HALF, 0, 0]),
        np.array([0, 2 * ROOM_HALF, 0]),
        n,
        n,
        unweld=True,
    )
    checker = ((q // n + q % n) % 2)[:, None]
    return gv, gf, np.where(checker == 1, floor_a, floor_b)


def _room_walls(rng: np.random.Generator) -> list[_Piece]:
    """Four walls of a random tint with a darker band, each with a darker panel (door / picture) in front."""
    hue = rng.uniform(0, 1)
    wall = np.array([0.78, 0.76, 0.72]) + 0.08 * np.array(
        [np.cos(2 * np.pi * hue), np.cos(2 * np.pi * (hue + 1 / 3)), np.cos(2 * np.pi * (hue + 2 / 3))]
    )
    corners = [(-ROOM_HALF, -ROOM_HALF), (ROOM_HALF, -ROOM_HALF), (ROOM_HALF, ROOM_HALF), (-ROOM_HALF, ROOM_HALF)]
    pieces = []
    for k in range(4):
        a = np.array([*corners[k], 0.0])
        b = np.array([*corners[(k + 1) % 4], 0.0])
        gv, gf, uvw, _ = _grid_quads(a, b - a, np.array([0, 0, ROOM_HEIGHT]), 10, 6, unweld=False)
        shade = wall * (0.86 + 0.14 * uvw[:, 1:2]) * (0.92 + 0.08 * (k % 2))
        band = (uvw[:, 1:2] > 0.28) & (uvw[:, 1:2] < 0.34)
        pieces.append((gv, gf, np.where(band, wall * 0.7, shade)))
        # the panel sits slightly in front of the wall
        inward = -np.array([a[0] + b[0], a[1] + b[1], 0.0])
        inward /= np.linalg.norm(inward)
        c = rng.uniform(0.25, 0.7)
        pv, pf, _, _ = _grid_quads(
            a + (b - a) * c + inward * 0.01 + np.array([0, 0, 0.9]),
            (b - a) * 0.12,
            np.array([0, 0, 0.9]),
            2,
            2,
            unweld=False,
        )
        pieces.append(_flat(pv, pf, np.array([0.35, 0.3, 0.28]) * rng.uniform(0.7, 1.3, size=3)))
    return pieces


def _merge(pieces: list[_Piece], part_id: int) -> MeshPart:
    """One vertex-coloured MeshPart from pieces (face indices offset, colours clipped to [0, 1])."""
    faces, offset = [], 0
    for verts, ff, _ in pieces:
        faces.append(ff + offset)
        offset += len(verts)
    return MeshPart(
        _t(np.concatenate([p[0] for p in pieces])),
        torch.as_tensor(np.concatenate(faces)),
        part_id,
        vertex_colors=_t(np.clip(np.concatenate([p[2] for p in pieces]), 0, 1)),
    )


def build_stage(rng: np.random.Generator) -> list[MeshPart]:
    """Table (tiled wood texture, with a front apron) and a room (floor tiles, walls).

    Returns:
        list of MeshParts with part ids ``STAGE_PART_ID`` (table) and
        ``STAGE_PART_ID + 1`` (room: table aprons and legs, floor, walls).
    """
    top, tex = _table_top(rng)
    edge_col = tex.reshape(-1, 3).mean(0) * 0.75
    pieces = _table_frame(edge_col)
    pieces.append(_room_floor(rng))
    pieces += _room_walls(rng)
    return [top, _merge(pieces, STAGE_PART_ID + 1)]


def world_light() -> np.ndarray:
    """Direction (world, unit) the key light travels: from above, front-left."""
    d = np.array([0.35, 0.45, -1.0])
    return d / np.linalg.norm(d)


def light_for_camera(world2cam: np.ndarray) -> Light:
    """The world light expressed in one camera's frame (the rasteriser lights in camera space)."""
    d = np.asarray(world2cam)[:3, :3] @ world_light()
    return Light(direction=tuple(float(x) for x in d), ambient=0.42, diffuse=0.62, specular=0.08, shininess=24.0)
