"""Held-out rendering quality of a HOGS model: PSNR / SSIM / LPIPS inside the foreground box.

Metrics follow the paper's protocol: each held-out (view, frame) image is cropped to the
box of its dilated hand/object mask (the region the photometric loss sees), the ground
truth keeps only the hand/object pixels (black elsewhere, like the render), and the
render is compared in that box. SSIM is kornia's (11×11 Gaussian window, or 3×3 for
boxes smaller than 11 px). LPIPS needs pretrained network weights that cannot be
downloaded here: :func:`load_lpips` returns ``None`` with the reason when they are not
available locally.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Callable, Optional, Sequence

import numpy as np
import torch
from torch import Tensor

from hogsa_loader.train.hogs_data import ViewSample, dilate_mask
from hogsa_loader.train.losses import box_of, psnr, ssim_map

__all__ = ["RenderFn", "RefineFn", "LpipsFn", "gt_and_region", "box_metrics", "evaluate_samples", "load_lpips"]

#: samples → (rgb (B, H, W, 3) premultiplied on black, alpha (B, H, W)).
RenderFn = Callable[[Sequence[ViewSample]], tuple[Tensor, Tensor]]
#: (rgb (B, H, W, 3), alpha (B, H, W)) → refined rgb (B, H, W, 3).
RefineFn = Callable[[Tensor, Tensor], Tensor]
#: (pred (B, 3, H, W), gt (B, 3, H, W)) in [0, 1] → (B,) distances.
LpipsFn = Callable[[Tensor, Tensor], Tensor]


def gt_and_region(
    samples: Sequence[ViewSample], margin: int, device: torch.device | str = "cpu"
) -> tuple[Tensor, Tensor]:
    """Ground truth with the background blacked out (B, H, W, 3) and the loss region (B, H, W) bool.

    Args:
        samples: images with part masks.
        margin: dilation of the hand/object mask in pixels (the region's margin).
    """
    img = torch.as_tensor(np.stack([s.image for s in samples]), device=device).float() / 255.0
    mask = torch.as_tensor(np.stack([s.mask for s in samples]), device=device) > 0
    return img * mask[..., None], dilate_mask(mask, margin)


def box_metrics(pred: Tensor, gt: Tensor, region: Tensor, lpips_fn: Optional[LpipsFn] = None) -> dict[str, Any]:
    """PSNR / SSIM (/ LPIPS) of one image inside the box of its region.

    Args:
        pred, gt: (H, W, 3) in [0, 1]; region: (H, W) bool.
    """
    y0, y1, x0, x1 = box_of(region)
    p, g = pred[None, y0:y1, x0:x1].clamp(0, 1), gt[None, y0:y1, x0:x1]
    win = 11 if min(y1 - y0, x1 - x0) >= 11 else 3
    out: dict[str, Any] = {"psnr": psnr(p, g), "ssim": float(ssim_map(p, g, win).mean()), "box": [y0, y1, x0, x1]}
    if lpips_fn is not None:
        out["lpips"] = float(lpips_fn(p.permute(0, 3, 1, 2), g.permute(0, 3, 1, 2)).mean())
    return out


def _mean(rows: Sequence[dict[str, Any]], key: str) -> Optional[float]:
    vals = [r[key] for r in rows if r.get(key) is not None]
    return float(np.mean(vals)) if vals else None


@torch.no_grad()
def evaluate_samples(
    render_fn: RenderFn,
    samples: Sequence[ViewSample],
    names: Sequence[str],
    margin: int,
    *,
    refine: Optional[RefineFn] = None,
    lpips_fn: Optional[LpipsFn] = None,
    device: torch.device | str = "cpu",
    keep: int = 0,
) -> dict[str, Any]:
    """Metrics of held-out samples, overall, per view and per sample.

    Args:
        render_fn: renders a list of samples.
        samples: held-out images.
        names: sequence name per ``ViewSample.seq_index``.
        margin: loss-region dilation (px at the samples' resolution).
        refine: optional refinement of the renders (e.g. the SRM) before scoring.
        lpips_fn: optional LPIPS distance.
        keep: return the first ``keep`` (gt, render) image pairs under ``images``.

    Returns:
        ``psnr``, ``ssim``, ``lpips`` (None without ``lpips_fn``), ``alpha_outside`` (mean
        rendered alpha outside the region), ``per_view`` (list of per-view means),
        ``per_sample`` rows, and ``images`` when ``keep`` > 0.
    """
    rows, images = [], []
    for s in samples:
        gt, region = gt_and_region([s], margin, device)
        rgb, alpha = render_fn([s])
        if refine is not None:
            rgb = refine(rgb, alpha)
        m = box_metrics(rgb[0], gt[0], region[0], lpips_fn)
        outside = ~region[0]
        m.update(
            sequence=names[s.seq_index],
            frame=s.frame,
            view=s.view,
            alpha_outside=float(alpha[0][outside].mean()) if bool(outside.any()) else 0.0,
        )
        rows.append(m)
        if len(images) < keep:
            images.append((gt[0].cpu(), rgb[0].clamp(0, 1).cpu()))
    per_view = []
    for v in sorted({r["view"] for r in rows}):
        rv = [r for r in rows if r["view"] == v]
        per_view.append(
            {"view": v, "n": len(rv), "psnr": _mean(rv, "psnr"), "ssim": _mean(rv, "ssim"), "lpips": _mean(rv, "lpips")}
        )
    out: dict[str, Any] = {
        "psnr": _mean(rows, "psnr"),
        "ssim": _mean(rows, "ssim"),
        "lpips": _mean(rows, "lpips"),
        "alpha_outside": _mean(rows, "alpha_outside"),
        "num_samples": len(rows),
        "per_view": per_view,
        "per_sample": rows,
    }
    if keep:
        out["images"] = images
    return out


def load_lpips(device: torch.device | str = "cpu") -> tuple[Optional[LpipsFn], str]:
    """An LPIPS (AlexNet) distance if the ``lpips`` package and its weights are available locally.

    Nothing is downloaded: torchvision's AlexNet weights must already be in the torch hub
    cache (``$TORCH_HOME/hub/checkpoints/alexnet-*.pth``).

    Returns:
        ``(fn, note)``: ``fn`` is None when LPIPS is unavailable; ``note`` says why.
    """
    try:
        import lpips  # type: ignore[import-not-found]  # deferred: optional dependency
        import torchvision  # type: ignore[import-not-found]  # noqa: F401  # deferred: optional dependency
    except ImportError as exc:
        return None, f"LPIPS not computed: package {exc.name!r} is not installed (pip install lpips torchvision)"
    hub = Path(torch.hub.get_dir()) / "checkpoints"
    if not (hub.is_dir() and any(hub.glob("alexnet-*.pth"))):
        return None, f"LPIPS not computed: no local AlexNet weights in {hub} (they cannot be downloaded here)"
    net = lpips.LPIPS(net="alex", verbose=False).to(device).eval()

    def fn(pred: Tensor, gt: Tensor) -> Tensor:
        return net(pred * 2 - 1, gt * 2 - 1).flatten()

    return fn, "LPIPS (AlexNet, lpips package)"
