"""Alpha compositing of rendered (premultiplied) foregrounds onto backgrounds.

:func:`composite` / :class:`AlphaComposite` apply the premultiplied "over" operator;
:func:`harmonize` is an optional, mild photometric matching of the foreground to the
background statistics (off by default in :class:`AlphaComposite`). All functions work on
channels-last tensors, batch first.
"""

from __future__ import annotations

from typing import Optional, Union

import torch
from torch import nn

__all__ = ["composite", "harmonize", "AlphaComposite", "Harmonize"]


def _alpha4(alpha: torch.Tensor, rgb: torch.Tensor) -> torch.Tensor:
    if alpha.dim() == rgb.dim() - 1:
        alpha = alpha.unsqueeze(-1)
    if alpha.dim() != rgb.dim() or alpha.shape[-1] != 1 or alpha.shape[:-1] != rgb.shape[:-1]:
        raise ValueError(
            f"alpha must be (B, H, W) or (B, H, W, 1) for rgb {tuple(rgb.shape)}, got {tuple(alpha.shape)}"
        )
    return alpha


def composite(rgb: torch.Tensor, alpha: torch.Tensor, background: torch.Tensor, clamp: bool = False) -> torch.Tensor:
    """Premultiplied "over": ``rgb + (1 − alpha) · background``.

    Gaussian splatting renders colour already multiplied by opacity on a black background
    (``C = Σ cᵢ αᵢ Tᵢ``, ``A = Σ αᵢ Tᵢ``), i.e. **premultiplied** colour. The "over" operator
    is then

        out = rgb + (1 − α) · background

    so ``α = 1`` gives the foreground exactly and ``α = 0`` the background exactly.

    Args:
        rgb: (B, H, W, 3) premultiplied foreground colour (colour × alpha, on black).
        alpha: (B, H, W, 1) or (B, H, W) opacity in [0, 1].
        background: (B, H, W, 3), or broadcastable to it; moved to ``rgb``'s device/dtype.
        clamp: clamp the result to [0, 1] (useful when ``rgb`` comes from a network,
            e.g. super-resolution, and may leave the range).

    Returns:
        (B, H, W, 3) composited colour, ``rgb``'s dtype and device.
    """
    if rgb.shape[-1] != 3:
        raise ValueError(f"rgb must be channels-last (..., 3), got {tuple(rgb.shape)}")
    a = _alpha4(alpha, rgb).to(rgb.dtype)
    bg = background.to(device=rgb.device, dtype=rgb.dtype)
    out = torch.addcmul(rgb, 1.0 - a, bg)
    return out.clamp(0.0, 1.0) if clamp else out


