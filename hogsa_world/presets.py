"""World presets: which subjects, sequences, frame counts and image sizes to generate.

A preset is a plain frozen dataclass so tests can shrink one with ``dataclasses.replace``.
Sequence names follow ARCTIC (``<object>_<grab|use>_<NN>``); subject ids and the held-out
validation subject follow ARCTIC's protocol (val = s05, test = s03).

``small``, ``small_styles`` and ``demo`` (the three sequences ``hogsa demo`` uses) have ARCTIC's image sizes, so
ARCTIC's own loader reads them as ARCTIC. ``tiny``
keeps 256-px crops and ego images × 0.1 to stay fast: the project's reader takes the sizes
from ``meta/hogsa_world.json``, while ARCTIC's loader, which hard-codes 1000 px and 0.3,
would cut the wrong patches; readers asked for ARCTIC-exact samples refuse it
(:meth:`~hogsa_loader.assets.arctic.ArcticRoot.require_arctic_sizes`).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

from hogsa_loader.assets.conventions import EGO_IMAGE_SIZE
from hogsa_world.grasp import GRASP_DESIGNS

__all__ = ["SequencePlan", "SubjectPlan", "WorldPreset", "PRESETS", "get_preset"]

ACTIONS = ("grab", "use")
SPLITS = ("train", "val", "test")


@dataclass(frozen=True)
class SequencePlan:
    """One sequence to generate.

    Attributes:
        object: procedural object; (object, action) must be one of
            :data:`~hogsa_world.grasp.GRASP_DESIGNS` (box grab/use, laptop grab,
            notebook grab).
        action: ``grab`` (both hands carry the object) or ``use`` (one hand holds the
            base, the other opens and closes the top part).
        index: the ``NN`` of the sequence name.
    """

    object: str
    action: str
    index: int = 1

    def __post_init__(self) -> None:
        if self.action not in ACTIONS:
            raise ValueError(f"action must be one of {ACTIONS}, got {self.action!r}")

        if (self.object, self.action) not in GRASP_DESIGNS:
            raise ValueError(f"({self.object!r}, {self.action!r}) has no designed grasp; choose from {GRASP_DESIGNS}")

    @property
    def name(self) -> str:
        """ARCTIC sequence name, e.g. ``box_use_01``."""
        return f"{self.object}_{self.action}_{self.index:02d}"


@dataclass(frozen=True)
class SubjectPlan:
    """A subject and its sequences.

    Attributes:
        sid: ``s01``..``s10``.
        split: ``train``, ``val`` or ``test`` (goes into ``splits_json``).
        sequences: the sequences recorded by this subject.
    """

    sid: str
    split: str
    sequences: tuple[SequencePlan, ...]

    def __post_init__(self) -> None:
        if self.split not in SPLITS:
            raise ValueError(f"split must be one of {SPLITS}, got {self.split!r}")


@dataclass(frozen=True)
class WorldPreset:
    """Everything that sizes a generated world.

    Attributes:
        name: preset name recorded in ``hogsa_world.json``.
        subjects: the subjects (ids must be unique).
        num_frames: GT frames per sequence F (ARCTIC asserts F > 50).
        cropped_size: side of the allocentric cropped images (ARCTIC: 1000).
        ego_image_scale: egocentric cropped image = full 2800x2000 frame times this
            (ARCTIC: 0.3 -> 840x600).
        supersample: rasteriser supersampling factor.
        jpeg_quality: OpenCV JPEG quality of the cropped images.
        grasp_iters: optimisation steps per grasp.
        preview_frames: frames per row of ``world_preview.png``.
        grasp_style: how much each subject's grasps differ from the designed ones (0: every
            subject holds an object the same way, up to its hand shape; 1: each subject slides,
            turns, tilts and curls its hands its own way, drawn per subject and sequence).
    """

    name: str
    subjects: tuple[SubjectPlan, ...]
    num_frames: int
    cropped_size: int
    ego_image_scale: float
    supersample: int = 1
    jpeg_quality: int = 95
    grasp_iters: int = 140
    preview_frames: int = 5
    grasp_style: float = 0.0

    def __post_init__(self) -> None:
        if self.num_frames <= 51:
            raise ValueError(f"num_frames must be >= 52 (ARCTIC asserts > 50 frames), got {self.num_frames}")
        sids = [s.sid for s in self.subjects]
        if len(set(sids)) != len(sids) or not sids:
            raise ValueError(f"subject ids must be unique and non-empty: {sids}")
        if self.cropped_size < 16 or not 0.0 < self.ego_image_scale <= 1.0:
            raise ValueError("cropped_size must be >= 16 and ego_image_scale in (0, 1]")
        if not 0.0 <= self.grasp_style <= 1.0:
            raise ValueError(f"grasp_style must be in [0, 1], got {self.grasp_style}")

    @property
    def objects(self) -> tuple[str, ...]:
        """Object names used, in first-use order."""
        names: list[str] = []
        for s in self.subjects:
            for q in s.sequences:
                if q.object not in names:
                    names.append(q.object)
        return tuple(names)

    @property
    def ego_size(self) -> tuple[int, int]:
        """(width, height) of the egocentric cropped images."""
        return (
            int(round(EGO_IMAGE_SIZE[0] * self.ego_image_scale)),
            int(round(EGO_IMAGE_SIZE[1] * self.ego_image_scale)),
        )


def _seqs(*items: tuple[str, str]) -> tuple[SequencePlan, ...]:
    return tuple(SequencePlan(o, a, 1) for o, a in items)


PRESETS: dict[str, WorldPreset] = {
    # 2 subjects x 1 sequence x 64 frames x 9 views; small crops (not ARCTIC's sizes);
    # < 1 min on 2 idle CPU cores.
    "tiny": WorldPreset(
        name="tiny",
        subjects=(
            SubjectPlan("s01", "train", _seqs(("box", "use"))),
            SubjectPlan("s05", "val", _seqs(("box", "grab"))),
        ),
        num_frames=64,
        cropped_size=256,
        ego_image_scale=0.1,
    ),
    # ARCTIC image sizes (1000x1000 crops, 840x600 ego); 3 subjects, 3 objects, 6 sequences.
    "small": WorldPreset(
        name="small",
        subjects=(
            SubjectPlan("s01", "train", _seqs(("box", "grab"), ("laptop", "grab"))),
            SubjectPlan("s02", "train", _seqs(("notebook", "grab"), ("box", "use"))),
            SubjectPlan("s05", "val", _seqs(("laptop", "grab"), ("box", "use"))),
        ),
        num_frames=64,
        cropped_size=1000,
        ego_image_scale=0.3,
    ),
    # What `hogsa demo` trains on and streams, at ARCTIC's image sizes: the sequences of its two
    # (subject, object) models and one of the held-out subject (the real validation frames).
    "demo": WorldPreset(
        name="demo",
        subjects=(
            SubjectPlan("s01", "train", _seqs(("box", "grab"))),
            SubjectPlan("s02", "train", _seqs(("notebook", "grab"))),
            SubjectPlan("s05", "val", _seqs(("box", "use"))),
        ),
        num_frames=64,
        cropped_size=1000,
        ego_image_scale=0.3,
    ),
}

# `small` with every grasp moved from its design, drawn per subject and sequence: the held-out subject's grasps are
# not the training subjects' (as in ARCTIC, where every subject has its own motions).
PRESETS["small_styles"] = replace(PRESETS["small"], name="small_styles", grasp_style=1.0)

# `small_styles` with five times its held-out sequences, to evaluate models trained on `small_styles`:
# every subject and sequence draws from its own random stream, so its generated files for
# `small_styles`' sequences are the same; the held-out subject records a second take of its two
# sequences and the two designs it lacked, and a subject of the test split records every design once.
PRESETS["small_styles_heldout"] = replace(
    PRESETS["small_styles"],
    name="small_styles_heldout",
    subjects=(
        *PRESETS["small_styles"].subjects[:2],
        SubjectPlan(
            "s05",
            "val",
            (
                *PRESETS["small_styles"].subjects[2].sequences,
                SequencePlan("box", "grab"),
                SequencePlan("notebook", "grab"),
                SequencePlan("laptop", "grab", 2),
                SequencePlan("box", "use", 2),
            ),
        ),
        SubjectPlan("s03", "test", _seqs(*GRASP_DESIGNS)),
    ),
)


def get_preset(name: str) -> WorldPreset:
    """Preset by name (KeyError lists the known ones)."""
    try:
        return PRESETS[name]
    except KeyError:
        raise KeyError(f"unknown world preset {name!r}; known: {sorted(PRESETS)}") from None
