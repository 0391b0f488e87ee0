"""The posed-Gaussian batch every Gaussian model returns, plus SH colour helpers.

A :class:`GaussianSet` holds world-space, post-activation Gaussians for B samples in the
layout :func:`hogsa_loader.render.gaussians.render_gaussians` takes (gsplat 1.5.3):
means (B, N, 3), wxyz quats (B, N, 4), linear scales (B, N, 3), opacities in [0, 1]
(B, N) and SH coefficients (B, N, K, 3) with K = (sh_degree + 1)^2, bases first and RGB
last; colour = max(SH(dir) + 0.5, 0).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Optional

import torch
from torch import Tensor, nn

__all__ = ["GaussianSet", "SplatAppearance", "SH_C0", "num_sh_bases", "rgb_to_sh", "sh_to_rgb"]

#: Degree-0 real SH constant (gsplat ``_eval_sh_bases_fast``).
SH_C0 = 0.28209479177387814


def num_sh_bases(sh_degree: int) -> int:
    """K = (sh_degree + 1)^2 coefficients per colour channel; degree must be 0..3."""
    if not 0 <= int(sh_degree) <= 3:
        raise ValueError(f"sh_degree must be in 0..3, got {sh_degree}")
    return (int(sh_degree) + 1) ** 2


def rgb_to_sh(rgb: Tensor) -> Tensor:
    """DC coefficient giving colour ``rgb`` from every direction: ``(rgb - 0.5) / C0``."""
    return (rgb - 0.5) / SH_C0


def sh_to_rgb(dc: Tensor) -> Tensor:
    """Inverse of :func:`rgb_to_sh` (view-independent part of the colour, unclamped)."""
    return dc * SH_C0 + 0.5


@dataclass
class GaussianSet:
    """World-space Gaussians of one part (or a composed scene) for B samples.

    Attributes:
        means: (B, N, 3) centres, metres.
        quats: (B, N, 4) rotations, wxyz.
        scales: (B, N, 3) linear standard deviations along the rotation's columns.
        opacities: (B, N) in [0, 1].
        sh: (B, N, K, 3) SH coefficients, K = (sh_degree + 1)^2. Parts return a view
            expanded along B (stride 0) of their (N, K, 3) parameters.
        sh_degree: 0..3.
        part_ids: (N,) int64 part index of every Gaussian (e.g. 0 right hand, 1 left
            hand, 2 object).
        normals: optional (B, N, 3) unit surface normals (mesh-bound Gaussians: the
            posed face normal; free Gaussians: the skinned template normal).
    """

    means: Tensor
    quats: Tensor
    scales: Tensor
    opacities: Tensor
    sh: Tensor
    sh_degree: int
    part_ids: Tensor
    normals: Optional[Tensor] = None

    def __post_init__(self) -> None:
        B, N = self.means.shape[:2]
        K = num_sh_bases(self.sh_degree)
        expect = {
            "means": (B, N, 3),
            "quats": (B, N, 4),
            "scales": (B, N, 3),
            "opacities": (B, N),
            "sh": (B, N, K, 3),
            "part_ids": (N,),
        }
        if self.normals is not None:
            expect["normals"] = (B, N, 3)
        for name, shape in expect.items():
            got = tuple(getattr(self, name).shape)
            if got != shape:
                raise ValueError(f"GaussianSet.{name} must be {shape}, got {got}")

    @property
    def batch_size(self) -> int:
        return int(self.means.shape[0])

    @property
    def num_gaussians(self) -> int:
        return int(self.means.shape[1])

    def with_part_id(self, part_id: int) -> "GaussianSet":
        """A copy whose Gaussians all carry ``part_id``."""
        return replace(self, part_ids=torch.full_like(self.part_ids, int(part_id)))

    def expand_batch(self, batch_size: int) -> "GaussianSet":
        """Broadcast a B = 1 set to ``batch_size`` samples (views, no copy)."""
        if self.batch_size == batch_size:
            return self
        if self.batch_size != 1:
            raise ValueError(f"cannot broadcast a batch of {self.batch_size} to {batch_size}")

        def ex(t: Optional[Tensor]) -> Optional[Tensor]:
            return None if t is None else t.expand(batch_size, *t.shape[1:])

        return replace(
            self,
            means=ex(self.means),
            quats=ex(self.quats),
            scales=ex(self.scales),
            opacities=ex(self.opacities),
            sh=ex(self.sh),
            normals=ex(self.normals),
        )


class SplatAppearance(nn.Module):
    """Appearance parameters every Gaussian model has, and the assembly of its output.

    Learnable parameters (checkpoint names, gsplat's parameterisation): ``sh_dc``
    (N, 1, 3) and ``sh_rest`` (N, K - 1, 3) (split so that they can get separate
    learning rates, like gsplat's ``sh0``/``shN``), ``opacity_logits`` (N,).
    Subclasses call :meth:`_init_appearance` in their constructor.
    """

    sh_degree: int

    def _init_appearance(
        self, num: int, sh_degree: int, init_opacity: float, colors: Optional[Tensor], dtype: torch.dtype
    ) -> None:
        """Create the parameters: SH DC from ``colors`` ((N, 3), (3,) or None = grey)."""
        if not 0.0 < init_opacity < 1.0:
            raise ValueError(f"init_opacity must be in (0, 1), got {init_opacity}")
        nb = num_sh_bases(sh_degree)
        self.sh_degree = int(sh_degree)
        self.sh_dc = nn.Parameter(torch.zeros(num, 1, 3, dtype=dtype))
        self.sh_rest = nn.Parameter(torch.zeros(num, nb - 1, 3, dtype=dtype))
        p = float(init_opacity)
        self.opacity_logits = nn.Parameter(torch.full((num,), math.log(p / (1.0 - p)), dtype=dtype))
        self.set_colors_(torch.full((3,), 0.5, dtype=dtype) if colors is None else colors)

    @property
    def num_gaussians(self) -> int:
        return int(self.opacity_logits.shape[0])

    @torch.no_grad()
    def set_colors_(self, rgb: Tensor) -> None:
        """View-independent colours: SH DC from ``rgb`` ((N, 3) or (3,), in [0, 1]),
        higher bands zero."""
        rgb = torch.as_tensor(rgb).to(self.sh_dc)
        if rgb.shape == (3,):
            rgb = rgb.expand(self.num_gaussians, 3)
        if rgb.shape != (self.num_gaussians, 3):
            raise ValueError(f"colors must be (3,) or ({self.num_gaussians}, 3), got {tuple(rgb.shape)}")
        self.sh_dc.copy_(rgb_to_sh(rgb)[:, None, :])
        self.sh_rest.zero_()

    def opacities(self) -> Tensor:
        """(N,) sigmoid of the logits."""
        return torch.sigmoid(self.opacity_logits)

    def sh(self) -> Tensor:
        """(N, K, 3) SH coefficients."""
        return torch.cat([self.sh_dc, self.sh_rest], dim=1)

    def _gaussian_set(
        self, means: Tensor, quats: Tensor, scales: Tensor, part_id: int, normals: Optional[Tensor]
    ) -> GaussianSet:
        """A :class:`GaussianSet` from posed geometry (B, N, .) and this appearance (shared
        by the B samples: expanded views)."""
        B, N = means.shape[0], self.num_gaussians
        return GaussianSet(
            means=means,
            quats=quats,
            scales=scales,
            opacities=self.opacities()[None].expand(B, N),
            sh=self.sh()[None].expand(B, N, -1, 3),
            sh_degree=self.sh_degree,
            part_ids=torch.full((N,), int(part_id), dtype=torch.long, device=means.device),
            normals=normals,
        )
