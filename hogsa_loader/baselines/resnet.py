"""ResNet-18 / ResNet-50 feature extractors with torchvision's parameter names.

The modules are named exactly as torchvision's ``resnet18`` / ``resnet50`` (``conv1``,
``bn1``, ``layer1`` … ``layer4``; blocks with ``conv1``, ``bn1``, ``conv2``, ``bn2``,
``conv3``, ``bn3``, ``downsample.0/.1``; the stride of a bottleneck sits on its 3×3
convolution, "ResNet v1.5"), so torchvision ImageNet weights load by name. As in ARCTIC's
ArcticNet-SF backbone there is no ``avgpool`` and no ``fc``: :meth:`ResNet.forward`
returns the ``layer4`` map, and the state dict has no ``fc.*`` entry.

torchvision itself is not imported (its PyPI wheel does not load against a CPU-only
torch build).
"""

from __future__ import annotations

from pathlib import Path
from typing import Literal, Optional, Union

import torch
from safetensors.torch import load_file
from torch import Tensor, nn

from hogsa_loader.errors import AssetError, PathLike

__all__ = [
    "BACKBONE_CHANNELS",
    "BasicBlock",
    "Bottleneck",
    "ResNet",
    "build_backbone",
    "check_state_keys",
    "load_backbone_weights",
    "read_state_dict",
    "resnet18",
    "resnet50",
]

BackboneName = Literal["resnet18", "resnet50"]

#: Channels of the ``layer4`` feature map.
BACKBONE_CHANNELS: dict[str, int] = {"resnet18": 512, "resnet50": 2048}


def _conv3x3(c_in: int, c_out: int, stride: int = 1) -> nn.Conv2d:
    return nn.Conv2d(c_in, c_out, kernel_size=3, stride=stride, padding=1, bias=False)


def _conv1x1(c_in: int, c_out: int, stride: int = 1) -> nn.Conv2d:
    return nn.Conv2d(c_in, c_out, kernel_size=1, stride=stride, bias=False)


class BasicBlock(nn.Module):
    """Two 3×3 convolutions with an identity (or projected) shortcut.

    Args:
        c_in: input channels; planes: output channels; stride: of the first conv;
        downsample: shortcut projection (``conv1x1`` + BN) or None.
    """

    expansion = 1

    def __init__(self, c_in: int, planes: int, stride: int = 1, downsample: Optional[nn.Module] = None):
        super().__init__()
        self.conv1 = _conv3x3(c_in, planes, stride)
        self.bn1 = nn.BatchNorm2d(planes)
        self.relu = nn.ReLU(inplace=True)
        self.conv2 = _conv3x3(planes, planes)
        self.bn2 = nn.BatchNorm2d(planes)
        self.downsample = downsample

    def forward(self, x: Tensor) -> Tensor:
        """x: (B, c_in, H, W) -> (B, planes, H/stride, W/stride)."""
        out = self.relu(self.bn1(self.conv1(x)))
        out = self.bn2(self.conv2(out))
        identity = x if self.downsample is None else self.downsample(x)
        return self.relu(out + identity)


class Bottleneck(nn.Module):
    """1×1 → 3×3 (strided) → 1×1 bottleneck, output ``4 · planes`` channels.

    Args:
        c_in: input channels; planes: bottleneck width; stride: of the 3×3 conv;
        downsample: shortcut projection or None.
    """

    expansion = 4

    def __init__(self, c_in: int, planes: int, stride: int = 1, downsample: Optional[nn.Module] = None):
        super().__init__()
        self.conv1 = _conv1x1(c_in, planes)
        self.bn1 = nn.BatchNorm2d(planes)
        self.conv2 = _conv3x3(planes, planes, stride)
        self.bn2 = nn.BatchNorm2d(planes)
        self.conv3 = _conv1x1(planes, planes * self.expansion)
        self.bn3 = nn.BatchNorm2d(planes * self.expansion)
        self.relu = nn.ReLU(inplace=True)
        self.downsample = downsample

    def forward(self, x: Tensor) -> Tensor:
        """x: (B, c_in, H, W) -> (B, 4·planes, H/stride, W/stride)."""
        out = self.relu(self.bn1(self.conv1(x)))
        out = self.relu(self.bn2(self.conv2(out)))
        out = self.bn3(self.conv3(out))
        identity = x if self.downsample is None else self.downsample(x)
        return self.relu(out + identity)


class ResNet(nn.Module):
    """ResNet trunk without the classifier (torchvision names, torchvision init).

    Args:
        block: :class:`BasicBlock` or :class:`Bottleneck`.
        layers: blocks per stage, e.g. ``(2, 2, 2, 2)`` for ResNet-18.
    """

    def __init__(self, block: type[Union[BasicBlock, Bottleneck]], layers: tuple[int, int, int, int]):
        super().__init__()
        self._c = 64
        self.conv1 = nn.Conv2d(3, 64, kernel_size=7, stride=2, padding=3, bias=False)
        self.bn1 = nn.BatchNorm2d(64)
        self.relu = nn.ReLU(inplace=True)
        self.maxpool = nn.MaxPool2d(kernel_size=3, stride=2, padding=1)
        self.layer1 = self._stage(block, 64, layers[0], 1)
        self.layer2 = self._stage(block, 128, layers[1], 2)
        self.layer3 = self._stage(block, 256, layers[2], 2)
        self.layer4 = self._stage(block, 512, layers[3], 2)
        self.out_channels = 512 * block.expansion
        for m in self.modules():
            if isinstance(m, nn.Conv2d):
                nn.init.kaiming_normal_(m.weight, mode="fan_out", nonlinearity="relu")
            elif isinstance(m, nn.BatchNorm2d):
                nn.init.ones_(m.weight)
                nn.init.zeros_(m.bias)

    def _stage(self, block: type, planes: int, n: int, stride: int) -> nn.Sequential:
        c_out = planes * block.expansion
        down = None
        if stride != 1 or self._c != c_out:
            down = nn.Sequential(_conv1x1(self._c, c_out, stride), nn.BatchNorm2d(c_out))
        blocks = [block(self._c, planes, stride, down)]
        self._c = c_out
        blocks += [block(c_out, planes) for _ in range(1, n)]
        return nn.Sequential(*blocks)

    def forward(self, x: Tensor) -> Tensor:
        """x: (B, 3, H, W) normalised images -> (B, C, ⌈H/32⌉, ⌈W/32⌉) ``layer4`` features."""
        x = self.maxpool(self.relu(self.bn1(self.conv1(x))))
        return self.layer4(self.layer3(self.layer2(self.layer1(x))))


