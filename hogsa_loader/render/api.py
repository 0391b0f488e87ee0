"""The one public Gaussian-splatting entry point, :func:`render`, with two backends.

* ``"torch"``: :func:`hogsa_loader.render.gaussians.render_gaussians`, the CPU rasteriser
  (PyTorch, with compiled compositing kernels on the CPU; any device, float32 or float64,
  differentiable).
* ``"gsplat"``: gsplat 1.5.3's CUDA ``rasterization()`` (CUDA float32 tensors only; see
  :mod:`hogsa_loader.render.gsplat_backend`).
* ``"auto"``: ``"gsplat"`` when the tensors are CUDA float32 and gsplat's CUDA extension
  loads, otherwise ``"torch"``. The choice is in ``RenderOutput.meta["backend"]`` (and
  why, in ``meta["backend_reason"]``).

Both backends follow gsplat 1.5.3's conventions (listed in the docstring of
:mod:`hogsa_loader.render.gaussians`), so they agree up to float32 rounding.

The first CPU render of a process sets glibc's allocator to keep its working memory between
calls (:func:`hogsa_loader.system.keep_allocator_memory`; ``HOGSA_KEEP_MEMORY=0`` opts out).
"""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor

from hogsa_loader.render.gaussians import (
    ED_EPS,
    RenderOutput,
    project_gaussians,
    quat_scale_to_covar,
    render_gaussians,
)
from hogsa_loader.render.gsplat_backend import (
    BackendUnavailableError,
    gsplat_unavailable_reason,
    render_gsplat,
)
from hogsa_loader.system import keep_allocator_memory

__all__ = ["render", "antialias_compensation", "BackendUnavailableError", "BACKENDS", "RENDER_MODES"]

