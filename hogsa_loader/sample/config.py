"""``LoaderConfig``: every setting of a :class:`~hogsa_loader.sample.dataset.HOGSADataset`, in small groups.

The same fields make the ``hogsa export`` flags
(:func:`~hogsa_loader.cli.dataclass_args.add_dataclass_arguments`) and the settings an export
records (:func:`export_info`): a new loader option is one field here.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any, Mapping, Optional, Union

from hogsa_loader.models.srm.model import TTA_CODES
from hogsa_loader.sample.augment import ArcticConfig
from hogsa_loader.sample.cameras import CameraConfig

__all__ = [
    "BackgroundConfig",
    "PoseConfig",
    "RefinementConfig",
    "SampleConfig",
    "SampleChecks",
    "RunConfig",
    "LoaderConfig",
    "export_info",
    "with_options",
    "is_default",
    "SRM_TTA_CHOICES",
]

#: Test-time augmentation copies the bundle's SRM accepts (``SRM.refine(tta=...)``).
SRM_TTA_CHOICES: tuple[int, ...] = tuple(sorted(TTA_CODES))


def _comma_joined(names: Optional[tuple[str, ...]]) -> Optional[str]:
    """Names recorded as one comma-separated string (as the flag takes them)."""
    return None if names is None else ",".join(names)


@dataclass(frozen=True)
class BackgroundConfig:
    """Backgrounds behind the renders (:func:`~hogsa_loader.compose.make_backgrounds`; none: procedural)."""

    coco_root: Optional[str] = field(default=None, metadata={"help": "COCO folder for backgrounds"})
    coco_ann: Optional[str] = field(default=None, metadata={"help": "COCO instances json (default under --coco-root)"})
    folder: Optional[str] = field(
        default=None, metadata={"help": "plain image folder for backgrounds", "name": "background_folder"}
    )
    categories: Optional[tuple[str, ...]] = field(
        default=None,
        metadata={
            "help": "COCO categories for backgrounds (names, or one comma-separated list)",
            "recorded": _comma_joined,
        },
    )
    exclude_person: bool = field(
        default=False, metadata={"help": "no COCO background showing people (their hands would be unlabelled hands)"}
    )
    image_dir: Optional[str] = field(
        default=None, metadata={"help": "COCO image folder (default under --coco-root)", "name": "coco_image_dir"}
    )
    camera_plates: bool = field(
        default=False,
        metadata={
            "help": "--background-folder holds plates (hogsa plates): a sample seen through a dataset camera gets "
            "that camera's own plate, cut by its crop box"
        },
    )

    def __post_init__(self) -> None:
        if self.categories is not None:
            cats = tuple(c for item in self.categories for c in str(item).split(",") if c)
            object.__setattr__(self, "categories", cats or None)

    def make_kwargs(self) -> dict[str, Any]:
        """Keyword arguments of :func:`~hogsa_loader.compose.make_backgrounds`."""
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}


@dataclass(frozen=True)
class PoseConfig:
    """Where the poses come from: a registered pose source and its options."""

    kind: str = field(
        default="perturb",
        metadata={
            "help": "pose source: perturb (annotated grasps perturbed), bank (the bundle's pose banks), online (POM "
            "per render batch)",
            "name": "poses",
            "choices": ("perturb", "bank", "online"),
        },
    )
    options: Mapping[str, Any] = field(
        default_factory=dict,
        metadata={"help": "keyword arguments of the pose-source factory", "name": "pose_options", "cli": False},
    )


@dataclass(frozen=True)
class RefinementConfig:
    """Refinement of the renders by the bundle's SRM."""

    srm: bool = field(default=False, metadata={"help": "apply the bundle's SRM (scale-1 models only)"})
    srm_tta: int = field(
        default=1,
        metadata={
            "help": "with --srm: test-time augmentation (symmetric copies averaged; 8x the SRM cost at 8)",
            "choices": SRM_TTA_CHOICES,
        },
    )

    def __post_init__(self) -> None:
        if isinstance(self.srm_tta, bool) or self.srm_tta not in SRM_TTA_CHOICES:
            raise ValueError(f"srm_tta must be one of {sorted(SRM_TTA_CHOICES)}, got {self.srm_tta!r}")
        if self.srm_tta != 1 and not self.srm:
            raise ValueError("srm_tta applies to the bundle's SRM: give srm=True (and no explicit refiner)")