def resnet18() -> ResNet:
    """Randomly initialised ResNet-18 trunk (512 output channels)."""
    return ResNet(BasicBlock, (2, 2, 2, 2))


def resnet50() -> ResNet:
    """Randomly initialised ResNet-50 trunk (2048 output channels)."""
    return ResNet(Bottleneck, (3, 4, 6, 3))


def build_backbone(name: BackboneName, weights: Optional[PathLike] = None) -> ResNet:
    """A ResNet trunk by name, optionally with weights from a local file.

    Args:
        name: ``"resnet18"`` or ``"resnet50"``.
        weights: torchvision ``.pth`` or ``.safetensors`` file (see
            :func:`load_backbone_weights`); None = random init.

    Returns:
        the :class:`ResNet`.
    """
    builders = {"resnet18": resnet18, "resnet50": resnet50}
    if name not in builders:
        raise ValueError(f"unknown backbone {name!r}; choose one of {sorted(builders)}")
    model = builders[name]()
    if weights is not None:
        load_backbone_weights(model, weights)
    return model


def read_state_dict(path: PathLike, weights_only: bool = True) -> dict[str, Tensor]:
    """Tensors of a ``.safetensors`` file or of a ``torch.save`` file (on CPU).

    Args:
        path: the file.
        weights_only: passed to ``torch.load``; False unpickles arbitrary objects (which
            can run code): only for files you trust.

    Returns:
        the loaded mapping (a Lightning checkpoint is returned whole, not unwrapped).
    """
    path = Path(path)
    if not path.is_file():
        raise AssetError(path, "file is missing")
    if path.suffix == ".safetensors":
        try:
            return load_file(str(path), device="cpu")
        except Exception as exc:  # safetensors raises its own error types
            raise AssetError(path, f"not a readable safetensors file ({exc})") from None
    try:
        obj = torch.load(path, map_location="cpu", weights_only=weights_only)
    except Exception as exc:  # pickle / zip errors of any kind
        hint = " (it holds non-tensor objects; weights_only=False loads it if you trust it)" if weights_only else ""
        raise AssetError(path, f"cannot load with torch.load: {type(exc).__name__}: {exc}{hint}") from None
    if not isinstance(obj, dict):
        raise AssetError(path, f"expected a dict of tensors, got {type(obj).__name__}")
    return obj


def check_state_keys(path: PathLike, own: dict[str, Tensor], state: dict[str, Tensor], what: str) -> None:
    """AssetError naming ``path`` unless ``state`` has ``own``'s keys and shapes.

    ``num_batches_tracked`` entries may be missing (older torchvision files lack them).

    Args:
        path: the file ``state`` came from (for the message).
        own: the expected ``{key: tensor}``; state: the loaded one.
        what: what ``state`` should be, e.g. ``"a ResNet-18 backbone"``.
    """
    optional = {k for k in own if k.endswith("num_batches_tracked")}
    missing = sorted(set(own) - set(state) - optional)
    unexpected = sorted(set(state) - set(own))
    wrong = sorted(k for k in set(own) & set(state) if tuple(own[k].shape) != tuple(state[k].shape))
    if missing or unexpected or wrong:
        parts = [
            f"{name} ({len(keys)}): {keys[:8]}{' …' if len(keys) > 8 else ''}"
            for name, keys in (("missing keys", missing), ("unexpected keys", unexpected), ("shape mismatch", wrong))
            if keys
        ]
        raise AssetError(path, f"weights do not fit {what}: " + "; ".join(parts))


def load_backbone_weights(model: ResNet, path: PathLike) -> None:
    """Load torchvision ImageNet weights (or any state dict with its names) into ``model``.

    ``fc.*`` entries are ignored; everything else must match by name and shape
    (``num_batches_tracked``, absent from older torchvision files, may be missing).

    Args:
        model: the :class:`ResNet` to fill in place.
        path: a ``.pth``/``.pt`` state dict (read with ``torch.load(weights_only=True)``)
            or a ``.safetensors`` file.

    Raises:
        AssetError: naming the file and the missing / unexpected / mis-shaped keys.
    """
    state = {k: v for k, v in read_state_dict(path).items() if not k.startswith("fc.")}
    if not all(isinstance(v, Tensor) for v in state.values()):
        raise AssetError(path, "expected a flat dict of tensors (a state dict)")
    own = model.state_dict()
    check_state_keys(path, own, state, f"a ResNet trunk with {model.out_channels} output channels")
    for k in own:
        if k.endswith("num_batches_tracked") and k not in state:
            state[k] = own[k]
    model.load_state_dict(state, strict=True)
