"""Settings of POM's offline jobs: fitting a ContactNet and building a pose bank.

Grouped dataclasses whose field ``metadata`` carries the command-line help, ``required``
and the name of the :mod:`hogsa_loader.cli.checks` validator (``check``);
``hogsa train contactnet`` and ``hogsa train bank`` derive their flags
from them.
"""

# ruff: noqa: UP045  (Optional[...] fields: hogsa_loader.cli.dataclass_args reads typing.Optional)
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Literal, Optional

from hogsa_loader.assets.arctic_processing import FRAME_MARGIN
from hogsa_loader.models.pom.pipeline import check_bank_frames
from hogsa_loader.train.config import Dataset, dataset_field, mano_dir_field, object_mesh_dir_field
from hogsa_loader.train.config import field_options as _opt

__all__ = [
    "BankDataConfig",
    "BankPOMConfig",
    "BankRunConfig",
    "ContactNetDataConfig",
    "ContactNetJobConfig",
    "ContactNetOptimConfig",
    "ContactNetRunConfig",
    "PoseBankConfig",
]


def _tuple(value: Any) -> Any:
    """A list as a tuple; None and tuples unchanged."""
    return tuple(value) if isinstance(value, list) else value


# --------------------------------------------------------------------------------------
# ContactNet
# --------------------------------------------------------------------------------------


@dataclass
class ContactNetDataConfig:
    """The annotated frames: the training subjects, and those ContactNet is validated on."""

    root: str = field(
        default="", metadata=_opt("dataset root (ARCTIC ./data, or the H2O root)", required=True, name="data")
    )
    dataset: Dataset = dataset_field()
    mano_dir: Optional[str] = mano_dir_field()
    object_mesh_dir: Optional[str] = object_mesh_dir_field()
    val_subjects: Optional[tuple[str, ...]] = field(
        default=None,
        metadata=_opt(
            "training subjects kept out of ContactNet's training to validate it on (unset: none; ContactNet "
            "trains on every training subject)"
        ),
    )
    allow_held_out: Optional[tuple[str, ...]] = field(
        default=None,
        metadata=_opt(
            "subjects the dataset's protocol holds out (ARCTIC: s03, s05; H2O: subject4) to read all the same "
            "(unset: none are read)"
        ),
    )

    def __post_init__(self) -> None:
        self.val_subjects, self.allow_held_out = _tuple(self.val_subjects), _tuple(self.allow_held_out)


@dataclass
class ContactNetOptimConfig:
    """Steps, batch, sampled object points, learning rate and seed."""

    iters: int = field(default=1500, metadata=_opt("training steps", "non_negative_int"))
    batch: int = field(default=8, metadata=_opt("frames per step", "positive_int", name="batch_size"))
    points: int = field(default=512, metadata=_opt("object points per training sample", "positive_int"))
    lr: float = field(default=1e-3, metadata=_opt("Adam learning rate", "positive_float"))
    seed: int = field(default=0, metadata=_opt("random seed", name="seed"))


@dataclass
class ContactNetRunConfig:
    """Run folder and validation cadence."""

    out: str = field(default="", metadata=_opt("run folder", required=True, name="out"))
    val_every: int = field(default=100, metadata=_opt("validate every N steps", "positive_int"))


@dataclass
class ContactNetJobConfig:
    """All settings of one ContactNet fit (:func:`~hogsa_loader.train.pom_jobs.fit_contactnet`)."""

    data: ContactNetDataConfig = field(default_factory=ContactNetDataConfig, metadata={"flat": True})
    optim: ContactNetOptimConfig = field(default_factory=ContactNetOptimConfig)
    run: ContactNetRunConfig = field(default_factory=ContactNetRunConfig)


# --------------------------------------------------------------------------------------
# pose bank
# --------------------------------------------------------------------------------------


