"""POM's two offline jobs as functions: fit a ContactNet, build a pose bank.

``hogsa train contactnet`` and ``hogsa train bank`` (``hogsa train
contactnet`` / ``hogsa train bank``) are thin command lines over these; ``hogsa demo`` calls
them directly. Their settings are :class:`~hogsa_loader.train.pom_config.ContactNetJobConfig`
and :class:`~hogsa_loader.train.pom_config.PoseBankConfig`.
"""

from __future__ import annotations

import json
import time
import zlib
from dataclasses import asdict
from pathlib import Path
from typing import Any, Optional, Sequence, Union

import numpy as np
import torch
from tqdm import tqdm

from hogsa_loader.assets.arctic import ArcticRoot
from hogsa_loader.assets.protocol import training_subjects
from hogsa_loader.assets.roots import DatasetRoot, open_dataset_root
from hogsa_loader.models.pom.bank import save_pose_bank
from hogsa_loader.models.pom.contactnet import ContactNet, load_contactnet, save_contactnet
from hogsa_loader.models.pom.hands import SIDES, HandInfo, hand_infos
from hogsa_loader.models.pom.metrics import grasp_metrics
from hogsa_loader.models.pom.objects import ObjectSet
from hogsa_loader.models.pom.optimize import POMConfig
from hogsa_loader.models.pom.perturb import KEEP_ARTICULATION, FingerNoise, PerturbConfig
from hogsa_loader.models.pom.pipeline import augment, contact_frames
from hogsa_loader.models.pom.state import GraspState, load_frames
from hogsa_loader.train.contactnet import (
    ContactData,
    TrainConfig,
    build_contact_data,
    evaluate_contactnet,
    train_contactnet,
)
from hogsa_loader.train.pom_config import BankDataConfig, ContactNetDataConfig, ContactNetJobConfig, PoseBankConfig

__all__ = [
    "PoseRoot",
    "bank_finger_noise",
    "build_pose_bank",
    "fit_contactnet",
    "open_pose_root",
    "sequences_of",
    "save_contactnet_curve",
    "variant_seed",
]


