"""Compose posed parts into one scene batch and render it with per-part alpha masks.

Composition concatenates the Gaussians of every part along N (same B samples; a B = 1
part, e.g. a static object, is broadcast). Each Gaussian keeps its part id, so
:func:`render_scene` returns ``part_alpha`` (B, C, H, W, num_parts) with one accumulated
opacity channel per part, which sums to ``alpha``.
"""

from __future__ import annotations

from typing import Optional, Sequence

import torch
from torch import Tensor

from hogsa_loader.models.gaussians.gaussian_set import GaussianSet, num_sh_bases
from hogsa_loader.render.api import render
from hogsa_loader.render.gaussians import RenderOutput, sh_colors
from hogsa_loader.render.settings import Backend, RenderMode

__all__ = ["SH_POLICIES", "pad_sh", "compose", "render_scene", "headlight_colors"]

#: ``"pad"``: raise lower SH degrees to the highest one with zero coefficients (exact:
#: the extra bands contribute nothing); ``"strict"``: all parts must share one degree.
SH_POLICIES = ("pad", "strict")


def pad_sh(sh: Tensor, sh_degree: int) -> Tensor:
    """Zero-pad (..., K, 3) SH coefficients to ``(sh_degree + 1)^2`` bases."""
    nb = num_sh_bases(sh_degree)
    if sh.shape[-2] > nb:
        raise ValueError(f"cannot pad {sh.shape[-2]} SH bases down to {nb}")
    if sh.shape[-2] == nb:
        return sh
    pad = sh.new_zeros(*sh.shape[:-2], nb - sh.shape[-2], 3)
    return torch.cat([sh, pad], dim=-2)


def _is_batch_broadcast(t: Tensor) -> bool:
    return t.shape[0] == 1 or t.stride(0) == 0


def compose(sets: Sequence[GaussianSet], sh_policy: str = "pad") -> GaussianSet:
    """Concatenate posed parts into one scene.

    Args:
        sets: posed parts, each with B samples (or B = 1, broadcast).
        sh_policy: ``"pad"`` or ``"strict"`` (see :data:`SH_POLICIES`).

    Returns:
        one :class:`GaussianSet` with N = sum of the parts' N, part ids kept; normals
        are kept only when every part has them.
    """
    if not sets:
        raise ValueError("compose needs at least one GaussianSet")
    if sh_policy not in SH_POLICIES:
        raise ValueError(f"sh_policy must be one of {SH_POLICIES}, got {sh_policy!r}")
    degrees = [s.sh_degree for s in sets]
    if sh_policy == "strict" and len(set(degrees)) > 1:
        raise ValueError(f"parts have different SH degrees {degrees}; use sh_policy='pad' or equal degrees")
    deg = max(degrees)
    B = max(s.batch_size for s in sets)
    sets = [s.expand_batch(B) for s in sets]
    shared_sh = all(_is_batch_broadcast(s.sh) for s in sets)
    if shared_sh:  # parameters shared by all samples: concatenate once, expand (no copy)
        sh0 = torch.cat([pad_sh(s.sh[0], deg) for s in sets], 0)
        sh = sh0[None].expand(B, *sh0.shape)
    else:
        sh = torch.cat([pad_sh(s.sh, deg) for s in sets], 1)
    normals = None
    if all(s.normals is not None for s in sets):
        normals = torch.cat([s.normals for s in sets], 1)  # type: ignore[misc]
    return GaussianSet(
        means=torch.cat([s.means for s in sets], 1),
        quats=torch.cat([s.quats for s in sets], 1),
        scales=torch.cat([s.scales for s in sets], 1),
        opacities=torch.cat([s.opacities for s in sets], 1),
        sh=sh,
        sh_degree=deg,
        part_ids=torch.cat([s.part_ids for s in sets], 0),
        normals=normals,
    )