BACKENDS = ("auto", "torch", "gsplat")
RENDER_MODES = ("RGB", "RGB+ED", "RGB+D")
# render_gaussians keyword arguments reachable through **torch_backend_options (the others
# are arguments of render itself). For the gsplat backend: tile_size is passed on,
# valid is applied as opacity 0, and chunk / tile_batch / checkpoint / compositor (speed /
# memory knobs that do not change results) are ignored.
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
    backend: str = "auto",
    sh_degree: int | None = None,
    near_plane: float = 0.01,
    far_plane: float = 1e10,
    backgrounds: Tensor | None = None,
    render_mode: str = "RGB",
    part_ids: Tensor | None = None,
    num_parts: int = 0,
    packed: bool = True,
    antialiased: bool = False,
    eps2d: float = 0.3,
    **torch_backend_options: Any,
) -> RenderOutput:
    """Rasterize 3D Gaussians into B x C images (gsplat 1.5.3 ``rasterization`` conventions).

    Batching: B samples (scenes), each with the same number N of Gaussians (pad with
    zero-opacity Gaussians) and C cameras. The batched layout is below; an unbatched call
    drops the leading B everywhere (means (N, 3), viewmats (C, 4, 4), ... ) and gets
    outputs without it (rgb (C, H, W, 3), ...). Every tensor must be on one device, and
    every floating tensor must have one dtype (float32 or float64; gsplat: float32).

    Conventions: world-to-camera ``viewmats`` in the OpenCV convention (x right, y down,
    z forward; ``p_cam = R p + t``); pinhole ``Ks`` (skew ignored); pixel (row i, col j)
    is sampled at ``(j + 0.5, i + 0.5)``; 2D covariance ``J R Sigma R^T J^T + eps2d I``;
    ``alpha = min(0.999, o exp(-q/2))``, samples with ``alpha < 1/255`` skipped, a pixel
    stops before its transmittance would reach 1e-4; front-to-back compositing by
    camera-space z; ``rgb = sum_i c_i alpha_i T_i + T_final * background``.

    Args:
        means: (B, N, 3) world-space Gaussian centres.
        quats: (B, N, 4) rotations as quaternions in **wxyz** order; need not be
            normalised (they are normalised inside).
        scales: (B, N, 3) per-axis standard deviations, **linear** (exp already applied,
            not log-scales).
        opacities: (B, N) in [0, 1] (sigmoid already applied). Gaussians with opacity
            below 1/255 are culled (this is how padding works).
        colors: with ``sh_degree=None``, post-activation colour features (B, N, D) or per
            camera (B, C, N, D), any D >= 1 (D = 3 for RGB), used as given (no offset, no
            clamp). With ``sh_degree`` set, SH coefficients (B, N, K, 3) or
            (B, C, N, K, 3), K >= (sh_degree + 1)^2, bases in gsplat / Inria order
            (index l^2 + l + m); colour = ``max(SH(mean - camera centre) + 0.5, 0)``.
        viewmats: (B, C, 4, 4) world-to-camera matrices (OpenCV, ``inv(cam_to_world)``).
        Ks: (B, C, 3, 3) intrinsics ``[[fx, 0, cx], [0, fy, cy], [0, 0, 1]]`` in pixels.
            Not differentiable with the gsplat backend.
        width, height: image size W, H in pixels.
        backend: "auto" (default), "torch" or "gsplat" (see the module docstring).
        sh_degree: None for plain colours, or the SH degree 0..4 to evaluate (may be
            lower than the stored K allows).
        near_plane, far_plane: Gaussians with camera z < near_plane or z > far_plane are
            culled (gsplat's ``near_plane`` / ``far_plane``).
        backgrounds: (B, C, D) colour behind the Gaussians (D = 3 with SH), or None (0).
            Part and depth channels always have background 0.
        render_mode: "RGB" (no depth), "RGB+ED" (``depth`` = expected camera z
            ``sum(w z) / max(alpha, 1e-10)``, 0 where nothing was hit) or "RGB+D"
            (``depth`` = accumulated ``sum(w z)``), as gsplat's modes.
        part_ids: (B, N) integer part index of each Gaussian in [0, num_parts), or -1 for
            none. Needed iff ``num_parts > 0``.
        num_parts: P, the number of ``part_alpha`` channels (0 = none).
        packed: gsplat's packed mode (only visible (camera, Gaussian) pairs are kept);
            a memory / speed option that does not change the images. Ignored by the torch
            backend.
        antialiased: gsplat's ``rasterize_mode="antialiased"`` (Mip-Splatting): each
            Gaussian's opacity is multiplied, per camera, by
            ``rho = sqrt(det(cov2d) / det(cov2d + eps2d I))`` (also for culling and its
            pixel extent, as gsplat's projection kernel does). The torch backend
            implements it exactly that way (:func:`antialias_compensation`, then one
            image per (sample, camera) with its own opacities, which costs C copies of
            the Gaussians).
        eps2d: 2D dilation (px^2) added to the projected covariance.
        **torch_backend_options: keyword arguments of ``render_gaussians``:
            ``tile_size`` (16), ``valid`` ((B, N) bool, False = padding),
            ``chunk``, ``tile_batch``, ``checkpoint``, ``compositor`` (speed / memory
            knobs). With the gsplat backend ``tile_size`` is passed on, ``valid``
            becomes opacity 0, the speed knobs are ignored. Any other name is a TypeError.

    The first call on CPU tensors sets this process's glibc allocator to keep freed memory
    (:func:`hogsa_loader.system.keep_allocator_memory`; ``HOGSA_KEEP_MEMORY=0`` opts out).

    Returns:
        :class:`~hogsa_loader.render.gaussians.RenderOutput` with
        ``rgb`` (B, C, H, W, D) (D = 3 with SH), background included;
        ``alpha`` (B, C, H, W, 1) = 1 - final transmittance;
        ``depth`` (B, C, H, W, 1) per ``render_mode``, or None for "RGB";
        ``part_alpha`` (B, C, H, W, P) = sum of the compositing weights of each part's
        Gaussians (sums to ``alpha`` when every Gaussian has a part), or None;
        ``meta``: ``backend`` ("torch" / "gsplat"), ``backend_reason``, ``render_mode``,
        ``antialiased``, ``batched``, plus the backend's own projection results, always in
        the batched layout: the torch backend's (``radii`` (B, C, N, 2), ``means2d``,
        ``depths``, ``conics``, ``colors``, ``n_isects``, ...; with ``antialiased`` also
        ``opacities`` (B, C, N) after compensation) or gsplat's ``meta`` dict (packed:
        ``batch_ids``, ``camera_ids``, ``gaussian_ids``, ``radii`` (nnz, 2), ...).

    Raises:
        ValueError: bad shapes or values; TypeError: bad dtypes or unknown options;
        BackendUnavailableError: ``backend="gsplat"`` cannot run here (CPU tensors, not
            float32, no CUDA, gsplat missing or its CUDA extension not loadable). The
            torch backend is always available; "auto" falls back to it.
    """
    unknown = sorted(set(torch_backend_options) - set(TORCH_BACKEND_OPTIONS))
    if unknown:
        raise TypeError(f"render() got unknown option(s) {unknown}; allowed: {list(TORCH_BACKEND_OPTIONS)}")
    if backend not in BACKENDS:
        raise ValueError(f"backend must be one of {BACKENDS}, got {backend!r}")
    if render_mode not in RENDER_MODES:
        raise ValueError(f"render_mode must be one of {RENDER_MODES}, got {render_mode!r}")

    x = _validate(
        means, quats, scales, opacities, colors, viewmats, Ks, width, height, sh_degree,
        near_plane, far_plane, backgrounds, part_ids, num_parts, eps2d, torch_backend_options,
    )  # fmt: skip
    chosen, reason = _choose_backend(backend, means.device, means.dtype,
                                     int(torch_backend_options.get("tile_size", 16)))  # fmt: skip

    if chosen == "gsplat":
        opts = {k: torch_backend_options[k] for k in ("tile_size", "valid") if k in torch_backend_options}
        if "valid" in opts:
            opts["valid"] = x["valid"]
        out = render_gsplat(
            x["means"], x["quats"], x["scales"], x["opacities"], x["colors"], x["viewmats"], x["Ks"],
            width, height, sh_degree=sh_degree, near_plane=near_plane, far_plane=far_plane,
            backgrounds=x["backgrounds"], render_mode=render_mode, part_ids=x["part_ids"],
            num_parts=num_parts, packed=packed, antialiased=antialiased, eps2d=eps2d, **opts,
        )  # fmt: skip
    else:
        if x["means"].device.type == "cpu":
            keep_allocator_memory()
        opts = dict(torch_backend_options)
        if "valid" in opts:
            opts["valid"] = x["valid"]
        out = _render_torch(
            x["means"], x["quats"], x["scales"], x["opacities"], x["colors"], x["viewmats"], x["Ks"],
            width, height, sh_degree=sh_degree, near_plane=near_plane, far_plane=far_plane,
            backgrounds=x["backgrounds"], render_mode=render_mode, part_ids=x["part_ids"],
            num_parts=num_parts, antialiased=antialiased, eps2d=eps2d, options=opts,
        )  # fmt: skip

    out.meta.update(
        backend=chosen, backend_reason=reason, render_mode=render_mode, antialiased=antialiased, batched=x["batched"]
    )
    if not x["batched"]:
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
# torch backend
# --------------------------------------------------------------------------------------


