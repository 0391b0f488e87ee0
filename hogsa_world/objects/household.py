"""Seven of ARCTIC's objects built from pieces: capsule machine, espresso machine, ketchup
bottle, microwave, stand mixer, waffle iron, scissors.

Sizes follow the real objects (10-40 cm); each is two parts, the top articulated about
the z axis through the origin by ``R_z(-θ)`` (``θ = 0`` closed). Lid-like tops (every
object but the scissors) lie in ``x <= 0, y >= GAP/2`` with the hinge at their ``x = 0``
edge and the bottom in ``y <= -GAP/2``, so opening by ``θ`` in ``[0, π/2]`` swings the
top up and back without entering the bottom (as the boxes of
:mod:`hogsa_world.objects.procedural`): the microwave door and the mixer head are such
tops. The scissors' blades are stacked along the hinge instead (top ``z >= GAP/2``,
bottom ``z <= -GAP/2``) and open in the x-y plane. The piece of each part that meets the
other part shares its grid with it, so the closed parts face each other at exactly the
gap. Geometry is fixed; the seed only changes colours, photographs and print.
"""

from __future__ import annotations

import math
from typing import Callable, Sequence

import numpy as np

from hogsa_loader.assets.objects.template import BOTTOM, TOP
from hogsa_world.objects.compound import CompoundSpec, Piece, box_piece, disc_profile, lathe
from hogsa_world.objects.procedural import (
    GAP_MM,
    PHOTOS,
    Image,
    Painter,
    brushed,
    circle,
    fill_rect,
    jitter_colour,
    material,
    paste,
    photo,
    smooth_noise,
    text,
    text_lines,
)

__all__ = ["HOUSEHOLD_SPECS"]

G = GAP_MM / 2.0  # the closed parts face each other at +-G


# ======================================================================================
# Painters shared by several objects
# ======================================================================================


def _sub_rng(rng: np.random.Generator) -> np.random.Generator:
    return np.random.default_rng(rng.integers(0, 2**32))


def plastic(rgb: Sequence[float], r: np.random.Generator, strength: float = 0.12) -> Painter:
    """Smooth coloured plastic."""

    def paint(h: int, w: int, s: float) -> Image:
        return material(h, w, rgb, smooth_noise(h, w, r, 8), strength)

    return paint


def metal(rgb: Sequence[float], r: np.random.Generator) -> Painter:
    """Brushed metal."""

    def paint(h: int, w: int, s: float) -> Image:
        return material(h, w, rgb, 0.8 * brushed(h, w, r) + 0.2 * smooth_noise(h, w, r), 0.35)

    return paint


def wood(rgb: Sequence[float], r: np.random.Generator) -> Painter:
    """Wood: long streaks plus slow rings of growth."""

    def paint(h: int, w: int, s: float) -> Image:
        streak = brushed(h, w, r)
        waves = np.sin(np.linspace(0, 6 + 10 * r.random(), w)[None, :] + 3 * smooth_noise(h, w, r, 4))
        return material(h, w, rgb, 0.6 * streak + 0.4 * (0.5 + 0.5 * waves), 0.35)

    return paint


def decorated(base: Painter, *steps: Callable[[Image, float], None]) -> Painter:
    """``base`` followed by drawing steps ``step(img, px_per_mm)``."""

    def paint(h: int, w: int, s: float) -> Image:
        img = base(h, w, s)
        for step in steps:
            step(img, s)
        return img

    return paint


def _lighter(rgb: Sequence[float], k: float = 1.25) -> tuple[float, float, float]:
    return tuple(min(1.0, k * c) for c in rgb)  # type: ignore[return-value]


def _darker(rgb: Sequence[float], k: float = 0.45) -> tuple[float, float, float]:
    return tuple(k * c for c in rgb)  # type: ignore[return-value]


def _ring_profile(major: float, tube: float, half_height: float, centre_h: float, n: int = 12) -> np.ndarray:
    """(n, 2) closed ``(r, h)`` loop of a ring's tube, counter-clockwise."""
    t = 2.0 * math.pi * np.arange(n) / n
    return np.stack([major + tube * np.cos(t), centre_h + half_height * np.sin(t)], 1)


