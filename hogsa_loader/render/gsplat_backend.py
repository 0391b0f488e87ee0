"""The ``"gsplat"`` backend of :func:`hogsa_loader.render.render`: gsplat 1.5.3's CUDA
``rasterization()`` behind the entry point's conventions.

gsplat is imported lazily, and only for CUDA tensors: on a CPU-only machine this module
never touches gsplat's CUDA extension (importing ``gsplat.cuda._backend`` starts a JIT
build of the extension when it finds a CUDA toolkit).

Start with :func:`render_gsplat` (its docstring lists the facts about gsplat 1.5.3 this
backend relies on) and :func:`gsplat_unavailable_reason`.
"""

from __future__ import annotations

import functools
from typing import Any, Callable

import torch
from torch import Tensor

from hogsa_loader.errors import HogsaError
from hogsa_loader.render.gaussians import RenderOutput, camera_colors, part_channels
from hogsa_loader.render.settings import RenderSettings, SplatInputs

__all__ = ["BackendUnavailableError", "MAX_GSPLAT_TILE", "gsplat_unavailable_reason", "render_gsplat"]

#: Largest ``tile_size`` gsplat 1.5.3 can launch: its raster kernel runs one thread per
#: pixel of a tile, and a CUDA block holds at most 1024 threads.
MAX_GSPLAT_TILE = 32


class BackendUnavailableError(HogsaError, RuntimeError):
    """The requested renderer backend cannot run here (no CUDA, gsplat missing or its
    CUDA extension not usable, unsupported dtype or option)."""


@functools.lru_cache(maxsize=None)
def _probe_extension() -> str | None:
    """None when gsplat and its CUDA extension load, else why not (cached: a failed
    import of ``gsplat.cuda._backend`` would otherwise retry the JIT build every call)."""
    try:
        import gsplat  # noqa: F401  # deferred: optional CUDA dependency, imported only for CUDA tensors
    except Exception as e:  # ImportError, or anything gsplat's own imports raise
        return f"gsplat is not importable ({type(e).__name__}: {e}); install it with `pip install gsplat==1.5.3`"
    try:
        from gsplat.cuda._backend import _C  # deferred: importing it may JIT-build the CUDA extension
    except Exception as e:  # the JIT build / load of the extension failed
        msg = str(e).strip().splitlines()[-1][:300] if str(e).strip() else ""
        return f"gsplat's CUDA extension failed to load ({type(e).__name__}: {msg})"
    if _C is None:
        return (
            "gsplat's CUDA extension is not available (gsplat found no CUDA toolkit / nvcc "
            "to JIT-build it, and no prebuilt wheel is installed)"
        )
    return None


def gsplat_unavailable_reason(
    device: torch.device, dtype: torch.dtype | None = None, tile_size: int = 16
) -> str | None:
    """Why the gsplat backend cannot render tensors on ``device`` of ``dtype`` with tiles of
    ``tile_size`` (None = it can).

    Cheap for non-CUDA devices and oversized tiles (gsplat is not imported); for CUDA
    devices the first call may JIT-compile gsplat's extension (minutes, once per machine).
    """
    if tile_size > MAX_GSPLAT_TILE:
        return (
            f"tile_size {tile_size} > {MAX_GSPLAT_TILE}: gsplat's raster kernel runs tile_size² threads per "
            "block, at most 1024"
        )
    if device.type != "cuda":
        return f"the tensors are on '{device}', and gsplat's rasteriser runs on CUDA tensors only"
    if not torch.cuda.is_available():
        return "CUDA is not available in this PyTorch build / machine"
    if dtype is not None and dtype != torch.float32:
        return f"gsplat's CUDA kernels are float32 only, got {dtype}"
    return _probe_extension()


def _load_rasterization() -> Callable[..., Any]:
    """gsplat's ``rasterization`` function."""
    from gsplat import rasterization  # deferred: optional CUDA dependency, imported only for CUDA tensors

    return rasterization


def _gsplat_version() -> str:
    try:
        import gsplat  # deferred: optional CUDA dependency, imported only for CUDA tensors

        return str(getattr(gsplat, "__version__", "unknown"))
    except Exception:  # pragma: no cover - only reached after a successful probe
        return "unknown"


