"""The two arguments of one Gaussian-splatting call, shared by :func:`hogsa_loader.render.render`
and its backends: :class:`SplatInputs` (the tensors and the image size) and
:class:`RenderSettings` (everything else)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal, NamedTuple, get_args

from torch import Tensor

__all__ = [
    "SplatInputs",
    "RenderSettings",
    "Backend",
    "RenderMode",
    "Compositor",
    "BACKENDS",
    "RENDER_MODES",
    "COMPOSITORS",
]

Backend = Literal["auto", "torch", "gsplat"]
RenderMode = Literal["RGB", "RGB+ED", "RGB+D"]
Compositor = Literal["auto", "torch", "numba"]
BACKENDS: tuple[str, ...] = get_args(Backend)
RENDER_MODES: tuple[str, ...] = get_args(RenderMode)
COMPOSITORS: tuple[str, ...] = get_args(Compositor)


class SplatInputs(NamedTuple):
    """What one call renders: B samples of N Gaussians each (pad with ``valid`` False or
    zero opacity), seen by C cameras, into W x H images.

    The shapes are the batched layout the backends take; :func:`~hogsa_loader.render.render`
    also takes every tensor without its leading B (one sample). All float tensors share one
    device and one dtype.

    Attributes:
        means: (B, N, 3) world-space centres.
        quats: (B, N, 4) rotations as quaternions in wxyz order (normalised by the renderer).
        scales: (B, N, 3) per-axis standard deviations, linear (not log-scales).
        opacities: (B, N) in [0, 1] (sigmoid already applied); below 1/255 culls.
        colors: with ``RenderSettings.sh_degree`` None, features (B, N, D) or per camera
            (B, C, N, D), any D >= 1, used as given; otherwise SH coefficients (B, N, K, 3)
            or (B, C, N, K, 3) with K >= (sh_degree + 1)^2 (D = 3).
        viewmats: (B, C, 4, 4) world-to-camera matrices, OpenCV (x right, y down, z forward).
        Ks: (B, C, 3, 3) pinhole intrinsics ``[[fx, 0, cx], [0, fy, cy], [0, 0, 1]]`` in pixels.
        width, height: image size W, H in pixels.
        backgrounds: (B, C, D) colour behind the Gaussians, or None (0).
        part_ids: (B, N) integer part in [0, num_parts), or -1 for none; given iff
            ``RenderSettings.num_parts > 0``.
        valid: (B, N) bool, False marks padding Gaussians (culled), or None (all valid).
    """

    means: Tensor
    quats: Tensor
    scales: Tensor
    opacities: Tensor
    colors: Tensor
    viewmats: Tensor
    Ks: Tensor
    width: int
    height: int
    backgrounds: Tensor | None = None
    part_ids: Tensor | None = None
    valid: Tensor | None = None


@dataclass(frozen=True, kw_only=True)
class RenderSettings:
    """How to render: projection, outputs, backend and speed knobs (checked on construction).

    Attributes:
        sh_degree: None for plain colours, or the SH degree 0..4 to evaluate.
        near_plane, far_plane: Gaussians with camera z (metres) below ``near_plane`` or
            above ``far_plane`` are culled.
        eps2d: 2D dilation (px^2) added to the projected covariance.
        render_mode: "RGB" (no depth), "RGB+ED" (expected camera z
            ``sum(w z) / max(alpha, 1e-10)``, 0 where nothing was hit) or "RGB+D"
            (accumulated ``sum(w z)``), as gsplat's modes.
        num_parts: P, the number of ``part_alpha`` channels (0 = none; > 0 needs
            ``part_ids``).
        antialiased: gsplat's ``rasterize_mode="antialiased"`` (Mip-Splatting): each
            Gaussian's opacity is multiplied, per camera, by
            ``rho = sqrt(det(cov2d) / det(cov2d + eps2d I))``.
        tile_size: tile edge in pixels (gsplat: at most 32).
        backend: the backend :func:`~hogsa_loader.render.render` picks ("auto", "torch",
            "gsplat"); the backends themselves ignore it.
        packed: gsplat's packed mode (memory / speed only; ignored by the torch backend).
        compositor: the torch backend's compositor: "torch" (vectorised PyTorch, any
            device and dtype), "numba" (compiled CPU kernels, float32 / float64, opacities
            at most 1, first-order gradients) or "auto" (the kernels wherever they can run).
        chunk: Gaussians per compositing step of the PyTorch compositor (speed only).
        tile_batch: tiles composited together by the PyTorch compositor (bounds memory).
        checkpoint: recompute each tile batch of the PyTorch compositor in the backward
            pass instead of keeping its intermediates (memory only).
        debug: also run the checks that read tensor values (e.g. the range of
            ``part_ids``) on CUDA tensors, where they synchronise the GPU; on CPU tensors
            they always run.

    Raises:
        ValueError / TypeError: a value out of range or of the wrong type.
    """

    sh_degree: int | None = None
    near_plane: float = 0.01
    far_plane: float = 1e10
    eps2d: float = 0.3
    render_mode: RenderMode = "RGB"
    num_parts: int = 0
    antialiased: bool = False
    tile_size: int = 16
    backend: Backend = "auto"
    packed: bool = True
    compositor: Compositor = "auto"
    chunk: int = 32
    tile_batch: int = 2048
    checkpoint: bool = False
    debug: bool = False

    def __post_init__(self) -> None:
        _check_choices(self)
        _check_numbers(self)


def _is_int(v: object) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def _check_choices(s: RenderSettings) -> None:
    """The ``Literal`` fields hold one of their values."""
    if s.backend not in BACKENDS:
        raise ValueError(f"backend must be one of {BACKENDS}, got {s.backend!r}")
    if s.render_mode not in RENDER_MODES:
        raise ValueError(f"render_mode must be one of {RENDER_MODES}, got {s.render_mode!r}")
    if s.compositor not in COMPOSITORS:
        raise ValueError(f"compositor must be 'auto', 'torch' or 'numba', got {s.compositor!r}")


def _check_numbers(s: RenderSettings) -> None:
    """Types and ranges of the numeric fields."""
    if s.sh_degree is not None and (not _is_int(s.sh_degree) or not 0 <= s.sh_degree <= 4):
        raise ValueError(f"sh_degree must be None or an int in 0..4, got {s.sh_degree!r}")
    for name in ("near_plane", "far_plane", "eps2d"):
        v = getattr(s, name)
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            raise TypeError(f"{name} must be a number, got {type(v).__name__}")
    if not s.near_plane < s.far_plane:
        raise ValueError(f"need near_plane < far_plane, got {s.near_plane} and {s.far_plane}")
    if s.eps2d < 0:
        raise ValueError(f"eps2d must be >= 0, got {s.eps2d}")
    if not _is_int(s.num_parts) or s.num_parts < 0:
        raise ValueError(f"num_parts must be an int >= 0, got {s.num_parts!r}")
    if not _is_int(s.tile_size) or s.tile_size <= 0:
        raise ValueError(f"tile_size must be a positive int, got {s.tile_size!r}")
