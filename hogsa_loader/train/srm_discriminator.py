"""Conditional wavelet discriminator (StyleGAN2 / SWAGAN style)."""

from __future__ import annotations

import math
from typing import Optional, Sequence

import torch
from torch import Tensor, nn

from hogsa_loader.models.srm.stylegan import ConvBlock, ConvLayer, EqualLinear, FromRGB, HaarTransform

__all__ = ["ConditionalDiscriminator"]


class ConditionalDiscriminator(nn.Module):
    """D(image, condition) → (B,) logits.

    Input: ``concat(image, condition)`` — the real or refined image (B, 3, H, W) and the coarse
    render it is conditioned on (B, C_cond, H, W; the SRM uses premultiplied RGB + alpha,
    upsampled to the output size when the SRM upsamples), all in [−1, 1]. The concatenation
    is Haar-transformed (4·(3 + C_cond) channels at H/2), projected by a FromRGB, and
    ConvBlocks halve the resolution down to 4×4, each level also receiving a FromRGB skip of
    the blur-downsampled wavelet image. Then minibatch standard deviation (group ≤ 4, one
    feature), ConvLayer(C+1 → C), EqualLinear(16·C → C, leaky ReLU), EqualLinear(C → 1).

    The number of blocks follows ``size`` (the training crop size); H and W must equal it.

    Args:
        size: input H = W (power of two, ≥ 16).
        cond_channels: condition channels (0: unconditional).
        channels: widths by level from the top wavelet level (size/2) down to 4×4; when
            shorter than needed, the last width is repeated.
        stddev_group: minibatch-stddev group size.
    """

    def __init__(
        self, size: int, cond_channels: int = 4, channels: Optional[Sequence[int]] = None, stddev_group: int = 4
    ) -> None:
        super().__init__()
        if size < 16 or size & (size - 1):
            raise ValueError(f"discriminator size must be a power of two >= 16, got {size}")
        self.size, self.cond_channels, self.stddev_group = size, cond_channels, stddev_group
        n_blocks = int(math.log2(size // 2)) - 2  # size/2 → 4
        widths = list(channels or [32, 64, 128, 128, 128, 128, 128])
        while len(widths) < n_blocks + 1:
            widths.append(widths[-1])
        widths = widths[: n_blocks + 1]
        self.widths = widths
        img_ch = 4 * (3 + cond_channels)
        self.dwt = HaarTransform()
        self.from_rgb = nn.ModuleList([FromRGB(img_ch, widths[0], downsample=False)])
        self.blocks = nn.ModuleList()
        for i in range(1, n_blocks + 1):
            self.blocks.append(ConvBlock(widths[i - 1], widths[i]))
            if i < n_blocks:
                self.from_rgb.append(FromRGB(img_ch, widths[i], downsample=True))
        c = widths[-1]
        self.final_conv = ConvLayer(c + 1, c, 3)
        self.final_linear = nn.Sequential(EqualLinear(c * 16, c, activation=True), EqualLinear(c, 1))

    def forward(self, image: Tensor, cond: Optional[Tensor] = None) -> Tensor:
        """image (B, 3, S, S), cond (B, C_cond, S, S) → logits (B,)."""
        if image.shape[-1] != self.size or image.shape[-2] != self.size:
            raise ValueError(f"discriminator expects {self.size}x{self.size} inputs, got {tuple(image.shape[-2:])}")
        x = image if cond is None or self.cond_channels == 0 else torch.cat([image, cond], 1)
        img = self.dwt(x)
        img, h = self.from_rgb[0](img)
        for i, block in enumerate(self.blocks):
            h = block(h)
            if i + 1 < len(self.from_rgb):
                img, r = self.from_rgb[i + 1](img)
                h = h + r
        h = self._stddev(h)
        h = self.final_conv(h)
        return self.final_linear(h.flatten(1)).squeeze(1)

    def _stddev(self, x: Tensor) -> Tensor:
        """Append one channel: the minibatch standard deviation (averaged over C, H, W)."""
        b, c, h, w = x.shape
        g = min(b, self.stddev_group)
        while b % g:
            g -= 1
        y = x.reshape(g, -1, c, h, w)
        y = torch.sqrt(y.var(0, unbiased=False) + 1e-8).mean((1, 2, 3))  # (B/g,)
        y = y.reshape(-1, 1, 1, 1).repeat(g, 1, h, w)
        return torch.cat([x, y], 1)
