"""HOGS training losses: masked L1 / SSIM photometric loss, alpha supervision, metrics.

Images are (B, H, W, 3) in [0, 1]; ``region`` is a (B, H, W) bool map of the pixels the
photometric loss sees (the dilated hand/object mask), ``outside`` the pixels whose
rendered alpha must be 0, ``inside`` (the eroded mask) those whose alpha must be 1.

Why alpha inside: the ground truth is the foreground on black, so a render with alpha 0.5
and twice the colour matches it as well as an opaque one; on black nobody can tell, but
composited onto a background by the loader such Gaussians show the background through
the hands. The inside term makes the silhouette opaque.
"""

from __future__ import annotations

import kornia
import torch
from torch import Tensor

__all__ = ["masked_l1", "ssim_map", "masked_ssim", "alpha_outside", "alpha_inside", "hogs_loss", "psnr", "box_of"]


def _mean(x: Tensor, w: Tensor) -> Tensor:
    return (x * w).sum() / w.sum().clamp(min=1.0)


def masked_l1(pred: Tensor, gt: Tensor, region: Tensor) -> Tensor:
    """Mean absolute error over the region's pixels (and channels)."""
    return _mean((pred - gt).abs().mean(-1), region.to(pred.dtype))


def ssim_map(pred: Tensor, gt: Tensor, window: int = 11) -> Tensor:
    """(B, H, W) SSIM map (kornia, Gaussian window), averaged over channels."""
    m = kornia.metrics.ssim(pred.permute(0, 3, 1, 2), gt.permute(0, 3, 1, 2), window, max_val=1.0)
    return m.mean(1)


def masked_ssim(pred: Tensor, gt: Tensor, region: Tensor, window: int = 11) -> Tensor:
    """Mean SSIM over the region's pixels."""
    return _mean(ssim_map(pred, gt, window), region.to(pred.dtype))


def alpha_outside(alpha: Tensor, outside: Tensor) -> Tensor:
    """Mean rendered alpha (B, H, W) over the pixels that must stay empty."""
    return _mean(alpha, outside.to(alpha.dtype))


def alpha_inside(alpha: Tensor, inside: Tensor) -> Tensor:
    """Mean ``1 − alpha`` (B, H, W) over the pixels that must be opaque."""
    return _mean(1.0 - alpha, inside.to(alpha.dtype))


def hogs_loss(
    pred: Tensor,
    gt: Tensor,
    alpha: Tensor,
    region: Tensor,
    l_r: Tensor,
    *,
    lambda_ssim: float = 0.2,
    lambda_r: float = 0.5,
    lambda_alpha: float = 1.0,
    inside: Tensor | None = None,
    lambda_alpha_in: float = 0.0,
) -> tuple[Tensor, dict[str, float]]:
    """``(1 − λ_SSIM)·L1 + λ_SSIM·(1 − SSIM)`` on the region + ``λ_R·L_R`` + ``λ_A·alpha`` outside
    (+ ``λ_Ain·(1 − alpha)`` inside, when ``inside`` is given).

    Returns:
        the loss and its terms as floats (``l1``, ``ssim``, ``photo``, ``l_r``, ``alpha_out``,
        ``alpha_in``).
    """
    l1 = masked_l1(pred, gt, region)
    ss = masked_ssim(pred, gt, region)
    photo = (1.0 - lambda_ssim) * l1 + lambda_ssim * (1.0 - ss)
    a_out = alpha_outside(alpha, ~region)
    loss = photo + lambda_r * l_r + lambda_alpha * a_out
    a_in = alpha_inside(alpha, inside) if inside is not None else alpha.new_zeros(())
    if inside is not None and lambda_alpha_in:
        loss = loss + lambda_alpha_in * a_in
    terms = {
        k: float(v.detach())
        for k, v in (("l1", l1), ("ssim", ss), ("photo", photo), ("l_r", l_r), ("alpha_out", a_out), ("alpha_in", a_in))
    }
    return loss, terms


def psnr(pred: Tensor, gt: Tensor) -> float:
    """PSNR (dB, peak 1) of two images of any equal shape."""
    mse = float(((pred - gt) ** 2).mean())
    return float("inf") if mse == 0 else -10.0 * float(torch.log10(torch.tensor(mse)))


def box_of(mask: Tensor) -> tuple[int, int, int, int]:
    """``(y0, y1, x0, x1)`` (exclusive ends) of a (H, W) bool mask; the whole image if empty."""
    ys = torch.nonzero(mask.any(1)).flatten()
    xs = torch.nonzero(mask.any(0)).flatten()
    if ys.numel() == 0:
        return 0, mask.shape[0], 0, mask.shape[1]
    return int(ys[0]), int(ys[-1]) + 1, int(xs[0]), int(xs[-1]) + 1
