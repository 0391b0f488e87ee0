"""CPU 3D Gaussian splatting rasteriser with gsplat 1.5.3 conventions.

One public entry point, :func:`render_gaussians`, which runs on any device (it is written for the CPU, where gsplat's
CUDA kernels cannot run) and is differentiable with respect to ``means``, ``quats``, ``scales``, ``opacities`` and
``colors`` (RGB or SH coefficients). Projection, colours and tiling are PyTorch (autograd). Compositing has two
implementations with the same results within float rounding: vectorised PyTorch (autograd; any device and dtype) and
compiled CPU kernels (:mod:`hogsa_loader.render.splat_kernels`, numba, with a hand-written backward pass). Every
gsplat convention, checked against the gsplat 1.5.3 sources (paths relative to the ``gsplat`` package), is stated
where it applies: :func:`project_gaussians` (camera, projection, culling; radii and tiles in its helpers),
:func:`camera_colors` (SH colours), :class:`RenderOutput` (compositing, depth and the known differences from gsplat's
CUDA kernels).
"""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from typing import Any, NamedTuple, Optional

import numpy as np
import torch
import torch.nn.functional as F
import torch.utils.checkpoint
from torch import Tensor

from hogsa_loader.geometry.quaternion import quat_to_matrix
from hogsa_loader.render import splat_kernels
from hogsa_loader.render.raster_kernels import pixel_centres, use_kernels
from hogsa_loader.render.settings import RenderSettings, SplatInputs

__all__ = [
    "RenderOutput",
    "render_gaussians",
    "project_gaussians",
    "quat_scale_to_covar",
    "sh_colors",
    "camera_colors",
    "part_channels",
    "antialias_compensation",
    "warm_up_compositor",
]

ALPHA_THRESHOLD = 1.0 / 255.0  # cuda/include/Common.h: ALPHA_THRESHOLD
ALPHA_MAX = 0.999  # RasterizeToPixels3DGSFwd.cu: min(0.999f, opac * __expf(-sigma))
T_MIN = 1e-4  # RasterizeToPixels3DGSFwd.cu: if (next_T <= 1e-4f) done
RADIUS_EXTENT = 3.33  # ProjectionEWA3DGSFused.cu: float extend = 3.33f
ED_EPS = 1e-10  # rendering.py: render_alphas.clamp(min=1e-10)

# Real SH constants (Sloan, "Efficient Spherical Harmonic Evaluation", JCGT 2013), the
# values gsplat uses in SphericalHarmonicsCUDA.cu / _torch_impl.py: _eval_sh_bases_fast.
_SH_C0 = 0.2820947917738781
_SH_C1 = 0.48860251190292


@dataclass
class RenderOutput:
    """Result of :func:`render_gaussians`.

    Attributes:
        rgb: (B, C, H, W, D) composited colour (D = 3 for RGB / SH), background included.
        alpha: (B, C, H, W, 1) accumulated opacity ``1 - T_final``.
        depth: (B, C, H, W, 1) camera-space depth per ``render_mode``: "RGB+ED", the
            expected ``sum(w z) / max(alpha, 1e-10)`` (0 where alpha is 0); "RGB+D", the
            accumulated ``sum(w z)``; None for "RGB".
        part_alpha: (B, C, H, W, num_parts) ``sum(w)`` over the Gaussians of each part, or
            None when ``num_parts == 0``. Sums to ``alpha`` if every Gaussian has a part.
        meta: projection results, gsplat names: ``radii`` (B, C, N, 2) int32 (0 = culled),
            ``means2d`` (B, C, N, 2) (in the autograd graph: call ``retain_grad()`` on it
            before ``backward`` to read its gradient, as gsplat's densification does),
            ``depths`` (B, C, N), ``conics`` (B, C, N, 3), ``colors`` (B, C, N, D) (after SH),
            ``n_isects`` (int), ``tile_width``, ``tile_height``, ``tile_size``.

    * Compositing (``cuda/csrc/RasterizeToPixels3DGSFwd.cu``): pixel (row i, col j) is sampled
      at ``(j + 0.5, i + 0.5)``; ``alpha = min(0.999, o exp(-sigma))`` with
      ``sigma = 0.5 (A dx^2 + C dy^2) + B dx dy`` (conic ``(A, B, C)`` = inverse cov2d);
      samples with ``alpha < 1/255`` are skipped; a pixel stops *before* the Gaussian whose
      ``next_T = T (1 - alpha)`` would be ``<= 1e-4`` (that Gaussian is excluded);
      ``rgb = sum_i c_i alpha_i T_i + T_final bg``, ``alpha = 1 - T_final``.
    * Depth is gsplat's "ED" mode (``rendering.py: rasterization``): the camera-space z is
      composited like a colour channel (background 0) and divided by
      ``max(alpha, 1e-10)``; pixels with ``alpha == 0`` get depth 0.

    Known, deliberate differences from gsplat's CUDA kernels (all at float32 rounding level):

    * ``log(o) - sigma`` is evaluated as a quadratic polynomial in tile-local pixel
      coordinates (one matmul per chunk; the compiled compositor evaluates it per pixel), and
      ``alpha = exp(log o - sigma)`` instead of ``o * __expf(-sigma)``; within a chunk of D
      Gaussians the transmittance is a ``cumprod`` times the transmittance before the chunk
      (gsplat and the compiled compositor: one running product).
      The cut-off keeps ``alpha > 1/255`` (gsplat: ``>=``). Decisions taken exactly at a
      threshold (``alpha`` = 1/255, ``next_T`` = 1e-4) can therefore flip in rare cases.
    * gsplat also skips a sample when ``sigma < 0``; for a positive-definite conic that only
      happens by rounding, and it is not reproduced.
    * Gradients come from autograd, and for compositing by the compiled compositor from its
      backward pass (the same rules). As in gsplat's backward kernels, nothing flows through
      the 0.999 clamp (``RasterizeToPixels3DGSBwd.cu``: ``if (opac * vis <= 0.999f)``), the
      1/255 cut-off, the termination test or the integer radii; the clamped Jacobian and the
      SH view direction (into ``means``) are differentiated like gsplat's VJPs do. Gradients
      into ``viewmats`` / ``Ks`` may flow but are not tested.
    """

    rgb: Tensor
    alpha: Tensor
    depth: Tensor | None
    part_alpha: Tensor | None
    meta: dict[str, Any] = field(default_factory=dict)


# --------------------------------------------------------------------------------------
# Step 1: covariance and projection
# --------------------------------------------------------------------------------------


def quat_scale_to_covar(quats: Tensor, scales: Tensor) -> Tensor:
    """World covariance ``Sigma = (R S)(R S)^T``.

    Args:
        quats: (..., 4) wxyz, need not be normalised.
        scales: (..., 3) linear standard deviations (not log).

    Returns:
        (..., 3, 3) covariance.
    """
    m = quat_to_matrix(quats) * scales[..., None, :]
    return m @ m.transpose(-1, -2)