@dataclass
class BankDataConfig:
    """The dataset, the ContactNet and which sequences and frames are optimised."""

    root: str = field(
        default="", metadata=_opt("dataset root (ARCTIC ./data, or the H2O root)", required=True, name="data")
    )
    dataset: Dataset = dataset_field()
    mano_dir: Optional[str] = mano_dir_field()
    object_mesh_dir: Optional[str] = object_mesh_dir_field()
    contactnet: str = field(default="", metadata=_opt("ContactNet run folder", required=True))
    subjects: Optional[tuple[str, ...]] = field(
        default=None, metadata=_opt("subjects (unset: every subject the dataset's protocol does not hold out)")
    )
    sequences: Optional[tuple[str, ...]] = field(
        default=None, metadata=_opt("sid/seq ids, e.g. s01/box_grab_01 (unset: all of those subjects)")
    )
    allow_held_out: Optional[tuple[str, ...]] = field(
        default=None,
        metadata=_opt(
            "subjects the dataset's protocol holds out (ARCTIC: s03, s05; H2O: subject4) to read all the same "
            "(unset: none are read)"
        ),
    )
    per_sequence: int = field(default=16, metadata=_opt("frames per sequence (evenly spaced)", "positive_int"))
    variants: int = field(default=1, metadata=_opt("perturbations per frame", "positive_int"))
    frames: Literal["contact", "all"] = field(
        default="contact",
        metadata=_opt(
            "contact: frames where a hand touches the object (grasps, whose hands are more closed than a "
            "sequence's on average); all: every frame within the margin, so that frames without contact keep their "
            "share of the data (POM pulls only the hands touching in the source frame)"
        ),
    )

    frame_margin: int = field(
        default=FRAME_MARGIN,
        metadata=_opt(
            "annotated frames left out at each end of a sequence (ARCTIC's data loaders leave out 10 images at "
            "each end; the loader's perturb poses leave out 10 annotated frames)",
            "non_negative_int",
        ),
    )

    def __post_init__(self) -> None:
        self.subjects, self.sequences = _tuple(self.subjects), _tuple(self.sequences)
        self.allow_held_out = _tuple(self.allow_held_out)
        if self.per_sequence < 1 or self.variants < 1:
            raise ValueError(f"per_sequence and variants must be >= 1, got {self.per_sequence} and {self.variants}")
        check_bank_frames(self.frames)


@dataclass
class BankPOMConfig:
    """The start perturbation, the POM optimisation and which grasps are kept."""

    iters: int = field(default=200, metadata=_opt("POM iterations", "non_negative_int"))
    batch: int = field(default=16, metadata=_opt("grasps optimised at once", "positive_int", name="batch_size"))
    arti_range: Optional[tuple[float, ...]] = field(
        default=None,
        metadata=_opt(
            "draw the articulation angle uniformly in [LO, HI] rad (the paper: 0.0314,0.628) instead of keeping the "
            "annotated angle",
            count=2,
        ),
    )
    keep_rejected: bool = field(default=False, metadata=_opt("also keep grasps that fail acceptance"))
    finger_scale: float = field(
        default=0.0,
        metadata=_opt(
            "finger-pose noise added to each start, in standard deviations of the selected sequences' annotated hands "
            "along their principal directions (0: none)",
            "non_negative_float",
        ),
    )
    finger_components: int = field(
        default=6, metadata=_opt("principal directions of the finger noise per hand", "positive_int")
    )

    def __post_init__(self) -> None:
        self.arti_range = _tuple(self.arti_range)
        if self.finger_scale < 0 or not 1 <= self.finger_components <= 45:
            raise ValueError(
                f"finger_scale must be >= 0 and finger_components in 1..45, got {self.finger_scale} and "
                f"{self.finger_components}"
            )


@dataclass
class BankRunConfig:
    """Bank folder, seed and device."""

    out: str = field(default="", metadata=_opt("bank folder", required=True, name="out"))
    seed: int = field(
        default=0,
        metadata=_opt(
            "base seed; each (sequence, variant) draws from a seed derived from it (variant_seed)", name="seed"
        ),
    )
    device: str = field(default="cpu", metadata=_opt("torch device", "torch_device", name="device"))


@dataclass
class PoseBankConfig:
    """All settings of one pose-bank build (:func:`~hogsa_loader.train.pom_jobs.build_pose_bank`)."""

    data: BankDataConfig = field(default_factory=BankDataConfig, metadata={"flat": True})
    pom: BankPOMConfig = field(default_factory=BankPOMConfig)
    run: BankRunConfig = field(default_factory=BankRunConfig)
