"""Procedural textured articulated objects in ARCTIC's template layout.

Real ARCTIC templates cannot be downloaded here, so the project generates look-alikes and
writes them exactly like ``meta/object_vtemplates/<obj>/`` (see
:mod:`hogsa_loader.assets.objects.template`), one for each of ARCTIC's 11 object names. Here:
box (juice box with a flip lid), laptop, notebook and phone (flip phone), each two
rounded boxes joined by a hinge; the other seven are assembled from several pieces per
part in :mod:`hogsa_world.objects.household` and textured by the same atlas code.
"""

from __future__ import annotations

import colorsys
import math
import os
import zlib
from dataclasses import dataclass, field
from functools import lru_cache
from typing import Callable, Optional, Sequence

import cv2
import numpy as np

from hogsa_loader.assets.objects.template import BOTTOM, OBJECT_NAMES, TOP
from hogsa_loader.extras import require

__all__ = ["GAP_MM", "ATLAS_SIZE", "FLAT_SPECS", "PROCEDURAL_NAMES", "build_parts", "build_textured", "object_rng"]

#: Gap between the two parts in the closed state (mm).
GAP_MM = 1.0
#: Side of the square texture atlas (px).
ATLAS_SIZE = 1024
#: Padding around every chart in the atlas (px), filled by edge replication.
CHART_PAD = 4
NUM_MOCAP = 5

Image = np.ndarray  # (H, W, 3) float32 RGB in [0, 1]
Painter = Callable[[int, int, float], Image]  # (height px, width px, px per mm) -> image


# ======================================================================================
# Geometry: rounded boxes built from face grids
# ======================================================================================


@dataclass(frozen=True)
class Slab:
    """One part: an axis-aligned box with rounded edges (mm).

    Attributes:
        size: (dx, dy, dz) extents; x points away from the hinge, y is the stacking
            direction, z runs along the hinge.
        radius: edge rounding radius (clamped to 45% of the smallest extent).
    """

    size: tuple[float, float, float]
    radius: float


@dataclass
class PartMesh:
    """A welded mesh plus its texture charts (a rounded box has 6, one per face).

    Attributes:
        verts: (V, 3) float64 welded vertices (mm).
        faces: (F, 3) int64 outward-oriented triangles.
        chart_verts: per chart, (Vc, 3) vertices (unwelded copies).
        chart_faces: per chart, (Fc, 3) triangles into the chart's vertices.
        chart_param: per chart, (Vc, 2) in-chart coordinates ``(fu, fv)`` in [0, 1].
        chart_keys: per chart, its name (box faces: ``"+x"`` ...).
        chart_size: per chart, (width, height) extents in mm along (u, v).
        chart_to_welded: per chart, (Vc,) indices into ``verts``.
        chart_painters: optional painter of each chart (parts assembled from pieces);
            empty: the object's spec chooses by face name.
    """

    verts: np.ndarray
    faces: np.ndarray
    chart_verts: list[np.ndarray] = field(default_factory=list)
    chart_faces: list[np.ndarray] = field(default_factory=list)
    chart_param: list[np.ndarray] = field(default_factory=list)
    chart_keys: list[str] = field(default_factory=list)
    chart_size: list[tuple[float, float]] = field(default_factory=list)
    chart_to_welded: list[np.ndarray] = field(default_factory=list)
    chart_painters: list[Painter] = field(default_factory=list)


_AXES = "xyz"


def face_key(axis: int, sign: int) -> str:
    """Face name from its outward normal, e.g. ``(1, -1) -> "-y"``."""
    return ("+" if sign > 0 else "-") + _AXES[axis]


def _unit(key: str) -> np.ndarray:
    """``"+x"`` -> (1, 0, 0)."""
    v = np.zeros(3)
    v[_AXES.index(key[1])] = 1.0 if key[0] == "+" else -1.0
    return v


def default_up(key: str) -> str:
    """Image "up" on a face: ``-x`` (away from the hinge) on ±y faces, ``+y`` elsewhere."""
    return "-x" if key[1] == "y" else "+y"


def axis_samples(lo: float, hi: float, radius: float, spacing: float, band: int) -> np.ndarray:
    """1-D grid coordinates over ``[lo, hi]`` for one box axis.

    The flat middle ``[lo + r, hi - r]`` is sampled uniformly at about ``spacing``; each
    rounded band gets ``band`` samples placed so that the projected points are uniform in
    angle on the 45° of arc that belong to this face.

    Returns:
        (n,) increasing coordinates with ``lo`` and ``hi`` included.
    """
    inner = hi - lo - 2.0 * radius
    n = max(2, int(math.ceil(inner / spacing - 1e-9)) + 1)
    flat = np.linspace(lo + radius, hi - radius, n)
    phi = np.pi / 4.0 * np.arange(band, 0, -1) / band  # 45° .. >0
    left = lo + radius * (1.0 - np.tan(phi))
    right = hi - radius + radius * np.tan(phi[::-1])
    return np.concatenate([left, flat, right])


def _round_points(points: np.ndarray, lo: np.ndarray, hi: np.ndarray, radius: float) -> np.ndarray:
    """Project box-surface points onto the rounded box (offset of the inner box by r)."""
    q = np.clip(points, lo + radius, hi - radius)
    d = points - q
    return q + radius * d / np.linalg.norm(d, axis=1, keepdims=True)


def _face_grid_tris(nb: int, nc: int, sign: int) -> np.ndarray:
    """Triangles of an (nb, nc) vertex grid on a box face, row-major vertex ids.

    Args:
        nb, nc: samples along the face's axes b and c (a, b, c cyclic).
        sign: -1 or +1, the side of axis a the face is on; triangles face outward.

    Returns:
        (2 (nb-1) (nc-1), 3) int64 triangles.
    """
    g = np.arange(nb * nc).reshape(nb, nc)
    v00, v10 = g[:-1, :-1].ravel(), g[1:, :-1].ravel()
    v11, v01 = g[1:, 1:].ravel(), g[:-1, 1:].ravel()
    if sign > 0:  # e_b x e_c = e_a: counter-clockwise in (b, c) faces +a
        return np.concatenate([np.stack([v00, v10, v11], 1), np.stack([v00, v11, v01], 1)])
    return np.concatenate([np.stack([v00, v11, v10], 1), np.stack([v00, v01, v11], 1)])