def save_contactnet_curve(path: Path, hist: dict) -> None:
    """Training loss (contact-weighted BCE, smoothed) and validation BCE (unweighted) / MAE /
    IoU@0.5 against the iteration, as PNG."""
    import matplotlib  # deferred: start-up cost, only the PNG writers need it

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # deferred: after the Agg backend is chosen

    fig, ax = plt.subplots(1, 2, figsize=(10, 3.6))
    tl = np.asarray(hist["train_loss"])
    if len(tl):
        k = max(1, len(tl) // 50)
        smooth = np.convolve(tl, np.ones(k) / k, mode="valid")
        ax[0].plot(np.arange(len(smooth)) + k, smooth, label="train BCE, weighted 1 + w·target (smoothed)")
    if hist["val"]:
        its = [v[0] for v in hist["val"]]
        ax[0].plot(its, [v[1]["loss"] for v in hist["val"]], "o-", label="val BCE (unweighted)")
        ax[1].plot(its, [v[1]["mae"] for v in hist["val"]], "o-", label="val MAE")
        ax[1].plot(its, [v[1]["iou05"] for v in hist["val"]], "s-", label="val IoU@0.5")
    ax[0].set_xlabel("iteration")
    ax[0].legend()
    ax[0].set_yscale("log")
    ax[1].set_xlabel("iteration")
    if hist["val"]:
        ax[1].legend()
    else:
        ax[1].text(0.5, 0.5, "no validation subjects (--val-subjects)", ha="center", va="center")
    fig.suptitle("ContactNet training")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


#: A dataset root the pose stages read: ARCTIC, or H2O with its MANO and mesh folders.
PoseRoot = DatasetRoot


def open_pose_root(data: Union[ContactNetDataConfig, BankDataConfig]) -> PoseRoot:
    """The root of a pose stage's ``data`` group (:func:`~hogsa_loader.assets.roots.open_dataset_root`
    of its ``dataset``, ``root``, ``mano_dir`` and ``object_mesh_dir``).

    Raises:
        UsageError: an H2O job lacks ``mano_dir`` or ``object_mesh_dir``, or an ARCTIC job is
            given one (ARCTIC's are in its root).
        AssetError: a folder is missing.
    """
    return open_dataset_root(data.dataset, data.root, data.mano_dir, data.object_mesh_dir)


def sequences_of(root: PoseRoot, subjects: Sequence[str]) -> list[str]:
    """Sorted ``"sid/seq"`` ids of ``subjects`` (a subject without sequences has none); no
    other subject's files are read, so a held-out subject's labels are never opened."""
    out: list[str] = []
    for sid in dict.fromkeys(subjects):
        if isinstance(root, ArcticRoot) and not (root.raw_dir / sid).is_dir():
            continue
        out += root.sequences(sid)
    return sorted(out)


def _split_subjects(root: PoseRoot, data: ContactNetDataConfig) -> tuple[list[str], list[str]]:
    """``(subjects ContactNet trains on, subjects it is validated on)``: the subjects with
    sequences that the dataset's protocol does not hold out (unless named in
    ``data.allow_held_out``); ``data.val_subjects`` (none by default) are kept out of training.

    Raises:
        UsageError: a held-out subject asked for without ``allow_held_out``.
        ValueError: no training subject is left.
    """
    pool = training_subjects(root, None, data.allow_held_out or (), "ContactNet")
    val_subj = training_subjects(root, data.val_subjects or (), data.allow_held_out or (), "ContactNet validation")
    with_sequences = {s.split("/")[0] for s in sequences_of(root, [*pool, *val_subj])}
    pool = [s for s in pool if s in with_sequences]
    missing = sorted(set(val_subj) - with_sequences)
    if missing:
        raise ValueError(f"validation subjects {missing} have no sequence in {root.data_root}")
    train_subj = [s for s in pool if s not in val_subj]
    if not train_subj:
        raise ValueError(f"no training subject left: subjects {pool}, validated on {val_subj}")
    return train_subj, val_subj


def _train_with_bar(
    train: ContactData,
    val: Optional[ContactData],
    infos: dict[str, HandInfo],
    objects: ObjectSet,
    tc: TrainConfig,
    progress: bool,
) -> tuple[ContactNet, dict]:
    """:func:`~hogsa_loader.train.contactnet.train_contactnet` with a progress bar; ``(model, history)``."""
    bar = tqdm(total=tc.iters, disable=not progress, desc="contactnet")

    def step(it: int, info: dict) -> None:
        bar.update(1)
        bar.set_postfix({k: f"{v:.4f}" for k, v in info.items() if k in ("loss", "mae", "iou05")})

    model, hist = train_contactnet(train, val, infos, objects, tc, step)
    bar.close()
    return model, hist


def _contactnet_metrics(
    hist: dict, final: dict, subjects: tuple[list[str], list[str]], sizes: tuple[int, int], iters: int, prep: float
) -> dict[str, Any]:
    """The ``metrics.json`` of a fit: subjects, frame counts, final and initial validation scores, timings."""
    first = hist["val"][0][1] if hist["val"] else {}
    return {
        "val_subjects": subjects[1],
        "train_subjects": subjects[0],
        "train_frames": sizes[0],
        "val_frames": sizes[1],
        "iters": iters,
        "val_mae": final.get("mae"),
        "val_iou05": final.get("iou05"),
        "val_loss": final.get("loss"),
        "val_clean_mae": final.get("clean_mae"),
        "val_clean_iou05": final.get("clean_iou05"),
        "val_loss_initial": first.get("loss"),
        "val_perturbation_scale": 0.5,
        "train_seconds": hist["seconds"],
        "prep_seconds": prep,
        "threads": torch.get_num_threads(),
    }


def fit_contactnet(cfg: ContactNetJobConfig, *, progress: bool = True) -> dict[str, Any]:
    """Train ContactNet on the annotated frames of the training subjects of ``cfg.data.root``,
    validated on the subjects of ``cfg.data.val_subjects`` (kept out of its training).

    Writes ``contactnet.safetensors`` + ``manifest.json``, ``metrics.json``,
    ``history.json`` and ``curve.png`` into ``cfg.run.out``.

    Args:
        cfg: data root, validation subjects and the held-out subjects allowed, optimiser settings (see
            :class:`~hogsa_loader.train.contactnet.TrainConfig`), run folder and validation cadence.
        progress: show a progress bar.

    Returns:
        the metrics written to ``metrics.json`` (``val_mae``, ``val_iou05``, ...).

    Raises:
        UsageError: a subject the dataset's protocol holds out is asked for without
            ``cfg.data.allow_held_out``.
        ValueError: no training subject is left after ``val_subjects``.
    """
    o = cfg.optim
    root = open_pose_root(cfg.data)
    train_subj, val_subj = _split_subjects(root, cfg.data)
    infos = hand_infos(root.mano_layers())
    objects = ObjectSet(root.object_templates(load_texture=False))
    tc = TrainConfig(iters=o.iters, batch=o.batch, points=o.points, lr=o.lr, val_every=cfg.run.val_every, seed=o.seed)
    t0 = time.perf_counter()
    train = build_contact_data(root, train_subj, infos, objects, near=tc.near)
    val = build_contact_data(root, val_subj, infos, objects, near=tc.near) if val_subj else None
    prep = time.perf_counter() - t0
    model, hist = _train_with_bar(train, val, infos, objects, tc, progress)
    out = Path(cfg.run.out)
    out.mkdir(parents=True, exist_ok=True)
    final: dict = {}
    if val is not None and val.size:  # the loop always scores its last step: reuse that, it is the same weights
        last_scored = hist["val"] and hist["val"][-1][0] == o.iters
        final = hist["val"][-1][1] if last_scored else evaluate_contactnet(model, val, infos, objects)
    metrics = _contactnet_metrics(
        hist, final, (train_subj, val_subj), (train.size, val.size if val is not None else 0), o.iters, prep
    )
    metrics["held_out_read"] = sorted(set(cfg.data.allow_held_out or ()) & set(train_subj + val_subj))
    training = {
        k: metrics[k] for k in ("val_subjects", "train_subjects", "held_out_read", "iters", "val_mae", "val_iou05")
    }
    save_contactnet(model, out, {"training": training, "data": str(root.data_root), "dataset": cfg.data.dataset})
    (out / "metrics.json").write_text(json.dumps(metrics, indent=2))
    (out / "history.json").write_text(json.dumps({"train_loss": hist["train_loss"], "val": hist["val"]}))
    save_contactnet_curve(out / "curve.png", hist)
    return metrics


def variant_seed(seed: int, sequence: str, variant: int) -> int:
    """Seed of one (sequence, variant) of a pose bank: 31 bits of ``SeedSequence([seed,
    crc32(sequence), variant])`` for the ``"sid/seq"`` id, so no two (sequence, variant)
    pairs share their draws and a sequence draws the same whatever other sequences are
    selected (the per-batch seeds inside :func:`~hogsa_loader.models.pom.pipeline.augment` add at
    most the sequence's frame count to it)."""
    key = zlib.crc32(str(sequence).encode("utf-8"))
    return int(np.random.SeedSequence([int(seed), key, int(variant)]).generate_state(1)[0] >> 1)


def _bank_sequences(root: PoseRoot, cfg: PoseBankConfig) -> list[str]:
    """The ``"sid/seq"`` ids of ``root`` selected by ``cfg.data.subjects`` / ``sequences``: never
    of a subject the dataset's protocol holds out, unless named in ``cfg.data.allow_held_out``.

    Raises:
        UsageError: a held-out subject asked for (by ``subjects`` or ``sequences``) without
            ``allow_held_out``.
    """
    allow = cfg.data.allow_held_out or ()
    requested = cfg.data.subjects
    if requested is None and cfg.data.sequences:
        requested = tuple(dict.fromkeys(s.split("/")[0] for s in cfg.data.sequences))
    seqs = sequences_of(root, training_subjects(root, requested, allow, "the pose bank"))
    if cfg.data.sequences:
        seqs = [s for s in seqs if s in set(cfg.data.sequences)]
    return seqs


class _BankParts:
    """What the optimised variants of every sequence add up to: kept grasp states, their
    sources and metrics, the optimised count and the drop reasons."""

    def __init__(self) -> None:
        self.states: list[GraspState] = []
        self.sources: list[tuple[str, str, int]] = []
        self.metrics: dict[str, list[np.ndarray]] = {
            k: [] for k in ("penetration_depth", "intersection", "contact_ratio", "accept")
        }
        self.dropped = {"nonfinite": 0, "implausible": 0, "penetration": 0, "rejected": 0}
        self.total = 0

    def add(self, frames: Any, aug: Any, m: dict[str, np.ndarray], keep_rejected: bool) -> None:
        """Keep the accepted (or, with ``keep_rejected``, all finite) grasps of one variant."""
        self.total += frames.state.batch
        for k, c in aug.dropped.items():
            self.dropped[k] += c
        ok = aug.keep.numpy()
        keep = ok & (m["accept"] | keep_rejected)
        if not keep_rejected:
            self.dropped["rejected"] += int((ok & ~m["accept"]).sum())
        idx = torch.as_tensor(keep.nonzero()[0], dtype=torch.long)
        self.states.append(aug.result.select(idx))
        self.sources += [frames.sources[int(i)] for i in idx]
        for k in self.metrics:
            self.metrics[k].append(m[k][keep].astype("float32"))


def _optimise_sequences(
    root: PoseRoot,
    seqs: list[str],
    net: ContactNet,
    pom: POMConfig,
    pert: PerturbConfig,
    cfg: PoseBankConfig,
    progress: bool,
    fingers: Optional[FingerNoise] = None,
) -> _BankParts:
    """Perturb and optimise ``cfg.data.variants`` times the selected frames of every sequence."""
    infos = hand_infos(root.mano_layers())
    objects = ObjectSet(root.object_templates(load_texture=False))
    parts = _BankParts()
    for seq in tqdm(seqs, disable=not progress, desc="pose bank"):
        frames = contact_frames(
            root,
            [seq],
            infos,
            objects,
            per_sequence=cfg.data.per_sequence,
            frames=cfg.data.frames,
            frame_margin=cfg.data.frame_margin,
        )
        if frames.state.batch == 0:
            continue
        for v in range(cfg.data.variants):
            aug = augment(
                frames,
                infos,
                objects,
                net,
                pom,
                seed=variant_seed(cfg.run.seed, seq, v),
                batch=cfg.pom.batch,
                perturb_config=pert,
                device=cfg.run.device,
                fingers=fingers,
            )
            m = grasp_metrics(aug.result, infos, objects, frames.active)
            parts.add(frames, aug, m, cfg.pom.keep_rejected)
    return parts


def bank_finger_noise(root: PoseRoot, seqs: list[str], cfg: PoseBankConfig) -> Optional[FingerNoise]:
    """The bank's finger noise: principal directions of every annotated frame of ``seqs``
    (None when ``cfg.pom.finger_scale`` is 0)."""
    if cfg.pom.finger_scale == 0:
        return None
    state, _ = load_frames(root, seqs)
    poses = {side: state.hands[side].pose for side in SIDES}
    return FingerNoise.fit(poses, cfg.pom.finger_components, cfg.pom.finger_scale)


def build_pose_bank(cfg: PoseBankConfig, *, progress: bool = True) -> dict[str, Any]:
    """Optimise perturbed frames of every sequence with POM and save the kept grasps.

    Each (sequence, variant) draws from its own seed derived from ``(cfg.run.seed, sequence
    id, variant)`` (:func:`variant_seed`). The start perturbation keeps the annotated
    articulation (:data:`~hogsa_loader.models.pom.perturb.KEEP_ARTICULATION`: the paper's ranges,
    annotated θ kept, so the bank's θ follows the data's) unless ``cfg.pom.arti_range`` asks
    for a uniform draw. With ``cfg.pom.finger_scale`` the start fingers also get
    :class:`~hogsa_loader.models.pom.perturb.FingerNoise` along the principal directions of the
    selected sequences' annotated hands (:func:`bank_finger_noise`); the manifest's
    ``finger_noise`` records its scale and the standard deviation of each direction.

    Args:
        cfg: data root, ContactNet, selection of sequences and frames; POM settings; bank
            folder, seed and device.
        progress: show a progress bar.

    Returns:
        a summary (``bank``, ``entries``, ``optimised``, ``dropped`` by reason, ``seconds``).

    Raises:
        ValueError: no frame was selected.
    """
    root = open_pose_root(cfg.data)
    net = load_contactnet(cfg.data.contactnet, cfg.run.device)
    pom = POMConfig(iters=cfg.pom.iters)
    pert = KEEP_ARTICULATION if cfg.pom.arti_range is None else PerturbConfig(arti_range=tuple(cfg.pom.arti_range))
    t0 = time.perf_counter()
    seqs = _bank_sequences(root, cfg)
    fingers = bank_finger_noise(root, seqs, cfg)
    parts = _optimise_sequences(root, seqs, net, pom, pert, cfg, progress, fingers)
    if not parts.states:
        raise ValueError(
            f"no {'contact ' if cfg.data.frames == 'contact' else ''}frame found in {root.data_root} "
            f"(subjects {list(cfg.data.subjects or []) or 'all'})"
        )
    state = GraspState.cat(parts.states)
    info = {
        "data": str(root.data_root),
        "dataset": cfg.data.dataset,
        "contactnet": str(cfg.data.contactnet),
        "per_sequence": cfg.data.per_sequence,
        "variants": cfg.data.variants,
        "frames": cfg.data.frames,
        "frame_margin": cfg.data.frame_margin,
        "held_out_read": sorted(set(cfg.data.allow_held_out or ()) & {q.split("/")[0] for q in seqs}),
        "seed": cfg.run.seed,
        "optimised": parts.total,
        "dropped": parts.dropped,
        "config": {k: getattr(pom, k) for k in pom.__dataclass_fields__},
        "perturbation": asdict(pert),
        "finger_noise": None
        if fingers is None
        else {
            "scale": fingers.scale,
            "components": cfg.pom.finger_components,
            "std": {side: b.norm(dim=1).tolist() for side, b in fingers.basis.items()},
        },
        "seconds": time.perf_counter() - t0,
    }
    path = save_pose_bank(
        cfg.run.out, state, parts.sources, {k: np.concatenate(v) for k, v in parts.metrics.items()}, info
    )
    return {
        "bank": str(path.parent),
        "entries": state.batch,
        "optimised": parts.total,
        "dropped": parts.dropped,
        "seconds": info["seconds"],
    }