def antialias_compensation(
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    viewmats: Tensor,
    Ks: Tensor,
    width: int,
    height: int,
    eps2d: float = 0.3,
    near_plane: float = 0.01,
    far_plane: float = 1e10,
) -> Tensor:
    """gsplat's antialiasing factor ``rho = sqrt(max(0, det(cov2d) / det(cov2d + eps2d I)))``.

    Computed from the blurred conic ``Q = (cov2d + eps2d I)^-1`` returned by
    :func:`project_gaussians` as ``det(I - eps2d Q) = (1 - eps2d A)(1 - eps2d C) -
    eps2d^2 B^2`` (the same ratio). Differentiable (rho = 0 where the ratio is <= 0).

    Args:
        means (B, N, 3), quats (B, N, 4) wxyz, scales (B, N, 3) linear,
        viewmats (B, C, 4, 4), Ks (B, C, 3, 3), width, height, eps2d, near/far planes.

    Returns:
        (B, C, N) compensation factors in [0, 1].
    """
    covars = quat_scale_to_covar(quats, scales)
    _, _, _, conics = project_gaussians(means, covars, viewmats, Ks, width, height, eps2d, near_plane, far_plane)
    a, b, c = conics.unbind(-1)
    ratio = (1.0 - eps2d * a) * (1.0 - eps2d * c) - (eps2d * eps2d) * b * b
    ok = ratio > 0  # also False for NaN (degenerate, culled anyway)
    safe = torch.where(ok, ratio, torch.ones_like(ratio))
    return torch.where(ok, torch.sqrt(safe), torch.zeros_like(ratio))


