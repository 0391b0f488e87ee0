"""SRM losses: L1, VGG19 perceptual loss (or a documented substitute), GAN, lazy R1.

Images are (B, 3, H, W) in [−1, 1] (StyleUNet's convention). :func:`perceptual_loss` gives
:class:`VGGPerceptualLoss` (from local weights) or its substitute :class:`LaplacianPyramidL1`;
:func:`l1_loss`, :func:`g_nonsaturating` (``softplus(−D(fake))``), :func:`d_logistic`
(``softplus(−D(real)) + softplus(D(fake))``) and :func:`r1_penalty` are the other terms.
"""

from __future__ import annotations

import sys
import warnings
from pathlib import Path
from typing import Callable, Optional, Union

import torch
import torch.nn.functional as F
from safetensors.torch import load_file
from torch import Tensor, nn

from hogsa_loader.errors import AssetError, PathLike

__all__ = [
    "VGG19_CFG",
    "VGG_SLICES",
    "PERCEPTUAL_DEFAULT_WEIGHT",
    "SubstituteWarning",
    "vgg19_features",
    "load_vgg19_features",
    "VGGPerceptualLoss",
    "LaplacianPyramidL1",
    "perceptual_loss",
    "l1_loss",
    "g_nonsaturating",
    "d_logistic",
    "r1_penalty",
]

#: torchvision's VGG19 configuration "E": conv widths, "M" = 2×2 max pool.
VGG19_CFG: tuple[Union[int, str], ...] = (
    64,
    64,
    "M",
    128,
    128,
    "M",
    256,
    256,
    256,
    256,
    "M",
    512,
    512,
    512,
    512,
    "M",
    512,
    512,
    512,
    512,
    "M",
)
#: ``features`` index ranges of the five perceptual slices (≈ relu1_1 … relu5_1).
VGG_SLICES: tuple[tuple[int, int], ...] = ((0, 2), (2, 7), (7, 12), (12, 21), (21, 30))
#: Default weight of the perceptual term by kind.
PERCEPTUAL_DEFAULT_WEIGHT = {"vgg": 0.03, "laplacian": 1.0}


class SubstituteWarning(UserWarning):
    """The VGG perceptual loss could not be used; a substitute replaces it."""


def vgg19_features() -> nn.Sequential:
    """Untrained ``torchvision.models.vgg19().features`` (same module indices)."""
    layers: list[nn.Module] = []
    c = 3
    for v in VGG19_CFG:
        if v == "M":
            layers.append(nn.MaxPool2d(2, 2))
        else:
            layers += [nn.Conv2d(c, int(v), 3, padding=1), nn.ReLU(inplace=False)]
            c = int(v)
    return nn.Sequential(*layers)


def load_vgg19_features(path: PathLike) -> nn.Sequential:
    """VGG19 ``features`` filled from a local torchvision-format state dict.

    Accepts the full ``vgg19`` state dict (``features.*`` and ``classifier.*`` keys; the
    classifier is ignored) or a ``features``-only one (``0.weight`` …), as ``.pth``/``.pt``
    (loaded with ``weights_only=True``: no code runs) or ``.safetensors``.

    Raises:
        AssetError: missing/unreadable file, or keys/shapes that are not VGG19's.
    """
    path = Path(path)
    if not path.is_file():
        raise AssetError(path, "VGG19 weights file is missing")
    try:
        if path.suffix == ".safetensors":
            sd = load_file(str(path))
        else:
            sd = torch.load(str(path), map_location="cpu", weights_only=True)
    except Exception as exc:  # noqa: BLE001 - any reader failure is a bad file
        raise AssetError(path, f"cannot read VGG19 weights ({type(exc).__name__}: {exc})") from None
    if not isinstance(sd, dict):
        raise AssetError(path, f"expected a state dict, got {type(sd).__name__}")
    if any(k.startswith("features.") for k in sd):
        sd = {k[len("features.") :]: v for k, v in sd.items() if k.startswith("features.")}
    feats = vgg19_features()
    want = feats.state_dict()
    missing = sorted(set(want) - set(sd))
    if missing:
        raise AssetError(
            path, f"not a torchvision VGG19 state dict: missing {missing[:4]}{'...' if len(missing) > 4 else ''}"
        )
    bad = [k for k in want if tuple(sd[k].shape) != tuple(want[k].shape)]
    if bad:
        raise AssetError(
            path,
            f"VGG19 tensor shapes differ for {bad[:4]} (e.g. {tuple(sd[bad[0]].shape)} vs {tuple(want[bad[0]].shape)})",
        )
    feats.load_state_dict({k: sd[k].float() for k in want})
    return feats


class VGGPerceptualLoss(nn.Module):
    """Σ_slices mean |φ_s(x) − φ_s(y)| with frozen VGG19 features.

    Torchvision's ``vgg19().features`` architecture rebuilt here (no torchvision needed) and
    filled from a **local** torchvision-format state dict (``features.N.weight`` /
    ``features.N.bias`` keys, ``.pth`` read with ``weights_only=True`` or ``.safetensors``);
    slices [0,2), [2,7), [7,12), [12,21), [21,30) (≈ relu1_1 … relu5_1), weight 1 each, L1
    between features summed; inputs stay in [−1, 1] without ImageNet normalisation (as StyleUNet
    does). Nothing is downloaded.

    Args:
        features: VGG19 ``features`` (see :func:`load_vgg19_features`).
        resize: bilinearly resize both images to this square size first (StyleUNet: 512;
            None keeps the size).
    """

    kind = "vgg"

    def __init__(self, features: nn.Sequential, resize: Optional[int] = None) -> None:
        super().__init__()
        self.slices = nn.ModuleList([nn.Sequential(*[features[i] for i in range(a, b)]) for a, b in VGG_SLICES])
        for p in self.parameters():
            p.requires_grad_(False)
        self.resize = resize
        self.eval()

    def train(self, mode: bool = True) -> "VGGPerceptualLoss":  # always frozen
        return super().train(False)

    def forward(self, x: Tensor, y: Tensor) -> Tensor:
        if self.resize:
            x = F.interpolate(x, size=(self.resize, self.resize), mode="bilinear", align_corners=False)
            y = F.interpolate(y, size=(self.resize, self.resize), mode="bilinear", align_corners=False)
        loss = x.new_zeros(())
        hx, hy = x, y.detach()
        for s in self.slices:
            hx, hy = s(hx), s(hy)
            loss = loss + (hx - hy).abs().mean()
        return loss