# ======================================================================================
# Objects
# ======================================================================================


def _capsulemachine(rng: np.random.Generator) -> CompoundSpec:
    """Capsule coffee machine: head + column + drip tray, lid with a capsule button.

    175 x 295 x 120 mm; the lid covers the brewing head and opens upward.
    """
    r = _sub_rng(rng)
    body = jitter_colour(rng, 0.47, 0.35, 0.8)
    accent = jitter_colour(rng, 0.95, 0.45, 0.95)
    dark = (0.12, 0.12, 0.13)
    body_p, accent_p, inner_p = plastic(body, r), plastic(accent, r), plastic((0.8, 0.8, 0.82), r)

    def head_front(img: Image, s: float) -> None:
        fill_rect(img, (0.3, 0.25, 0.7, 0.6), (0.1, 0.1, 0.12))
        text(img, "12:30", (0.5, 0.43), 0.18 * img.shape[0], (0.95, 0.4, 0.35), max_width_px=0.35 * img.shape[1])

    def chamber(img: Image, s: float) -> None:
        circle(img, (0.65, 0.5), 14 * s, dark)
        circle(img, (0.65, 0.5), 18 * s, (0.7, 0.7, 0.72), max(1, int(s)))

    def column_front(img: Image, s: float) -> None:
        h, w = img.shape[:2]
        text(img, "CAPSULE", (0.5, 0.12), 0.05 * h, _darker(body), max_width_px=0.8 * w, bold=True)
        text_lines(img, (0.2, 0.75, 0.8, 0.92), 3, _darker(body), r)

    def grille(img: Image, s: float) -> None:
        for i in range(1, 12):
            fill_rect(img, (i / 12 - 0.01, 0.15, i / 12 + 0.01, 0.85), _darker(accent, 0.6))

    def lid_top(img: Image, s: float) -> None:
        text(img, "BREW", (0.45, 0.8), 0.1 * img.shape[0], _darker(body), max_width_px=0.4 * img.shape[1], bold=True)

    bottom = [
        box_piece(
            (-170, -70, -55),
            (0, -G, 55),
            8,
            body_p,
            spacing=12.0,
            painters={"-x": decorated(body_p, head_front), "+y": decorated(body_p, chamber)},
        ),
        box_piece(
            (-110, -245, -50), (-3, -60, 50), 8, body_p, spacing=16.0, painters={"-x": decorated(body_p, column_front)}
        ),
        box_piece(
            (-175, -255, -60), (0, -235, 60), 5, accent_p, spacing=14.0, painters={"+y": decorated(accent_p, grille)}
        ),
        Piece(
            lathe(disc_profile(10, -95, -66, 2, 2, 2), axis=1, centre=(-140, 0, 0), segments=20),
            metal((0.75, 0.75, 0.78), r),
        ),
        Piece(lathe(disc_profile(18, -118, -106, 3, 3, 2), axis=0, centre=(0, -150, 0), segments=24), accent_p),
    ]
    top = [
        box_piece(
            (-170, G, -55),
            (0, 32, 55),
            8,
            body_p,
            spacing=12.0,
            painters={"+y": decorated(body_p, lid_top), "-y": decorated(inner_p, chamber)},
        ),
        Piece(lathe(disc_profile(18, 28, 40, 3, 3, 2), axis=1, centre=(-60, 0, 0), segments=24), accent_p),
    ]
    return CompoundSpec("capsulemachine", {TOP: top, BOTTOM: bottom})


