"""StyleGAN2 building blocks in pure PyTorch (CPU and CUDA), with Haar wavelets (SWAGAN): the
blocks of StyleAvatar's StyleUNet. No custom CUDA ops: the [1, 3, 3, 1] blur is a depthwise
convolution. Shapes use B batch, C channels, H×W spatial size; every module is fully convolutional.
"""

from __future__ import annotations

import math
from typing import Optional

import torch
import torch.nn.functional as F
from torch import Tensor, nn

__all__ = [
    "blur_kernel",
    "Blur",
    "upsample2",
    "downsample2",
    "EqualConv2d",
    "EqualLinear",
    "FusedLeakyReLU",
    "ModulatedConv2d",
    "NoiseInjection",
    "StyledConv",
    "HaarTransform",
    "InverseHaarTransform",
    "ToRGB",
    "FromRGB",
    "ConvLayer",
    "ConvBlock",
    "MappingNetwork",
    "PixelNorm",
]

_SQRT2 = math.sqrt(2.0)


def blur_kernel(taps: tuple[int, ...] = (1, 3, 3, 1)) -> Tensor:
    """(k, k) separable blur kernel normalised to sum 1."""
    k = torch.tensor(taps, dtype=torch.float32)
    k2 = k[:, None] * k[None, :]
    return k2 / k2.sum()


class Blur(nn.Module):
    """Depthwise [1, 3, 3, 1] blur with explicit zero padding ``(pad0, pad1)`` on each side.

    ``gain`` multiplies the kernel (4 after zero-insertion upsampling by 2).
    (B, C, H, W) → (B, C, H + pad0 + pad1 − 3, W + pad0 + pad1 − 3).
    """

    def __init__(self, pad: tuple[int, int], gain: float = 1.0) -> None:
        super().__init__()
        self.register_buffer("kernel", blur_kernel() * gain, persistent=False)
        self.pad = pad

    def forward(self, x: Tensor) -> Tensor:
        c = x.shape[1]
        x = F.pad(x, (self.pad[0], self.pad[1], self.pad[0], self.pad[1]))
        w = self.kernel.to(x.dtype)[None, None].expand(c, 1, -1, -1)
        return F.conv2d(x, w, groups=c)


def upsample2(x: Tensor) -> Tensor:
    """Blur-upsample ×2 of an image (B, C, H, W) → (B, C, 2H, 2W).

    Zero-insertion followed by the [1, 3, 3, 1] blur equals bilinear interpolation with
    half-pixel centres (weights 1/4, 3/4) away from the border; the border is replicated
    instead of zero-padded, which avoids dark rims.
    """
    return F.interpolate(x, scale_factor=2.0, mode="bilinear", align_corners=False)


def downsample2(x: Tensor) -> Tensor:
    """Blur ([1, 3, 3, 1]) then take every other pixel: (B, C, H, W) → (B, C, H/2, W/2)."""
    c = x.shape[1]
    w = blur_kernel().to(x)[None, None].expand(c, 1, -1, -1)
    x = F.pad(x, (1, 1, 1, 1), mode="replicate")
    return F.conv2d(x, w, stride=2, groups=c)


class EqualConv2d(nn.Module):
    """Conv2d with equalised learning rate: weight ~ N(0, 1) × 1/√(C_in·k²) at run time."""

    def __init__(
        self, in_ch: int, out_ch: int, kernel: int, stride: int = 1, padding: int = 0, bias: bool = True
    ) -> None:
        super().__init__()
        self.weight = nn.Parameter(torch.randn(out_ch, in_ch, kernel, kernel))
        self.scale = 1.0 / math.sqrt(in_ch * kernel * kernel)
        self.bias = nn.Parameter(torch.zeros(out_ch)) if bias else None
        self.stride, self.padding = stride, padding

    def forward(self, x: Tensor) -> Tensor:
        b = None if self.bias is None else self.bias.to(x.dtype)
        return F.conv2d(x, (self.weight * self.scale).to(x.dtype), b, stride=self.stride, padding=self.padding)


