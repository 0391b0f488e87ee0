"""StyleUNet generator (StyleAvatar's), sized for per-sample use in a loader.

Encoder–decoder in the Haar-wavelet domain (the network runs at half the input resolution):
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from typing import Any, Optional, Sequence

import torch
import torch.nn.functional as F
from torch import Tensor, nn
from torch.utils.flop_counter import FlopCounterMode

from hogsa_loader.models.srm.stylegan import (
    ConvBlock,
    ConvLayer,
    FromRGB,
    HaarTransform,
    InverseHaarTransform,
    MappingNetwork,
    StyledConv,
    ToRGB,
)

__all__ = ["StyleUNetConfig", "StyleUNet", "count_gflops"]


@dataclass
class StyleUNetConfig:
    """Architecture settings (stored in the SRM manifest).

    Attributes:
        in_channels: input channels (SRM: straight RGB + alpha = 4).
        channels: feature width per level, level 0 at the top wavelet resolution (H/2).
        style_dim, mlp_num: style code size and mapping layers.
        scale: output resolution factor (1 or 2).
        wavelet: Haar-wavelet RGB skips (SWAGAN/StyleAvatar) or plain RGB skips.
        residual: predict a correction of the input's first three channels.
        extra_channels: width of the extra up stage when ``scale=2``.
    """

    in_channels: int = 4
    channels: list[int] = field(default_factory=lambda: [32, 64, 128, 128, 128])
    style_dim: int = 64
    mlp_num: int = 4
    scale: int = 1
    wavelet: bool = True
    residual: bool = True
    extra_channels: int = 16

    def to_json(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_json(cls, d: dict[str, Any]) -> "StyleUNetConfig":
        known = set(cls.__dataclass_fields__)
        unknown = sorted(set(d) - known)
        if unknown:
            raise ValueError(f"unknown StyleUNet settings {unknown}")
        d = dict(d)
        if "channels" in d:
            d["channels"] = [int(c) for c in d["channels"]]
        return cls(**d)


class StyleUNet(nn.Module):
    """StyleUNet: (B, C_in, H, W) → (B, 3, scale·H, scale·W).

    * **Encoder.** The input image (B, C_in, H, W) → DWT (4·C_in, H/2, W/2) → FromRGB → level-0
      features (``channels[0]``). Each of the ``len(channels) − 1`` levels: ConvBlock (conv +
      blur/stride-2 conv) to ``channels[i]`` plus a FromRGB skip of the blur-downsampled
      wavelet image. Every level's feature is kept.
    * **Decoder.** A 3×3 "comb" conv on the deepest feature, then per level (deepest first):
      U-Net skip (concatenate the encoder feature of that resolution, 3×3 conv 2C → C; not at
      the deepest level, where the comb conv plays that role), StyledConv ×2 up, StyledConv,
      ToRGB (wavelet skip accumulation). A last stage at the top wavelet level fuses the
      level-0 encoder feature and adds a StyledConv + ToRGB without upsampling; with
      ``scale=2`` one more up stage (StyledConv ×2 up, StyledConv, ToRGB) follows.
    * **Output.** IWT of the 12-channel skip → RGB at ``scale``·H. With ``residual=True`` (this
      project's default) the net predicts a correction added to the input's first three
      channels (bilinearly upsampled when ``scale=2``); the ToRGB layers start at a tenth of
      the usual weight so the untrained net is close to the identity. Values are in the
      caller's range (the SRM wrapper uses [−1, 1]), no tanh.
    * **Style.** A mapping network turns z ~ N(0, I_style) into the modulation style;
      :class:`StyleUNet` takes z (or None: the stored inference code ``z_infer``).

    Default :class:`StyleUNetConfig`: ``channels=(32, 64, 128, 128, 128)``, style 64, wavelet skips.
    At 256² in → 256² out it costs 5.2 GFLOPs (2.6 GMACs; :func:`count_gflops`).
    Input H and W must be multiples of ``2 ** len(channels)``.

    Args:
        cfg: :class:`StyleUNetConfig`.
    """

    def __init__(self, cfg: Optional[StyleUNetConfig] = None) -> None:
        super().__init__()
        cfg = cfg or StyleUNetConfig()
        if cfg.scale not in (1, 2):
            raise ValueError(f"scale must be 1 or 2, got {cfg.scale}")
        if len(cfg.channels) < 2:
            raise ValueError("channels needs at least two levels")
        self.cfg = cfg
        ch = list(cfg.channels)
        L = len(ch) - 1
        sd = cfg.style_dim
        wl = cfg.wavelet
        img_ch = 4 * cfg.in_channels if wl else cfg.in_channels
        self.dwt = HaarTransform()
        self.iwt = InverseHaarTransform()
        self.mapping = MappingNetwork(sd, cfg.mlp_num)
        self.register_buffer("z_infer", torch.randn(1, sd, generator=torch.Generator().manual_seed(0)))
        # encoder
        self.from_rgb = nn.ModuleList([FromRGB(img_ch, ch[0], wavelet=wl, downsample=False)])
        self.enc = nn.ModuleList()
        for i in range(1, L + 1):
            self.enc.append(ConvBlock(ch[i - 1], ch[i]))
            self.from_rgb.append(FromRGB(img_ch, ch[i], wavelet=wl, downsample=True))
        # decoder
        self.comb = ConvLayer(ch[L], ch[L], 3)
        self.fuse = nn.ModuleList()  # fuse[j] for level L-1-j ... 0 (the deepest uses comb)
        self.up1 = nn.ModuleList()
        self.up2 = nn.ModuleList()
        self.to_rgb = nn.ModuleList()
        for i in range(L, 0, -1):
            if i < L:
                self.fuse.append(ConvLayer(2 * ch[i], ch[i], 3))
            self.up1.append(StyledConv(ch[i], ch[i - 1], sd, upsample=True))
            self.up2.append(StyledConv(ch[i - 1], ch[i - 1], sd))
            self.to_rgb.append(ToRGB(ch[i - 1], sd, wavelet=wl, upsample=i < L))
        self.fuse.append(ConvLayer(2 * ch[0], ch[0], 3))
        self.top = StyledConv(ch[0], ch[0], sd)
        self.to_rgb.append(ToRGB(ch[0], sd, wavelet=wl, upsample=False))
        if cfg.scale == 2:
            self.extra1 = StyledConv(ch[0], cfg.extra_channels, sd, upsample=True)
            self.extra2 = StyledConv(cfg.extra_channels, cfg.extra_channels, sd)
            self.to_rgb.append(ToRGB(cfg.extra_channels, sd, wavelet=wl, upsample=True))
        if cfg.residual:
            with torch.no_grad():
                for t in self.to_rgb:
                    t.conv.weight.mul_(0.1)

    @property
    def multiple(self) -> int:
        """H and W must be multiples of this."""
        return 2 ** len(self.cfg.channels)

    def style(self, z: Optional[Tensor], batch: int) -> Tensor:
        """Style vectors (B, style_dim) from z (B, style_dim) or the stored inference code."""
        if z is None:
            z = self.z_infer.expand(batch, -1)
        return self.mapping(z.to(self.z_infer.dtype))  # (the parameters' dtype: fp32, or fp16/bf16 weights)

    def forward(self, x: Tensor, z: Optional[Tensor] = None, noise_mode: str = "random") -> Tensor:
        """Refine.

        Args:
            x: (B, C_in, H, W) input (first three channels: the image to correct).
            z: (B, style_dim) style codes; None uses ``z_infer``.
            noise_mode: ``"random"`` (training) or ``"none"`` (deterministic inference).

        Returns:
            (B, 3, scale·H, scale·W).
        """
        B, _, H, W = x.shape
        m = self.multiple
        if H % m or W % m:
            raise ValueError(f"StyleUNet input size {H}x{W} must be a multiple of {m}")
        s = self.style(z, B).to(x.dtype)
        img = self.dwt(x) if self.cfg.wavelet else F.avg_pool2d(x, 2)  # plain: half-res input image
        img, h = self.from_rgb[0](img)
        feats = [h]
        for block, frgb in zip(self.enc, self.from_rgb[1:]):
            img, r = frgb(img)
            h = block(h) + r
            feats.append(h)
        L = len(feats) - 1
        d = self.comb(feats[L])
        skip: Optional[Tensor] = None
        j = 0
        for k, i in enumerate(range(L, 0, -1)):
            if i < L:
                d = self.fuse[j](torch.cat([d, feats[i]], 1))
                j += 1
            d = self.up1[k](d, s, noise_mode)
            d = self.up2[k](d, s, noise_mode)
            skip = self.to_rgb[k](d, s, skip)
        d = self.fuse[j](torch.cat([d, feats[0]], 1))
        d = self.top(d, s, noise_mode)
        skip = self.to_rgb[L](d, s, skip)
        if self.cfg.scale == 2:
            d = self.extra1(d, s, noise_mode)
            d = self.extra2(d, s, noise_mode)
            skip = self.to_rgb[L + 1](d, s, skip)
        out = (
            self.iwt(skip)
            if self.cfg.wavelet
            else F.interpolate(skip, scale_factor=2.0, mode="bilinear", align_corners=False)
        )
        if self.cfg.residual:
            base = x[:, :3]
            if self.cfg.scale == 2:
                base = F.interpolate(base, scale_factor=2.0, mode="bilinear", align_corners=False)
            out = out + base
        return out


def count_gflops(model: nn.Module, height: int = 256, width: Optional[int] = None, in_channels: int = 4) -> float:
    """Forward GFLOPs (1 multiply-add = 2 FLOPs) of ``model`` on one (1, C, H, W) input,
    counted by ``torch.utils.flop_counter.FlopCounterMode`` (convolutions, matmuls)."""
    width = width or height
    p = next(model.parameters())
    x = torch.zeros(1, in_channels, height, width, device=p.device, dtype=p.dtype)
    with torch.no_grad(), FlopCounterMode(display=False) as fc:
        model(x, noise_mode="none") if isinstance(model, StyleUNet) else model(x)
    return fc.get_total_flops() / 1e9


def _parse_channels(spec: Sequence[int] | str) -> list[int]:
    if isinstance(spec, str):
        return [int(c) for c in spec.split(",") if c]
    return [int(c) for c in spec]
