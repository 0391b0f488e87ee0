"""Settings of one SRM training run, grouped: data, model, loss, optimiser, run.

Field ``metadata`` holds the command-line help, ``required`` and the name of the
:mod:`hogsa_loader.cli.checks` validator (``check``); ``hogsa train srm`` derives its
flags from these classes. ``config.json`` keeps the settings flat
(:meth:`SRMTrainConfig.to_json`), with the data root under the key ``data``.
"""

# ruff: noqa: UP045  (Optional[...] fields: hogsa_loader.cli.dataclass_args reads typing.Optional)
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Literal, Mapping, Optional

from hogsa_loader.train.config import config_from_flat, flat_config, flat_defaults
from hogsa_loader.train.config import field_options as _opt

__all__ = ["SRMDataConfig", "SRMLossConfig", "SRMModelConfig", "SRMOptimConfig", "SRMRunConfig", "SRMTrainConfig"]


def _tuple(value: Any) -> Any:
    """A list (as read from JSON) as a tuple; None and tuples unchanged."""
    return tuple(value) if isinstance(value, list) else value


@dataclass
class SRMDataConfig:
    """The HOGS runs, which of their renders are training inputs, the windows and the cache."""

    root: str = field(
        default="",
        metadata=_opt("dataset root (ARCTIC ./data) the HOGS runs were trained on", required=True, name="data"),
    )
    hogs: str = field(default="", metadata=_opt("folder of finished HOGS runs (or one run folder)", required=True))
    runs: Optional[tuple[str, ...]] = field(
        default=None, metadata=_opt("run folder names to use (default: all finished)")
    )
    pairs: Optional[Literal["own", "cross", "both"]] = field(
        default=None,
        metadata=_opt(
            "training inputs: each run's renders of its own training views (own), renders by view-fold runs "
            "that did not see the view (cross), or both (unset: both with cross-hogs, else own)"
        ),
    )
    cross_hogs: Optional[str] = field(
        default=None,
        metadata=_opt("folder of view-fold HOGS runs: same subject/object, trained on subsets of the training views"),
    )
    val_views: Optional[tuple[int, ...]] = field(
        default=None,
        metadata=_opt(
            "training views kept out of SRM training to pick the best checkpoint (their fold renders with "
            "cross-hogs); the saved model is the best one",
            "non_negative_int",
        ),
    )
    max_val: int = field(default=32, metadata=_opt("validation samples per run (evenly spaced)", "positive_int"))
    augment: Literal["none", "flip", "d4"] = field(
        default="d4",
        metadata=_opt("random flips (and 90° turns with d4) of each training window, input and target alike"),
    )
    cache: Optional[str] = field(
        default=None, metadata=_opt("folder for the coarse HOGS renders, shareable between SRM runs (unset: OUT/cache)")
    )
    image_size: Optional[int] = field(
        default=None, metadata=_opt("output / GT resolution (unset: the runs' image size)", "positive_int")
    )
    crop: int = field(
        default=128, metadata=_opt("training window at the output resolution (0: full images)", "non_negative_int")
    )

    def __post_init__(self) -> None:
        self.runs, self.val_views = _tuple(self.runs), _tuple(self.val_views)
        if self.pairs is None:
            self.pairs = "both" if self.cross_hogs else "own"


@dataclass
class SRMModelConfig:
    """The StyleUNet generator."""

    scale: int = field(
        default=1, metadata=_opt("output resolution factor (renders at image-size/scale)", choices=(1, 2))
    )
    channels: tuple[int, ...] = field(
        default=(32, 64, 128, 128, 128), metadata=_opt("StyleUNet widths per level, top (H/2) first", "positive_int")
    )
    style_dim: int = field(default=64, metadata=_opt("style vector width", "positive_int"))
    wavelet: bool = field(default=True, metadata=_opt("Haar-wavelet skips (no: plain RGB skips)"))

    def __post_init__(self) -> None:
        self.channels = _tuple(self.channels)


@dataclass
class SRMLossConfig:
    """``λ_L1·L1 + λ_P·perceptual + λ_GAN·GAN`` and the R1 penalty."""

    lambda_l1: float = field(default=5.0, metadata=_opt("weight of the L1 term", "non_negative_float"))
    lambda_perc: Optional[float] = field(
        default=None,
        metadata=_opt(
            "weight of the perceptual term (unset: 0.03 with VGG, 1.0 with the substitute)", "non_negative_float"
        ),
    )
    lambda_gan: float = field(default=1.0, metadata=_opt("0 disables the discriminator", "non_negative_float"))
    r1_gamma: float = field(default=10.0, metadata=_opt("R1 penalty weight γ", "non_negative_float"))
    r1_every: int = field(default=16, metadata=_opt("lazy R1 every N steps", "positive_int"))
    vgg_weights: Optional[str] = field(
        default=None, metadata=_opt("local torchvision vgg19 state dict (.pth or .safetensors)")
    )


@dataclass
class SRMOptimConfig:
    """Steps, batch, Adam learning rate and the EMA of the generator."""

    iters: int = field(default=4000, metadata=_opt("training steps", "non_negative_int"))
    batch_size: int = field(default=4, metadata=_opt("windows per step", "positive_int", name="batch_size"))
    lr: float = field(default=0.002, metadata=_opt("Adam learning rate (before the lazy-R1 ratio)", "positive_float"))
    ema_decay: float = field(default=0.999, metadata=_opt("EMA decay of the generator", "unit_float"))


@dataclass
class SRMRunConfig:
    """Run folder, device, seed and evaluation/checkpoint cadence."""

    out: str = field(default="", metadata=_opt("SRM run folder", required=True, name="out"))
    device: str = field(default="cpu", metadata=_opt("torch device", "torch_device", name="device"))
    seed: int = field(default=0, metadata=_opt("random seed", name="seed"))
    eval_every: int = field(default=500, metadata=_opt("evaluate every N steps (0: at the end)", "non_negative_int"))
    ckpt_every: int = field(default=500, metadata=_opt("checkpoint every N steps (0: at the end)", "non_negative_int"))
    strip_views: int = field(default=4, metadata=_opt("held-out samples in samples.png", "positive_int"))


@dataclass
class SRMTrainConfig:
    """All settings of one SRM run."""

    data: SRMDataConfig = field(default_factory=SRMDataConfig, metadata={"flat": True})
    model: SRMModelConfig = field(default_factory=SRMModelConfig)
    loss: SRMLossConfig = field(default_factory=SRMLossConfig)
    optim: SRMOptimConfig = field(default_factory=SRMOptimConfig)
    run: SRMRunConfig = field(default_factory=SRMRunConfig)

    #: flat settings that may differ between a run and its resumption
    RESUMABLE = ("iters", "eval_every", "ckpt_every", "device", "strip_views", "cache")
    #: group fields stored under another flat name in config.json
    FLAT_NAMES = {"root": "data"}

    def to_json(self) -> dict[str, Any]:
        """The flat settings written to the run's ``config.json``."""
        return flat_config(self)

    @classmethod
    def from_json(cls, settings: Mapping[str, Any]) -> SRMTrainConfig:
        """The config from flat settings (``config.json`` keys; unset ones keep their defaults)."""
        return config_from_flat(cls, settings)

    @classmethod
    def defaults(cls) -> dict[str, Any]:
        """``{flat setting: default}``."""
        return flat_defaults(cls)