def project_gaussians(
    means: Tensor,
    covars: Tensor,
    viewmats: Tensor,
    Ks: Tensor,
    width: int,
    height: int,
    eps2d: float = 0.3,
    near: float = 0.01,
    far: float = 1e10,
    opacities: Tensor | None = None,
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """EWA projection of 3D Gaussians (gsplat ``fully_fused_projection``, pinhole).

    * Camera: ``viewmats`` are world->camera, OpenCV (x right, y down, z forward);
      ``p_cam = R p + t``. Intrinsics ``K = [[fx, 0, cx], [0, fy, cy], [0, 0, 1]]``; the skew
      ``K[0, 1]`` is ignored, as in the CUDA kernel (``cuda/include/Utils.cuh: persp_proj``).
    * Projection (``cuda/include/Utils.cuh: persp_proj``, ``cuda/_torch_impl.py: _persp_proj``):
      ``means2d = (fx x/z + cx, fy y/z + cy)``; EWA Jacobian evaluated at x/z, y/z clamped to
      ``[-(cx/fx + 0.3 tan_fovx), (W - cx)/fx + 0.3 tan_fovx]`` (tan_fovx = W / (2 fx); same
      for y), ``cov2d = J R Sigma R^T J^T + eps2d I`` (``Utils.cuh: add_blur``),
      ``Sigma = (R_q S)(R_q S)^T`` with the quaternion (w, x, y, z) normalised
      (``Utils.cuh: quat_to_rotmat``, ``_torch_impl.py: _quat_scale_to_covar_preci``).
    * Culling (``cuda/csrc/ProjectionEWA3DGSFused.cu: projection_ewa_3dgs_fused_fwd_kernel``, as
      called by ``rendering.py: rasterization``, which passes the opacities): a Gaussian is
      dropped from a camera when ``z < near`` or ``z > far``, when ``det(cov2d) <= 0``, when
      ``opacity < 1/255``, or when its box lies outside the image.

    Args:
        means: (B, N, 3) world positions.
        covars: (B, N, 3, 3) world covariances.
        viewmats: (B, C, 4, 4) world->camera (OpenCV).
        Ks: (B, C, 3, 3) intrinsics.
        width, height: image size in pixels.
        eps2d: isotropic 2D dilation added to cov2d (px^2).
        near, far: a Gaussian is culled when ``z < near`` or ``z > far``.
        opacities: (B, N) or None. When given, the opacity-aware radius of the CUDA kernel
            is used and ``opacity < 1/255`` culls; when None, radius = ceil(3.33 sigma_i)
            as in ``_torch_impl._fully_fused_projection``.

    Returns:
        radii (B, C, N, 2) int32 (0 where culled), means2d (B, C, N, 2),
        depths (B, C, N) camera z, conics (B, C, N, 3) = upper triangle (A, B, C) of
        inverse cov2d.
    """
    rot = viewmats[..., :3, :3]  # (B, C, 3, 3)
    trans = viewmats[..., :3, 3]  # (B, C, 3)
    means_c = torch.einsum("bcij,bnj->bcni", rot, means) + trans[:, :, None, :]
    cov_c = torch.einsum("bcij,bnjk,bclk->bcnil", rot, covars, rot)  # R Sigma R^T
    x, y, z_cam = means_c.unbind(-1)  # (B, C, N)
    # culled depths (e.g. z = 0: padding at the camera centre) are replaced by 1 before any
    # division, so their never-used projections stay finite and their gradients are exactly 0
    # (as gsplat's backward, which skips radius-0 Gaussians), not inf * 0 = NaN
    with torch.no_grad():
        z_in = (z_cam >= near) & (z_cam <= far)
    z = torch.where(z_in, z_cam, torch.ones_like(z_cam))
    fx, fy = Ks[..., 0, 0, None], Ks[..., 1, 1, None]  # (B, C, 1)
    cx, cy = Ks[..., 0, 2, None], Ks[..., 1, 2, None]
    rz = 1.0 / z
    a, b, d = _projected_covariance(x, y, z, rz, cov_c, Ks, width, height, eps2d)
    det = a * d - b * b
    inv_det = 1.0 / torch.where(det > 0, det, torch.ones_like(det))
    conics = torch.stack([d * inv_det, -b * inv_det, a * inv_det], -1)
    means2d = torch.stack([fx * x * rz + cx, fy * y * rz + cy], -1)
    with torch.no_grad():
        radii = _radii(z, a, d, z_in & (det > 0), means2d, opacities, width, height)
    return radii, means2d, z_cam, conics


def _projected_covariance(
    x: Tensor, y: Tensor, z: Tensor, rz: Tensor, cov_c: Tensor, Ks: Tensor, width: int, height: int, eps2d: float
) -> tuple[Tensor, Tensor, Tensor]:
    """Entries ``(a, b, d)`` of ``cov2d = J cov_c J^T + eps2d I = [[a, b], [b, d]]``, each (B, C, N).

    Args:
        x, y, z: (B, C, N) camera-space centres (culled z replaced by 1); rz = 1 / z.
        cov_c: (B, C, N, 3, 3) camera-space covariances; Ks: (B, C, 3, 3).
        width, height: image size (px); eps2d: dilation (px^2).

    ``J = [[fx/z, 0, -fx tx/z^2], [0, fy/z, -fy ty/z^2]]`` with ``tx / z``, ``ty / z``
    clamped to the image's field of view widened by 0.3 ``tan_fov`` on each side.
    """
    fx, fy = Ks[..., 0, 0, None], Ks[..., 1, 1, None]  # (B, C, 1)
    cx, cy = Ks[..., 0, 2, None], Ks[..., 1, 2, None]
    tan_fovx, tan_fovy = 0.5 * width / fx, 0.5 * height / fy
    lim_x_pos, lim_x_neg = (width - cx) / fx + 0.3 * tan_fovx, cx / fx + 0.3 * tan_fovx
    lim_y_pos, lim_y_neg = (height - cy) / fy + 0.3 * tan_fovy, cy / fy + 0.3 * tan_fovy
    tx = z * torch.minimum(torch.maximum(x * rz, -lim_x_neg), lim_x_pos)
    ty = z * torch.minimum(torch.maximum(y * rz, -lim_y_neg), lim_y_pos)
    j00, j02 = fx * rz, -fx * tx * rz * rz
    j11, j12 = fy * rz, -fy * ty * rz * rz
    c = cov_c
    a = j00 * j00 * c[..., 0, 0] + 2 * j00 * j02 * c[..., 0, 2] + j02 * j02 * c[..., 2, 2] + eps2d
    b = j00 * j11 * c[..., 0, 1] + j00 * j12 * c[..., 0, 2] + j02 * j11 * c[..., 2, 1] + j02 * j12 * c[..., 2, 2]
    d = j11 * j11 * c[..., 1, 1] + 2 * j11 * j12 * c[..., 1, 2] + j12 * j12 * c[..., 2, 2] + eps2d
    return a, b, d


def _radii(
    z: Tensor, a: Tensor, d: Tensor, ok: Tensor, means2d: Tensor, opacities: Tensor | None, width: int, height: int
) -> Tensor:
    """Integer pixel radii (B, C, N, 2) int32 of the projected Gaussians, 0 where culled.

    Args:
        z: (B, C, N) camera z (its dtype is the extent's); a, d: (B, C, N) diagonal of
            cov2d; ok: (B, C, N) bool, in the depth range with
            ``det(cov2d) > 0``; means2d: (B, C, N, 2).
        opacities: (B, N) for the opacity-aware extent (and ``opacity < 1/255`` culls),
            or None for the extent 3.33.
        width, height: image size; a Gaussian whose box misses the image is culled.

    * Radius (``cuda/csrc/ProjectionEWA3DGSFused.cu: projection_ewa_3dgs_fused_fwd_kernel``):
      per axis ``r_x = ceil(e sqrt(cov2d_xx))``, ``r_y = ceil(e sqrt(cov2d_yy))`` with the
      opacity-aware extent ``e = min(3.33, sqrt(2 ln(255 o)))``. gsplat's pure-torch
      ``_fully_fused_projection`` uses ``e = 3.33`` (it gets no opacities);
      :func:`project_gaussians` does that too when ``opacities`` is None.
    """
    if opacities is None:
        extent = torch.full_like(z, RADIUS_EXTENT)
    else:
        o = opacities.detach()[:, None, :].expand_as(z)
        ok = ok & (o >= ALPHA_THRESHOLD)
        extent = torch.sqrt(2.0 * torch.log(o.clamp(min=ALPHA_THRESHOLD) / ALPHA_THRESHOLD))
        extent = extent.clamp(max=RADIUS_EXTENT)
    rx = torch.ceil(extent * torch.sqrt(a.detach().clamp(min=0)))
    ry = torch.ceil(extent * torch.sqrt(d.detach().clamp(min=0)))
    ok &= (rx > 0) | (ry > 0)  # radius_clip = 0
    mx, my = means2d.detach().unbind(-1)
    ok &= (mx + rx > 0) & (mx - rx < width) & (my + ry > 0) & (my - ry < height)
    return torch.stack([rx, ry], -1).where(ok[..., None], 0.0).to(torch.int32)


def antialias_compensation(inputs: SplatInputs, settings: RenderSettings | None = None) -> Tensor:
    """gsplat's antialiasing factor ``rho = sqrt(max(0, det(cov2d) / det(cov2d + eps2d I)))``.

    Computed from the blurred conic ``Q = (cov2d + eps2d I)^-1`` returned by
    :func:`project_gaussians` as ``det(I - eps2d Q) = (1 - eps2d A)(1 - eps2d C) -
    eps2d^2 B^2`` (the same ratio). Differentiable (rho = 0 where the ratio is <= 0).

    Args:
        inputs: batched :class:`~hogsa_loader.render.settings.SplatInputs`; means (B, N, 3),
            quats (B, N, 4), scales (B, N, 3), viewmats (B, C, 4, 4), Ks (B, C, 3, 3),
            width and height are used (no opacity culling).
        settings: ``eps2d``, ``near_plane`` and ``far_plane`` are used (None = the defaults).

    Returns:
        (B, C, N) compensation factors in [0, 1].
    """
    x, s = inputs, RenderSettings() if settings is None else settings
    eps2d = s.eps2d
    covars = quat_scale_to_covar(x.quats, x.scales)
    _, _, _, conics = project_gaussians(
        x.means, covars, x.viewmats, x.Ks, x.width, x.height, eps2d, s.near_plane, s.far_plane
    )
    a, b, c = conics.unbind(-1)
    ratio = (1.0 - eps2d * a) * (1.0 - eps2d * c) - (eps2d * eps2d) * b * b
    ok = ratio > 0  # also False for NaN (degenerate, culled anyway)
    safe = torch.where(ok, ratio, torch.ones_like(ratio))
    return torch.where(ok, torch.sqrt(safe), torch.zeros_like(ratio))


# --------------------------------------------------------------------------------------
# Step 2: view-dependent colours
# --------------------------------------------------------------------------------------


def _sh_bases(num_bases: int, dirs: Tensor) -> Tensor:
    """Real SH basis values, gsplat ordering (index l^2 + l + m).

    Args:
        num_bases: 1, 4, 9, 16 or 25.
        dirs: (..., 3) unit directions.

    Returns:
        (..., num_bases).
    """
    x, y, z = dirs.unbind(-1)
    out = [torch.full_like(x, _SH_C0)]
    if num_bases > 1:
        out += [-_SH_C1 * y, _SH_C1 * z, -_SH_C1 * x]
    if num_bases > 4:
        z2 = z * z
        c1, s1 = x * x - y * y, 2 * x * y
        tb = -1.092548430592079 * z
        p6 = 0.9461746957575601 * z2 - 0.3153915652525201
        out += [0.5462742152960395 * s1, tb * y, p6, tb * x, 0.5462742152960395 * c1]
    if num_bases > 9:
        c2, s2 = x * c1 - y * s1, x * s1 + y * c1
        tc = -2.285228997322329 * z2 + 0.4570457994644658
        tb = 1.445305721320277 * z
        ta = -0.5900435899266435
        p12 = z * (1.865881662950577 * z2 - 1.119528997770346)
        out += [ta * s2, tb * s1, tc * y, p12, tc * x, tb * c1, ta * c2]
    if num_bases > 16:
        c3, s3 = x * c2 - y * s2, x * s2 + y * c2
        td = z * (-4.683325804901025 * z2 + 2.007139630671868)
        tc = 3.31161143515146 * z2 - 0.47308734787878
        tb = -1.770130769779931 * z
        ta = 0.6258357354491763
        p20 = 1.984313483298443 * z * p12 - 1.006230589874905 * p6
        out += [ta * s3, tb * s2, tc * s1, td * y, p20, td * x, tc * c1, tb * c2, ta * c3]
    return torch.stack(out, -1)


def sh_colors(sh_degree: int, dirs: Tensor, coeffs: Tensor) -> Tensor:
    """Evaluate SH colours (gsplat ``spherical_harmonics``; no +0.5 offset here).

    Args:
        sh_degree: 0..4; only the first (sh_degree + 1)^2 coefficients are used.
        dirs: (..., 3) view directions (normalised here).
        coeffs: (..., K, 3), K >= (sh_degree + 1)^2.

    Returns:
        (..., 3) raw SH value.
    """
    if not 0 <= sh_degree <= 4:
        raise ValueError(f"sh_degree must be in 0..4, got {sh_degree}")
    nb = (sh_degree + 1) ** 2
    if coeffs.shape[-2] < nb:
        raise ValueError(f"sh_degree={sh_degree} needs K >= {nb} coefficients, got {coeffs.shape[-2]}")
    bases = _sh_bases(nb, F.normalize(dirs, p=2, dim=-1))
    return (bases[..., None] * coeffs[..., :nb, :]).sum(-2)


def camera_colors(colors: Tensor, sh_degree: int | None, means: Tensor, viewmats: Tensor) -> Tensor:
    """Per-camera colours (B, C, N, D) from plain colours or SH coefficients.

    ``colors`` is (B, N, D) / (B, C, N, D) when ``sh_degree`` is None, else (B, N, K, 3) /
    (B, C, N, K, 3). SH colours get gsplat's ``clamp_min(sh + 0.5, 0)``.

    * SH colours (``rendering.py: rasterization``, ``cuda/csrc/SphericalHarmonicsCUDA.cu``,
      ``_torch_impl.py: _spherical_harmonics``): view direction ``mean - camera centre`` with
      the centre ``inv(viewmat)[:3, 3]``, normalised; real SH basis of degree <= 4, index
      ``l^2 + l + m``; colour ``= max(SH(dir) + 0.5, 0)``. Plain colours (``sh_degree=None``)
      are used as given, with no offset and no clamp, like gsplat.
    """
    B, C = viewmats.shape[:2]
    N = means.shape[1]
    if sh_degree is None:
        if colors.dim() == 3:
            colors = colors[:, None]
        return colors.expand(B, C, N, colors.shape[-1])
    campos = torch.linalg.inv(viewmats)[..., :3, 3]  # (B, C, 3): camera centre in world
    dirs = means[:, None, :, :] - campos[:, :, None, :]  # (B, C, N, 3)
    if colors.dim() == 4:
        colors = colors[:, None]
    coeffs = colors.expand(B, C, N, *colors.shape[-2:])
    return torch.clamp_min(sh_colors(sh_degree, dirs, coeffs) + 0.5, 0.0)


# --------------------------------------------------------------------------------------
# Step 3: tile intersection and sorting
# --------------------------------------------------------------------------------------


@torch.no_grad()
def _intersect_tiles(
    means2d: Tensor, radii: Tensor, depths: Tensor, tile_size: int, tile_w: int, tile_h: int
) -> tuple[Tensor, Tensor, Tensor]:
    """List the (image, tile, Gaussian) intersections, sorted front to back per tile.

    Args:
        means2d: (I, N, 2); radii: (I, N, 2) int32; depths: (I, N).
        tile_size, tile_w, tile_h: tile edge in px and the tile grid size.

    Returns:
        flat_ids (K,) int64 index into I * N, tile_ids (K,) int64 global tile index
        ``image * tile_h * tile_w + ty * tile_w + tx`` (non-decreasing), and
        tile_counts (I * tile_h * tile_w,) int64.

    * Tiles (``cuda/csrc/IntersectTile.cu: intersect_tile_kernel``): tile range
      ``[floor(m/ts - r/ts), ceil(m/ts + r/ts))`` clamped to the grid, in float32. The
      intersections are sorted by (image, tile, float32 depth bits) with a *stable* sort of
      keys laid out in (image, Gaussian) order, like gsplat's CUB radix sort, so exact
      depth ties keep the Gaussian index order.
    """
    n_img, n = depths.shape
    n_tiles = tile_h * tile_w
    ts = float(tile_size)
    m = means2d.float()
    r = radii.float()
    # float32 arithmetic of IntersectTile.cu; negative values clamp to 0 as the uint cast does
    lo = torch.floor(m / ts - r / ts)
    hi = torch.ceil(m / ts + r / ts)
    lim = torch.tensor([tile_w, tile_h], dtype=torch.float32, device=m.device)
    lo = torch.minimum(lo.clamp(min=0), lim).long()
    hi = torch.minimum(hi.clamp(min=0), lim).long()
    span = (hi - lo).clamp(min=0)
    counts = span[..., 0] * span[..., 1]
    counts = torch.where((radii > 0).all(-1), counts, 0).reshape(-1)  # (I * N,)
    flat = torch.nonzero(counts).squeeze(1)
    cnt = counts[flat]
    total = int(cnt.sum())
    dev = means2d.device
    if total == 0:
        empty = torch.zeros(0, dtype=torch.long, device=dev)
        return empty, empty, torch.zeros(n_img * n_tiles, dtype=torch.long, device=dev)
    flat_ids = torch.repeat_interleave(flat, cnt, output_size=total)
    first = torch.cumsum(cnt, 0) - cnt
    local = torch.arange(total, device=dev) - torch.repeat_interleave(first, cnt, output_size=total)
    w = span[..., 0].reshape(-1)[flat_ids]
    lo_f = lo.reshape(-1, 2)[flat_ids]
    tx = lo_f[:, 0] + local % w
    ty = lo_f[:, 1] + local // w
    tile_ids = (flat_ids // n) * n_tiles + ty * tile_w + tx
    # key = tile << 32 | float32 depth bits (positive floats sort like their bit patterns)
    depth_bits = depths.float().reshape(-1)[flat_ids].view(torch.int32).long() & 0xFFFFFFFF
    keys = (tile_ids << 32) | depth_bits
    keys, perm = torch.sort(keys, stable=True)  # stable: ties keep (image, Gaussian) order
    tile_ids = keys >> 32
    flat_ids = flat_ids[perm]
    tile_counts = torch.bincount(tile_ids, minlength=n_img * n_tiles)
    return flat_ids, tile_ids, tile_counts


# --------------------------------------------------------------------------------------
# Step 4: compositing
# --------------------------------------------------------------------------------------


def _tile_basis(tile_size: int, dtype: torch.dtype, device: torch.device) -> Tensor:
    """(P, 6) monomials [lx^2, ly^2, lx ly, lx, ly, 1] of tile-local pixel-centre coords
    (origin at the tile centre, row-major pixels)."""
    r = torch.arange(tile_size, dtype=dtype, device=device) - (tile_size - 1) / 2
    ly, lx = torch.meshgrid(r, r, indexing="ij")
    lx, ly = lx.reshape(-1), ly.reshape(-1)
    return torch.stack([lx * lx, ly * ly, lx * ly, lx, ly, torch.ones_like(lx)], -1)


def _gaussian_table(means2d: Tensor, conics: Tensor, log_opac: Tensor, feats: Tensor) -> Tensor:
    """Per (image, Gaussian) rows read by the compositor, plus an inert dummy row.

    Args:
        means2d (M, 2), conics (M, 3), log_opac (M,), feats (M, F), M = I * N.

    Returns:
        (M + 1, 9 + F) = [mx, my, A, B, C, -A/2, -C/2, -B, log o | feats]; the last row
        has log o = -1e4 (alpha = 0) and pads chunks past the end of a tile's list.
    """
    a, b, c = conics.unbind(-1)
    rows = torch.cat([means2d, conics, torch.stack([-0.5 * a, -0.5 * c, -b, log_opac], -1), feats], -1)
    dummy = torch.zeros(1, rows.shape[1], dtype=rows.dtype, device=rows.device)
    dummy[0, 8] = -1e4
    return torch.cat([rows, dummy], 0)


def _chunk_coefficients(rows: Tensor, origin: Tensor) -> Tensor:
    """Coefficients of ``log(o) - sigma`` as a quadratic in tile-local coordinates.

    Args:
        rows: (na, D, 9 + F) Gaussian rows (see :func:`_gaussian_table`).
        origin: (na, 2) pixel coordinates of each tile's centre.

    Returns:
        (na, 6, D), to be multiplied by the (P, 6) basis. The offsets ``m - origin`` are
        taken first (small numbers), which keeps float32 cancellation small.
    """
    dx = rows[..., 0] - origin[:, 0:1]
    dy = rows[..., 1] - origin[:, 1:2]
    a, b, c = rows[..., 2], rows[..., 3], rows[..., 4]
    qx = a * dx + b * dy  # Q d, Q = [[A, B], [B, C]]
    qy = b * dx + c * dy
    const = rows[..., 8] - 0.5 * (qx * dx + qy * dy)  # log o - d^T Q d / 2
    return torch.cat([rows[..., 5:8], torch.stack([qx, qy, const], -1)], -1).transpose(1, 2)


def _composite_chunk(
    coef: Tensor, feat: Tensor, basis: Tensor, t_prev: Tensor, done: Tensor
) -> tuple[Tensor, Tensor, Tensor]:
    """Front-to-back compositing of one depth chunk for a set of tiles.

    Args:
        coef: (na, 6, D) quadratic coefficients (front to back along D).
        feat: (na, D, F) features of the chunk's Gaussians.
        basis: (P, 6) tile-local monomials.
        t_prev: (na, P) transmittance before the chunk; done: (na, P) bool.

    Returns:
        out (na, P, F) = sum_j w_j feat_j, new transmittance (na, P), and the pixels that
        terminated in this chunk (na, P) bool.

    ``alpha_j = min(0.999, exp(G_j))`` (0 below 1/255), ``next_T_j = T_prev prod_{i<=j}
    (1 - alpha_i)`` by cumprod, kept while ``next_T_j > 1e-4`` (gsplat's exclusive stop;
    the kept set is a prefix), weights ``w_j = alpha_j T_j = next_T_j alpha_j / (1 -
    alpha_j)`` (``1 - alpha >= 0.001``). F.threshold / hardtanh are used because their
    forward and backward kernels are much cheaper on CPU than ``where`` / ``clamp``.
    """
    g = torch.matmul(basis, coef)  # (na, P, D) = log(o) - sigma
    alpha = F.hardtanh(F.threshold(torch.exp(g), ALPHA_THRESHOLD, 0.0), 0.0, ALPHA_MAX)
    one_minus = 1.0 - alpha
    next_t = torch.cumprod(one_minus, -1) * t_prev.masked_fill(done, 0.0)[..., None]
    kept_next_t = F.threshold(next_t, T_MIN, 0.0)  # next_T where the pixel goes on, else 0
    w = kept_next_t * (alpha / one_minus)
    out = torch.bmm(w, feat)
    with torch.no_grad():
        n_keep = (kept_next_t > 0).sum(-1, keepdim=True)
        saturated = n_keep.squeeze(-1) < coef.shape[-1]
    last = next_t.gather(-1, (n_keep - 1).clamp(min=0)).squeeze(-1)
    t_new = torch.where(n_keep.squeeze(-1) > 0, last, t_prev)
    return out, t_new, saturated


def _composite_tiles(
    table: Tensor,
    gids: Tensor,
    tile_start: Tensor,
    tile_count: Tensor,
    origin: Tensor,
    pix_done: Tensor,
    basis: Tensor,
    chunk: int,
) -> tuple[Tensor, Tensor]:
    """Composite a batch of tiles, chunk by chunk, dropping tiles that are finished.

    Args:
        table: (M + 1, 9 + F) Gaussian rows (row M is the inert dummy).
        gids: (K + 1,) int64 sorted intersection -> table row (last entry = M, dummy).
        tile_start, tile_count: (nt,) int64 offsets / lengths of the tiles' lists.
        origin: (nt, 2) tile centres in pixel coordinates.
        pix_done: (nt, P) bool, True for padding pixels outside the image.
        basis: (P, 6); chunk: D.

    Returns:
        acc (nt, P, F) = sum_i w_i feat_i and the final transmittance (nt, P).
    """
    dev, dtype = table.device, table.dtype
    nt, p = pix_done.shape
    k_end = gids.shape[0] - 1
    ncol = table.shape[1]
    ar = torch.arange(chunk, device=dev)
    trans = torch.ones(nt, p, dtype=dtype, device=dev)
    done = pix_done.clone()
    act = torch.arange(nt, device=dev)
    outs: list[Tensor] = []
    out_idx: list[Tensor] = []
    k = 0
    while act.numel() > 0:
        full = act.numel() == nt
        pos = k + ar  # (D,)
        idx = torch.where(pos < tile_count[act, None], tile_start[act, None] + pos, k_end)
        rows = table.index_select(0, gids[idx.reshape(-1)]).view(act.numel(), chunk, ncol)
        coef = _chunk_coefficients(rows, origin if full else origin[act])
        t_a = trans if full else trans.index_select(0, act)
        d_a = done if full else done.index_select(0, act)
        out, t_new, sat = _composite_chunk(coef, rows[..., 9:], basis, t_a, d_a)
        outs.append(out)
        out_idx.append(act)
        trans = t_new if full else trans.index_copy(0, act, t_new)
        d_a = d_a | sat
        if full:
            done = d_a
        else:
            done[act] = d_a
        k += chunk
        alive = (tile_count[act] > k) & ~d_a.all(1)
        act = act[alive]
    acc = torch.zeros(nt, p, ncol - 9, dtype=dtype, device=dev)
    if outs:
        acc = acc.index_add(0, torch.cat(out_idx), torch.cat(outs))
    return acc, trans


_POOL: Optional[tuple[int, int, ThreadPoolExecutor]] = None  # (owner pid, threads, pool) of the compositor


def _thread_pool(n: int) -> ThreadPoolExecutor:
    """This process's threads for the compiled compositor (kept between calls, so that no
    thread, stack or allocator arena is created per render; made anew in a forked child,
    whose copy of the parent's pool has no threads)."""
    global _POOL
    if _POOL is None or _POOL[0] != os.getpid() or _POOL[1] < n:
        if _POOL is not None and _POOL[0] == os.getpid():
            _POOL[2].shutdown(wait=False)
        _POOL = (os.getpid(), n, ThreadPoolExecutor(max_workers=n, thread_name_prefix="hogsa-composite"))
    return _POOL[2]


def _run_split(kernel: Any, work: Tensor, args: tuple, scratch: tuple[int, torch.dtype]) -> None:
    """Run ``kernel(sel, *args, scratch_i)`` over the busy tiles, dealt round-robin (they
    come sorted by list length) to as many threads as torch uses (the caller's and pool
    threads; the kernels release the GIL). Each thread gets its own scratch array of
    ``scratch`` = (size, dtype)."""
    n = max(1, min(torch.get_num_threads(), work.numel()))
    parts = [np.ascontiguousarray(work[i::n].numpy()) for i in range(n)]
    buf = torch.empty(n, scratch[0], dtype=scratch[1]).numpy()
    others = [_thread_pool(n - 1).submit(kernel, part, *args, buf[i + 1]) for i, part in enumerate(parts[1:])]
    try:
        kernel(parts[0], *args, buf[0])
    finally:
        for f in others:
            f.result()


class _CompiledComposite(torch.autograd.Function):
    """Compositing of the busy tiles by :mod:`hogsa_loader.render.splat_kernels`, with its
    hand-written backward pass (the same gradients as the PyTorch compositor)."""

    @staticmethod
    def forward(
        ctx: Any,
        means2d: Tensor,
        conics: Tensor,
        log_o: Tensor,
        feats: Tensor,
        radii: Tensor,
        gids: Tensor,
        busy: Tensor,
        start: Tensor,
        count: Tensor,
        geometry: tuple[int, ...],
    ) -> tuple[Tensor, Tensor]:
        """means2d (M, 2), conics (M, 3), log_o (M,), feats (M, F), radii (M, 2) int32,
        gids (K,), busy / start / count (nb,) int64, geometry ``(tile_size, tile_w, n_tiles,
        width, height)`` -> acc (nb, P, F), trans (nb, P)."""
        tile_size = geometry[0]
        nb, p, nf = busy.shape[0], tile_size * tile_size, feats.shape[1]
        dtype = feats.dtype
        tables = tuple(t.detach().contiguous() for t in (means2d.to(dtype), conics.to(dtype), log_o.to(dtype), feats))
        consts = torch.tensor([ALPHA_THRESHOLD, ALPHA_MAX, T_MIN, 1.0], dtype=dtype)
        acc = torch.zeros(nb, p, nf, dtype=dtype)
        trans = torch.ones(nb, p, dtype=dtype)
        last = torch.zeros(nb, p, dtype=torch.int32)
        radii = radii.contiguous()
        order = torch.argsort(count, descending=True, stable=True)
        ts, tile_w, n_tiles = geometry[:3]
        pxs, pys = (pixel_centres(n, dtype).numpy() for n in (tile_w * ts, n_tiles // tile_w * ts))
        common = (
            busy.numpy(),
            start.numpy(),
            count.numpy(),
            gids.numpy(),
            *(t.numpy() for t in tables[:3]),
            radii.numpy(),
            tables[3].numpy(),
            *geometry,
            pxs,
            pys,
            consts.numpy(),
        )
        _run_split(
            splat_kernels.composite_forward, order, (*common, acc.numpy(), trans.numpy(), last.numpy()), (p, torch.bool)
        )
        ctx.save_for_backward(*tables, gids, trans, last)  # (in-place changes before backward are caught)
        ctx.common, ctx.order = common, order  # the kernels' shared arguments, views of the saved tensors
        ctx.dtypes = (means2d.dtype, conics.dtype, log_o.dtype)
        return acc, trans

    @staticmethod
    def backward(ctx: Any, v_acc: Tensor, v_trans: Tensor) -> tuple[Any, ...]:
        if torch.is_grad_enabled():  # backward(create_graph=True): the kernels' gradients are not differentiable
            raise RuntimeError(
                "the compiled compositor gives first-order gradients only; render with "
                "compositor='torch' for higher-order ones"
            )
        m2d, _, _, feats, gids, trans, last = ctx.saved_tensors
        dtype, nf = feats.dtype, feats.shape[1]
        grads = torch.zeros(gids.shape[0], splat_kernels.GRAD_COLUMNS + nf, dtype=dtype)
        _run_split(
            splat_kernels.composite_backward,
            ctx.order,
            (
                *ctx.common,
                trans.numpy(),
                last.numpy(),
                v_acc.to(dtype).contiguous().numpy(),
                v_trans.to(dtype).contiguous().numpy(),
                grads.numpy(),
            ),
            (2 * trans.shape[1] + nf, dtype),
        )
        per_row = torch.zeros(m2d.shape[0], grads.shape[1], dtype=dtype).index_add_(0, gids, grads)
        d_m2d, d_con, d_lo = per_row[:, 0:2], per_row[:, 2:5], per_row[:, 5]
        d_feat = per_row[:, splat_kernels.GRAD_COLUMNS :]
        t_m2d, t_con, t_lo = ctx.dtypes
        return (d_m2d.to(t_m2d), d_con.to(t_con), d_lo.to(t_lo), d_feat) + (None,) * 6


# --------------------------------------------------------------------------------------
# Public entry point
# --------------------------------------------------------------------------------------


class _Layout(NamedTuple):
    """Sizes of one call: B samples, C cameras, N Gaussians, the W x H image cut into
    ``tile_w`` x ``tile_h`` tiles of ``tile_size`` px, and the dtype / device of the images.

    Notation: B samples (scenes), C cameras per sample, N Gaussians per sample (a dense,
    padded tensor), I = B * C images, K (Gaussian, tile) intersections, P = tile_size**2
    pixels per tile, D Gaussians per compositing chunk, F feature channels.

    Padding: samples with fewer than N Gaussians should pass ``valid`` (B, N) False for the
    padding, or set their opacity to 0 (``opacity < 1/255`` is culled, as in gsplat).
    """

    B: int
    C: int
    N: int
    width: int
    height: int
    tile_size: int
    tile_w: int
    tile_h: int
    dtype: torch.dtype
    device: torch.device

    @property
    def n_tiles(self) -> int:
        return self.tile_w * self.tile_h


def render_gaussians(inputs: SplatInputs, settings: RenderSettings | None = None) -> RenderOutput:
    """Render 3D Gaussians into B x C images with gsplat 1.5.3 conventions.

    Args:
        inputs: :class:`~hogsa_loader.render.settings.SplatInputs` in the batched layout:
            means (B, N, 3), quats (B, N, 4) wxyz (need not be unit), scales (B, N, 3)
            linear, opacities (B, N) (``< 1/255`` culls), colors (B, N, D) or (B, C, N, D),
            or with ``settings.sh_degree`` SH coefficients (B, N, K, 3) or (B, C, N, K, 3)
            (colour = max(SH(dir) + 0.5, 0)), viewmats (B, C, 4, 4) world->camera OpenCV,
            Ks (B, C, 3, 3) (skew ignored), width, height, backgrounds (B, C, D) or None
            (= 0), part_ids (B, N) (needed iff ``settings.num_parts > 0``), valid (B, N)
            bool or None (padding may instead get zero opacity).
        settings: :class:`~hogsa_loader.render.settings.RenderSettings` (None = the
            defaults); ``backend``, ``packed`` and ``debug`` are not used here.

    Returns:
        :class:`RenderOutput` with rgb (B, C, H, W, D), alpha (B, C, H, W, 1),
        depth (B, C, H, W, 1) or None, part_alpha (B, C, H, W, num_parts) or None, meta.
        With ``settings.antialiased``, each (sample, camera) pair is rendered as a sample
        of its own with opacities ``o * rho`` (:func:`antialias_compensation`; C copies of
        the Gaussians), and ``meta`` also holds ``opacities`` and ``compensations`` (B, C, N).
    """
    s = RenderSettings() if settings is None else settings
    _check_shapes(inputs, s.num_parts)
    if s.antialiased:
        return _render_antialiased(inputs, s)
    means, quats, scales, opacities, colors, viewmats, Ks, width, height, backgrounds, part_ids, valid = inputs
    kernels = _use_compiled_compositor(s.compositor, means, colors, opacities)
    ts = s.tile_size
    lay = _Layout(
        means.shape[0],
        viewmats.shape[1],
        means.shape[1],
        width,
        height,
        ts,
        (width + ts - 1) // ts,
        (height + ts - 1) // ts,
        means.dtype,
        means.device,
    )

    # 1. projection (gsplat: fully_fused_projection with opacities)
    covars = quat_scale_to_covar(quats, scales)
    radii, means2d, depths, conics = project_gaussians(
        means, covars, viewmats, Ks, width, height, s.eps2d, s.near_plane, s.far_plane, opacities
    )
    if valid is not None:
        radii = radii * valid[:, None, :, None].to(radii.dtype)
    # 2. colours (B, C, N, D) and the other composited channels (I*N, F)
    cols = camera_colors(colors, s.sh_degree, means, viewmats)
    feat = _features(cols, depths, part_ids, s, lay)
    # 3. tiles
    n_img = lay.B * lay.C
    flat_ids, _, tile_counts = _intersect_tiles(
        means2d.detach().reshape(n_img, lay.N, 2),
        radii.reshape(n_img, lay.N, 2),
        depths.detach().reshape(n_img, lay.N),
        ts,
        lay.tile_w,
        lay.tile_h,
    )
    # 4. compositing
    acc, trans = _composite(means2d, conics, opacities, feat, radii, flat_ids, tile_counts, lay, s, kernels)
    out = _to_output(acc, trans, cols.shape[-1], backgrounds, s, lay)
    out.meta = {
        "radii": radii,
        "means2d": means2d,
        "depths": depths,
        "conics": conics,
        "colors": cols,
        "n_isects": int(flat_ids.numel()),
        "tile_width": lay.tile_w,
        "tile_height": lay.tile_h,
        "tile_size": ts,
    }
    return out


def _check_shapes(x: SplatInputs, num_parts: int) -> None:
    """The batched layout of :func:`render_gaussians` (no tensor values are read)."""
    means, quats, scales, opacities, viewmats, Ks = x.means, x.quats, x.scales, x.opacities, x.viewmats, x.Ks
    B, N = means.shape[:2]
    C = viewmats.shape[1]
    if means.shape != (B, N, 3) or quats.shape != (B, N, 4) or scales.shape != (B, N, 3):
        raise ValueError("means/quats/scales must be (B, N, 3)/(B, N, 4)/(B, N, 3)")
    if opacities.shape != (B, N):
        raise ValueError(f"opacities must be (B, N) = {(B, N)}, got {tuple(opacities.shape)}")
    if viewmats.shape != (B, C, 4, 4) or Ks.shape != (B, C, 3, 3):
        raise ValueError("viewmats/Ks must be (B, C, 4, 4)/(B, C, 3, 3)")
    if num_parts > 0 and x.part_ids is None:
        raise ValueError("num_parts > 0 needs part_ids")


def _use_compiled_compositor(compositor: str, means: Tensor, colors: Tensor, opacities: Tensor) -> bool:
    """Whether the compiled CPU kernels composite (see ``RenderSettings.compositor``).

    Raises:
        ValueError: ``"numba"`` where the kernels cannot run (also: an opacity above 1,
            whose pixels reach beyond the radius where the kernels look).
    """
    kernels = use_kernels("compositor", compositor, [means, colors, opacities], differentiable=True)
    if kernels and opacities.numel() > 0 and bool(opacities.detach().max() > 1.0):  # CPU tensors only
        if compositor == "numba":
            raise ValueError("compositor='numba' cannot run: an opacity is above 1")
        kernels = False
    return kernels


def part_channels(part_ids: Tensor, num_parts: int, dtype: torch.dtype) -> Tensor:
    """(..., N) part index in [0, num_parts) or -1 -> (..., N, num_parts) one-hot, zero for -1."""
    onehot = F.one_hot(part_ids.long().clamp(min=0), num_parts).to(dtype)
    return onehot * (part_ids >= 0)[..., None].to(dtype)


def _features(cols: Tensor, depths: Tensor, part_ids: Tensor | None, s: RenderSettings, lay: _Layout) -> Tensor:
    """(I*N, F) composited channels: colours cols (B, C, N, D), then camera z depths
    (B, C, N) unless ``render_mode`` is "RGB", then the ``num_parts`` one-hot part channels."""
    feats = [cols]
    if s.render_mode != "RGB":
        feats.append(depths[..., None])
    if s.num_parts > 0:
        assert part_ids is not None
        onehot = part_channels(part_ids, s.num_parts, lay.dtype)  # (B, N, num_parts)
        feats.append(onehot[:, None].expand(lay.B, lay.C, lay.N, s.num_parts))
    feat = torch.cat(feats, -1)
    return feat.reshape(lay.B * lay.C * lay.N, feat.shape[-1])


def _composite(
    means2d: Tensor,
    conics: Tensor,
    opacities: Tensor,
    feat: Tensor,
    radii: Tensor,
    flat_ids: Tensor,
    tile_counts: Tensor,
    lay: _Layout,
    s: RenderSettings,
    kernels: bool,
) -> tuple[Tensor, Tensor]:
    """Composite every tile.

    Args:
        means2d (B, C, N, 2), conics (B, C, N, 3), opacities (B, N), feat (I*N, F),
        radii (B, C, N, 2) int32; flat_ids (K,), tile_counts (I * n_tiles,) from
        :func:`_intersect_tiles`; kernels: use the compiled compositor.

    Returns:
        acc (I * n_tiles, P, F) = sum_i w_i feat_i (0 for empty tiles) and the final
        transmittance (I * n_tiles, P).
    """
    p, nf = lay.tile_size * lay.tile_size, feat.shape[1]
    acc = torch.zeros(lay.B * lay.C * lay.n_tiles, p, nf, dtype=lay.dtype, device=lay.device)
    trans = torch.ones(lay.B * lay.C * lay.n_tiles, p, dtype=lay.dtype, device=lay.device)
    busy = torch.nonzero(tile_counts).squeeze(1)
    if busy.numel() == 0:
        return acc, trans
    # clamp: rows with opacity < 1/255 are culled and never read; without it a zero
    # opacity (the padding convention) gives log(0) and a NaN opacity gradient
    log_o = torch.log(opacities.clamp(min=ALPHA_THRESHOLD))[:, None, :].expand(lay.B, lay.C, lay.N).reshape(-1)
    tile_start = torch.cumsum(tile_counts, 0) - tile_counts
    if kernels:
        acc_b, trans_b = _CompiledComposite.apply(
            means2d.reshape(-1, 2),
            conics.reshape(-1, 3),
            log_o,
            feat,
            radii.reshape(-1, 2),
            flat_ids,
            busy,
            tile_start[busy],
            tile_counts[busy],
            (lay.tile_size, lay.tile_w, lay.n_tiles, lay.width, lay.height),
        )
        return acc.index_copy(0, busy, acc_b), trans.index_copy(0, busy, trans_b)
    table = _gaussian_table(means2d.reshape(-1, 2), conics.reshape(-1, 3), log_o, feat)
    ids, acc_b, trans_b = _composite_torch(table, flat_ids, busy, tile_start, tile_counts, lay, s)
    return acc.index_copy(0, ids, acc_b), trans.index_copy(0, ids, trans_b)


def _tile_pixels(busy: Tensor, lay: _Layout) -> tuple[Tensor, Tensor]:
    """Centres (nb, 2) in pixels of the tiles ``busy`` (nb,) (global tile indices), and
    their padding pixels outside the image (nb, P) bool, which start "done" as in the
    CUDA kernel."""
    ts = lay.tile_size
    local_tile = busy % lay.n_tiles
    tx, ty = local_tile % lay.tile_w, local_tile // lay.tile_w
    origin = (torch.stack([tx, ty], -1) * ts).to(lay.dtype) + ts / 2.0  # (nb, 2)
    r = torch.arange(ts, device=lay.device)
    px = tx[:, None, None] * ts + r[None, None, :]
    py = ty[:, None, None] * ts + r[None, :, None]
    outside = ((px >= lay.width) | (py >= lay.height)).reshape(-1, ts * ts)
    return origin, outside


def _composite_torch(
    table: Tensor,
    flat_ids: Tensor,
    busy: Tensor,
    tile_start: Tensor,
    tile_counts: Tensor,
    lay: _Layout,
    s: RenderSettings,
) -> tuple[Tensor, Tensor, Tensor]:
    """The PyTorch compositor over the busy tiles, ``s.tile_batch`` tiles at a time.

    Args:
        table: (M + 1, 9 + F) rows of :func:`_gaussian_table`; flat_ids: (K,) sorted
            intersections; busy: (nb,) tiles with work; tile_start, tile_counts:
            (I * n_tiles,) offsets / lengths of the tiles' lists.

    Returns:
        tile indices (nb,) in the order of the results, acc (nb, P, F), trans (nb, P).
    """
    gids = torch.cat([flat_ids, flat_ids.new_full((1,), lay.B * lay.C * lay.N)])
    basis = _tile_basis(lay.tile_size, lay.dtype, lay.device)
    origin, outside = _tile_pixels(busy, lay)
    # longest lists first so that a batch holds tiles of similar work
    order = torch.argsort(tile_counts[busy], descending=True, stable=True)
    accs, ts, ids = [], [], []
    for grp in order.split(s.tile_batch):
        tiles = busy[grp]
        args = (table, gids, tile_start[tiles], tile_counts[tiles], origin[grp], outside[grp], basis, s.chunk)
        if s.checkpoint and torch.is_grad_enabled() and table.requires_grad:
            a_g, t_g = torch.utils.checkpoint.checkpoint(_composite_tiles, *args, use_reentrant=False)
        else:
            a_g, t_g = _composite_tiles(*args)
        accs.append(a_g)
        ts.append(t_g)
        ids.append(tiles)
    return torch.cat(ids), torch.cat(accs), torch.cat(ts)


def _to_output(
    acc: Tensor, trans: Tensor, n_col: int, backgrounds: Tensor | None, s: RenderSettings, lay: _Layout
) -> RenderOutput:
    """Images from the per-tile results acc (I * n_tiles, P, F) and trans (I * n_tiles, P);
    the first ``n_col`` feature channels are colours (meta left empty)."""

    def to_image(x: Tensor) -> Tensor:  # (I * n_tiles, P, F) -> (B, C, H, W, F)
        f, ts = x.shape[-1], lay.tile_size
        x = x.reshape(lay.B, lay.C, lay.tile_h, lay.tile_w, ts, ts, f).permute(0, 1, 2, 4, 3, 5, 6)
        return x.reshape(lay.B, lay.C, lay.tile_h * ts, lay.tile_w * ts, f)[:, :, : lay.height, : lay.width]

    img = to_image(acc)
    t_final = to_image(trans[..., None])  # (B, C, H, W, 1)
    alpha = 1.0 - t_final
    rgb = img[..., :n_col]
    if backgrounds is not None:
        rgb = rgb + t_final * backgrounds[:, :, None, None, :]
    depth = None
    if s.render_mode != "RGB":
        depth = img[..., n_col : n_col + 1] / alpha.clamp(min=ED_EPS)
        if s.render_mode == "RGB+D":  # the accumulated sum(w z): ED times the same clamped alpha
            depth = depth * alpha.clamp(min=ED_EPS)
    part_alpha = img[..., acc.shape[-1] - s.num_parts :] if s.num_parts > 0 else None
    return RenderOutput(rgb=rgb, alpha=alpha, depth=depth, part_alpha=part_alpha)


def _render_antialiased(x: SplatInputs, s: RenderSettings) -> RenderOutput:
    """:func:`render_gaussians` with ``s.antialiased``: per-camera opacities o * rho, so each
    (sample, camera) pair becomes one sample of a B*C-sample, 1-camera call."""
    B, C = x.viewmats.shape[:2]
    N = x.means.shape[1]
    rho = antialias_compensation(x, s)  # (B, C, N)
    op_c = x.opacities[:, None, :] * rho  # (B, C, N)

    def per_gaussian(t: Tensor | None) -> Tensor | None:  # (B, N, ...) -> (B*C, N, ...)
        return None if t is None else t[:, None].expand(B, C, *t.shape[1:]).reshape(B * C, *t.shape[1:])

    def per_camera(t: Tensor | None) -> Tensor | None:  # (B, C, ...) -> (B*C, 1, ...)
        return None if t is None else t.reshape(B * C, 1, *t.shape[2:])

    per_cam_colors = x.colors.dim() == (4 if s.sh_degree is None else 5)
    flat = SplatInputs(
        per_gaussian(x.means),
        per_gaussian(x.quats),
        per_gaussian(x.scales),
        op_c.reshape(B * C, N),  # type: ignore[arg-type]
        per_camera(x.colors) if per_cam_colors else per_gaussian(x.colors),
        per_camera(x.viewmats),  # type: ignore[arg-type]
        per_camera(x.Ks),
        x.width,
        x.height,
        backgrounds=per_camera(x.backgrounds),  # type: ignore[arg-type]
        part_ids=per_gaussian(x.part_ids),
        valid=per_gaussian(x.valid),
    )
    out = render_gaussians(flat, replace(s, antialiased=False))

    def back(t: Tensor | None) -> Tensor | None:  # (B*C, 1, ...) -> (B, C, ...)
        return None if t is None else t.reshape(B, C, *t.shape[2:])

    meta = {k: back(v) if isinstance(v, Tensor) else v for k, v in out.meta.items()}
    meta["opacities"] = op_c
    meta["compensations"] = rho
    return RenderOutput(
        rgb=back(out.rgb), alpha=back(out.alpha), depth=back(out.depth), part_alpha=back(out.part_alpha), meta=meta
    )  # type: ignore[arg-type]


def warm_up_compositor() -> None:
    """Compile (or load from numba's cache) the compiled compositor for float32 scenes,
    forward and backward, now: e.g. in a parent process before it forks renderers, so that
    they do not each compile it."""
    if not splat_kernels.AVAILABLE:
        return
    with torch.enable_grad():
        _warm_up()


def _warm_up() -> None:
    means = torch.tensor([[[0.0, 0.0, 1.0]]], requires_grad=True)
    K = torch.tensor([[[[10.0, 0.0, 4.0], [0.0, 10.0, 4.0], [0.0, 0.0, 1.0]]]])
    x = SplatInputs(
        means,
        torch.tensor([[[1.0, 0.0, 0.0, 0.0]]]),
        torch.full((1, 1, 3), 0.1),
        torch.full((1, 1), 0.5),
        torch.ones(1, 1, 3),
        torch.eye(4)[None, None],
        K,
        8,
        8,
    )
    out = render_gaussians(x, RenderSettings(render_mode="RGB+ED", compositor="numba"))
    out.rgb.sum().backward()
