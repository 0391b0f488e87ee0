"""Settings of one HOGS training run, grouped: data, model, loss, optimiser, run.

Every field's ``metadata`` carries its command-line help (``help``), whether the flag must be
given (``required``) and the name of its :mod:`hogsa_loader.cli.checks` validator
(``check``); ``hogsa train hogs`` derives its flags from these classes. The run folder's
``config.json`` keeps the settings flat (:meth:`HogsConfig.to_json`), with the data root
under the key ``data``.
"""

# ruff: noqa: UP045  (Optional[...] fields: hogsa_loader.cli.dataclass_args reads typing.Optional)
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Literal, Mapping, Optional

from hogsa_loader.train.config import (
    Dataset,
    config_from_flat,
    dataset_field,
    flat_config,
    flat_defaults,
    mano_dir_field,
    object_mesh_dir_field,
)
from hogsa_loader.train.config import field_options as _opt

__all__ = ["HogsConfig", "HogsDataConfig", "HogsLossConfig", "HogsModelConfig", "HogsOptimConfig", "HogsRunConfig"]


def _tuple(value: Any) -> Any:
    """A list (as read from JSON) as a tuple; None and tuples unchanged."""
    return tuple(value) if isinstance(value, list) else value


def name_float(text: str) -> tuple[str, float]:
    """``"opacity_logits=0.01"`` → ``("opacity_logits", 0.01)``.

    Raises:
        ValueError: not ``NAME=VALUE`` with a number as the value.
    """
    name, sep, value = text.partition("=")
    if not sep or not name.strip():
        raise ValueError(f"expected NAME=VALUE, got {text!r}")
    return name.strip(), float(value)


@dataclass
class HogsDataConfig:
    """Dataset, subject/object, camera views and the train/held-out split."""

    root: str = field(
        default="", metadata=_opt("dataset root (ARCTIC ./data, or the H2O root)", required=True, name="data")
    )
    subject: str = field(default="", metadata=_opt("subject, e.g. s01 (H2O: subject1)", required=True))
    object: str = field(default="", metadata=_opt("object name, e.g. box", required=True))
    dataset: Dataset = dataset_field()
    sequences: Optional[tuple[str, ...]] = field(
        default=None, metadata=_opt("sequence names, H2O as scene/seq (unset: all with the object)")
    )
    mano_dir: Optional[str] = mano_dir_field()
    object_mesh_dir: Optional[str] = object_mesh_dir_field()
    masks: Literal["auto", "files", "render"] = field(
        default="auto",
        metadata=_opt(
            "part masks: the dataset's files, or rendered from the annotated meshes (auto: files if present)"
        ),
    )
    window: Literal["crop", "fg"] = field(
        default="crop",
        metadata=_opt(
            "train on the whole cropped image (crop) or on a window around the posed hands and object of each "
            "frame (fg: more pixels on them at the same resolution; ARCTIC only)"
        ),
    )
    image_size: Optional[int] = field(
        default=None, metadata=_opt("training resolution (unset: ARCTIC cropped size, H2O 256)", "positive_int")
    )
    views: Optional[tuple[int, ...]] = field(
        default=None, metadata=_opt("camera views used (unset: ARCTIC 1-8, H2O 0-3; 4 = H2O ego)", "non_negative_int")
    )
    eval_views: Optional[tuple[int, ...]] = field(
        default=None, metadata=_opt("held-out views (unset: ARCTIC 8, H2O 3)", "non_negative_int")
    )
    eval_every_frame: int = field(default=8, metadata=_opt("hold out one frame in N", "positive_int"))
    frame_stride: int = field(default=1, metadata=_opt("use every N-th frame", "positive_int"))
    max_eval: int = field(default=8, metadata=_opt("held-out samples evaluated", "positive_int"))

    def __post_init__(self) -> None:
        self.sequences, self.views, self.eval_views = map(_tuple, (self.sequences, self.views, self.eval_views))


@dataclass
class HogsModelConfig:
    """The Gaussians of the hands and the object, and their shading."""

    gaussians: Literal["mesh", "free"] = field(
        default="mesh", metadata=_opt("mesh: Gaussians on the mesh faces (GaMeS); free: 3DGS-style")
    )
    k: int = field(default=2, metadata=_opt("Gaussians per face", "positive_int"))
    sh_degree: int = field(default=3, metadata=_opt("spherical-harmonics degree", choices=range(4)))
    hand_subdivide: int = field(default=0, metadata=_opt("hand mesh subdivision levels", choices=range(3)))
    object_subdivide: Optional[int] = field(
        default=None, metadata=_opt("0-2 (unset: until >= min-object-faces faces)", choices=range(3))
    )
    min_object_faces: int = field(
        default=8000, metadata=_opt("object faces the default subdivision reaches", "positive_int")
    )
    shading: Literal["lambert", "none"] = field(
        default="lambert",
        metadata=_opt(
            "lambert: learn one directional light in the world frame with the Gaussians; none: unshaded SH "
            "colours as in the paper"
        ),
    )