def _chart_param(box_pts: np.ndarray, key_name: str, up_name: str, size: np.ndarray) -> tuple[np.ndarray, float, float]:
    """Chart parameters of one box face: u along (up x normal), v along up, both in [0, 1].

    Args:
        box_pts: (n, 3) the face's grid points on the unrounded box (mm).
        key_name: the face's key (its outward normal, see :func:`face_key`).
        up_name: the face's image-up direction key.
        size: (3,) box extent ``hi - lo`` (mm).

    Returns:
        (param (n, 2), ext_u, ext_v): the parameters and the chart's extent along u and v (mm).
    """
    normal = _unit(key_name)
    v_dir = _unit(up_name)
    u_dir = np.cross(v_dir, normal)
    pu, pv = box_pts @ u_dir, box_pts @ v_dir
    ext_u = float(np.abs(size) @ np.abs(u_dir))
    ext_v = float(np.abs(size) @ np.abs(v_dir))
    param = np.stack([(pu - pu.min()) / ext_u, (pv - pv.min()) / ext_v], axis=1)
    return param, ext_u, ext_v


def rounded_box(
    lo: Sequence[float],
    hi: Sequence[float],
    radius: float,
    spacing: float,
    band: int = 3,
    up: Optional[dict[str, str]] = None,
) -> PartMesh:
    """Closed, outward-oriented mesh of a box with rounded edges and its 6 charts.

    Args:
        lo, hi: (3,) box corners (mm).
        radius: rounding radius (mm).
        spacing: target edge length on flat regions (mm).
        band: samples per rounded band and face.
        up: optional face -> image-up overrides (see :func:`default_up`).

    Returns:
        the welded mesh and its per-face charts.
    """
    lo = np.asarray(lo, dtype=np.float64)
    hi = np.asarray(hi, dtype=np.float64)
    radius = min(radius, 0.45 * float((hi - lo).min()))
    coords = [axis_samples(lo[a], hi[a], radius, spacing, band) for a in range(3)]
    counts = [len(c) for c in coords]
    up = up or {}

    keys_all, tris_all, charts = [], [], []
    for a in range(3):
        b, c = (a + 1) % 3, (a + 2) % 3
        nb, nc = counts[b], counts[c]
        ib, ic = np.meshgrid(np.arange(nb), np.arange(nc), indexing="ij")
        for sign in (-1, 1):
            idx = np.zeros((nb * nc, 3), dtype=np.int64)
            idx[:, a] = 0 if sign < 0 else counts[a] - 1
            idx[:, b] = ib.ravel()
            idx[:, c] = ic.ravel()
            key = (idx[:, 0] * counts[1] + idx[:, 1]) * counts[2] + idx[:, 2]
            tris = _face_grid_tris(nb, nc, sign)
            box_pts = np.stack([coords[k][idx[:, k]] for k in range(3)], axis=1)
            keys_all.append(key)
            tris_all.append(tris)
            charts.append((face_key(a, sign), box_pts))

    all_keys = np.concatenate(keys_all)
    uniq, inverse = np.unique(all_keys, return_inverse=True)
    # welded vertex positions, from the flattened 3-D grid index
    iz = uniq % counts[2]
    iy = (uniq // counts[2]) % counts[1]
    ix = uniq // (counts[2] * counts[1])
    welded_box = np.stack([coords[0][ix], coords[1][iy], coords[2][iz]], axis=1)
    welded = _round_points(welded_box, lo, hi, radius)

    mesh = PartMesh(verts=welded, faces=np.zeros((0, 3), dtype=np.int64))
    faces, offset = [], 0
    for (key_name, box_pts), keys, tris in zip(charts, keys_all, tris_all):
        n = keys.shape[0]
        to_welded = inverse[offset : offset + n]
        offset += n
        faces.append(to_welded[tris])
        param, ext_u, ext_v = _chart_param(box_pts, key_name, up.get(key_name, default_up(key_name)), hi - lo)
        mesh.chart_verts.append(welded[to_welded])
        mesh.chart_faces.append(tris)
        mesh.chart_param.append(param)
        mesh.chart_keys.append(key_name)
        mesh.chart_size.append((ext_u, ext_v))
        mesh.chart_to_welded.append(to_welded)
    mesh.faces = np.concatenate(faces).astype(np.int64)
    return mesh


def part_boxes(bottom: Slab, top: Slab, gap: float = GAP_MM) -> dict[int, tuple[np.ndarray, np.ndarray]]:
    """Closed-state boxes of both parts (mm): hinge at x = 0, stacked along y.

    Returns:
        ``{TOP: (lo, hi), BOTTOM: (lo, hi)}``.
    """
    bx, by, bz = bottom.size
    tx, ty, tz = top.size
    return {
        BOTTOM: (np.array([-bx, -gap / 2 - by, -bz / 2]), np.array([0.0, -gap / 2, bz / 2])),
        TOP: (np.array([-tx, gap / 2, -tz / 2]), np.array([0.0, gap / 2 + ty, tz / 2])),
    }


# ======================================================================================
# Texture helpers (float32 RGB images in [0, 1])
# ======================================================================================


@lru_cache(maxsize=None)
def _photo_cached(name: str) -> np.ndarray:
    skimage_data = require("skimage.data", "demo", "the generated world's photographic textures")
    skimage_io = require("skimage.io", "demo", "the generated world's photographic textures")
    path = os.path.join(os.path.dirname(skimage_data.__file__), name)
    img = np.asarray(skimage_io.imread(path))
    if img.ndim == 2:
        img = np.repeat(img[..., None], 3, axis=2)
    img = img[..., :3].astype(np.float32) / 255.0
    img.setflags(write=False)
    return img


def photo(name: str) -> Image:
    """A photograph shipped inside scikit-image's wheel (``skimage/data/<name>``)."""
    return _photo_cached(name)


def fit(img: Image, h: int, w: int) -> Image:
    """Centre-crop ``img`` to the aspect of (h, w) and resize (cover)."""
    ih, iw = img.shape[:2]
    scale = max(h / ih, w / iw)
    ch, cw = min(ih, int(round(h / scale))), min(iw, int(round(w / scale)))
    y0, x0 = (ih - ch) // 2, (iw - cw) // 2
    crop = np.ascontiguousarray(img[y0 : y0 + ch, x0 : x0 + cw])
    interp = cv2.INTER_AREA if scale < 1 else cv2.INTER_CUBIC
    return np.clip(cv2.resize(crop, (max(w, 1), max(h, 1)), interpolation=interp), 0, 1)


def grain(h: int, w: int, source: str, px_per_texel: float, rng: np.random.Generator) -> np.ndarray:
    """(h, w) grey structure in [0, 1] from a texture photo (brick, gravel, grass ...).

    The photo is scaled by ``px_per_texel``, tiled and cropped at a seeded offset.
    """
    src = photo(source).mean(axis=2)
    size = max(8, int(round(src.shape[0] * px_per_texel)))
    src = cv2.resize(src, (size, size), interpolation=cv2.INTER_AREA if px_per_texel < 1 else cv2.INTER_LINEAR)
    reps = (h // size + 2, w // size + 2)
    tiled = np.tile(src, reps)
    y0, x0 = int(rng.integers(0, size)), int(rng.integers(0, size))
    out = tiled[y0 : y0 + h, x0 : x0 + w]
    lo, hi = np.percentile(out, 2), np.percentile(out, 98)
    return np.clip((out - lo) / max(hi - lo, 1e-6), 0, 1).astype(np.float32)


def smooth_noise(h: int, w: int, rng: np.random.Generator, cells: int = 6) -> np.ndarray:
    """(h, w) smooth random field in [0, 1] (bicubic upsampled random grid)."""
    gh, gw = max(2, int(round(cells * h / max(h, w))) + 1), max(2, int(round(cells * w / max(h, w))) + 1)
    small = rng.random((gh, gw)).astype(np.float32)
    return np.clip(cv2.resize(small, (w, h), interpolation=cv2.INTER_CUBIC), 0, 1)


def brushed(h: int, w: int, rng: np.random.Generator, horizontal: bool = True) -> np.ndarray:
    """(h, w) brushed-metal streaks in [0, 1]."""
    noise = rng.random((h, w)).astype(np.float32)
    k = max(3, (w if horizontal else h) // 6)
    ksize = (k, 1) if horizontal else (1, k)
    out = cv2.blur(noise, ksize)
    lo, hi = out.min(), out.max()
    return (out - lo) / max(hi - lo, 1e-6)


def material(h: int, w: int, rgb: Sequence[float], structure: np.ndarray, strength: float) -> Image:
    """Flat colour modulated by a grey structure map: ``rgb * (1 + strength (s - 0.5))``."""
    base = np.asarray(rgb, dtype=np.float32)[None, None, :]
    mod = 1.0 + strength * (structure[..., None] - 0.5)
    return np.clip(np.broadcast_to(base, (h, w, 3)) * mod, 0, 1).astype(np.float32)


def paste(canvas: Image, img: Image, rect: Sequence[float]) -> Image:
    """Paste ``img`` (cover-fitted) into ``rect`` = (x0, y0, x1, y1) fractions of canvas."""
    h, w = canvas.shape[:2]
    x0, y0 = int(round(rect[0] * w)), int(round(rect[1] * h))
    x1, y1 = max(x0 + 1, int(round(rect[2] * w))), max(y0 + 1, int(round(rect[3] * h)))
    canvas[y0:y1, x0:x1] = fit(img, y1 - y0, x1 - x0)
    return canvas


def fill_rect(canvas: Image, rect: Sequence[float], rgb: Sequence[float]) -> Image:
    """Fill ``rect`` (fractions) with a colour."""
    h, w = canvas.shape[:2]
    x0, y0 = int(round(rect[0] * w)), int(round(rect[1] * h))
    x1, y1 = max(x0 + 1, int(round(rect[2] * w))), max(y0 + 1, int(round(rect[3] * h)))
    canvas[y0:y1, x0:x1] = np.asarray(rgb, dtype=np.float32)
    return canvas


def text(
    canvas: Image,
    words: str,
    center: Sequence[float],
    height_px: float,
    rgb: Sequence[float],
    max_width_px: Optional[float] = None,
    bold: bool = False,
) -> Image:
    """Draw ``words`` centred at ``center`` (fractions) with cap height ``height_px``."""
    if height_px < 3:
        return canvas
    font = cv2.FONT_HERSHEY_DUPLEX if bold else cv2.FONT_HERSHEY_SIMPLEX
    (tw, th), _ = cv2.getTextSize(words, font, 1.0, 1)
    scale = height_px / max(th, 1)
    if max_width_px is not None and tw * scale > max_width_px:
        scale = max_width_px / max(tw, 1)
    thick = max(1, int(round(scale * (2.2 if bold else 1.4))))
    (tw, th), _ = cv2.getTextSize(words, font, scale, thick)
    h, w = canvas.shape[:2]
    org = (int(round(center[0] * w - tw / 2)), int(round(center[1] * h + th / 2)))
    mask = np.zeros((h, w), dtype=np.uint8)  # OpenCV 5 draws text on 8-bit images only
    cv2.putText(mask, words, org, font, scale, 255, thick, cv2.LINE_AA)
    alpha = (mask.astype(np.float32) / 255.0)[..., None]
    canvas[...] = canvas * (1.0 - alpha) + np.asarray(rgb, dtype=np.float32) * alpha
    return canvas


def text_lines(
    canvas: Image, rect: Sequence[float], rows: int, rgb: Sequence[float], rng: np.random.Generator
) -> Image:
    """Fake small print: rows of word-like bars inside ``rect`` (fractions)."""
    h, w = canvas.shape[:2]
    x0, y0, x1, y1 = rect[0] * w, rect[1] * h, rect[2] * w, rect[3] * h
    pitch = (y1 - y0) / max(rows, 1)
    bar = max(1, int(round(pitch * 0.45)))
    colour = tuple(float(c) for c in rgb)
    for r in range(rows):
        y = int(round(y0 + r * pitch + pitch * 0.3))
        x = x0
        end = x1 - (rng.random() * 0.4 * (x1 - x0) if r == rows - 1 else 0)
        while x < end:
            word = pitch * (0.8 + 2.5 * rng.random())
            xe = min(x + word, end)
            if xe - x >= 1:
                cv2.rectangle(canvas, (int(x), y), (int(xe), y + bar), colour, -1)
            x = xe + pitch * 0.5
    return canvas


def barcode(canvas: Image, rect: Sequence[float], rng: np.random.Generator) -> Image:
    """A white box with black bars (fractions rect)."""
    h, w = canvas.shape[:2]
    fill_rect(canvas, rect, (0.97, 0.97, 0.95))
    x0, y0, x1, y1 = (
        int(round(rect[0] * w)),
        int(round(rect[1] * h)),
        int(round(rect[2] * w)),
        int(round(rect[3] * h)),
    )
    x = x0 + max(1, (x1 - x0) // 12)
    while x < x1 - max(1, (x1 - x0) // 12):
        bw = int(rng.integers(1, 4))
        canvas[y0 + (y1 - y0) // 8 : y1 - (y1 - y0) // 5, x : x + bw] = 0.05
        x += bw + int(rng.integers(1, 4))
    return canvas


def circle(
    canvas: Image, center: Sequence[float], radius_px: float, rgb: Sequence[float], thickness: int = -1
) -> Image:
    """Filled (or outlined) anti-aliased circle at ``center`` (fractions)."""
    h, w = canvas.shape[:2]
    cv2.circle(
        canvas,
        (int(round(center[0] * w)), int(round(center[1] * h))),
        max(1, int(round(radius_px))),
        tuple(float(c) for c in rgb),
        thickness,
        cv2.LINE_AA,
    )
    return canvas


def hsv(hue: float, sat: float, val: float) -> tuple[float, float, float]:
    """HSV (hue in turns) -> RGB tuple."""
    r, g, b = colorsys.hsv_to_rgb(hue % 1.0, min(max(sat, 0.0), 1.0), min(max(val, 0.0), 1.0))
    return (r, g, b)


def jitter_colour(
    rng: np.random.Generator, hue: float, sat: float, val: float, dh: float = 0.06, ds: float = 0.12, dv: float = 0.12
) -> tuple[float, float, float]:
    """A seeded variation of an HSV colour."""
    return hsv(hue + dh * rng.uniform(-1, 1), sat + ds * rng.uniform(-1, 1), val + dv * rng.uniform(-1, 1))


# ======================================================================================
# Atlas
# ======================================================================================


_PACK_ORDERS: tuple[Callable[[tuple[int, int]], tuple[int, int]], ...] = (
    lambda wh: (-wh[1], -wh[0]),  # tallest first
    lambda wh: (-wh[0] * wh[1], -wh[1]),  # largest first
    lambda wh: (-wh[0], -wh[1]),  # widest first
)


def _shelf_pack(sizes: Sequence[tuple[int, int]], side: int, pad: int) -> Optional[list[tuple[int, int]]]:
    """Place (w, h) rectangles on shelves; the first of a few orders that fits wins.

    Returns:
        top-left pixel of each rectangle's interior, or None if no order fits.
    """
    for order_key in _PACK_ORDERS:
        order = sorted(range(len(sizes)), key=lambda i: (order_key(sizes[i]), i))
        pos = _shelf_pack_order(sizes, order, side, pad)
        if pos is not None:
            return pos
    return None


def _shelf_pack_order(
    sizes: Sequence[tuple[int, int]], order: Sequence[int], side: int, pad: int
) -> Optional[list[tuple[int, int]]]:
    """Shelf packing in a given order; None if the rectangles do not fit."""
    pos: list[tuple[int, int]] = [(0, 0)] * len(sizes)
    x = y = shelf = 0
    for i in order:
        w, h = sizes[i][0] + 2 * pad, sizes[i][1] + 2 * pad
        if w > side:
            return None
        if x + w > side:
            x, y, shelf = 0, y + shelf, 0
        if y + h > side:
            return None
        pos[i] = (x + pad, y + pad)
        x += w
        shelf = max(shelf, h)
    return pos


def pack_charts(
    sizes_mm: Sequence[tuple[float, float]], side: int = ATLAS_SIZE, pad: int = CHART_PAD
) -> tuple[float, list[tuple[int, int]], list[tuple[int, int]]]:
    """Largest common scale (px/mm) at which all charts fit a ``side`` x ``side`` atlas.

    Returns:
        (px_per_mm, top-left positions, pixel sizes (w, h)).
    """

    def px(s: float) -> list[tuple[int, int]]:
        return [(max(2, int(round(w * s))), max(2, int(round(h * s)))) for w, h in sizes_mm]

    lo, hi = 1e-3, 100.0
    for _ in range(50):
        mid = 0.5 * (lo + hi)
        if _shelf_pack(px(mid), side, pad) is None:
            hi = mid
        else:
            lo = mid
    sizes = px(lo)
    pos = _shelf_pack(sizes, side, pad)
    assert pos is not None
    return lo, pos, sizes


def _to_uint8(img: Image) -> np.ndarray:
    return np.clip(img * 255.0 + 0.5, 0, 255).astype(np.uint8)


# ======================================================================================
# Object specifications
# ======================================================================================


@dataclass
class ObjectSpec:
    """Everything needed to build one procedural object.

    Canonical frame (ARCTIC's convention): the hinge is the z axis through the origin
    and the top part (``parts.json`` value 0) is articulated by ``R_z(-θ)``. Both parts lie in
    ``x <= 0`` with the hinge at their ``x = 0`` edge; the bottom part occupies
    ``y <= -GAP/2`` and the top part ``y >= +GAP/2`` (a 1 mm gap). For ``θ`` in ``[0, π/2]``
    every top point keeps ``y' = -x sin θ + y cos θ >= 0``, so the top swings up and back
    (opens) without entering the bottom part; ``θ = 0`` is closed.

    Faces of each rounded box are named by their outward normal (``"+x"``, ``"-y"``, ...):
    ``+x`` is the hinge side, ``-x`` the front, ``+y`` up. Each face is one texture chart;
    the charts are packed in a 1024x1024 atlas painted from real photographs shipped with
    scikit-image (``skimage/data``) plus drawn details (text, keys, stripes), tinted by the
    seed. Output is deterministic: the same seed gives byte-identical files.

    Attributes:
        name: object name (ARCTIC name when it mimics an ARCTIC object).
        bottom, top: the two parts.
        spacing: target grid spacing on flat faces (mm).
        band: samples per rounded band.
        up: per part, face -> image-up overrides.
        painters: per part, face -> painter; missing faces use ``default``.
        default: per part, the painter used for unlisted faces.
    """

    name: str
    bottom: Slab
    top: Slab
    spacing: float
    band: int
    painters: dict[int, dict[str, Painter]]
    default: dict[int, Painter]
    up: dict[int, dict[str, str]] = field(default_factory=dict)


def object_rng(name: str, seed: int) -> np.random.Generator:
    """The generator of object ``name``'s variation under ``seed`` (the same for every run)."""
    return np.random.default_rng([int(seed) & 0xFFFFFFFF, zlib.crc32(name.encode("utf-8"))])


PHOTOS = ("astronaut.png", "chelsea.png", "coffee.png", "rocket.jpg", "hubble_deep_field.jpg", "motorcycle_left.png")


def _spec_box(rng: np.random.Generator) -> ObjectSpec:
    """Juice box (ARCTIC "box"): 70 x 159 x 110 mm body + flip lid."""
    hue = rng.random()
    body = jitter_colour(rng, hue, 0.75, 0.85)
    accent = jitter_colour(rng, hue + 0.5, 0.8, 0.7)
    card = jitter_colour(rng, 0.09, 0.35, 0.72, dh=0.02)
    label = PHOTOS[int(rng.integers(0, 3))] if rng.random() < 0.5 else "coffee.png"
    brand = ("ARCTIC", "NORDIC", "POLAR", "FJORD")[int(rng.integers(0, 4))]
    r = np.random.default_rng(rng.integers(0, 2**32))

    def front(h: int, w: int, s: float) -> Image:
        img = material(h, w, body, grain(h, w, "gravel.png", 0.6, r), 0.12)
        fill_rect(img, (0, 0.06, 1, 0.24), accent)
        text(img, brand, (0.5, 0.15), 0.1 * h, (1, 1, 1), max_width_px=0.86 * w, bold=True)
        paste(img, photo(label), (0.08, 0.3, 0.92, 0.78))
        text(img, "100% JUICE  1 L", (0.5, 0.86), 0.05 * h, (1, 1, 1), max_width_px=0.8 * w)
        text_lines(img, (0.1, 0.91, 0.9, 0.98), 2, (0.1, 0.1, 0.1), r)
        return img

    def back(h: int, w: int, s: float) -> Image:
        img = material(h, w, body, grain(h, w, "gravel.png", 0.6, r), 0.12)
        fill_rect(img, (0.08, 0.1, 0.92, 0.62), (0.96, 0.96, 0.93))
        text(img, "NUTRITION FACTS", (0.5, 0.15), 0.035 * h, (0.05, 0.05, 0.05), max_width_px=0.75 * w)
        text_lines(img, (0.12, 0.2, 0.88, 0.6), 12, (0.15, 0.15, 0.15), r)
        barcode(img, (0.25, 0.7, 0.75, 0.86), r)
        return img

    def side(h: int, w: int, s: float) -> Image:
        img = material(h, w, body, grain(h, w, "gravel.png", 0.6, r), 0.12)
        fill_rect(img, (0, 0.06, 1, 0.24), accent)
        paste(img, fit(photo(label), 64, 64), (0.15, 0.35, 0.85, 0.6))
        text_lines(img, (0.1, 0.66, 0.9, 0.95), 8, (0.1, 0.1, 0.1), r)
        return img

    def top_inner(h: int, w: int, s: float) -> Image:
        img = material(h, w, (0.78, 0.78, 0.8), grain(h, w, "gravel.png", 0.4, r), 0.5)
        circle(img, (0.5, 0.4), 0.12 * min(h, w), (0.12, 0.12, 0.14))
        circle(img, (0.5, 0.4), 0.16 * min(h, w), (0.6, 0.6, 0.62), 2)
        return img

    def cardboard(h: int, w: int, s: float) -> Image:
        return material(h, w, card, grain(h, w, "gravel.png", 0.5, r), 0.45)

    def lid_top(h: int, w: int, s: float) -> Image:
        img = material(h, w, accent, grain(h, w, "brick.png", 0.5, r), 0.2)
        text(img, brand, (0.5, 0.45), 0.22 * h, (1, 1, 1), max_width_px=0.8 * w, bold=True)
        text(img, "OPEN", (0.5, 0.8), 0.1 * h, body, max_width_px=0.4 * w)
        return img

    def lid_side(h: int, w: int, s: float) -> Image:
        img = material(h, w, accent, grain(h, w, "brick.png", 0.5, r), 0.2)
        fill_rect(img, (0, 0.75, 1, 1), body)
        return img

    return ObjectSpec(
        name="box",
        bottom=Slab((70.0, 130.0, 110.0), 4.0),
        top=Slab((70.0, 28.0, 110.0), 4.0),
        spacing=5.5,
        band=3,
        painters={
            BOTTOM: {"-x": front, "+x": back, "+z": side, "-z": side, "+y": top_inner, "-y": cardboard},
            TOP: {"+y": lid_top, "-y": cardboard},
        },
        default={BOTTOM: side, TOP: lid_side},
    )


_KEY_ROWS = ("1234567890-=", "QWERTYUIOP[]", "ASDFGHJKL;'", "ZXCVBNM,./")


def _draw_keyboard(img: Image, s: float, shell: tuple) -> None:
    """Draw a laptop keyboard (19 mm key pitch at ``s`` px/mm: a half-height function row, 4
    character rows, a space bar) and a touchpad in shell colour ``shell`` onto (H, W, 3) ``img``."""
    h, w = img.shape[:2]
    pitch = 19.0 * s
    key = 0.82 * pitch
    x_start = 0.5 * w - 7.25 * pitch
    top = 0.07 * h
    for c in range(14):
        x = x_start + c * pitch * 1.036
        cv2.rectangle(img, (int(x), int(top)), (int(x + key), int(top + 0.5 * key)), (0.08, 0.08, 0.09), -1)
    for row, chars in enumerate(_KEY_ROWS):
        y = top + 0.62 * pitch + row * pitch
        x0 = x_start + 0.3 * row * pitch
        for c, ch in enumerate(chars):
            x = x0 + c * pitch
            cv2.rectangle(img, (int(x), int(y)), (int(x + key), int(y + key)), (0.08, 0.08, 0.09), -1)
            text(img, ch, ((x + key / 2) / w, (y + key / 2) / h), 0.3 * key, (0.85, 0.85, 0.85))
    y = top + 0.62 * pitch + 4 * pitch
    cv2.rectangle(
        img, (int(x_start + 3 * pitch), int(y)), (int(x_start + 10 * pitch), int(y + key)), (0.08, 0.08, 0.09), -1
    )
    fill_rect(img, (0.33, 0.62, 0.67, 0.95), tuple(min(1.0, 1.08 * c) for c in shell))


def _spec_laptop(rng: np.random.Generator) -> ObjectSpec:
    """Laptop: 210 x 16 x 300 mm base with keyboard + 210 x 7 x 300 mm screen."""
    shell_hue = rng.random()
    shell = jitter_colour(rng, shell_hue, 0.03 + 0.12 * rng.random(), 0.45 + 0.4 * rng.random(), ds=0.02, dv=0.02)
    dark = tuple(0.35 * c for c in shell)
    screen_photo = PHOTOS[int(rng.integers(0, len(PHOTOS)))]
    sticker = PHOTOS[int(rng.integers(0, len(PHOTOS)))]
    r = np.random.default_rng(rng.integers(0, 2**32))

    def metal(h: int, w: int, s: float) -> Image:
        return material(h, w, shell, 0.7 * brushed(h, w, r) + 0.3 * smooth_noise(h, w, r), 0.25)

    def keyboard(h: int, w: int, s: float) -> Image:
        img = metal(h, w, s)
        _draw_keyboard(img, s, shell)
        return img

    def underside(h: int, w: int, s: float) -> Image:
        img = material(h, w, dark, smooth_noise(h, w, r, 12), 0.3)
        for fx, fy in ((0.08, 0.1), (0.92, 0.1), (0.08, 0.9), (0.92, 0.9)):
            circle(img, (fx, fy), 6 * s, (0.02, 0.02, 0.02))
        for i in range(24):
            x = int((0.3 + 0.4 * i / 23) * w)
            cv2.line(img, (x, int(0.2 * h)), (x, int(0.35 * h)), (0.03, 0.03, 0.03), max(1, int(s)))
        text_lines(img, (0.35, 0.7, 0.65, 0.8), 2, (0.5, 0.5, 0.5), r)
        return img

    def side(h: int, w: int, s: float) -> Image:
        img = metal(h, w, s)
        for i in range(3):
            fill_rect(img, (0.1 + 0.08 * i, 0.35, 0.15 + 0.08 * i, 0.65), (0.05, 0.05, 0.05))
        return img

    def display(h: int, w: int, s: float) -> Image:
        img = np.full((h, w, 3), 0.04, dtype=np.float32)
        paste(img, photo(screen_photo), (0.04, 0.06, 0.96, 0.94))
        circle(img, (0.5, 0.03), 1.2 * s, (0.2, 0.2, 0.25))
        return img

    def lid(h: int, w: int, s: float) -> Image:
        img = metal(h, w, s)
        circle(img, (0.5, 0.5), 0.12 * min(h, w), tuple(min(1.0, c * 1.25) for c in shell))
        circle(img, (0.5, 0.5), 0.12 * min(h, w), dark, max(1, int(s)))
        paste(img, photo(sticker), (0.68, 0.66, 0.9, 0.9))
        return img

    return ObjectSpec(
        name="laptop",
        bottom=Slab((210.0, 16.0, 300.0), 4.0),
        top=Slab((210.0, 7.0, 300.0), 2.5),
        spacing=9.0,
        band=3,
        painters={BOTTOM: {"+y": keyboard, "-y": underside, "+z": side, "-z": side}, TOP: {"-y": display, "+y": lid}},
        default={BOTTOM: metal, TOP: metal},
        up={BOTTOM: {"+y": "+x"}},
    )


def _spec_notebook(rng: np.random.Generator) -> ObjectSpec:
    """A5 notebook: cover (148 x 2.5 x 210 mm) hinged over the page block + back cover."""
    cover = jitter_colour(rng, rng.random(), 0.6, 0.55)
    paper = jitter_colour(rng, 0.14, 0.08, 0.96, dh=0.02, ds=0.04, dv=0.02)
    cover_photo = ("motorcycle_left.png", "chelsea.png", "astronaut.png")[int(rng.integers(0, 3))]
    r = np.random.default_rng(rng.integers(0, 2**32))

    def leather(h: int, w: int, s: float) -> Image:
        return material(h, w, cover, grain(h, w, "grass.png", 0.35, r), 0.35)

    def front_cover(h: int, w: int, s: float) -> Image:
        img = leather(h, w, s)
        fill_rect(img, (0.1, 0.1, 0.9, 0.27), paper)
        text(img, "NOTEBOOK", (0.5, 0.185), 0.06 * h, (0.1, 0.1, 0.12), max_width_px=0.7 * w, bold=True)
        paste(img, photo(cover_photo), (0.12, 0.34, 0.88, 0.8))
        text(img, "A5  80 SHEETS", (0.5, 0.9), 0.03 * h, paper, max_width_px=0.6 * w)
        return img

    def ruled(h: int, w: int, s: float) -> Image:
        img = material(h, w, paper, smooth_noise(h, w, r, 10), 0.05)
        for y in np.arange(0.1 * h, h - 2, 7.0 * s):
            cv2.line(img, (0, int(y)), (w, int(y)), (0.55, 0.7, 0.9), 1, cv2.LINE_AA)
        cv2.line(img, (int(0.12 * w), 0), (int(0.12 * w), h), (0.9, 0.35, 0.35), 1, cv2.LINE_AA)
        return img

    def first_page(h: int, w: int, s: float) -> Image:
        img = ruled(h, w, s)
        page = photo("page.png").mean(axis=2)
        lo, hi = np.percentile(page, 5), np.percentile(page, 60)
        page = np.clip((page - lo) / max(hi - lo, 1e-6), 0, 1)  # scan background -> white
        pw = int(0.8 * w)
        ph = max(1, min(int(0.6 * h), int(round(pw * page.shape[0] / page.shape[1]))))
        ink = fit(np.repeat(page[..., None], 3, axis=2), ph, pw)
        y0, x0 = int(0.15 * h), int(0.14 * w)
        img[y0 : y0 + ph, x0 : x0 + pw] *= ink  # print the scanned page onto the paper
        return img

    def page_edges(h: int, w: int, s: float) -> Image:
        img = material(h, w, paper, smooth_noise(h, w, r, 8), 0.05)
        stripes = (np.sin(np.arange(h) * 2.4 + r.random((h,)) * 0.8) * 0.5 + 0.5).astype(np.float32)
        img *= (0.9 + 0.1 * stripes)[:, None, None]
        return img

    def back_cover(h: int, w: int, s: float) -> Image:
        img = leather(h, w, s)
        barcode(img, (0.6, 0.82, 0.85, 0.93), r)
        text_lines(img, (0.15, 0.84, 0.5, 0.92), 2, paper, r)
        return img

    def spine(h: int, w: int, s: float) -> Image:
        return material(h, w, tuple(0.6 * c for c in cover), grain(h, w, "grass.png", 0.3, r), 0.4)

    return ObjectSpec(
        name="notebook",
        bottom=Slab((148.0, 10.0, 210.0), 1.5),
        top=Slab((148.0, 2.5, 210.0), 0.9),
        spacing=5.5,
        band=2,
        painters={
            BOTTOM: {"+y": first_page, "-y": back_cover, "+x": spine},
            TOP: {"+y": front_cover, "-y": ruled, "+x": spine},
        },
        default={BOTTOM: page_edges, TOP: leather},
        up={BOTTOM: {"+y": "+z", "-y": "+z"}, TOP: {"+y": "+z", "-y": "+z"}},
    )


def _spec_phone(rng: np.random.Generator) -> ObjectSpec:
    """Flip phone (ARCTIC "phone"): two 95 x 9-11 x 50 mm halves hinged at a short edge."""
    shell = jitter_colour(rng, rng.random(), 0.45, 0.55)
    inner = tuple(0.5 * c + 0.05 for c in shell)
    screen_photo = ("hubble_deep_field.jpg", "astronaut.png", "rocket.jpg")[int(rng.integers(0, 3))]
    outer_photo = ("coffee.png", "chelsea.png", "rocket.jpg")[int(rng.integers(0, 3))]
    r = np.random.default_rng(rng.integers(0, 2**32))

    def plastic(h: int, w: int, s: float) -> Image:
        return material(h, w, shell, smooth_noise(h, w, r, 5) * 0.5 + 0.5 * brushed(h, w, r), 0.2)

    def keypad(h: int, w: int, s: float) -> Image:
        img = material(h, w, inner, smooth_noise(h, w, r, 5), 0.2)
        circle(img, (0.5, 0.2), 0.16 * w, (0.75, 0.75, 0.78))
        circle(img, (0.5, 0.2), 0.07 * w, tuple(inner))
        fill_rect(img, (0.08, 0.14, 0.26, 0.24), (0.2, 0.65, 0.25))
        fill_rect(img, (0.74, 0.14, 0.92, 0.24), (0.75, 0.2, 0.2))
        labels = "123456789*0#"
        for i, ch in enumerate(labels):
            row, col = divmod(i, 3)
            x0, y0 = 0.1 + col * 0.28, 0.36 + row * 0.13
            cv2.rectangle(
                img, (int(x0 * w), int(y0 * h)), (int((x0 + 0.24) * w), int((y0 + 0.1) * h)), (0.85, 0.85, 0.87), -1
            )
            text(img, ch, ((x0 + 0.12), (y0 + 0.05)), 0.05 * h, (0.1, 0.1, 0.1))
        return img

    def inner_screen(h: int, w: int, s: float) -> Image:
        img = material(h, w, inner, smooth_noise(h, w, r, 5), 0.2)
        fill_rect(img, (0.08, 0.2, 0.92, 0.78), (0.02, 0.02, 0.03))
        paste(img, photo(screen_photo), (0.11, 0.23, 0.89, 0.75))
        fill_rect(img, (0.38, 0.07, 0.62, 0.1), (0.1, 0.1, 0.1))
        return img

    def outer(h: int, w: int, s: float) -> Image:
        img = plastic(h, w, s)
        paste(img, photo(outer_photo), (0.25, 0.3, 0.75, 0.55))
        circle(img, (0.5, 0.15), 0.08 * w, (0.05, 0.05, 0.06))
        circle(img, (0.5, 0.15), 0.08 * w, (0.7, 0.7, 0.72), max(1, int(0.5 * s)))
        return img

    def back(h: int, w: int, s: float) -> Image:
        img = plastic(h, w, s)

        cv2.rectangle(
            img, (int(0.1 * w), int(0.3 * h)), (int(0.9 * w), int(0.9 * h)), tuple(inner), max(1, int(0.4 * s))
        )
        text(img, "PHONE", (0.5, 0.6), 0.05 * h, tuple(inner), max_width_px=0.5 * w, bold=True)
        return img

    return ObjectSpec(
        name="phone",
        bottom=Slab((95.0, 11.0, 50.0), 3.0),
        top=Slab((95.0, 9.0, 50.0), 3.0),
        spacing=2.6,
        band=3,
        painters={BOTTOM: {"+y": keypad, "-y": back}, TOP: {"-y": inner_screen, "+y": outer}},
        default={BOTTOM: plastic, TOP: plastic},
        up={BOTTOM: {"+y": "+x"}},
    )


FLAT_SPECS: dict[str, Callable[[np.random.Generator], ObjectSpec]] = {
    "box": _spec_box,
    "laptop": _spec_laptop,
    "notebook": _spec_notebook,
    "phone": _spec_phone,
}

#: Names :func:`~hogsa_world.objects.catalogue.make_object` knows: all 11 ARCTIC objects, in ARCTIC's index order.
PROCEDURAL_NAMES: tuple[str, ...] = OBJECT_NAMES


# ======================================================================================
# Assembly
# ======================================================================================


def build_parts(spec: ObjectSpec) -> dict[int, PartMesh]:
    """Meshes of both parts in the closed state (mm)."""
    boxes = part_boxes(spec.bottom, spec.top)
    slabs = {TOP: spec.top, BOTTOM: spec.bottom}
    return {
        part: rounded_box(
            boxes[part][0], boxes[part][1], slabs[part].radius, spec.spacing, spec.band, up=spec.up.get(part)
        )
        for part in (TOP, BOTTOM)
    }


def _painter(spec: Optional[ObjectSpec], mesh: PartMesh, part: int, k: int) -> Painter:
    """The painter of chart ``k`` of a part: its own, or the spec's for its face name."""
    if mesh.chart_painters:
        return mesh.chart_painters[k]
    if spec is None:
        raise ValueError("a part without chart painters needs an ObjectSpec")
    return spec.painters.get(part, {}).get(mesh.chart_keys[k], spec.default[part])


def build_textured(spec: Optional[ObjectSpec], parts: dict[int, PartMesh]) -> dict[str, np.ndarray]:
    """Atlas image and textured mesh (charts unwelded; same surface as the welded mesh).

    Args:
        spec: whose painters paint the charts by face name; None when every part carries
            its own chart painters (parts assembled from pieces).
        parts: both parts' meshes and charts.

    Returns:
        dict with ``verts`` (Vt,3) mm, ``faces``, ``uv`` (Vt,2) OBJ convention,
        ``parts`` (Vt,), ``image`` (S,S,3) uint8.
    """
    charts = [(p, k) for p in (TOP, BOTTOM) for k in range(len(parts[p].chart_keys))]
    sizes_mm = [parts[p].chart_size[k] for p, k in charts]
    s, positions, sizes_px = pack_charts(sizes_mm)
    side = ATLAS_SIZE
    atlas = np.full((side, side, 3), 0.5, dtype=np.float32)
    verts, faces, uvs, labels = [], [], [], []
    offset = 0
    for (p, k), (x0, y0), (w, h) in zip(charts, positions, sizes_px):
        mesh = parts[p]
        img = np.ascontiguousarray(_painter(spec, mesh, p, k)(h, w, s), dtype=np.float32)
        assert img.shape == (h, w, 3), (p, mesh.chart_keys[k], img.shape)
        padded = cv2.copyMakeBorder(img, CHART_PAD, CHART_PAD, CHART_PAD, CHART_PAD, cv2.BORDER_REPLICATE)
        atlas[y0 - CHART_PAD : y0 + h + CHART_PAD, x0 - CHART_PAD : x0 + w + CHART_PAD] = padded
        fu, fv = mesh.chart_param[k][:, 0], mesh.chart_param[k][:, 1]
        u = (x0 + fu * w) / side
        v = 1.0 - (y0 + (1.0 - fv) * h) / side
        verts.append(mesh.chart_verts[k])
        faces.append(mesh.chart_faces[k] + offset)
        uvs.append(np.stack([u, v], axis=1))
        labels.append(np.full(mesh.chart_verts[k].shape[0], p, dtype=np.int64))
        offset += mesh.chart_verts[k].shape[0]
    return {
        "verts": np.concatenate(verts),
        "faces": np.concatenate(faces),
        "uv": np.concatenate(uvs),
        "parts": np.concatenate(labels),
        "image": _to_uint8(atlas),
    }
