"""ContactNet training on the annotated frames of an ARCTIC-format or H2O dataset.

Samples: every frame (of the chosen subjects) where at least one hand touches the object
(within 2 cm), both hands of it. Input: the object's surface samples (canonical frame, a
random subset per step) and the hand's vertices after a random, milder version of the POM
perturbation (rotation/jitter scaled by U[0, 1]; a quarter of the samples unperturbed), so
that the network learns the contact of the *annotated* grasp from a displaced hand — what
POM asks of it. Target: GraspTTA's map ``2 − 2σ(2 d_cm)`` of the annotated hand. Loss:
binary cross-entropy with these soft targets, each point weighted ``1 + 10·target``
(contact points are ~2 % of the cloud; unweighted, the network never predicts > 0.5).
Validation on held-out subjects with a fixed perturbation: MAE, IoU of the maps thresholded
at 0.5, loss.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Callable, Mapping, Optional, Sequence

import torch
import torch.nn.functional as F
from torch import Tensor

from hogsa_loader.models.pom.contactnet import ContactNet, ContactNetConfig, contact_map
from hogsa_loader.models.pom.geometry import nearest
from hogsa_loader.models.pom.hands import SIDES, HandInfo
from hogsa_loader.models.pom.objects import ObjectSet
from hogsa_loader.models.pom.perturb import PerturbConfig, perturb
from hogsa_loader.models.pom.state import GraspState, canonical_hands, load_frames

__all__ = ["TrainConfig", "ContactData", "build_contact_data", "train_contactnet", "evaluate_contactnet"]


@dataclass
class TrainConfig:
    """ContactNet training settings (``near``: a frame is used when a hand is this close to
    the object, :func:`build_contact_data`)."""

    iters: int = 1500
    batch: int = 8
    points: int = 512
    lr: float = 1e-3
    clean_fraction: float = 0.25
    val_every: int = 100
    seed: int = 0
    near: float = 0.02
    pos_weight: float = 10.0
    net: ContactNetConfig = field(default_factory=ContactNetConfig)


@dataclass
class ContactData:
    """Frames used for ContactNet (original grasps) and their sources."""

    state: GraspState
    sources: list[tuple[str, str, int]]

    @property
    def size(self) -> int:
        return self.state.batch


def build_contact_data(
    root, subjects: Sequence[str], infos: Mapping[str, HandInfo], objects: ObjectSet, near: float = 0.02
) -> ContactData:
    """Frames of ``subjects`` where a hand is within ``near`` of the object."""
    seqs = [q for sid in dict.fromkeys(subjects) for q in root.sequences(sid)]
    if not seqs:
        raise ValueError(f"no sequences for subjects {list(subjects)}")
    state, src = load_frames(root, seqs)
    with torch.no_grad():
        hands = canonical_hands(state, infos)
        keep = torch.zeros(state.batch, dtype=torch.bool)
        for s in SIDES:
            keep |= objects.sdf(hands[s].vertices, state.obj_names, state.obj_arti).min(1).values < near
    idx = keep.nonzero().squeeze(-1)
    return ContactData(state.select(idx), [src[int(i)] for i in idx])


def _batch(
    data: ContactData,
    idx: Tensor,
    infos,
    objects,
    points: Optional[int],
    gen: torch.Generator,
    scale: float,
    clean: Tensor,
) -> tuple[dict, Tensor]:
    """Inputs/targets of one batch: per side (obj_pts, hand_in, target); plus obj points."""
    st = data.state.select(idx)
    obj, _ = objects.points(st.obj_names, st.obj_arti, count=points, generator=gen if points else None)
    pert, _ = perturb(st, infos, objects, gen, PerturbConfig(scale=scale, arti_range=None))
    for s in SIDES:  # unperturbed rows
        for k in ("rot", "trans"):
            getattr(pert.hands[s], k)[clean] = getattr(st.hands[s], k)[clean]
    pert.obj_rot, pert.obj_trans = st.obj_rot, st.obj_trans  # hands move relative to the object
    with torch.no_grad():
        gt = canonical_hands(st, infos)
        inp = canonical_hands(pert, infos)
    out = {}
    for s in SIDES:
        d2, _ = nearest(obj, gt[s].vertices)
        out[s] = (inp[s].vertices, contact_map(d2.sqrt()))
    return out, obj


def evaluate_contactnet(
    model: ContactNet,
    data: ContactData,
    infos,
    objects,
    seed: int = 123,
    scale: float = 0.5,
    batch: int = 16,
    max_frames: int = 48,
) -> dict[str, float]:
    """Validation MAE, IoU@0.5 and BCE on a fixed perturbation (and MAE/IoU unperturbed).

    Uses at most ``max_frames`` frames, evenly spaced, with all object points. ``loss`` is the
    plain BCE (training minimises a contact-weighted one). The model's train/eval mode is
    restored.
    """
    was_training = model.training
    model.eval()
    if data.size > max_frames:
        keep = torch.linspace(0, data.size - 1, max_frames).round().long()
        data = ContactData(data.state.select(keep), [data.sources[int(i)] for i in keep])
    res = {}
    for tag, sc in (("", scale), ("clean_", 0.0)):
        gen = torch.Generator().manual_seed(seed)
        abs_sum, n, inter, union, bce = 0.0, 0, 0.0, 0.0, 0.0
        for s0 in range(0, data.size, batch):
            idx = torch.arange(s0, min(s0 + batch, data.size))
            clean = torch.full((idx.numel(),), sc == 0.0, dtype=torch.bool)
            b, obj = _batch(data, idx, infos, objects, None, gen, sc, clean)
            with torch.no_grad():
                for s in SIDES:
                    verts, tgt = b[s]
                    pred = model(obj, verts, infos[s].prior_mask, torch.full((idx.numel(),), infos[s].side_sign))
                    abs_sum += float((pred - tgt).abs().sum())
                    bce += float(F.binary_cross_entropy(pred.clamp(1e-6, 1 - 1e-6), tgt, reduction="sum"))
                    n += tgt.numel()
                    pb, tb = pred > 0.5, tgt > 0.5
                    inter += float((pb & tb).sum())
                    union += float((pb | tb).sum())
        res[f"{tag}mae"] = abs_sum / max(n, 1)
        res[f"{tag}iou05"] = inter / union if union > 0 else float("nan")
        res[f"{tag}loss"] = bce / max(n, 1)
    model.train(was_training)
    return res


def train_contactnet(
    train: ContactData,
    val: Optional[ContactData],
    infos,
    objects,
    config: TrainConfig = TrainConfig(),
    progress: Optional[Callable[[int, dict], None]] = None,
) -> tuple[ContactNet, dict]:
    """Train a ContactNet.

    Args:
        train / val: frames (val may be None); infos: hands; objects: geometry.
        config: :class:`TrainConfig`.
        progress: called as ``progress(iteration, info)`` after every step.

    Returns:
        the model (eval mode) and a history dict: ``train_loss`` per step, ``val`` list of
        ``(iteration, metrics)``, ``seconds``.
    """
    torch.manual_seed(config.seed)
    gen = torch.Generator().manual_seed(config.seed)
    model = ContactNet(config.net)
    opt = torch.optim.Adam(model.parameters(), lr=config.lr)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, T_max=max(1, config.iters), eta_min=config.lr * 0.05)
    hist: dict = {"train_loss": [], "val": []}
    t0 = time.perf_counter()
    if val is not None and val.size:
        hist["val"].append((0, evaluate_contactnet(model, val, infos, objects)))
    for it in range(1, config.iters + 1):
        idx = torch.randint(0, train.size, (config.batch,), generator=gen)
        scale = float(torch.rand(1, generator=gen))
        clean = torch.rand(config.batch, generator=gen) < config.clean_fraction
        b, obj = _batch(train, idx, infos, objects, config.points, gen, scale, clean)
        loss = 0.0
        for s in SIDES:
            verts, tgt = b[s]
            pred = model(obj, verts, infos[s].prior_mask, torch.full((config.batch,), infos[s].side_sign))
            w = 1.0 + config.pos_weight * tgt  # contact points are rare (~2 %): weigh them up
            loss = loss + F.binary_cross_entropy(pred.clamp(1e-6, 1 - 1e-6), tgt, weight=w)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        sched.step()
        hist["train_loss"].append(float(loss.detach()) / 2)
        info = {"loss": hist["train_loss"][-1]}
        if val is not None and val.size and (it % config.val_every == 0 or it == config.iters):
            m = evaluate_contactnet(model, val, infos, objects)
            hist["val"].append((it, m))
            info.update(m)
        if progress is not None:
            progress(it, info)
    hist["seconds"] = time.perf_counter() - t0
    return model.eval(), hist