@dataclass
class HogsLossConfig:
    """Weights of the photometric, regularisation and alpha terms and the loss region."""

    margin: int = field(
        default=4,
        metadata=_opt(
            "mask dilation of the loss region (px of the cropped image; H2O: of a 256-px crop)", "non_negative_int"
        ),
    )
    lambda_ssim: float = field(default=0.2, metadata=_opt("weight of the D-SSIM term", "non_negative_float"))
    lambda_r: float = field(default=0.5, metadata=_opt("weight of the scale regulariser", "non_negative_float"))
    lambda_alpha: float = field(
        default=1.0, metadata=_opt("weight of alpha -> 0 outside the loss region", "non_negative_float")
    )
    lambda_alpha_in: float = field(
        default=1.0,
        metadata=_opt(
            "weight of alpha -> 1 inside the (eroded) mask; 0 = off (silhouettes may stay translucent)",
            "non_negative_float",
        ),
    )


@dataclass
class HogsOptimConfig:
    """Steps, batch and the Adam learning rates."""

    iters: int = field(default=2000, metadata=_opt("training steps", "non_negative_int"))
    batch_size: int = field(
        default=1, metadata=_opt("(frame, view) samples per step", "positive_int", name="batch_size")
    )
    lr_scale: float = field(
        default=1.0,
        metadata=_opt("multiply every learning rate except the position ones (offsets, means)", "positive_float"),
    )
    lr_overrides: dict[str, float] = field(
        default_factory=dict,
        metadata=_opt(
            "learning rates of single parameters as NAME=VALUE (e.g. opacity_logits=0.01)", type=name_float, list=True
        ),
    )
    sh_warmup: int = field(default=1000, metadata=_opt("raise the SH degree every N steps", "non_negative_int"))
    opacity_warmup: int = field(
        default=0, metadata=_opt("keep opacities frozen for the first N steps", "non_negative_int")
    )

    def __post_init__(self) -> None:
        self.lr_overrides = dict(self.lr_overrides)  # also from (name, value) pairs


@dataclass
class HogsRunConfig:
    """Run folder, device, seed, evaluation/checkpoint cadence and time budget."""

    out: str = field(default="", metadata=_opt("run folder", required=True, name="out"))
    device: str = field(default="cpu", metadata=_opt("torch device", "torch_device", name="device"))
    seed: int = field(default=0, metadata=_opt("random seed", name="seed"))
    eval_every: int = field(default=500, metadata=_opt("evaluate every N steps (0: at the end)", "non_negative_int"))
    ckpt_every: int = field(default=500, metadata=_opt("checkpoint every N steps (0: at the end)", "non_negative_int"))
    strip_views: int = field(default=4, metadata=_opt("held-out views in strip.png", "positive_int"))
    max_minutes: Optional[float] = field(
        default=None, metadata=_opt("training-time budget; the run ends early when it is used up", "positive_float")
    )


@dataclass
class HogsConfig:
    """All settings of one HOGS run (subject + object)."""

    data: HogsDataConfig = field(default_factory=HogsDataConfig, metadata={"flat": True})
    model: HogsModelConfig = field(default_factory=HogsModelConfig)
    loss: HogsLossConfig = field(default_factory=HogsLossConfig)
    optim: HogsOptimConfig = field(default_factory=HogsOptimConfig)
    run: HogsRunConfig = field(default_factory=HogsRunConfig)

    #: flat settings that may differ between a run and its resumption
    RESUMABLE = ("iters", "eval_every", "ckpt_every", "device", "strip_views", "max_minutes")
    #: group fields stored under another flat name in config.json
    FLAT_NAMES = {"root": "data"}

    def to_json(self) -> dict[str, Any]:
        """The flat settings written to the run's ``config.json``."""
        return flat_config(self)

    @classmethod
    def from_json(cls, settings: Mapping[str, Any]) -> HogsConfig:
        """The config from flat settings (``config.json`` keys; unset ones keep their defaults)."""
        return config_from_flat(cls, settings)

    @classmethod
    def defaults(cls) -> dict[str, Any]:
        """``{flat setting: default}``."""
        return flat_defaults(cls)