def _gauss_down(x: Tensor) -> Tensor:
    k = torch.tensor([1.0, 4.0, 6.0, 4.0, 1.0], device=x.device, dtype=x.dtype)
    k = (k[:, None] * k[None, :]) / 256.0
    c = x.shape[1]
    x = F.pad(x, (2, 2, 2, 2), mode="replicate")
    return F.conv2d(x, k[None, None].expand(c, 1, 5, 5), groups=c, stride=2)


class LaplacianPyramidL1(nn.Module):
    """``Σ_j mean |L_j(x) − L_j(y)|`` over a ``levels``-level Laplacian pyramid.

    The substitute for the VGG loss when no VGG weights are given (:func:`perceptual_loss`
    uses 5 levels; L_j: band-pass level j, the last level the low-pass residual), every
    band weighted 1 so the fine bands (edges,
    print, skin texture) count as much as the colour/low-pass error. It rewards sharp edges
    and correct mid-frequency texture like a perceptual loss, but has no learned features.

    L_j = G_j − up(G_{j+1}) (Gaussian 5-tap pyramid, bilinear up), the last level is the
    low-pass G_{levels−1}. Levels stop early when the image gets smaller than 8 px.
    """

    kind = "laplacian"

    def __init__(self, levels: int = 5) -> None:
        super().__init__()
        self.levels = levels

    def bands(self, x: Tensor) -> list[Tensor]:
        out = []
        g = x
        for _ in range(self.levels - 1):
            if min(g.shape[-2:]) < 8:
                break
            d = _gauss_down(g)
            up = F.interpolate(d, size=g.shape[-2:], mode="bilinear", align_corners=False)
            out.append(g - up)
            g = d
        out.append(g)
        return out

    def forward(self, x: Tensor, y: Tensor) -> Tensor:
        loss = x.new_zeros(())
        for bx, by in zip(self.bands(x), self.bands(y.detach())):
            loss = loss + (bx - by).abs().mean()
        return loss


def perceptual_loss(vgg_weights: Optional[PathLike], *, resize: Optional[int] = None, warn: bool = True) -> nn.Module:
    """The perceptual term: VGG19 from ``vgg_weights``, or (None) the Laplacian-pyramid
    substitute with a loud :class:`SubstituteWarning`. The returned module has ``.kind``
    (``"vgg"`` or ``"laplacian"``).

    Picks one and **warns** (``UserWarning`` + stderr) when it has to use the substitute;
    :data:`PERCEPTUAL_DEFAULT_WEIGHT` gives the default weight of each (0.03 for VGG as in
    StyleUNet; 1.0 for the substitute, whose values are pixel-scale).
    """
    if vgg_weights:
        return VGGPerceptualLoss(load_vgg19_features(vgg_weights), resize=resize)
    msg = (
        "no VGG19 weights given (--loss-vgg-weights PATH to a local torchvision vgg19 state dict): "
        "the perceptual term uses the Laplacian-pyramid L1 SUBSTITUTE instead of the VGG loss "
        f"(default weight {PERCEPTUAL_DEFAULT_WEIGHT['laplacian']} instead of {PERCEPTUAL_DEFAULT_WEIGHT['vgg']})"
    )
    if warn:
        warnings.warn(msg, SubstituteWarning, stacklevel=2)
        print(f"WARNING: {msg}", file=sys.stderr)
    return LaplacianPyramidL1()


def l1_loss(x: Tensor, y: Tensor) -> Tensor:
    """Mean absolute error."""
    return (x - y).abs().mean()


def g_nonsaturating(fake_logits: Tensor) -> Tensor:
    """Generator's non-saturating loss ``softplus(−D(G(x)))``, mean over the batch."""
    return F.softplus(-fake_logits).mean()


def d_logistic(real_logits: Tensor, fake_logits: Tensor) -> Tensor:
    """Discriminator's logistic loss ``softplus(−D(real)) + softplus(D(fake))``, batch mean."""
    return F.softplus(-real_logits).mean() + F.softplus(fake_logits).mean()


def r1_penalty(d_fn: Callable[[Tensor], Tensor], real: Tensor) -> tuple[Tensor, Tensor]:
    """R1: ``E_b ‖∇ₓ D(x_b)‖²`` at the real images (differentiable w.r.t. D's weights).

    Apply it every 16 D steps with weight γ/2·16, γ = 10 (lazy R1).

    Args:
        d_fn: image (B, 3, H, W) → logits (B,) (the condition already bound).
        real: real images; a leaf copy with ``requires_grad`` is made.

    Returns:
        (penalty scalar, real logits (B,)).
    """
    x = real.detach().requires_grad_(True)
    logits = d_fn(x)
    (grad,) = torch.autograd.grad(logits.sum(), x, create_graph=True)
    return grad.square().flatten(1).sum(1).mean(), logits