@dataclass(frozen=True)
class SampleConfig:
    """What a sample looks like: protocol, crop, augmentation, extra targets."""

    protocol: str = field(
        default="p1",
        metadata={
            "help": "p1 (allocentric: novel + dataset cameras, ARCTIC crops) or p2 (egocentric: the subject's head "
            "camera, whole frame)",
            "choices": ("p1", "p2"),
        },
    )
    split: str = field(default="train", metadata={"help": "split whose sequences the pose source may use"})
    augment: bool = field(
        default=True, metadata={"help": "ARCTIC training augmentation (rotation, scale, colour noise)"}
    )
    render_size: Optional[int] = field(
        default=None, metadata={"help": "side of the rendered crop (default 1.5 x img_res)", "type": "positive_int"}
    )
    arctic: ArcticConfig = field(default_factory=ArcticConfig, metadata={"cli": False})
    interfield: Union[bool, float] = field(
        default=False,
        metadata={
            "help": "also make the InterField-SF targets (dist.*/idx.*/object.v_len); in Python a float is the clamp "
            "in metres",
            "cli_type": bool,
        },
    )
    ego_distortion: bool = field(
        default=True,
        metadata={"help": "p2: pass the pixels through the egocentric lens distortion (labels stay undistorted)"},
    )
    other_hands: float = field(
        default=0.0,
        metadata={
            "help": "share of render batches that show another subject's hands: poses, object, cameras and labels "
            "stay the batch's own, the hand Gaussians (colours and learnt vertex offsets) come from another subject "
            "of the models, drawn uniformly (its run with the same object when it has one); 0: every model's own "
            "hands",
            "type": "unit_float",
        },
    )

    def __post_init__(self) -> None:
        if self.protocol not in ("p1", "p2"):
            raise ValueError(f"protocol must be 'p1' (allocentric) or 'p2' (egocentric), got {self.protocol!r}")
        if isinstance(self.other_hands, bool) or not 0.0 <= float(self.other_hands) <= 1.0:
            raise ValueError(f"other_hands is a share of the render batches, in [0, 1]; got {self.other_hands!r}")
        object.__setattr__(self, "other_hands", float(self.other_hands))  # 1 and 1.0 record alike


@dataclass(frozen=True)
class SampleChecks:
    """When a synthetic sample is dropped.

    Attributes:
        min_alpha_pixels: fewer crop pixels with alpha > 0.5 → ``empty_alpha`` (the object's
            own part alpha is held to the same minimum).
        hands: ``"any"`` drops a sample when any hand is invalid (out of the crop per
            ARCTIC's validity flags), ``"both"`` only when both are, ``"none"`` never;
            an invalid object (``is_valid`` = 0) is always dropped → ``out_of_crop``.
        min_on_alpha: a valid hand (or the object) whose in-crop 2D keypoints lie on the
            rendered alpha less often than this → ``label_pixel_mismatch``.
        near_m: any joint / object vertex closer than this to the camera plane →
            ``behind_camera``.
        max_consecutive_drops: the stream stops with
            :class:`~hogsa_loader.sample.dataset.DroppedSamplesError` (the drops by reason)
            after this many dropped samples in a row: inputs that no sample survives (absurd
            poses, a wrong bundle) fail instead of rendering forever.
        warn_drop_share: above this share of dropped samples (after 256 attempts) the stream
            warns once, with the drops by reason.
    """

    min_alpha_pixels: int = 64
    hands: str = "any"
    min_on_alpha: float = 0.8
    near_m: float = 0.05
    max_consecutive_drops: int = 512
    warn_drop_share: float = 0.5

    def __post_init__(self) -> None:
        if self.hands not in ("any", "both", "none"):
            raise ValueError(f"SampleChecks.hands must be 'any', 'both' or 'none', got {self.hands!r}")
        if int(self.max_consecutive_drops) < 1:
            raise ValueError(f"SampleChecks.max_consecutive_drops must be >= 1, got {self.max_consecutive_drops}")
        if not 0.0 <= float(self.warn_drop_share) <= 1.0:
            raise ValueError(f"SampleChecks.warn_drop_share must be in [0, 1], got {self.warn_drop_share}")


@dataclass(frozen=True)
class RunConfig:
    """Where and how much: device, render batch, seed, epoch, models."""

    device: str = field(
        default="cpu",
        metadata={"help": "cpu or cuda (cuda:LOCAL_RANK under torchrun)", "type": "torch_device", "record": "never"},
    )
    batch_size: int = field(
        default=8,
        metadata={"help": "render batch (samples per render call, one model per batch)", "type": "positive_int"},
    )
    seed: int = field(default=0, metadata={"help": "base seed of every random draw"})
    epoch: int = field(default=0, metadata={"help": "initial epoch (set_epoch)", "type": "non_negative_int"})
    num_samples: Optional[int] = field(
        default=None, metadata={"help": "samples per epoch (None: endless)", "cli": False, "record": "never"}
    )
    backend: str = field(default="auto", metadata={"help": "renderer backend", "choices": ("auto", "torch", "gsplat")})
    subjects: Optional[tuple[str, ...]] = field(
        default=None, metadata={"help": "restrict the models to these subjects"}
    )
    objects: Optional[tuple[str, ...]] = field(default=None, metadata={"help": "restrict the models to these objects"})
    allow_held_out: Optional[tuple[str, ...]] = field(
        default=None, metadata={"help": "held-out subjects whose models may be streamed all the same (with a warning)"}
    )

    def __post_init__(self) -> None:
        if self.batch_size < 1:
            raise ValueError(f"batch_size must be >= 1, got {self.batch_size}")
        for name in ("subjects", "objects", "allow_held_out"):
            value = getattr(self, name)
            if value is not None and not isinstance(value, tuple):
                object.__setattr__(self, name, tuple(value))


