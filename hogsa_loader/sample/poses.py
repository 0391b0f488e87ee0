"""Pose sources of the synthetic loader: where the hand and object poses of a sample come from.

:class:`PoseSource` is the protocol (its docstring gives the contract and the extension
point); :class:`PerturbPoses` (``"perturb"``) is the built-in source,
:func:`register_pose_source` adds others and :func:`make_pose_source` builds one by name.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Callable, Mapping, Optional, Protocol, Sequence, runtime_checkable

import numpy as np
import torch
from torch import Tensor

from hogsa_loader.assets.arctic import ArcticRoot
from hogsa_loader.assets.arctic_processing import FRAME_MARGIN, inner_frames
from hogsa_loader.assets.types import SequenceData

__all__ = [
    "PoseBatch",
    "PoseContext",
    "PoseSource",
    "PerturbPoses",
    "FrameTables",
    "POSE_SOURCES",
    "register_pose_source",
    "make_pose_source",
    "split_sequences",
]


@dataclass
class PoseBatch:
    """Poses of B samples of one (subject, object).

    Attributes:
        poses: ``{key: Tensor}`` with the :data:`~hogsa_loader.models.gaussians.hogs_model.POSE_KEYS`:
            ``{side}_rot`` (B, 3), ``{side}_pose`` (B, 45), ``{side}_betas`` (B, 10),
            ``{side}_trans`` (B, 3), ``obj_arti`` (B, 1), ``obj_rot`` (B, 3),
            ``obj_trans`` (B, 3); float64, CPU, ARCTIC world frame (m, axis-angle).
        provenance: B JSON-able dicts (source name, sequence, frame, ...).
    """

    poses: dict[str, Tensor]
    provenance: list[dict[str, Any]] = field(default_factory=list)

    def __len__(self) -> int:
        return int(self.poses["obj_rot"].shape[0])

    def select(self, keep: Sequence[int]) -> "PoseBatch":
        """The samples at positions ``keep``."""
        idx = torch.as_tensor(list(keep), dtype=torch.long)
        return PoseBatch({k: v[idx] for k, v in self.poses.items()}, [self.provenance[i] for i in keep])


@dataclass
class PoseContext:
    """What a pose-source factory gets.

    Attributes:
        root: the data root.
        keys: the ``(subject, object)`` pairs the loader will ask for.
        protocol: ``"p1"`` / ``"p2"``.
        split: split whose sequences may be used (``"train"``).
        bundle: the :class:`~hogsa_loader.models.bundle.Bundle` (pose banks, ContactNet).
        device: the loader's device.
    """

    root: ArcticRoot
    keys: list[tuple[str, str]]
    protocol: str = "p1"
    split: str = "train"
    bundle: Any = None
    device: str = "cpu"


@runtime_checkable
class PoseSource(Protocol):
    """A pose source.

    A pose source turns one random generator per sample into the posing parameters of a
    :class:`~hogsa_loader.models.gaussians.hogs_model.HogsModel` (ARCTIC world frame, the keys of
    :data:`~hogsa_loader.models.gaussians.hogs_model.POSE_KEYS`). Sources are pluggable:

    * ``"perturb"`` (:class:`PerturbPoses`): a random annotated frame of the (subject, object)'s
      training sequences, with Gaussian noise on the finger articulation (and optionally on
      the object articulation and the hands' placement);
    * further sources register a factory with :func:`register_pose_source` — the extension
      point for a pose bank (``"bank"``) and online pose optimisation (``"online"``)::

          def make_bank(context: PoseContext, **options) -> PoseSource: ...
          register_pose_source("bank", make_bank)

      A source may also define ``optimize(key, batch) -> PoseBatch`` (e.g. POM refinement);
      the loader times it separately as the ``pom`` stage.

    Randomness: :meth:`PoseSource.sample` must draw everything for sample i from ``rngs[i]``
    only, so samples are reproducible from (seed, sample index).
    """

    name: str

    def sample(self, key: tuple[str, str], rngs: Sequence[np.random.Generator]) -> PoseBatch:
        """Poses of ``len(rngs)`` samples of ``key`` = (subject, object); sample i uses ``rngs[i]`` only."""
        ...


def split_sequences(root: ArcticRoot, protocol: str, split: str) -> list[str]:
    """``"sid/seq"`` ids of a protocol split (``splits_json``), or every sequence when the
    root has no protocol file."""
    try:
        return list(root.protocol(protocol)[split])
    except Exception:  # noqa: BLE001 - a root without splits_json: use everything
        return root.sequences()


class FrameTables:
    """Base of the pose sources that keep a table of usable frames per (subject, object)
    in ``frames``: :attr:`keys` lists the pairs, :meth:`table` looks one up."""

    frames: dict[tuple[str, str], Any]
    #: What a table holds, named in the error for a pair without one.
    table_kind = "frames"

    @property
    def keys(self) -> list[tuple[str, str]]:
        """The (subject, object) pairs with at least one usable frame."""
        return sorted(self.frames)

    def table(self, key: tuple[str, str]) -> Any:
        """The table of ``key``; KeyError naming the pairs there are."""
        if key not in self.frames:
            raise KeyError(f"no {self.table_kind} for (subject, object) {key}; have {self.keys}")
        return self.frames[key]


class PerturbPoses(FrameTables):
    """Annotated training frames with small perturbations.

    Args:
        context: the :class:`PoseContext`.
        finger_std: std (rad) of Gaussian noise added to each of the 45 finger values.
        arti_std: std (rad) of noise on the object articulation (clamped at 0).
        hand_trans_std: std (m) of noise on each hand's translation (moves a hand relative
            to the object; 0 keeps the annotated contact).
        frame_margin: frames skipped at each end of a sequence (ARCTIC: 10).
        require_valid: use only frames whose hands and object are annotated as valid.
    """

    name = "perturb"
    table_kind = "'perturb' frames"

    def __init__(
        self,
        context: PoseContext,
        finger_std: float = 0.05,
        arti_std: float = 0.0,
        hand_trans_std: float = 0.0,
        frame_margin: int = FRAME_MARGIN,
        require_valid: bool = True,
    ) -> None:
        self.finger_std = float(finger_std)
        self.arti_std = float(arti_std)
        self.hand_trans_std = float(hand_trans_std)
        allowed = set(split_sequences(context.root, context.protocol, context.split))
        self.sequences: dict[tuple[str, str], list[SequenceData]] = {}
        self.frames: dict[tuple[str, str], np.ndarray] = {}  # (n, 2): sequence position, frame
        for key in context.keys:
            sid, obj = key
            seqs, frames = [], []
            for name in context.root.sequences(sid):
                seq_name = name.split("/", 1)[1]
                if name not in allowed or seq_name.split("_", 1)[0] != obj:
                    continue
                seq = context.root.sequence(sid, seq_name)
                idx = inner_frames(seq.num_frames, frame_margin)
                if require_valid:
                    ok = seq.right.valid[idx] & seq.left.valid[idx] & seq.object.valid[idx]
                    idx = idx[ok.astype(bool)]
                if len(idx):
                    frames.append(np.stack([np.full(len(idx), len(seqs)), idx], axis=1))
                    seqs.append(seq)
            if seqs:
                self.sequences[key] = seqs
                self.frames[key] = np.concatenate(frames, axis=0)

    def sample(self, key: tuple[str, str], rngs: Sequence[np.random.Generator]) -> PoseBatch:
        table = self.table(key)
        cols: dict[str, list[np.ndarray]] = {}
        prov = []

        def push(k: str, v: Any) -> None:
            cols.setdefault(k, []).append(np.asarray(v, dtype=np.float64).reshape(-1))

        for rng in rngs:
            si, f = table[int(rng.integers(len(table)))]
            seq = self.sequences[key][int(si)]
            noise = rng.standard_normal(45 * 2 + 1 + 6)
            for j, side in enumerate(("right", "left")):
                h = getattr(seq, side)
                push(f"{side}_rot", h.rot[f])
                push(f"{side}_pose", h.pose[f] + self.finger_std * noise[45 * j : 45 * (j + 1)])
                push(f"{side}_betas", h.betas)
                push(f"{side}_trans", h.trans[f] + self.hand_trans_std * noise[91 + 3 * j : 94 + 3 * j])
            push("obj_arti", max(0.0, float(seq.object.arti[f]) + self.arti_std * noise[90]))
            push("obj_rot", seq.object.rot[f])
            push("obj_trans", seq.object.trans[f])
            prov.append({"pose_source": self.name, "sequence": f"{seq.subject}/{seq.name}", "frame": int(f)})
        poses = {k: torch.as_tensor(np.stack(v), dtype=torch.float64) for k, v in cols.items()}
        return PoseBatch(poses, prov)


PoseFactory = Callable[..., PoseSource]
#: Registered pose-source factories: ``name -> factory(context, **options)``.
POSE_SOURCES: dict[str, PoseFactory] = {"perturb": PerturbPoses}


def register_pose_source(name: str, factory: PoseFactory) -> None:
    """Make the loader setting ``PoseConfig(kind=name)`` use ``factory(context, **options)``.

    Args:
        name: the pose-source name (e.g. ``"bank"``, ``"online"``).
        factory: callable ``(PoseContext, **options) -> PoseSource``.
    """
    POSE_SOURCES[str(name)] = factory


def make_pose_source(spec: Any, context: PoseContext, options: Optional[Mapping[str, Any]] = None) -> PoseSource:
    """Build a pose source from a registered name, or pass an instance through.

    Args:
        spec: a name of :data:`POSE_SOURCES` or an object with ``sample(key, rngs)``.
        context: the :class:`PoseContext`.
        options: keyword arguments of the factory.
    """
    if not isinstance(spec, str):
        if not hasattr(spec, "sample"):
            raise TypeError(f"poses must be a registered name or a PoseSource, got {type(spec).__name__}")
        return spec
    if spec not in POSE_SOURCES:
        raise ValueError(f"unknown pose source {spec!r}; registered: {sorted(POSE_SOURCES)}")
    return POSE_SOURCES[spec](context, **dict(options or {}))
