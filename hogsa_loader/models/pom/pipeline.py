"""POM end to end: pick annotated frames, perturb them, optimise them in batches.

Used by ``hogsa train bank`` and ``experiments/pom_quality.py``.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Literal, Mapping, Optional, Sequence

import numpy as np
import torch
from torch import Tensor

from hogsa_loader.assets.arctic_processing import FRAME_MARGIN
from hogsa_loader.models.pom.contactnet import ContactNet
from hogsa_loader.models.pom.hands import SIDES, HandInfo
from hogsa_loader.models.pom.objects import ObjectSet
from hogsa_loader.models.pom.optimize import POMConfig, optimise_grasps
from hogsa_loader.models.pom.perturb import FingerNoise, PerturbConfig, perturb
from hogsa_loader.models.pom.state import GraspState, contact_flags, load_frames

__all__ = ["ContactFrames", "contact_frames", "Augmented", "augment"]


#: The frame selections of a pose bank (``BankDataConfig.frames`` of the bank job).
BANK_FRAMES = ("contact", "all")


def check_bank_frames(frames: str) -> None:
    """Refuse a frame selection that is not one of :data:`BANK_FRAMES`."""
    if frames not in BANK_FRAMES:
        raise ValueError(f"frames must be 'contact' or 'all', got {frames!r}")


@dataclass
class ContactFrames:
    """Annotated frames to optimise, with the hands that touch the object in each.

    Attributes:
        state: B grasps; sources: B ``(subject, sequence, frame)``;
        active: side -> (B,) bool, hand touches (within 5 mm, SDF grid).
    """

    state: GraspState
    sources: list[tuple[str, str, int]]
    active: dict[str, Tensor]

    def select(self, idx: Tensor) -> "ContactFrames":
        return ContactFrames(
            self.state.select(idx), [self.sources[int(i)] for i in idx], {s: a[idx] for s, a in self.active.items()}
        )


def contact_frames(
    root,
    seq_ids: Sequence[str],
    infos: Mapping[str, HandInfo],
    objects: ObjectSet,
    per_sequence: Optional[int] = None,
    threshold: float = 0.005,
    frames: Literal["contact", "all"] = "contact",
    frame_margin: int = FRAME_MARGIN,
) -> ContactFrames:
    """Annotated frames of ``seq_ids`` and their touching hands.

    Args:
        root: the dataset root; seq_ids: ``sid/seq`` ids; infos, objects: hands and geometry.
        per_sequence: at most this many frames per sequence, evenly spaced over its
            candidates (None: all).
        threshold: a hand within this distance of the object touches it (m).
        frames: the candidates: ``"contact"``, frames where at least one hand touches the
            object (grasps); ``"all"``, every frame within the margin, so that frames without
            contact (hands reaching, releasing, away) keep their share of the sequence.
        frame_margin: annotated frames left out at each end of a sequence, the rule of the
            loader's ``"perturb"`` poses. ARCTIC's data loaders leave out the first and last 10
            images; with a subject's image offset k (``ioi_offset``) those are the annotated
            frames shifted by k, so the two rules differ by k frames at each end.
    """
    check_bank_frames(frames)
    state, src = load_frames(root, seq_ids, margin=frame_margin)
    act = contact_flags(state, infos, objects, threshold)
    ok = (act["right"] | act["left"]).numpy() if frames == "contact" else np.ones(state.batch, dtype=bool)
    keep = []
    seqs = np.array([f"{a}/{b}" for a, b, _ in src])
    for sid in dict.fromkeys(seqs):
        idx = np.flatnonzero((seqs == sid) & ok)
        if per_sequence is not None and len(idx) > per_sequence:
            idx = idx[np.linspace(0, len(idx) - 1, per_sequence).round().astype(int)]
        keep.extend(idx.tolist())
    k = torch.as_tensor(keep, dtype=torch.long)
    return ContactFrames(state, src, act).select(k)


@dataclass
class Augmented:
    """Output of :func:`augment` (all B samples, in the input order).

    Attributes:
        start: perturbed grasps; result: optimised grasps; keep: (B,) bool;
        dropped: reason -> count; seconds: optimisation wall time (perturbation excluded).
    """

    start: GraspState
    result: GraspState
    keep: Tensor
    dropped: dict[str, int]
    seconds: float


def augment(
    frames: ContactFrames,
    infos: Mapping[str, HandInfo],
    objects: ObjectSet,
    contactnet: Optional[ContactNet],
    config: POMConfig = POMConfig(),
    seed: int = 0,
    batch: int = 16,
    perturb_config: PerturbConfig = PerturbConfig(),
    device: str | torch.device = "cpu",
    fingers: Optional[FingerNoise] = None,
) -> Augmented:
    """Perturb (seeded; ``fingers``: finger-pose noise too) and optimise every frame,
    ``batch`` samples per optimiser call. The pose prior and the contact sets stay those of
    the annotated frames."""
    gen = torch.Generator().manual_seed(seed)
    start, _ = perturb(frames.state, infos, objects, gen, perturb_config, fingers)
    outs, keeps, secs = [], [], 0.0
    dropped = {"nonfinite": 0, "implausible": 0, "penetration": 0}
    B = start.batch
    for s0 in range(0, B, batch):
        idx = torch.arange(s0, min(B, s0 + batch))
        st = start.select(idx).map(lambda t: t.to(device))
        ref = frames.state.select(idx).map(lambda t: t.to(device))
        act = {s: frames.active[s][idx].to(device) for s in SIDES}
        t0 = time.perf_counter()
        res = optimise_grasps(
            st,
            infos,
            objects,
            contactnet,
            config,
            reference=ref,
            active=act,
            generator=torch.Generator().manual_seed(seed + s0),
        )
        secs += time.perf_counter() - t0
        outs.append(res.state.map(lambda t: t.cpu()))
        keeps.append(res.keep.cpu())
        for k, v in res.dropped.items():
            dropped[k] += v
    return Augmented(start, GraspState.cat(outs), torch.cat(keeps), dropped, secs)