def _espressomachine(rng: np.random.Generator) -> CompoundSpec:
    """Espresso machine: back column, housing with two group heads, portafilter, knobs and
    steam wand over a drip base; the top is the water-tank lid. 215 x 224 x 300 mm."""
    r = _sub_rng(rng)
    shell = jitter_colour(rng, 0.09, 0.3, 0.85, dh=0.03)
    white = jitter_colour(rng, 0.1, 0.05, 0.95, ds=0.03, dv=0.03)
    steel = (0.72, 0.72, 0.75)
    wood_p, white_p, steel_p = wood(shell, r), plastic(white, r), metal(steel, r)
    black_p = plastic((0.08, 0.08, 0.09), r, 0.3)

    def panel(img: Image, s: float) -> None:
        h, w = img.shape[:2]
        for fx in (0.2, 0.8):
            circle(img, (fx, 0.45), 13 * s, (0.95, 0.95, 0.95))
            circle(img, (fx, 0.45), 13 * s, (0.2, 0.2, 0.2), max(1, int(0.6 * s)))
        fill_rect(img, (0.4, 0.25, 0.6, 0.65), (0.3, 0.32, 0.36))
        for i in range(4):
            circle(img, (0.44 + 0.04 * (i % 2) * 3, 0.35 + 0.2 * (i // 2)), 3 * s, (0.9, 0.9, 0.95))
        text(img, "ESPRESSO", (0.5, 0.85), 0.12 * h, _darker(shell), max_width_px=0.3 * w, bold=True)

    def tank(img: Image, s: float) -> None:
        fill_rect(img, (0.1, 0.0, 0.9, 0.45), (0.1, 0.2, 0.3))

    def grille(img: Image, s: float) -> None:
        for i in range(1, 20):
            fill_rect(img, (i / 20 - 0.006, 0.2, i / 20 + 0.006, 0.8), (0.25, 0.25, 0.27))

    def lid_top(img: Image, s: float) -> None:
        text(img, "WATER", (0.5, 0.5), 0.2 * img.shape[0], _darker(shell), max_width_px=0.3 * img.shape[1], bold=True)

    bottom = [
        box_piece((-60, -197, -147), (-3, -3, 147), 6, wood_p, spacing=28.0),
        box_piece(
            (-150, -75, -150),
            (0, -G, 150),
            6,
            white_p,
            spacing=20.0,
            painters={"-x": decorated(white_p, panel), "+y": decorated(white_p, tank)},
        ),
        box_piece(
            (-150, -200, -150), (0, -186, 150), 4, wood_p, spacing=26.0, painters={"+y": decorated(wood_p, grille)}
        ),
        *[
            Piece(lathe(disc_profile(16, -100, -72, 3, 2, 2), axis=1, centre=(-105, 0, z), segments=16), steel_p)
            for z in (-70, 70)
        ],
        Piece(lathe(disc_profile(7, -215, -100, 3, 1, 2), axis=0, centre=(0, -92, -70), segments=16), black_p),
        *[
            Piece(lathe(disc_profile(15, -162, -146, 4, 2, 2), axis=0, centre=(0, -38, z), segments=16), black_p)
            for z in (-118, 118)
        ],
        Piece(lathe(disc_profile(4, -150, -70, 1.5, 1, 2), axis=1, centre=(-130, 0, 125), segments=12), steel_p),
    ]
    top = [
        box_piece((-150, G, -150), (0, 14, 150), 6, wood_p, spacing=20.0, painters={"+y": decorated(wood_p, lid_top)}),
        Piece(lathe(disc_profile(10, 10, 24, 3, 2, 2), axis=1, centre=(-40, 0, 0), segments=20), steel_p),
    ]
    return CompoundSpec("espressomachine", {TOP: top, BOTTOM: bottom})


def _ketchup(rng: np.random.Generator) -> CompoundSpec:
    """Squeeze bottle (oval, 72 x 207 x 50 mm) whose flip cap is the top part."""
    r = _sub_rng(rng)
    sauce = jitter_colour(rng, 0.0, 0.8, 0.65, dh=0.02)
    cap = jitter_colour(rng, 0.3, 0.6, 0.7)
    label_photo = PHOTOS[int(rng.integers(0, len(PHOTOS)))]
    brand = ("TOMATO", "KETCHUP", "HEINZE", "RED HOT")[int(rng.integers(0, 4))]
    cap_p = plastic(cap, r, 0.2)

    def bottle(h: int, w: int, s: float) -> Image:
        img = material(h, w, sauce, smooth_noise(h, w, r, 10), 0.25)
        for x0 in (0.02, 0.52):  # front and back labels
            fill_rect(img, (x0, 0.25, x0 + 0.46, 0.72), (0.95, 0.93, 0.85))
            paste(img, photo(label_photo), (x0 + 0.1, 0.42, x0 + 0.36, 0.64))
            text(img, brand, (x0 + 0.23, 0.33), 0.04 * h, sauce, max_width_px=0.4 * w, bold=True)
        text_lines(img, (0.55, 0.66, 0.93, 0.7), 1, (0.2, 0.2, 0.2), r)
        return img

    def cap_rings(img: Image, s: float) -> None:
        for fy in (0.35, 0.5, 0.65):
            fill_rect(img, (0, fy - 0.004, 1, fy + 0.004), _darker(cap, 0.7))

    body_profile = np.array(
        [[0, -195], [22, -193], [31, -187], [35, -178], [36, -165]]
        + [[36, y] for y in range(-150, -60, 15)]
        + [[35, -52], [32, -42], [26, -30], [21.5, -21], [20, -14], [0, -14]],
        dtype=float,
    )
    bottom = [
        Piece(lathe(body_profile, axis=1, centre=(-24, 0, 0), scale=(0.7, 1.0), segments=40), bottle),
        Piece(
            lathe(disc_profile(24, -20, -G, 3, rings=5), axis=1, centre=(-24, 0, 0), segments=40),
            decorated(cap_p, cap_rings),
        ),
    ]
    top = [Piece(lathe(disc_profile(24, G, 12, 3, rings=5), axis=1, centre=(-24, 0, 0), segments=40), cap_p)]
    return CompoundSpec("ketchup", {TOP: top, BOTTOM: bottom})


def _microwave(rng: np.random.Generator) -> CompoundSpec:
    """Microwave oven lying on its back (front = +y, world up = +z); the door is the top
    part, hinged at its left edge. 300 x 234 x 210 mm."""
    r = _sub_rng(rng)
    shell = jitter_colour(rng, 0.5, 0.25, 0.85)
    trim = jitter_colour(rng, 0.08, 0.35, 0.9)
    shell_p, trim_p = plastic(shell, r), wood(trim, r)
    chrome = metal((0.8, 0.8, 0.83), r)
    up_z = {"+y": "+z", "-y": "+z"}

    def front(img: Image, s: float) -> None:
        h, w = img.shape[:2]
        fill_rect(img, (0.04, 0.08, 0.63, 0.92), (0.07, 0.07, 0.08))  # cavity behind the door
        circle(img, (0.33, 0.75), 0.18 * h, (0.85, 0.85, 0.88), max(1, int(s)))
        fill_rect(img, (0.7, 0.08, 0.96, 0.25), (0.12, 0.18, 0.14))
        text(img, "0:45", (0.83, 0.165), 0.1 * h, (0.4, 1.0, 0.5), max_width_px=0.2 * w)
        for i in range(9):
            row, col = divmod(i, 3)
            fill_rect(
                img, (0.72 + 0.08 * col, 0.32 + 0.1 * row, 0.78 + 0.08 * col, 0.39 + 0.1 * row), (0.92, 0.92, 0.9)
            )
        circle(img, (0.83, 0.78), 0.08 * h, _darker(trim, 0.8))

    def window(img: Image, s: float) -> None:
        h, w = img.shape[:2]
        fill_rect(img, (0.1, 0.15, 0.85, 0.85), (0.1, 0.1, 0.12))
        fill_rect(img, (0.13, 0.2, 0.82, 0.8), (0.2, 0.22, 0.2))
        step = max(2, int(round(3 * s)))
        img[int(0.2 * h) : int(0.8 * h) : step, int(0.13 * w) : int(0.82 * w) : step] = 0.05
        text(img, "MICRO", (0.47, 0.08), 0.05 * h, _darker(shell), max_width_px=0.3 * w, bold=True)

    feet = [
        Piece(
            lathe(disc_profile(10, -110, -96, 2, 2, 2), axis=2, centre=(x, y, 0), segments=12),
            plastic((0.1, 0.1, 0.1), r),
        )
        for x in (-30, -270)
        for y in (-30, -170)
    ]
    bottom = [
        box_piece(
            (-300, -200, -100),
            (0, -G, 100),
            6,
            shell_p,
            spacing=18.0,
            up=up_z,
            painters={"+y": decorated(shell_p, front), "+z": trim_p, "-z": trim_p},
        ),
        *feet,
    ]
    top = [
        box_piece(
            (-200, G, -100),
            (0, 16, 100),
            6,
            shell_p,
            spacing=18.0,
            up=up_z,
            painters={"+y": decorated(shell_p, window), "-y": plastic((0.75, 0.75, 0.77), r)},
        ),
        box_piece((-195, 14, -60), (-178, 34, 60), 4, chrome, spacing=10.0),
    ]
    return CompoundSpec("microwave", {TOP: top, BOTTOM: bottom})


def _mixer(rng: np.random.Generator) -> CompoundSpec:
    """Stand mixer: base, column and bowl; the tilting head (top part) is hinged at the top
    of the column. 230 x 325 x 140 mm."""
    r = _sub_rng(rng)
    shell = jitter_colour(rng, 0.47, 0.4, 0.8)
    bowl_c = jitter_colour(rng, 0.97, 0.35, 0.95)
    shell_p, bowl_p = plastic(shell, r), plastic(bowl_c, r)
    base_p = wood(jitter_colour(rng, 0.09, 0.35, 0.85, dh=0.02), r)

    def head_side(img: Image, s: float) -> None:
        h, w = img.shape[:2]
        text(img, "MIXER", (0.5, 0.5), 0.25 * h, _lighter(shell, 1.3), max_width_px=0.5 * w, bold=True)

    def dial(img: Image, s: float) -> None:
        for i in range(6):
            fill_rect(img, (i / 6, 0.55, i / 6 + 0.02, 0.8), (0.95, 0.95, 0.95))

    bowl = np.array(
        [[0, -217], [40, -216], [58, -195], [66, -165], [68, -140], [62, -140], [56, -160], [40, -175], [0, -180]],
        dtype=float,
    )
    bottom = [
        box_piece((-230, -250, -70), (-3, -215, 70), 10, base_p, spacing=13.0),
        box_piece((-70, -245, -50), (0, -G, 50), 12, shell_p, spacing=13.0),
        Piece(lathe(bowl, axis=1, centre=(-140, 0, 0), segments=40), bowl_p),
        Piece(
            lathe(disc_profile(14, 48, 58, 3, 2, 2), axis=2, centre=(-35, -60, 0), segments=20), decorated(bowl_p, dial)
        ),
    ]
    top = [
        box_piece(
            (-200, G, -50),
            (0, 75, 50),
            12,
            shell_p,
            spacing=13.0,
            painters={"+z": decorated(shell_p, head_side), "-z": decorated(shell_p, head_side)},
        ),
        Piece(
            lathe(disc_profile(20, -212, -196, 4, 2, 2), axis=0, centre=(0, 38, 0), segments=24),
            metal((0.8, 0.8, 0.82), r),
        ),
    ]
    return CompoundSpec("mixer", {TOP: top, BOTTOM: bottom})


def _waffleiron(rng: np.random.Generator) -> CompoundSpec:
    """Round waffle iron: two 190 mm plates with square waffle inserts and handles, hinged
    at the back. 270 x 83 x 190 mm."""
    r = _sub_rng(rng)
    shell = jitter_colour(rng, 0.55, 0.15, 0.92)
    batter = jitter_colour(rng, 0.11, 0.7, 0.95, dh=0.02)
    shell_p = plastic(shell, r)
    grey = metal((0.55, 0.56, 0.6), r)
    black_p = plastic((0.1, 0.1, 0.11), r, 0.25)

    def waffle(img: Image, s: float) -> None:
        h, w = img.shape[:2]
        img[:] = material(h, w, batter, smooth_noise(h, w, r, 6), 0.3)
        step = max(3, int(round(16 * s)))
        bar = max(1, step // 4)
        for k in range(0, h, step):
            img[k : k + bar] = np.asarray(_darker(batter, 0.65), dtype=np.float32)
        for k in range(0, w, step):
            img[:, k : k + bar] = np.asarray(_darker(batter, 0.65), dtype=np.float32)

    def plate(img: Image, s: float) -> None:
        fill_rect(img, (0, 0.9, 1, 1), _darker(shell, 0.8))

    insert = dict(radius=3, spacing=14.0)
    bottom = [
        Piece(
            lathe(disc_profile(95, -40, -3, 8, 5, 2), axis=1, centre=(-100, 0, 0), segments=32),
            decorated(shell_p, plate),
        ),
        box_piece((-167, -8, -67), (-33, -G, 67), default=grey, painters={"+y": decorated(grey, waffle)}, **insert),
        box_piece((-14, -20, -25), (0, -G, 25), 3, black_p, spacing=8.0),
        box_piece((-270, -30, -14), (-190, -14, 14), 5, black_p, spacing=10.0),
        *[
            Piece(lathe(disc_profile(8, -48, -38, 2, 2, 2), axis=1, centre=(x, 0, z), segments=12), black_p)
            for x, z in ((-60, 45), (-60, -45), (-160, 0))
        ],
    ]
    top = [
        Piece(
            lathe(disc_profile(95, 3, 35, 8, 5, 2), axis=1, centre=(-100, 0, 0), segments=32), decorated(shell_p, plate)
        ),
        box_piece((-167, G, -67), (-33, 8, 67), default=grey, painters={"-y": decorated(grey, waffle)}, **insert),
        box_piece((-14, G, -25), (0, 20, 25), 3, black_p, spacing=8.0),
        box_piece((-270, 14, -14), (-190, 30, 14), 5, black_p, spacing=10.0),
    ]
    return CompoundSpec("waffleiron", {TOP: top, BOTTOM: bottom})


def _scissors(rng: np.random.Generator) -> CompoundSpec:
    """Scissors, 205 mm: each part is a blade, a shank and a finger ring; the blades are
    stacked along the pivot (the z axis) and the rings sit on opposite sides."""
    r = _sub_rng(rng)
    handle = jitter_colour(rng, rng.random(), 0.6, 0.5)
    steel_p = metal((0.78, 0.78, 0.8), r)
    handle_p = plastic(handle, r, 0.25)

    def blade_print(img: Image, s: float) -> None:
        h, w = img.shape[:2]
        text(img, "STAINLESS", (0.25, 0.55), 0.12 * h, (0.35, 0.35, 0.38), max_width_px=0.2 * w)

    blade = np.array(
        [[0, -130], [2, -120], [4, -100], [6, -80], [8, -55], [9.5, -30], [10, -10], [9, 0], [6, 6], [0, 10]],
        dtype=float,
    )

    def half(side: int) -> list[Piece]:
        z = 2.0 * side  # +1: top (z >= G), -1: bottom (z <= -G)
        lo, hi = sorted((side * G, side * (G + 3.0)))
        y0, y1 = sorted((-side * 4.0, -side * 22.0))
        return [
            Piece(
                lathe(blade, axis=0, centre=(0, 0, z), scale=(1.0, 0.15), segments=16), decorated(steel_p, blade_print)
            ),
            box_piece((4, y0, lo), (34, y1, hi), 1.2, handle_p, spacing=5.0),
            Piece(
                lathe(
                    _ring_profile(17, 4.5, 1.5, z),
                    axis=2,
                    centre=(50, -24 * side, 0),
                    scale=(1.25, 1.0),
                    segments=40,
                    loop=True,
                ),
                handle_p,
            ),
            Piece(
                lathe(disc_profile(5, *sorted((side * 3.0, side * 5.0)), 0.8), axis=2, centre=(0, 0, 0), segments=16),
                steel_p,
            ),
        ]

    return CompoundSpec("scissors", {TOP: half(1), BOTTOM: half(-1)})


#: ARCTIC name -> spec builder (the random generator only picks colours and print).
HOUSEHOLD_SPECS: dict[str, Callable[[np.random.Generator], CompoundSpec]] = {
    "capsulemachine": _capsulemachine,
    "espressomachine": _espressomachine,
    "ketchup": _ketchup,
    "microwave": _microwave,
    "mixer": _mixer,
    "waffleiron": _waffleiron,
    "scissors": _scissors,
}