class EqualLinear(nn.Module):
    """Linear with equalised learning rate (weight ~ N(0,1)/lr_mul scaled at run time)."""

    def __init__(
        self, in_dim: int, out_dim: int, bias_init: float = 0.0, lr_mul: float = 1.0, activation: bool = False
    ) -> None:
        super().__init__()
        self.weight = nn.Parameter(torch.randn(out_dim, in_dim) / lr_mul)
        self.bias = nn.Parameter(torch.full((out_dim,), float(bias_init)))
        self.scale = lr_mul / math.sqrt(in_dim)
        self.lr_mul = lr_mul
        self.activation = activation

    def forward(self, x: Tensor) -> Tensor:
        y = F.linear(x, self.weight * self.scale, self.bias * self.lr_mul)
        return F.leaky_relu(y, 0.2) * _SQRT2 if self.activation else y


class FusedLeakyReLU(nn.Module):
    """``leaky_relu(x + bias, 0.2) · √2`` with a learnable per-channel bias."""

    def __init__(self, channels: int) -> None:
        super().__init__()
        self.bias = nn.Parameter(torch.zeros(channels))

    def forward(self, x: Tensor) -> Tensor:
        return F.leaky_relu(x + self.bias.to(x.dtype)[None, :, None, None], 0.2) * _SQRT2