def _render_torch(
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
    sh_degree: int | None,
    near_plane: float,
    far_plane: float,
    backgrounds: Tensor | None,
    render_mode: str,
    part_ids: Tensor | None,
    num_parts: int,
    antialiased: bool,
    eps2d: float,
    options: dict[str, Any],
) -> RenderOutput:
    """render_gaussians on batched, validated inputs (+ antialiasing and "RGB+D")."""
    kw = dict(
        sh_degree=sh_degree, near=near_plane, far=far_plane, background=backgrounds, eps2d=eps2d,
        part_ids=part_ids, num_parts=num_parts, render_depth=render_mode != "RGB", **options,
    )  # fmt: skip
    if not antialiased:
        out = render_gaussians(means, quats, scales, opacities, colors, viewmats, Ks, width, height, **kw)
    else:
        out = _render_torch_antialiased(means, quats, scales, opacities, colors, viewmats, Ks, width, height, kw)
    if render_mode == "RGB+D" and out.depth is not None:
        # render_gaussians gives ED = sum(w z) / max(alpha, 1e-10); undo the division
        out.depth = out.depth * out.alpha.clamp(min=ED_EPS)
    return out


def _render_torch_antialiased(
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    opacities: Tensor,
    colors: Tensor,
    viewmats: Tensor,
    Ks: Tensor,
    width: int,
    height: int,
    kw: dict[str, Any],
) -> RenderOutput:
    """Antialiased rendering: per-camera opacities o * rho, so each (sample, camera) pair
    becomes one sample of a B*C-sample, 1-camera call of render_gaussians."""
    B, C = viewmats.shape[:2]
    N = means.shape[1]
    rho = antialias_compensation(
        means, quats, scales, viewmats, Ks, width, height, kw["eps2d"], kw["near"], kw["far"]
    )  # (B, C, N)
    op_c = opacities[:, None, :] * rho  # (B, C, N)

    def per_gaussian(t: Tensor) -> Tensor:  # (B, N, ...) -> (B*C, N, ...)
        return t[:, None].expand(B, C, *t.shape[1:]).reshape(B * C, *t.shape[1:])

    def per_camera(t: Tensor) -> Tensor:  # (B, C, ...) -> (B*C, 1, ...)
        return t.reshape(B * C, 1, *t.shape[2:])

    per_cam_colors = colors.dim() == (4 if kw["sh_degree"] is None else 5)
    cols = per_camera(colors) if per_cam_colors else per_gaussian(colors)
    kw = dict(kw)
    if kw["background"] is not None:
        kw["background"] = per_camera(kw["background"])
    if kw["part_ids"] is not None:
        kw["part_ids"] = per_gaussian(kw["part_ids"])
    if kw.get("valid") is not None:
        kw["valid"] = per_gaussian(kw["valid"])
    out = render_gaussians(
        per_gaussian(means), per_gaussian(quats), per_gaussian(scales), op_c.reshape(B * C, N), cols,
        per_camera(viewmats), per_camera(Ks), width, height, **kw,
    )  # fmt: skip

    def back(t: Tensor | None) -> Tensor | None:  # (B*C, 1, ...) -> (B, C, ...)
        return None if t is None else t.reshape(B, C, *t.shape[2:])

    meta = {k: back(v) if isinstance(v, Tensor) else v for k, v in out.meta.items()}
    meta["opacities"] = op_c
    meta["compensations"] = rho
    return RenderOutput(
        rgb=back(out.rgb), alpha=back(out.alpha), depth=back(out.depth), part_alpha=back(out.part_alpha), meta=meta
    )  # type: ignore[arg-type]


# --------------------------------------------------------------------------------------
# validation
# --------------------------------------------------------------------------------------


def _shape(t: Tensor) -> tuple[int, ...]:
    return tuple(t.shape)