def render_gsplat(inputs: SplatInputs, settings: RenderSettings) -> RenderOutput:
    """Render already-validated inputs with gsplat (the arguments of
    :func:`~hogsa_loader.render.gaussians.render_gaussians`: ``inputs`` in the batched
    layout, means (B, N, 3), viewmats (B, C, 4, 4), ...). ``settings.compositor``, ``chunk``,
    ``tile_batch`` and ``checkpoint`` are ignored.

    ``valid`` (B, N) False is applied as opacity 0, which gsplat culls (< 1/255), the same
    result as the torch backend's ``valid``. Returns a :class:`RenderOutput` whose ``meta``
    is gsplat's ``meta`` dict plus ``gsplat_version``.

    Facts about gsplat 1.5.3 this module relies on (read in ``gsplat/rendering.py`` and
    ``gsplat/cuda/_wrapper.py`` of the installed 1.5.3 sources):

    * ``rasterization()`` accepts leading batch dimensions: ``means [..., N, 3]``,
      ``viewmats [..., C, 4, 4]`` and renders all ``prod(...) * C`` images in one call, in
      packed or unpacked mode, returning ``render_colors [..., C, H, W, X]`` and
      ``render_alphas [..., C, H, W, 1]`` (float32) and a ``meta`` dict. So B samples go
      in as one leading dimension; no loop.
    * ``render_mode="RGB+ED"`` / ``"RGB+D"`` append the (expected / accumulated) camera z as
      the *last* channel of ``render_colors``; ED is ``sum(w z) / max(alpha, 1e-10)``.
    * With ``packed=True`` *and* ``backgrounds``, ``rasterize_to_pixels`` asserts
      ``backgrounds.shape == image_dims + (channels,)`` where ``image_dims`` is ``()`` for
      packed inputs, so any ``[..., C, D]`` background fails. This backend therefore never
      passes ``backgrounds`` to gsplat and composites it itself as
      ``rgb + (1 - alpha) * background``, which is the kernel's ``T_final * background``
      (``alpha = 1 - T_final``), differentiable through ``render_alphas``.
    * The kernels are float32 only (``data_ptr<float>``), and ``Ks`` gets no gradient.
    * With ``sh_degree`` set, colours go through gsplat's 3-channel SH kernel. When part
      channels are requested the SH colours are evaluated here first, with the torch backend's
      :func:`hogsa_loader.render.gaussians.camera_colors` (same convention:
      ``max(SH(mean - camera centre) + 0.5, 0)``), and the one-hot part channels are
      rendered as extra plain colour features next to them.

    Raises:
        BackendUnavailableError: gsplat cannot run on these tensors or tiles.
    """
    x, s = inputs, settings
    reason = gsplat_unavailable_reason(x.means.device, x.means.dtype, s.tile_size)
    if reason is not None:
        raise BackendUnavailableError(f"backend='gsplat' cannot run: {reason}")
    rasterization = _load_rasterization()
    opacities = x.opacities
    if x.valid is not None:
        opacities = opacities * x.valid.to(opacities.dtype)
    feats, gs_sh_degree = _features(x, s)
    n_col = 3 if s.sh_degree is not None else x.colors.shape[-1]
    render_colors, render_alphas, meta = rasterization(
        x.means.contiguous(),
        x.quats.contiguous(),
        x.scales.contiguous(),
        opacities.contiguous(),
        feats.contiguous(),
        x.viewmats.contiguous(),
        x.Ks.contiguous(),
        x.width,
        x.height,
        near_plane=s.near_plane,
        far_plane=s.far_plane,
        eps2d=s.eps2d,
        sh_degree=gs_sh_degree,
        packed=s.packed,
        tile_size=s.tile_size,
        backgrounds=None,  # composited below (gsplat 1.5.3 packed + backgrounds asserts)
        render_mode=s.render_mode,
        rasterize_mode="antialiased" if s.antialiased else "classic",
    )
    # render_colors (B, C, H, W, n_col [+ P] [+ 1 depth]), render_alphas (B, C, H, W, 1)
    rgb = render_colors[..., :n_col]
    if x.backgrounds is not None:
        rgb = rgb + (1.0 - render_alphas) * x.backgrounds[:, :, None, None, :]
    part_alpha = render_colors[..., n_col : n_col + s.num_parts] if s.num_parts > 0 else None
    depth = render_colors[..., -1:] if s.render_mode != "RGB" else None
    meta = dict(meta)
    meta["gsplat_version"] = _gsplat_version()
    return RenderOutput(rgb=rgb, alpha=render_alphas, depth=depth, part_alpha=part_alpha, meta=meta)


def _features(x: SplatInputs, s: RenderSettings) -> tuple[Tensor, int | None]:
    """The colour features gsplat renders, and the SH degree it evaluates them with.

    Without parts: ``x.colors`` as given, with ``s.sh_degree``. With ``s.num_parts`` P > 0,
    the one-hot part channels are appended as plain features, so SH colours are evaluated
    here first: (B, N, D + P) or (B, C, N, D + P), SH degree None.
    """
    if s.num_parts == 0:
        return x.colors, s.sh_degree
    assert x.part_ids is not None
    B, C = x.viewmats.shape[:2]
    N = x.means.shape[1]
    feats = x.colors if s.sh_degree is None else camera_colors(x.colors, s.sh_degree, x.means, x.viewmats)
    onehot = part_channels(x.part_ids, s.num_parts, x.means.dtype)  # (B, N, P)
    if feats.dim() == 4:  # per camera (B, C, N, D)
        onehot = onehot[:, None].expand(B, C, N, s.num_parts)
    return torch.cat([feats, onehot], -1), None