@dataclass(frozen=True)
class LoaderConfig:
    """Every setting of a :class:`~hogsa_loader.sample.dataset.HOGSADataset`, in groups.

    Attributes:
        backgrounds: :class:`BackgroundConfig` (overridden by an explicit ``backgrounds=`` source).
        poses: :class:`PoseConfig` (overridden by an explicit ``poses=`` source).
        refinement: :class:`RefinementConfig` (overridden by an explicit ``refiner=``).
        cameras: :class:`~hogsa_loader.sample.cameras.CameraConfig` (``p1`` cameras).
        sample: :class:`SampleConfig`.
        checks: :class:`SampleChecks` (when samples are dropped).
        run: :class:`RunConfig`.

    Field metadata: ``help``, ``type`` (a converter of :mod:`hogsa_loader.cli.checks`, by
    name) and ``choices`` shape the flag; ``name`` is the flag and recorded key where it
    differs from the field name; ``cli: False`` marks settings that are objects rather than
    flags; ``flat`` marks groups whose flags carry no group prefix; ``recorded`` writes the
    value for the export (default: JSON-able as is); ``record: "never"`` leaves out a setting
    that does not change the frames (device, sample count); every other one is recorded.
    """

    backgrounds: BackgroundConfig = field(default_factory=BackgroundConfig, metadata={"flat": True})
    poses: PoseConfig = field(default_factory=PoseConfig, metadata={"flat": True})
    refinement: RefinementConfig = field(default_factory=RefinementConfig, metadata={"flat": True})
    cameras: CameraConfig = field(default_factory=CameraConfig, metadata={"cli": False})
    sample: SampleConfig = field(default_factory=SampleConfig, metadata={"flat": True})
    checks: SampleChecks = field(default_factory=SampleChecks, metadata={"cli": False})
    run: RunConfig = field(default_factory=RunConfig, metadata={"flat": True})


def is_default(group: Any) -> bool:
    """True when every field of the dataclass ``group`` has its default value."""
    return group == type(group)()


def _json_value(value: Any) -> Any:
    if dataclasses.is_dataclass(value):
        return dataclasses.asdict(value)
    if isinstance(value, tuple):
        return list(value)
    if isinstance(value, Mapping):
        return dict(value)
    return value


def export_info(config: Any) -> dict[str, Any]:
    """The config as the flat JSON-able dict an export records (``index.json`` ``info``).

    Flat groups are merged into one level, each leaf under its ``name`` (default the field
    name); a field whose ``record`` is ``"never"`` is left out.
    """
    out: dict[str, Any] = {}
    for f in dataclasses.fields(config):
        value = getattr(config, f.name)
        if f.metadata.get("flat"):
            out.update(export_info(value))
            continue
        if f.metadata.get("record", "always") == "never":
            continue
        out[f.metadata.get("name", f.name)] = f.metadata.get("recorded", _json_value)(value)
    return out


def _option_names(config: Any) -> dict[str, tuple[str, ...]]:
    """``{option name: field path}`` of every option of ``config`` (flat groups merged;
    an option is named by its field name or its ``name``)."""
    out: dict[str, tuple[str, ...]] = {}
    for f in dataclasses.fields(config):
        if f.metadata.get("flat"):
            out.update({k: (f.name, *v) for k, v in _option_names(getattr(config, f.name)).items()})
            continue
        out[f.name] = (f.name,)
        out[f.metadata.get("name", f.name)] = (f.name,)
    return out


def with_options(config: Any = None, **options: Any) -> LoaderConfig:
    """``config`` (default ``LoaderConfig()``) with options replaced by name.

    Names are those of :func:`export_info` and the ``hogsa export`` flags (``seed``,
    ``batch_size``, ``background_folder``, ``poses``, ``srm``, ``protocol``, ...) or a
    non-flat group's name (``cameras``, ``checks``).

    Example:
        >>> with_options(seed=3, batch_size=4).run.batch_size
        4
    """
    config = LoaderConfig() if config is None else config
    names = _option_names(config)
    unknown = sorted(set(options) - set(names))
    if unknown:
        raise TypeError(f"unknown loader option(s) {unknown}; known: {sorted(names)}")
    for name, value in options.items():
        config = _replace_path(config, names[name], value)
    return config


def _replace_path(obj: Any, path: tuple[str, ...], value: Any) -> Any:
    if len(path) == 1:
        return dataclasses.replace(obj, **{path[0]: value})
    return dataclasses.replace(obj, **{path[0]: _replace_path(getattr(obj, path[0]), path[1:], value)})