def _validate(
    means: Any,
    quats: Any,
    scales: Any,
    opacities: Any,
    colors: Any,
    viewmats: Any,
    Ks: Any,
    width: Any,
    height: Any,
    sh_degree: Any,
    near_plane: Any,
    far_plane: Any,
    backgrounds: Any,
    part_ids: Any,
    num_parts: Any,
    eps2d: Any,
    options: dict[str, Any],
) -> dict[str, Any]:
    """Check every argument; return the tensors in the batched layout (+ ``batched``)."""
    named = dict(means=means, quats=quats, scales=scales, opacities=opacities, colors=colors,
                 viewmats=viewmats, Ks=Ks)  # fmt: skip
    if backgrounds is not None:
        named["backgrounds"] = backgrounds
    for name, t in named.items():
        if not isinstance(t, Tensor):
            raise TypeError(f"{name} must be a torch.Tensor, got {type(t).__name__}")
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

    batched = means.dim() == 3
    pre = "(B, " if batched else "("
    B = means.shape[0] if batched else 1
    N = means.shape[-2]
    lead = (B,) if batched else ()

    def need(name: str, t: Tensor, shape: tuple[int, ...], text: str) -> None:
        if _shape(t) != shape:
            raise ValueError(f"{name} must be {pre}{text} = {shape}, got {_shape(t)}")

    need("quats", quats, lead + (N, 4), "N, 4)")
    need("scales", scales, lead + (N, 3), "N, 3)")
    need("opacities", opacities, lead + (N,), "N)")
    if viewmats.dim() != len(lead) + 3 or viewmats.shape[-2:] != (4, 4) or _shape(viewmats)[: len(lead)] != lead:
        raise ValueError(f"viewmats must be {pre}C, 4, 4) with B = {B} as in means, got {_shape(viewmats)}")
    C = viewmats.shape[-3]
    if C < 1:
        raise ValueError("viewmats holds no camera (C = 0)")
    need("Ks", Ks, lead + (C, 3, 3), "C, 3, 3)")

    if sh_degree is not None:
        if isinstance(sh_degree, bool) or not isinstance(sh_degree, int) or not 0 <= sh_degree <= 4:
            raise ValueError(f"sh_degree must be None or an int in 0..4, got {sh_degree!r}")
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
        n_col = 3
    else:
        ok = colors.dim() in (len(lead) + 2, len(lead) + 3) and colors.shape[-1] >= 1
        ok = ok and _shape(colors)[:-1] in (lead + (N,), lead + (C, N))
        if not ok:
            raise ValueError(
                f"colors must be {pre}N, D) or {pre}C, N, D) with N = {N}, C = {C}, D >= 1 "
                f"(or pass sh_degree for SH coefficients), got {_shape(colors)}"
            )
        n_col = colors.shape[-1]
    if backgrounds is not None:
        need("backgrounds", backgrounds, lead + (C, n_col), "C, D)")

    for name, v in (("width", width), ("height", height)):
        if isinstance(v, bool) or not isinstance(v, int) or v <= 0:
            raise ValueError(f"{name} must be a positive int, got {v!r}")
    for name, v in (("near_plane", near_plane), ("far_plane", far_plane), ("eps2d", eps2d)):
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            raise TypeError(f"{name} must be a number, got {type(v).__name__}")
    if not near_plane < far_plane:
        raise ValueError(f"need near_plane < far_plane, got {near_plane} and {far_plane}")
    if eps2d < 0:
        raise ValueError(f"eps2d must be >= 0, got {eps2d}")

    if isinstance(num_parts, bool) or not isinstance(num_parts, int) or num_parts < 0:
        raise ValueError(f"num_parts must be an int >= 0, got {num_parts!r}")
    if num_parts > 0 and part_ids is None:
        raise ValueError("num_parts > 0 needs part_ids")
    if part_ids is not None:
        if num_parts == 0:
            raise ValueError("part_ids given but num_parts = 0; pass num_parts = the number of parts")
        if not isinstance(part_ids, Tensor):
            raise TypeError(f"part_ids must be a torch.Tensor, got {type(part_ids).__name__}")
        if part_ids.dtype.is_floating_point or part_ids.dtype.is_complex or part_ids.dtype == torch.bool:
            raise TypeError(f"part_ids must be an integer tensor, got {part_ids.dtype}")
        if part_ids.device != device:
            raise ValueError(f"part_ids is on device '{part_ids.device}' but means is on '{device}'")
        need("part_ids", part_ids, lead + (N,), "N)")
        if part_ids.numel() > 0:
            lo, hi = int(part_ids.min()), int(part_ids.max())
            if lo < -1 or hi >= num_parts:
                raise ValueError(f"part_ids must lie in [-1, {num_parts}), got values in [{lo}, {hi}]")

    valid = options.get("valid")
    if valid is not None:
        if not isinstance(valid, Tensor) or valid.dtype != torch.bool:
            raise TypeError("valid must be a bool tensor")
        if valid.device != device:
            raise ValueError(f"valid is on device '{valid.device}' but means is on '{device}'")
        need("valid", valid, lead + (N,), "N)")
    tile_size = options.get("tile_size", 16)
    if isinstance(tile_size, bool) or not isinstance(tile_size, int) or tile_size <= 0:
        raise ValueError(f"tile_size must be a positive int, got {tile_size!r}")

    out = dict(means=means, quats=quats, scales=scales, opacities=opacities, colors=colors,
               viewmats=viewmats, Ks=Ks, backgrounds=backgrounds, part_ids=part_ids, valid=valid)  # fmt: skip
    if not batched:
        out = {k: (None if v is None else v[None]) for k, v in out.items()}
    out["batched"] = batched
    return out
