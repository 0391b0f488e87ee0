"""The one public Gaussian-splatting entry point, :func:`render`, with two backends.

``"torch"`` is :func:`hogsa_loader.render.gaussians.render_gaussians`, the CPU rasteriser (PyTorch, with compiled
compositing kernels on the CPU; any device, float32 or float64, differentiable). ``"gsplat"`` is gsplat 1.5.3's CUDA
``rasterization()`` (CUDA float32 tensors only; see :mod:`hogsa_loader.render.gsplat_backend`). ``"auto"`` picks
``"gsplat"`` when the tensors are CUDA float32 and gsplat's CUDA extension loads, otherwise ``"torch"``; the choice is
in ``RenderOutput.meta["backend"]`` (and why, in ``meta["backend_reason"]``). Both backends take one
:class:`~hogsa_loader.render.settings.SplatInputs` (the tensors and the image size, batched) and one
:class:`~hogsa_loader.render.settings.RenderSettings`, follow gsplat 1.5.3's conventions (listed where they apply in
:mod:`hogsa_loader.render.gaussians`), and agree up to float32 rounding.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import torch
from torch import Tensor

from hogsa_loader.render.gaussians import RenderOutput, antialias_compensation, render_gaussians
from hogsa_loader.render.gsplat_backend import BackendUnavailableError, gsplat_unavailable_reason, render_gsplat
from hogsa_loader.render.settings import BACKENDS, RENDER_MODES, Backend, RenderMode, RenderSettings, SplatInputs
from hogsa_loader.system import keep_allocator_memory

__all__ = ["render", "antialias_compensation", "BackendUnavailableError", "BACKENDS", "RENDER_MODES"]

# RenderSettings fields reachable through render's **torch_backend_options, plus the
# render_gaussians tensor ``valid``. The gsplat backend uses tile_size, applies valid as
# opacity 0 and ignores the rest (speed / memory knobs that do not change results).
TORCH_BACKEND_OPTIONS = ("tile_size", "valid", "chunk", "tile_batch", "checkpoint", "compositor")


def render(
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    opacities: Tensor,
    colors: Tensor,
    viewmats: Tensor,
    Ks: Tensor,
    width: int,
    height: int,
    *,
    backend: Backend = "auto",
    sh_degree: int | None = None,
    near_plane: float = 0.01,
    far_plane: float = 1e10,
    backgrounds: Tensor | None = None,
    render_mode: RenderMode = "RGB",
    part_ids: Tensor | None = None,
    num_parts: int = 0,
    packed: bool = True,
    antialiased: bool = False,
    eps2d: float = 0.3,
    debug: bool = False,
    **torch_backend_options: Any,
) -> RenderOutput:
    """Rasterize 3D Gaussians into B x C images (gsplat 1.5.3 ``rasterization`` conventions).

    B samples (scenes) of N Gaussians each (pad with zero-opacity Gaussians), seen by C
    cameras; an unbatched call drops the leading B of every input and output. All tensors
    share one device and one float dtype (float32 or float64; gsplat: float32).
    Conventions (details in :mod:`hogsa_loader.render.gaussians`): OpenCV world-to-camera
    ``viewmats`` (x right, y down, z forward; ``p_cam = R p + t``), pinhole ``Ks`` (skew
    ignored), pixel (row i, col j) sampled at ``(j + 0.5, i + 0.5)``, 2D covariance
    ``J R Sigma R^T J^T + eps2d I``, ``alpha = min(0.999, o exp(-q/2))`` (below 1/255
    skipped; a pixel stops before its transmittance would reach 1e-4), front to back by
    camera z, ``rgb = sum_i c_i alpha_i T_i + T_final * background``.

    Args:
        means: (B, N, 3) world-space Gaussian centres.
        quats: (B, N, 4) rotations as quaternions in **wxyz** order (normalised inside).
        scales: (B, N, 3) per-axis standard deviations, **linear** (not log-scales).
        opacities: (B, N) in [0, 1] (sigmoid already applied); below 1/255 culls.
        colors: with ``sh_degree=None``, features (B, N, D) or per camera (B, C, N, D),
            any D >= 1, used as given (no offset, no clamp); with ``sh_degree``, SH
            coefficients (B, N, K, 3) or (B, C, N, K, 3), K >= (sh_degree + 1)^2, gsplat /
            Inria order (index l^2 + l + m), colour ``max(SH(mean - camera centre) + 0.5, 0)``.
        viewmats: (B, C, 4, 4) world-to-camera matrices (``inv(cam_to_world)``).
        Ks: (B, C, 3, 3) ``[[fx, 0, cx], [0, fy, cy], [0, 0, 1]]`` px (no gradient via gsplat).
        width, height: image size W, H in pixels.
        backgrounds: (B, C, D) colour behind the Gaussians (D = 3 with SH), or None (0);
            part and depth channels always have background 0.
        part_ids: (B, N) integer part in [0, num_parts), or -1 for none (iff num_parts > 0).
        backend, sh_degree, near_plane, far_plane, render_mode, num_parts, packed, antialiased, eps2d, debug:
            the :class:`~hogsa_loader.render.settings.RenderSettings` fields of the same names.
        **torch_backend_options: the ``RenderSettings`` fields ``tile_size`` (16; also used by gsplat),
            ``chunk``, ``tile_batch``, ``checkpoint`` and ``compositor`` (ignored by gsplat), and ``valid``
            ((B, N) bool, False = padding; gsplat: opacity 0). Any other name is a TypeError.

    Returns:
        :class:`~hogsa_loader.render.gaussians.RenderOutput`: rgb (B, C, H, W, D),
        alpha (B, C, H, W, 1), depth (B, C, H, W, 1) per ``render_mode`` (None for "RGB"),
        part_alpha (B, C, H, W, P) or None; ``meta`` holds ``backend``,
        ``backend_reason``, ``render_mode``, ``antialiased``, ``batched`` and the backend's
        own results in the batched layout (torch: see ``RenderOutput``; gsplat: its
        ``meta`` dict, packed: ``batch_ids``, ``gaussian_ids``, ``radii`` (nnz, 2), ...).

    Raises:
        ValueError / TypeError: bad shapes, values, dtypes or options; BackendUnavailableError:
        ``backend="gsplat"`` cannot run here (CPU tensors, not float32, no CUDA, gsplat or
        its CUDA extension missing; "auto" falls back to "torch").
    """
    fields = dict(backend=backend, sh_degree=sh_degree, near_plane=near_plane, far_plane=far_plane, eps2d=eps2d)
    fields.update(render_mode=render_mode, num_parts=num_parts, packed=packed, antialiased=antialiased, debug=debug)
    settings = _settings(torch_backend_options, **fields)
    valid = torch_backend_options.get("valid")
    inputs = SplatInputs(
        means, quats, scales, opacities, colors, viewmats, Ks, width, height, backgrounds, part_ids, valid
    )
    x, batched = _validate(inputs, settings)
    return _run_backend(x, settings, batched)


def _settings(torch_backend_options: dict[str, Any], **fields: Any) -> RenderSettings:
    """The one :class:`RenderSettings` of a :func:`render` call.

    Raises:
        TypeError: an option outside :data:`TORCH_BACKEND_OPTIONS`.
    """
    unknown = sorted(set(torch_backend_options) - set(TORCH_BACKEND_OPTIONS))
    if unknown:
        raise TypeError(f"render() got unknown option(s) {unknown}; allowed: {list(TORCH_BACKEND_OPTIONS)}")
    return RenderSettings(**fields, **{k: v for k, v in torch_backend_options.items() if k != "valid"})


def _run_backend(x: SplatInputs, settings: RenderSettings, batched: bool) -> RenderOutput:
    """Render validated, batched inputs with the backend ``settings.backend`` picks; the
    choice is recorded in ``meta`` (with ``render_mode``, ``antialiased``, ``batched``:
    whether the caller's inputs came batched; if not, the images lose their B = 1).

    The first torch-backend call on CPU tensors sets this process's glibc allocator to
    keep freed memory (:func:`hogsa_loader.system.keep_allocator_memory`;
    ``HOGSA_KEEP_MEMORY=0`` opts out).
    """
    chosen, reason = _choose_backend(settings.backend, x.means.device, x.means.dtype, settings.tile_size)
    if chosen == "torch" and x.means.device.type == "cpu":
        keep_allocator_memory()
    run = render_gsplat if chosen == "gsplat" else render_gaussians
    out = run(x, settings)
    out.meta.update(
        backend=chosen,
        backend_reason=reason,
        render_mode=settings.render_mode,
        antialiased=settings.antialiased,
        batched=batched,
    )
    return out if batched else _unbatched(out)


def _unbatched(out: RenderOutput) -> RenderOutput:
    """Drop the leading B = 1 of the images (``meta`` stays batched)."""
    out.rgb, out.alpha = out.rgb[0], out.alpha[0]
    out.depth = None if out.depth is None else out.depth[0]
    out.part_alpha = None if out.part_alpha is None else out.part_alpha[0]
    return out


# --------------------------------------------------------------------------------------
# backend choice
# --------------------------------------------------------------------------------------


def _choose_backend(backend: str, device: torch.device, dtype: torch.dtype, tile_size: int = 16) -> tuple[str, str]:
    """(chosen backend, why)."""
    if backend == "torch":
        return "torch", "requested"
    reason = gsplat_unavailable_reason(device, dtype, tile_size)
    if backend == "gsplat":
        if reason is not None:
            raise BackendUnavailableError(f"backend='gsplat' cannot run: {reason}. Use backend='torch' (or 'auto').")
        return "gsplat", "requested"
    if reason is None:
        return "gsplat", "auto: CUDA float32 tensors and gsplat's CUDA extension is usable"
    return "torch", f"auto: {reason}"


# --------------------------------------------------------------------------------------
# validation
# --------------------------------------------------------------------------------------


class _Dims(NamedTuple):
    """Sizes read from the inputs: ``lead`` is (B,) for batched inputs, else (); ``pre`` the
    start of the shapes in error messages."""

    lead: tuple[int, ...]
    N: int
    C: int
    pre: str


def _shape(t: Tensor) -> tuple[int, ...]:
    return tuple(t.shape)


def _need(name: str, t: Tensor, shape: tuple[int, ...], text: str, dims: _Dims) -> None:
    """ValueError unless ``t`` has ``shape`` (described as ``text`` after ``dims.pre``)."""
    if _shape(t) != shape:
        raise ValueError(f"{name} must be {dims.pre}{text} = {shape}, got {_shape(t)}")


def _validate(x: SplatInputs, settings: RenderSettings) -> tuple[SplatInputs, bool]:
    """Check every field of the inputs of :func:`render` (still unchecked, of any type)
    against the others and ``settings``; return them in the batched layout, and whether
    they came so."""
    named = dict(
        means=x.means,
        quats=x.quats,
        scales=x.scales,
        opacities=x.opacities,
        colors=x.colors,
        viewmats=x.viewmats,
        Ks=x.Ks,
    )
    if x.backgrounds is not None:
        named["backgrounds"] = x.backgrounds
    _check_types(named)
    dims = _check_geometry(x)
    n_col = _check_colors(x.colors, settings.sh_degree, dims)
    if x.backgrounds is not None:
        _need("backgrounds", x.backgrounds, dims.lead + (dims.C, n_col), "C, D)", dims)
    for name, v in (("width", x.width), ("height", x.height)):
        if isinstance(v, bool) or not isinstance(v, int) or v <= 0:
            raise ValueError(f"{name} must be a positive int, got {v!r}")
    _check_part_ids(x.part_ids, settings, x.means.device, dims)
    _check_valid(x.valid, x.means.device, dims)
    if dims.lead:
        return x, True
    return SplatInputs(*(t[None] if isinstance(t, Tensor) else t for t in x)), False  # B = 1


def _check_types(named: dict[str, Any]) -> None:
    """Every tensor is a floating torch.Tensor of the dtype and device of ``means``."""
    for name, t in named.items():
        if not isinstance(t, Tensor):
            raise TypeError(f"{name} must be a torch.Tensor, got {type(t).__name__}")
    means = named["means"]
    if means.dim() not in (2, 3) or means.shape[-1] != 3:
        raise ValueError(f"means must be (B, N, 3) or (N, 3), got {_shape(means)}")
    if not means.dtype.is_floating_point:
        raise TypeError(f"means must be a floating-point tensor, got {means.dtype}")
    dtype, device = means.dtype, means.device
    for name, t in named.items():
        if t.dtype != dtype:
            raise TypeError(f"{name} has dtype {t.dtype} but means has {dtype}; all float inputs need one dtype")
        if t.device != device:
            raise ValueError(f"{name} is on device '{t.device}' but means is on '{device}'; all inputs need one device")


def _check_geometry(x: SplatInputs) -> _Dims:
    """Shapes of the Gaussians and cameras, batched (leading B) or not."""
    means, quats, scales, opacities, viewmats, Ks = x.means, x.quats, x.scales, x.opacities, x.viewmats, x.Ks
    batched = means.dim() == 3
    B = means.shape[0] if batched else 1
    lead = (B,) if batched else ()
    dims = _Dims(lead, means.shape[-2], 0, "(B, " if batched else "(")
    N = dims.N
    _need("quats", quats, lead + (N, 4), "N, 4)", dims)
    _need("scales", scales, lead + (N, 3), "N, 3)", dims)
    _need("opacities", opacities, lead + (N,), "N)", dims)
    if viewmats.dim() != len(lead) + 3 or viewmats.shape[-2:] != (4, 4) or _shape(viewmats)[: len(lead)] != lead:
        raise ValueError(f"viewmats must be {dims.pre}C, 4, 4) with B = {B} as in means, got {_shape(viewmats)}")
    dims = dims._replace(C=viewmats.shape[-3])
    if dims.C < 1:
        raise ValueError("viewmats holds no camera (C = 0)")
    _need("Ks", Ks, lead + (dims.C, 3, 3), "C, 3, 3)", dims)
    return dims


def _check_colors(colors: Tensor, sh_degree: int | None, dims: _Dims) -> int:
    """Colour features or SH coefficients of the right shape; returns the colour width D."""
    lead, N, C, pre = dims
    if sh_degree is not None:
        nb = (sh_degree + 1) ** 2
        ok = colors.dim() in (len(lead) + 3, len(lead) + 4) and colors.shape[-1] == 3
        ok = ok and _shape(colors)[:-2] in (lead + (N,), lead + (C, N))
        if not ok:
            raise ValueError(
                f"with sh_degree set, colors must be SH coefficients {pre}N, K, 3) or {pre}C, N, K, 3) "
                f"with N = {N}, C = {C}, got {_shape(colors)}"
            )
        if colors.shape[-2] < nb:
            raise ValueError(f"sh_degree={sh_degree} needs K >= {nb} SH coefficients, got K = {colors.shape[-2]}")
        return 3
    ok = colors.dim() in (len(lead) + 2, len(lead) + 3) and colors.shape[-1] >= 1
    ok = ok and _shape(colors)[:-1] in (lead + (N,), lead + (C, N))
    if not ok:
        raise ValueError(
            f"colors must be {pre}N, D) or {pre}C, N, D) with N = {N}, C = {C}, D >= 1 "
            f"(or pass sh_degree for SH coefficients), got {_shape(colors)}"
        )
    return colors.shape[-1]


def _check_part_ids(part_ids: Any, settings: RenderSettings, device: torch.device, dims: _Dims) -> None:
    """``part_ids`` given iff ``num_parts > 0``: an integer (B, N) tensor on ``device`` with
    values in [-1, num_parts). The value range is read on CPU tensors, and on others only
    with ``settings.debug`` (reading it synchronises a GPU)."""
    num_parts = settings.num_parts
    if num_parts > 0 and part_ids is None:
        raise ValueError("num_parts > 0 needs part_ids")
    if part_ids is None:
        return
    if num_parts == 0:
        raise ValueError("part_ids given but num_parts = 0; pass num_parts = the number of parts")
    if not isinstance(part_ids, Tensor):
        raise TypeError(f"part_ids must be a torch.Tensor, got {type(part_ids).__name__}")
    if part_ids.dtype.is_floating_point or part_ids.dtype.is_complex or part_ids.dtype == torch.bool:
        raise TypeError(f"part_ids must be an integer tensor, got {part_ids.dtype}")
    if part_ids.device != device:
        raise ValueError(f"part_ids is on device '{part_ids.device}' but means is on '{device}'")
    _need("part_ids", part_ids, dims.lead + (dims.N,), "N)", dims)
    if part_ids.numel() > 0 and (part_ids.device.type == "cpu" or settings.debug):
        lo, hi = int(part_ids.min()), int(part_ids.max())
        if lo < -1 or hi >= num_parts:
            raise ValueError(f"part_ids must lie in [-1, {num_parts}), got values in [{lo}, {hi}]")


def _check_valid(valid: Any, device: torch.device, dims: _Dims) -> None:
    """``valid`` is None or a bool (B, N) tensor on ``device``."""
    if valid is None:
        return
    if not isinstance(valid, Tensor) or valid.dtype != torch.bool:
        raise TypeError("valid must be a bool tensor")
    if valid.device != device:
        raise ValueError(f"valid is on device '{valid.device}' but means is on '{device}'")
    _need("valid", valid, dims.lead + (dims.N,), "N)", dims)
