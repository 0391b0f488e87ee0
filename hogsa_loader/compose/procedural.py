"""Procedural backgrounds: the documented fallback when no background image is given.

Gradients, multi-octave value noise, stripes/checkers, soft blobs and "table top" planes
with lighting falloff and sensor grain (a lazily generated, seed-fixed pool of textures,
then random crops, flips and colour gains from the caller's generator). A draw from the
warm pool costs ≈ 1–3 ms, a pool texture ≈ 20–40 ms once
(:meth:`ProceduralBackgrounds.warm` builds all of them up front).
"""

from __future__ import annotations

import math
import threading
from typing import Optional, Sequence

import numpy as np
import torch
import torch.nn.functional as F

from hogsa_loader.compose.sources import BackgroundSource, CropSpec, _crop_resize, _torch_threads, _uniform

__all__ = ["ProceduralBackgrounds"]

_TEXTURE_LOCK = threading.RLock()

# --------------------------------------------------------------------------------------
# Procedural fallback
# --------------------------------------------------------------------------------------


class ProceduralBackgrounds(BackgroundSource):
    """Deterministic procedural backgrounds (the fallback when no image is given).

    Textures come from five families, in random colours:

    0. linear gradient between two colours at a random angle;
    1. multi-octave value noise (3–5 octaves of bicubically upsampled random grids) mapped
       onto a two-colour palette — cloth, stone, foliage-like textures;
    2. stripes or checkers (random period, angle, softness) — tiles, fabric;
    3. soft blobs: 3–8 Gaussian ellipses of random colours on a plain base — clutter;
    4. a "table top": a planar wood-like grain (stretched noise) under a vertical
       gradient (wall/plane horizon).

    Every texture gets a radial lighting falloff and per-pixel sensor grain.

    Speed: generating a texture costs tens of ms, so by default a **pool** of
    ``pool_size`` textures of side ``tile`` is used: texture ``k`` is generated on first
    use from a generator seeded with ``(pool_seed, k)`` alone (so it is the same in every
    process, whatever was drawn before) and kept; each sample draws a texture, a random
    crop (``crop``), a flip and a per-channel colour gain (``colour_jitter``) from the
    caller's generator — about a millisecond per image once the pool is warm.
    ``pool_size=0`` generates every image from the caller's generator directly.

    Everything is deterministic given the generator. These are not photographs: use COCO
    or a folder of photos for training.

    Args:
        pool_size: textures in the pool (0 = no pool).
        tile: side of the pool textures.
        pool_seed: seed of the pool.
        crop: random crop settings of pool textures.
        colour_jitter: per-channel gains ``U(1 − j, 1 + j)`` applied to pool crops.
        grain: std of the additive per-pixel noise.
    """

    kind = "procedural"
    FAMILIES: tuple[str, ...] = ("gradient", "noise", "pattern", "blobs", "table")

    def __init__(
        self,
        pool_size: int = 64,
        tile: int = 320,
        pool_seed: int = 0,
        crop: CropSpec = CropSpec(min_fraction=0.5),
        colour_jitter: float = 0.15,
        grain: float = 0.015,
    ) -> None:
        self.pool_size = int(pool_size)
        self.tile = int(tile)
        self.pool_seed = int(pool_seed)
        self.crop = crop
        self.colour_jitter = float(colour_jitter)
        self.grain = float(grain)
        self._pool: dict[int, np.ndarray] = {}

    def __len__(self) -> int:
        return self.pool_size

    def __repr__(self) -> str:
        return f"ProceduralBackgrounds(pool_size={self.pool_size}, tile={self.tile}, families={self.FAMILIES})"

    def __getstate__(self) -> dict:
        state = dict(self.__dict__)
        state["_pool"] = {}  # regenerated lazily (deterministically) in each process
        return state

    def warm(self) -> "ProceduralBackgrounds":
        """Generate the whole pool now (e.g. before a timed run or before forking workers)."""
        for k in range(self.pool_size):
            self.texture(k)
        return self

    def texture(self, k: int) -> np.ndarray:
        """Pool texture ``k``: (tile, tile, 3) uint8 RGB (generated on first use)."""
        tex = self._pool.get(k)
        if tex is None:
            with _TEXTURE_LOCK:  # one generator at a time (torch thread setting is global)
                tex = self._pool.get(k)
                if tex is None:
                    seed = int(
                        np.random.SeedSequence([self.pool_seed, int(k), 0x70C]).generate_state(1, np.uint64)[0] >> 1
                    )
                    g = torch.Generator().manual_seed(seed)
                    with _torch_threads(1):
                        img = self._one(self.tile, self.tile, g)
                    tex = (img * 255.0).round_().to(torch.uint8).numpy()
                    self._pool[k] = tex
        return tex

    @staticmethod
    def _grid(h: int, w: int) -> tuple[torch.Tensor, torch.Tensor]:
        ys = (torch.arange(h, dtype=torch.float32) + 0.5) / h
        xs = (torch.arange(w, dtype=torch.float32) + 0.5) / w
        return torch.meshgrid(ys, xs, indexing="ij")

    @staticmethod
    def _noise(h: int, w: int, g: torch.Generator, octaves: int, base: int, aniso: float = 1.0) -> torch.Tensor:
        """(h, w) value noise in ≈[0, 1]."""
        acc = torch.zeros(1, 1, h, w)
        amp, total = 1.0, 0.0
        for o in range(octaves):
            gh = max(2, int(base * 2**o))
            gw = max(2, int(base * 2**o * aniso))
            grid = torch.rand(1, 1, gh, gw, generator=g)
            acc += amp * F.interpolate(grid, size=(h, w), mode="bicubic", align_corners=False)
            total += amp
            amp *= 0.5
        n = (acc / total)[0, 0]
        lo, hi = n.min(), n.max()
        return (n - lo) / (hi - lo).clamp_min(1e-6)

    @staticmethod
    def _colour(g: torch.Generator) -> torch.Tensor:
        """A random RGB colour, saturation kept moderate (indoor-like palettes)."""
        base = torch.rand(3, generator=g)
        grey = base.mean()
        sat = 0.2 + 0.6 * torch.rand(1, generator=g)
        val = 0.15 + 0.8 * torch.rand(1, generator=g)
        c = grey + sat * (base - grey)
        return (c / c.max().clamp_min(1e-3) * val).clamp(0, 1)

    def _one(self, h: int, w: int, g: torch.Generator) -> torch.Tensor:
        yy, xx = self._grid(h, w)
        fam = int(torch.randint(len(self.FAMILIES), (1,), generator=g).item())
        c0, c1 = self._colour(g), self._colour(g)
        if fam == 0:
            ang = float(torch.rand(1, generator=g)) * 2 * math.pi
            t = (xx - 0.5) * math.cos(ang) + (yy - 0.5) * math.sin(ang) + 0.5
            t = t.clamp(0, 1)[..., None]
            img = c0 * (1 - t) + c1 * t
        elif fam == 1:
            octv = 3 + int(torch.randint(3, (1,), generator=g).item())
            base = 2 + int(torch.randint(6, (1,), generator=g).item())
            t = self._noise(h, w, g, octv, base)[..., None]
            gamma = 0.5 + 1.5 * float(torch.rand(1, generator=g))
            img = c0 * (1 - t**gamma) + c1 * t**gamma
        elif fam == 2:
            ang = float(torch.rand(1, generator=g)) * math.pi
            period = 0.03 + 0.25 * float(torch.rand(1, generator=g))
            soft = 0.02 + 0.3 * float(torch.rand(1, generator=g))
            checker = bool(torch.rand(1, generator=g) < 0.4)
            u = ((xx - 0.5) * math.cos(ang) + (yy - 0.5) * math.sin(ang)) / period
            s = torch.sin(u * 2 * math.pi)
            if checker:
                v = ((yy - 0.5) * math.cos(ang) - (xx - 0.5) * math.sin(ang)) / period
                s = s * torch.sin(v * 2 * math.pi)
            t = torch.sigmoid(s / soft)[..., None]
            img = c0 * (1 - t) + c1 * t
        elif fam == 3:
            img = c0.expand(h, w, 3).clone()
            k = 3 + int(torch.randint(6, (1,), generator=g).item())
            for _ in range(k):
                cx, cy = torch.rand(2, generator=g).tolist()
                sx, sy = (0.05 + 0.3 * torch.rand(2, generator=g)).tolist()
                ang = float(torch.rand(1, generator=g)) * math.pi
                dx, dy = xx - cx, yy - cy
                u = dx * math.cos(ang) + dy * math.sin(ang)
                v = -dx * math.sin(ang) + dy * math.cos(ang)
                a = torch.exp(-0.5 * ((u / sx) ** 2 + (v / sy) ** 2))[..., None]
                a = a * (0.5 + 0.5 * float(torch.rand(1, generator=g)))
                img = img * (1 - a) + self._colour(g) * a
        else:
            horizon = 0.2 + 0.5 * float(torch.rand(1, generator=g))
            wood = self._noise(h, w, g, 4, 3, aniso=0.15)
            rings = 0.5 + 0.5 * torch.sin(wood * (10 + 30 * float(torch.rand(1, generator=g))))
            t = (0.6 * wood + 0.4 * rings)[..., None]
            table = c0 * (0.75 + 0.25 * t)
            wall_t = (yy / max(horizon, 1e-3)).clamp(0, 1)[..., None]
            wall = c1 * (0.7 + 0.3 * wall_t)
            edge = torch.sigmoid((yy - horizon) / 0.01)[..., None]
            img = wall * (1 - edge) + table * edge
        # lighting falloff and grain
        lx, ly = torch.rand(2, generator=g).tolist()
        strength = 0.45 * float(torch.rand(1, generator=g))
        r2 = (xx - lx) ** 2 + (yy - ly) ** 2
        img = img * (1 - strength * r2.clamp(0, 1))[..., None]
        img = img + self.grain * torch.randn(h, w, 3, generator=g)
        return img.clamp(0, 1)

    def _draw(self, height: int, width: int, generator: torch.Generator) -> tuple[np.ndarray, Optional[np.ndarray]]:
        k = int(torch.randint(self.pool_size, (1,), generator=generator).item())
        u = _uniform(generator, 7)
        lo, hi = math.log(self.crop.min_fraction), math.log(self.crop.max_fraction)
        frac = math.exp(lo + (hi - lo) * u[0])
        img = _crop_resize(self.texture(k), height, width, frac, u[1], u[2], self.crop.hflip and u[3] < 0.5)
        gain = (1.0 - self.colour_jitter + 2.0 * self.colour_jitter * u[4:7]).astype(np.float32)
        return img, gain

    def _direct(self, n: int, h: int, w: int, generator: torch.Generator) -> torch.Tensor:
        out = torch.empty(n, h, w, 3, dtype=torch.float32)
        with _TEXTURE_LOCK, _torch_threads(1):
            for i in range(n):
                out[i] = self._one(h, w, generator)
        return out

    def sample(
        self, n: int, height: int, width: int, generator: torch.Generator, device: Optional[torch.device] = None
    ) -> torch.Tensor:
        """See :meth:`BackgroundSource.sample`: ``(n, H, W, 3)`` float32 in [0, 1]."""
        if self.pool_size <= 0:
            out = self._direct(n, int(height), int(width), generator)
            return out if device is None else out.to(device)
        return super().sample(n, height, width, generator, device)

    def sample_many(
        self, generators: Sequence[torch.Generator], height: int, width: int, device: Optional[torch.device] = None
    ) -> torch.Tensor:
        """See :meth:`BackgroundSource.sample_many`."""
        if self.pool_size <= 0:
            out = torch.cat([self._direct(1, int(height), int(width), g) for g in generators])
            return out if device is None else out.to(device)
        return super().sample_many(generators, height, width, device)