def headlight_colors(scene: GaussianSet, viewmats: Tensor, ambient: float = 0.45) -> Tensor:
    """Per-camera colours with a light at each camera (``sh_degree=None`` input).

    ``rgb = c_SH(dir) * (ambient + (1 - ambient) |n . dir|)`` with the view direction
    ``dir`` from the camera to the Gaussian and ``n`` the Gaussian's normal (two-sided).
    This gives untrained, albedo-initialised models the shading cues a trained model
    gets from its images; it needs ``scene.normals``.

    Args:
        scene: (B, N) Gaussians with normals.
        viewmats: (B, C, 4, 4) world->camera.
        ambient: fraction of the colour kept at grazing angles.

    Returns:
        (B, C, N, 3) colours.
    """
    if scene.normals is None:
        raise ValueError("headlight shading needs GaussianSet.normals")
    campos = torch.linalg.inv(viewmats)[..., :3, 3]  # (B, C, 3)
    dirs = scene.means[:, None] - campos[:, :, None, :]  # (B, C, N, 3)
    dirs = dirs / dirs.norm(dim=-1, keepdim=True).clamp(min=1e-12)
    C = viewmats.shape[1]
    sh = scene.sh[:, None].expand(-1, C, -1, -1, -1)
    base = torch.clamp_min(sh_colors(scene.sh_degree, dirs, sh) + 0.5, 0.0)
    cos = (dirs * scene.normals[:, None]).sum(-1, keepdim=True).abs()
    return base * (ambient + (1.0 - ambient) * cos)


def render_scene(
    scene: GaussianSet,
    viewmats: Tensor,
    Ks: Tensor,
    width: int,
    height: int,
    *,
    num_parts: Optional[int] = None,
    headlight: Optional[float] = None,
    colors: Optional[Tensor] = None,
    backend: Backend = "auto",
    render_mode: RenderMode = "RGB+ED",
    **render_kwargs: object,
) -> RenderOutput:
    """Render a composed scene with per-part alpha masks.

    Args:
        scene: (B, N) Gaussians (e.g. from :func:`compose`).
        viewmats: (B, C, 4, 4) world->camera (OpenCV); Ks: (B, C, 3, 3).
        width, height: image size.
        num_parts: part channels; default ``max(part_ids) + 1``.
        headlight: None renders the SH colours as they are; a float ``ambient`` in
            [0, 1] applies :func:`headlight_colors`.
        colors: (B, C, N, 3) precomputed per-camera colours (e.g. from a
            :class:`~hogsa_loader.models.gaussians.shading.DirectionalLight`); overrides the SH.
        backend: renderer backend of :func:`hogsa_loader.render.render` ("auto",
            "torch", "gsplat").
        render_mode: "RGB", "RGB+ED" (default: expected depth) or "RGB+D".
        **render_kwargs: passed to :func:`hogsa_loader.render.render` (near_plane,
            far_plane, backgrounds (B, C, 3), ...).

    Returns:
        :class:`RenderOutput`; ``part_alpha[..., p]`` is the opacity of part p.
    """
    B, N = scene.batch_size, scene.num_gaussians
    if num_parts is None:
        num_parts = int(scene.part_ids.max()) + 1 if N else 0
    part_ids = scene.part_ids[None].expand(B, N) if num_parts > 0 else None  # (an empty scene has no parts)
    if colors is not None:
        if headlight is not None:
            raise ValueError("pass either colors or headlight, not both")
        deg = None
    elif headlight is None:
        colors, deg = scene.sh, scene.sh_degree
    else:
        colors, deg = headlight_colors(scene, viewmats, float(headlight)), None
    return render(
        scene.means,
        scene.quats,
        scene.scales,
        scene.opacities,
        colors,
        viewmats,
        Ks,
        width,
        height,
        backend=backend,
        sh_degree=deg,
        part_ids=part_ids,
        num_parts=num_parts,
        render_mode=render_mode,
        **render_kwargs,  # type: ignore[arg-type]
    )