class ModulatedConv2d(nn.Module):
    """StyleGAN2 modulated convolution.

    A per-sample style ``s`` scales the input channels, then demodulation
    ``w'' = w·s / √(Σ (w·s)² + 1e-8)``. Implemented as "scale activations, shared convolution,
    scale outputs" (mathematically identical to the grouped per-sample weight form, faster on
    CPU, and counted correctly by ``torch.utils.flop_counter``). Upsampling: stride-2 transposed
    convolution + blur; downsampling: blur + stride-2 conv.

    Args:
        in_ch, out_ch, kernel: channels and (odd) kernel size.
        style_dim: style vector size.
        demodulate: normalise each output channel's effective weight to unit norm.
        upsample: ×2 by stride-2 transposed convolution + blur.
        downsample: ×½ by blur + stride-2 convolution.

    ``forward(x (B, C_in, H, W), style (B, style_dim)) -> (B, C_out, H', W')`` with
    H' = 2H, H or H/2.
    """

    def __init__(
        self,
        in_ch: int,
        out_ch: int,
        kernel: int,
        style_dim: int,
        *,
        demodulate: bool = True,
        upsample: bool = False,
        downsample: bool = False,
    ) -> None:
        super().__init__()
        if upsample and downsample:
            raise ValueError("upsample and downsample are exclusive")
        self.in_ch, self.out_ch, self.kernel = in_ch, out_ch, kernel
        self.weight = nn.Parameter(torch.randn(out_ch, in_ch, kernel, kernel))
        self.scale = 1.0 / math.sqrt(in_ch * kernel * kernel)
        self.modulation = EqualLinear(style_dim, in_ch, bias_init=1.0)
        self.demodulate, self.upsample, self.downsample = demodulate, upsample, downsample
        if upsample:
            # transposed conv (k=3, s=2) gives 2H+1 (+k−3); the blur pads it back to 2H
            p = 4 - 2 - (kernel - 1)
            self.blur = Blur(((p + 1) // 2 + 1, p // 2 + 1), gain=4.0)
        elif downsample:
            p = 4 - 2 + (kernel - 1)
            self.blur = Blur(((p + 1) // 2, p // 2))

    def forward(self, x: Tensor, style: Tensor) -> Tensor:
        s = self.modulation(style).to(x.dtype)  # (B, C_in)
        w = (self.weight * self.scale).to(x.dtype)  # (C_out, C_in, k, k)
        x = x * s[:, :, None, None]
        if self.upsample:
            y = F.conv_transpose2d(x, w.transpose(0, 1), stride=2, padding=0)
            y = self.blur(y)
        elif self.downsample:
            y = F.conv2d(self.blur(x), w, stride=2)
        else:
            y = F.conv2d(x, w, padding=self.kernel // 2)
        if self.demodulate:
            # Σ_{i,k} (w_oik · s_i)² per sample and output channel, in float32
            d = torch.rsqrt((w.float().square().sum((2, 3))[None] * s.float().square()[:, None, :]).sum(2) + 1e-8)
            y = y * d.to(y.dtype)[:, :, None, None]
        return y


class NoiseInjection(nn.Module):
    """``x + weight · noise`` with a learnable scalar weight initialised to 0.

    ``noise`` is (B, 1, H, W); when None a fresh N(0, 1) map is drawn.
    """

    def __init__(self) -> None:
        super().__init__()
        self.weight = nn.Parameter(torch.zeros(1))

    def forward(self, x: Tensor, noise: Optional[Tensor] = None) -> Tensor:
        if noise is None:
            noise = torch.randn(x.shape[0], 1, x.shape[2], x.shape[3], device=x.device, dtype=x.dtype)
        return x + self.weight.to(x.dtype) * noise


class StyledConv(nn.Module):
    """Modulated 3×3 conv (optionally ×2 upsampling) + noise + bias + leaky ReLU(0.2)·√2.

    ``forward(x, style, noise_mode)``: ``noise_mode`` is ``"random"`` (fresh N(0,1) per
    call) or ``"none"`` (no noise; deterministic inference).
    """

    def __init__(self, in_ch: int, out_ch: int, style_dim: int, *, upsample: bool = False) -> None:
        super().__init__()
        self.conv = ModulatedConv2d(in_ch, out_ch, 3, style_dim, upsample=upsample)
        self.noise = NoiseInjection()
        self.act = FusedLeakyReLU(out_ch)

    def forward(self, x: Tensor, style: Tensor, noise_mode: str = "random") -> Tensor:
        y = self.conv(x, style)
        if noise_mode == "random":
            y = self.noise(y)
        elif noise_mode != "none":
            raise ValueError(f"noise_mode must be 'random' or 'none', got {noise_mode!r}")
        return self.act(y)


def _haar_filters() -> Tensor:
    """(4, 1, 2, 2) orthonormal Haar analysis filters [LL, LH, HL, HH]."""
    lo = torch.tensor([1.0, 1.0]) / _SQRT2
    hi = torch.tensor([-1.0, 1.0]) / _SQRT2
    ll = lo[:, None] * lo[None, :]
    lh = hi[:, None] * lo[None, :]
    hl = lo[:, None] * hi[None, :]
    hh = hi[:, None] * hi[None, :]
    return torch.stack([ll, lh, hl, hh])[:, None]


class _Haar(nn.Module):
    """Holds the (4, 1, 2, 2) Haar filters of :func:`_haar_filters` (buffer ``filters``, not saved)."""

    def __init__(self) -> None:
        super().__init__()
        self.register_buffer("filters", _haar_filters(), persistent=False)


class HaarTransform(_Haar):
    """DWT: (B, C, H, W) → (B, 4C, H/2, W/2), channels ordered band-major ``[LL·C, LH·C, HL·C, HH·C]``."""

    def forward(self, x: Tensor) -> Tensor:
        b, c, h, w = x.shape
        f = self.filters.to(x.dtype)
        y = F.conv2d(x.reshape(b * c, 1, h, w), f, stride=2)  # (B·C, 4, H/2, W/2)
        return y.reshape(b, c, 4, h // 2, w // 2).transpose(1, 2).reshape(b, 4 * c, h // 2, w // 2)


class InverseHaarTransform(_Haar):
    """IWT: (B, 4C, H, W) → (B, C, 2H, 2W); exact inverse of :class:`HaarTransform`."""

    def forward(self, x: Tensor) -> Tensor:
        b, c4, h, w = x.shape
        c = c4 // 4
        y = x.reshape(b, 4, c, h, w).transpose(1, 2).reshape(b * c, 4, h, w)
        y = F.conv_transpose2d(y, self.filters.to(x.dtype), stride=2)
        return y.reshape(b, c, 2 * h, 2 * w)


class ToRGB(nn.Module):
    """1×1 modulated conv (no demodulation) + bias to the image channels (12 wavelet or 3 RGB),
    plus the previous skip brought to this resolution (IWT → blur-upsample ×2 → DWT).

    Args:
        in_ch: feature channels; style_dim: style size.
        wavelet: 12 wavelet channels (else 3 RGB channels).
        upsample: the incoming skip is at half resolution and is brought up first.

    ``forward(x (B, C, H, W), style, skip (B, 12|3, H/2|H, W/2|W) or None) -> (B, 12|3, H, W)``.
    """

    def __init__(self, in_ch: int, style_dim: int, *, wavelet: bool = True, upsample: bool = True) -> None:
        super().__init__()
        self.out_ch = 12 if wavelet else 3
        self.wavelet, self.upsample = wavelet, upsample
        self.conv = ModulatedConv2d(in_ch, self.out_ch, 1, style_dim, demodulate=False)
        self.bias = nn.Parameter(torch.zeros(1, self.out_ch, 1, 1))
        if wavelet:
            self.dwt, self.iwt = HaarTransform(), InverseHaarTransform()

    def forward(self, x: Tensor, style: Tensor, skip: Optional[Tensor] = None) -> Tensor:
        y = self.conv(x, style) + self.bias.to(x.dtype)
        if skip is not None:
            if self.upsample:
                skip = self.dwt(upsample2(self.iwt(skip))) if self.wavelet else upsample2(skip)
            y = y + skip
        return y


class FromRGB(nn.Module):
    """Image (wavelet or plain) → features: optional blur-downsample ×½, then 1×1 conv + act.

    ``forward(img (B, C_img, H, W)) -> (img' (B, C_img, H', W'), feat (B, out_ch, H', W'))``
    with H' = H/2 when ``downsample`` (the downsampled image is returned for the next level).
    """

    def __init__(self, img_ch: int, out_ch: int, *, wavelet: bool = True, downsample: bool = True) -> None:
        super().__init__()
        self.wavelet, self.downsample = wavelet, downsample
        if wavelet:
            self.dwt, self.iwt = HaarTransform(), InverseHaarTransform()
        self.conv = EqualConv2d(img_ch, out_ch, 1, bias=False)
        self.act = FusedLeakyReLU(out_ch)

    def forward(self, img: Tensor) -> tuple[Tensor, Tensor]:
        if self.downsample:
            img = self.dwt(downsample2(self.iwt(img))) if self.wavelet else downsample2(img)
        return img, self.act(self.conv(img))


class ConvLayer(nn.Module):
    """Equalised conv (k×k, optional blur + stride-2 downsampling) + fused leaky ReLU."""

    def __init__(
        self, in_ch: int, out_ch: int, kernel: int = 3, *, downsample: bool = False, activate: bool = True
    ) -> None:
        super().__init__()
        self.blur: Optional[Blur] = None
        if downsample:
            p = 4 - 2 + (kernel - 1)
            self.blur = Blur(((p + 1) // 2, p // 2))
            self.conv = EqualConv2d(in_ch, out_ch, kernel, stride=2, padding=0, bias=not activate)
        else:
            self.conv = EqualConv2d(in_ch, out_ch, kernel, padding=kernel // 2, bias=not activate)
        self.act: Optional[FusedLeakyReLU] = FusedLeakyReLU(out_ch) if activate else None

    def forward(self, x: Tensor) -> Tensor:
        if self.blur is not None:
            x = self.blur(x)
        x = self.conv(x)
        return self.act(x) if self.act is not None else x


class ConvBlock(nn.Module):
    """Encoder block: conv3×3 (C_in→C_in) + blur/stride-2 conv3×3 (C_in→C_out).

    (B, C_in, H, W) → (B, C_out, H/2, W/2).
    """

    def __init__(self, in_ch: int, out_ch: int) -> None:
        super().__init__()
        self.conv1 = ConvLayer(in_ch, in_ch, 3)
        self.conv2 = ConvLayer(in_ch, out_ch, 3, downsample=True)

    def forward(self, x: Tensor) -> Tensor:
        return self.conv2(self.conv1(x))


class PixelNorm(nn.Module):
    """x / √(mean(x²) + 1e-8) over the last dimension."""

    def forward(self, x: Tensor) -> Tensor:
        return x * torch.rsqrt(x.square().mean(-1, keepdim=True) + 1e-8)


class MappingNetwork(nn.Module):
    """z (B, D) → w (B, D): PixelNorm then ``n`` × (Linear(D→D), LeakyReLU(0.1)) (plain nn.Linear)."""

    def __init__(self, style_dim: int = 64, n: int = 4) -> None:
        super().__init__()
        layers: list[nn.Module] = [PixelNorm()]
        for i in range(n):
            layers.append(nn.Linear(style_dim, style_dim))
            if i < n - 1:
                layers.append(nn.LeakyReLU(0.1))
        self.net = nn.Sequential(*layers)

    def forward(self, z: Tensor) -> Tensor:
        return self.net(z)