def _weighted_stats(x: torch.Tensor, w: torch.Tensor, eps: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-image, per-channel weighted mean and std of ``x`` (B, H, W, 3) with ``w`` (B, H, W, 1)."""
    ws = w.sum(dim=(1, 2)).clamp_min(eps)  # (B, 1)
    mu = (x * w).sum(dim=(1, 2)) / ws
    var = ((x - mu[:, None, None]) ** 2 * w).sum(dim=(1, 2)) / ws
    return mu, var.clamp_min(0).sqrt()


def harmonize(
    rgb: torch.Tensor,
    alpha: torch.Tensor,
    background: torch.Tensor,
    strength: float = 0.3,
    max_gain: float = 1.5,
    eps: float = 1e-3,
) -> torch.Tensor:
    """Mild colour/brightness matching of a premultiplied foreground to its background.

    Per image and channel, the foreground colour statistics (alpha-weighted mean ``μf``
    and std ``σf`` of the *un*-premultiplied colour) are moved a fraction ``strength`` of
    the way to the background's (``μb``, ``σb``, over the whole background):

        c' = (c − μf) · g + μf + strength · (μb − μf),   g = clip((σb/σf)^strength, 1/max_gain, max_gain)

    applied directly to premultiplied colour (``rgb' = α c'``), then clamped to
    ``[0, α]``. No division by alpha happens, so transparent pixels stay exactly 0.

    Args:
        rgb: (B, H, W, 3) premultiplied foreground.
        alpha: (B, H, W, 1) or (B, H, W).
        background: (B, H, W, 3).
        strength: 0 = unchanged, 1 = full statistics transfer.
        max_gain: bound on the contrast gain (and its inverse).
        eps: minimum alpha mass / std.

    Returns:
        (B, H, W, 3) premultiplied, harmonised foreground.
    """
    if strength == 0:
        return rgb
    a = _alpha4(alpha, rgb).to(rgb.dtype)
    bg = background.to(device=rgb.device, dtype=rgb.dtype).expand_as(rgb)
    mass = a.sum(dim=(1, 2)).clamp_min(eps)  # (B, 1)
    mu_f = rgb.sum(dim=(1, 2)) / mass  # Σ α c / Σ α
    # Σ α c² = Σ rgb² / α where α > 0
    c2 = torch.where(a > eps, rgb * rgb / a.clamp_min(eps), torch.zeros_like(rgb))
    var_f = (c2.sum(dim=(1, 2)) / mass - mu_f**2).clamp_min(0)
    sd_f = var_f.sqrt().clamp_min(eps)
    mu_b, sd_b = _weighted_stats(bg, torch.ones_like(a), eps)
    gain = ((sd_b.clamp_min(eps) / sd_f) ** strength).clamp(1.0 / max_gain, max_gain)
    shift = mu_f + strength * (mu_b - mu_f)
    g4, mu4, sh4 = gain[:, None, None], mu_f[:, None, None], shift[:, None, None]
    out = (rgb - a * mu4) * g4 + a * sh4
    return torch.minimum(out.clamp_min(0.0), a.expand_as(out))


class Harmonize(nn.Module):
    """Module form of :func:`harmonize` (no parameters).

    Args:
        strength: fraction of the statistics transfer (0 = identity).
        max_gain: contrast gain bound.

    Shape:
        rgb (B, H, W, 3), alpha (B, H, W[, 1]), background (B, H, W, 3) → (B, H, W, 3).
    """

    def __init__(self, strength: float = 0.3, max_gain: float = 1.5) -> None:
        super().__init__()
        self.strength = float(strength)
        self.max_gain = float(max_gain)

    def forward(self, rgb: torch.Tensor, alpha: torch.Tensor, background: torch.Tensor) -> torch.Tensor:
        return harmonize(rgb, alpha, background, self.strength, self.max_gain)

    def extra_repr(self) -> str:
        return f"strength={self.strength}, max_gain={self.max_gain}"


class AlphaComposite(nn.Module):
    """Composite premultiplied renders onto backgrounds (optionally harmonised first).

    Args:
        harmonize: None/False/0 = off (default); a float = :class:`Harmonize` strength;
            or a :class:`Harmonize` module.
        clamp: clamp the output to [0, 1].

    Shape:
        rgb (B, H, W, 3) premultiplied, alpha (B, H, W, 1) or (B, H, W),
        background (B, H, W, 3) → (B, H, W, 3).

    Example:
        >>> comp = AlphaComposite()
        >>> out = comp(rgb, alpha, backgrounds.sample(B, H, W, gen).to(rgb.device))
    """

    def __init__(self, harmonize: Union[None, bool, float, Harmonize] = None, clamp: bool = True) -> None:
        super().__init__()
        self.harmonizer: Optional[Harmonize]
        if isinstance(harmonize, Harmonize):
            self.harmonizer = harmonize
        elif harmonize is None or harmonize is False or float(harmonize) == 0.0:
            self.harmonizer = None
        elif harmonize is True:
            self.harmonizer = Harmonize()
        else:
            self.harmonizer = Harmonize(float(harmonize))
        self.clamp = bool(clamp)

    def forward(self, rgb: torch.Tensor, alpha: torch.Tensor, background: torch.Tensor) -> torch.Tensor:
        if self.harmonizer is not None:
            rgb = self.harmonizer(rgb, alpha, background)
        return composite(rgb, alpha, background, clamp=self.clamp)

    def extra_repr(self) -> str:
        return f"clamp={self.clamp}"
