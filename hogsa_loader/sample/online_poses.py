"""``poses="online"``: POM inside the loader — perturb an annotated grasp and optimise it per batch.

:class:`OnlinePoses` is the pose source (its docstring describes the sampling, the
optimisation, dropped samples, determinism and cost). On a CPU prefer ``poses="bank"``
(the same optimisation, done offline).
"""

from __future__ import annotations

from dataclasses import replace
from typing import Any, Sequence

import numpy as np
import torch

from hogsa_loader.errors import AssetError
from hogsa_loader.models.pom.contactnet import load_contactnet
from hogsa_loader.models.pom.hands import hand_infos
from hogsa_loader.models.pom.objects import ObjectSet
from hogsa_loader.models.pom.optimize import POMConfig, optimise_grasps
from hogsa_loader.models.pom.perturb import KEEP_ARTICULATION, perturb
from hogsa_loader.models.pom.pipeline import contact_frames
from hogsa_loader.models.pom.state import GraspState
from hogsa_loader.sample.poses import FrameTables, PoseBatch, PoseContext, register_pose_source, split_sequences

__all__ = ["OnlinePoses"]

_HAND_KEYS = ("rot", "pose", "betas", "trans")


class OnlinePoses(FrameTables):
    """POM-optimised grasps made on the fly.

    For every sample, :meth:`OnlinePoses.sample` draws an annotated *contact* frame of the
    (subject, object)'s training sequences (a hand within 5 mm of the object) and a
    perturbation seed, both from the sample's own generator; :meth:`OnlinePoses.optimize`
    then applies the paper's perturbation (:func:`~hogsa_loader.models.pom.perturb.perturb`, one
    generator per sample; the annotated articulation θ kept) and optimises the whole render batch at once with
    :func:`~hogsa_loader.models.pom.optimize.optimise_grasps` (object fixed, both hands; the bundle's
    ContactNet), on the loader's device. The loader times this as the ``pom`` stage.

    Samples POM drops (non-finite, still penetrating, implausible articulation) are marked in
    their provenance (``"dropped": "pom"``) and the loader drops and counts them.

    Determinism: a sample's frame and perturbation come from its own seed; the object point
    subset the losses use is drawn from the batch's first sample, and the optimisation runs
    batched. The stream is therefore reproducible for the same seed and batch size (the same
    render batches), while :meth:`HOGSADataset.sample` regenerating one sample alone may give a
    slightly different grasp (another point subset).

    Cost: ``iters`` (200, the paper's) Adam steps per render batch — meant for CUDA; on a CPU
    prefer ``poses="bank"`` (the same optimisation, done offline).

    Args:
        context: the loader's :class:`PoseContext` (its bundle's ContactNet is used unless
            ``contactnet`` is given).
        contactnet: a ContactNet checkpoint folder (default: the bundle's).
        iters: POM iterations (paper: 200).
        perturb_scale: scales the paper's rotation and jitter ranges (1 = paper); θ keeps the
            annotated angle (:data:`~hogsa_loader.models.pom.perturb.KEEP_ARTICULATION`).
        contact_threshold: a source frame needs a hand within this distance (m).

    Raises:
        AssetError: no ContactNet, or a (subject, object) without contact frames.
    """

    name = "online"
    table_kind = "contact frames"

    def __init__(
        self,
        context: PoseContext,
        contactnet: Any = None,
        iters: int = 200,
        perturb_scale: float = 1.0,
        contact_threshold: float = 0.005,
    ) -> None:
        if contactnet is None:
            entry = getattr(context.bundle, "contactnet", None)
            if entry is None:
                where = getattr(context.bundle, "path", "the bundle")
                raise AssetError(
                    where,
                    "poses='online' needs a ContactNet (hogsa train contactnet, then "
                    "python -m hogsa_loader.cli.build_bundle --contactnet)",
                )
            contactnet = entry.path
        self.device = torch.device(context.device)
        self.net = load_contactnet(contactnet, self.device)
        self.infos = hand_infos(context.root.mano_layers())
        self.objects = ObjectSet(context.root.object_templates(load_texture=False))
        self.config = POMConfig(iters=int(iters))
        self.perturb_config = replace(KEEP_ARTICULATION, scale=float(perturb_scale))
        allowed = set(split_sequences(context.root, context.protocol, context.split))
        self.frames: dict[tuple[str, str], Any] = {}
        for sid, obj in context.keys:
            seqs = [
                s for s in context.root.sequences(sid) if s in allowed and s.split("/", 1)[1].split("_", 1)[0] == obj
            ]
            if not seqs:
                continue
            fr = contact_frames(context.root, seqs, self.infos, self.objects, threshold=contact_threshold)
            if fr.state.batch:
                self.frames[(sid, obj)] = fr
        missing = [k for k in context.keys if k not in self.frames]
        if missing and not self.frames:
            raise AssetError(
                context.root.data_root,
                f"no contact frames for (subject, object) {missing} in {context.protocol} {context.split}",
            )

    def sample(self, key: tuple[str, str], rngs: Sequence[np.random.Generator]) -> PoseBatch:
        """Source frames (un-optimised) and per-sample perturbation seeds."""
        fr = self.table(key)
        rows = [int(rng.integers(fr.state.batch)) for rng in rngs]
        seeds = [int(rng.integers(2**62)) for rng in rngs]
        prov = []
        for r, s in zip(rows, seeds):
            sid, seq, frame = fr.sources[r]
            prov.append(
                {
                    "pose_source": self.name,
                    "sequence": f"{sid}/{seq}",
                    "frame": int(frame),
                    "row": r,
                    "pom_seed": s,
                    "pom_iters": self.config.iters,
                }
            )
        return PoseBatch(_poses(fr.state.select(rows)), prov)

    def optimize(self, key: tuple[str, str], batch: PoseBatch) -> PoseBatch:
        """Perturb each sample with its own seed, then optimise the batch together."""
        fr = self.frames[key]
        rows = [int(p["row"]) for p in batch.provenance]
        ref = fr.state.select(rows)
        starts = [
            perturb(
                ref.select([b]),
                self.infos,
                self.objects,
                torch.Generator().manual_seed(int(p["pom_seed"])),
                self.perturb_config,
            )[0]
            for b, p in enumerate(batch.provenance)
        ]
        start = GraspState.cat(starts).map(lambda t: t.to(self.device))
        ref_d = ref.map(lambda t: t.to(self.device))
        active = {s: a[torch.as_tensor(rows)].to(self.device) for s, a in fr.active.items()}
        gen = torch.Generator().manual_seed(int(batch.provenance[0]["pom_seed"]) % (2**31))
        res = optimise_grasps(
            start, self.infos, self.objects, self.net, self.config, reference=ref_d, active=active, generator=gen
        )
        prov = [dict(p) for p in batch.provenance]
        for b, ok in enumerate(res.keep.cpu().tolist()):
            if not ok:
                prov[b]["dropped"] = "pom"
        return PoseBatch(_poses(res.state.map(lambda t: t.detach().cpu())), prov)


def _poses(state: Any) -> dict[str, torch.Tensor]:
    """A :class:`~hogsa_loader.models.pom.state.GraspState` as loader pose tensors (float64, CPU)."""
    out = {
        f"{s}_{k}": getattr(state.hands[s], k).detach().cpu().double() for s in ("right", "left") for k in _HAND_KEYS
    }
    out["obj_arti"] = state.obj_arti.detach().cpu().double().reshape(-1, 1)
    out["obj_rot"] = state.obj_rot.detach().cpu().double()
    out["obj_trans"] = state.obj_trans.detach().cpu().double()
    return out


register_pose_source("online", OnlinePoses)
