"""Texture lookup shared by the mesh rasteriser and the Gaussian colour initialisation."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

__all__ = ["sample_texture"]


def sample_texture(texture: Tensor, uv: Tensor) -> Tensor:
    """Bilinear texture lookup, OBJ convention (v = 0 at the image bottom), border clamp.

    Args:
        texture: (Ht, Wt, C) float image (cast to ``uv``'s dtype and device).
        uv: (N, 2) texture coordinates.

    Returns:
        (N, C) sampled values.
    """
    grid = torch.stack([uv[:, 0] * 2.0 - 1.0, (1.0 - uv[:, 1]) * 2.0 - 1.0], dim=-1)
    img = texture.permute(2, 0, 1)[None].to(uv)  # (1, C, Ht, Wt)
    out = F.grid_sample(
        img, grid[None, None], mode="bilinear", padding_mode="border", align_corners=False
    )  # (1, C, 1, N)
    return out[0, :, 0].T
