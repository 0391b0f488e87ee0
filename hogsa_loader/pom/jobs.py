"""POM's two offline jobs as functions: fit a ContactNet, build a pose bank.

``pretrain/train_contactnet.py`` and ``pretrain/build_pose_bank.py`` are thin command lines
over these; ``hogsa demo`` calls them directly.
"""

from __future__ import annotations

import json
import time
import zlib
from dataclasses import asdict
from pathlib import Path
from typing import Any, Optional, Sequence

import numpy as np
import torch

from hogsa_loader.datasets.arctic import ArcticRoot
from hogsa_loader.errors import PathLike
from hogsa_loader.pom.perturb import KEEP_ARTICULATION, PerturbConfig

__all__ = ["fit_contactnet", "build_pose_bank", "save_contactnet_curve", "variant_seed"]


def save_contactnet_curve(path: Path, hist: dict) -> None:
    """Training loss (contact-weighted BCE, smoothed) and validation BCE (unweighted) / MAE /
    IoU@0.5 against the iteration, as PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

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
    ax[1].legend()
    fig.suptitle("ContactNet training")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def fit_contactnet(
    data: PathLike,
    out: PathLike,
    *,
    iters: int = 1500,
    val_subjects: Optional[Sequence[str]] = None,
    batch: int = 8,
    points: int = 512,
    lr: float = 1e-3,
    val_every: int = 100,
    seed: int = 0,
    progress: bool = True,
) -> dict[str, Any]:
    """Train ContactNet on the annotated frames of ``data`` with held-out-subject validation.

    Writes ``contactnet.safetensors`` + ``manifest.json``, ``metrics.json``,
    ``history.json`` and ``curve.png`` into ``out``.

    Args:
        data: ARCTIC(-format) data root.
        out: run folder.
        val_subjects: held-out subjects (default: the last subject).
        iters, batch, points, lr, val_every, seed: see :class:`~hogsa_loader.pom.train.TrainConfig`.
        progress: show a progress bar.

    Returns:
        the metrics written to ``metrics.json`` (``val_mae``, ``val_iou05``, ...).

    Raises:
        ValueError: no training subject is left after ``val_subjects``.
    """
    from tqdm import tqdm

    from hogsa_loader.pom.contactnet import save_contactnet
    from hogsa_loader.pom.hands import hand_infos
    from hogsa_loader.pom.objects import ObjectSet
    from hogsa_loader.pom.train import TrainConfig, build_contact_data, evaluate_contactnet, train_contactnet

    root = ArcticRoot(data)
    subjects = sorted({s.split("/")[0] for s in root.sequences()})
    val_subj = list(val_subjects) if val_subjects else subjects[-1:]
    train_subj = [s for s in subjects if s not in val_subj]
    if not train_subj:
        raise ValueError(f"no training subject left: subjects {subjects}, held out {val_subj}")
    infos = hand_infos(root.mano_layers())
    objects = ObjectSet(root.object_templates(load_texture=False))
    cfg = TrainConfig(iters=iters, batch=batch, points=points, lr=lr, val_every=val_every, seed=seed)
    t0 = time.perf_counter()
    train = build_contact_data(root, train_subj, infos, objects, near=cfg.near)
    val = build_contact_data(root, val_subj, infos, objects, near=cfg.near) if val_subj else None
    prep = time.perf_counter() - t0
    bar = tqdm(total=iters, disable=not progress, desc="contactnet")

    def step(it: int, info: dict) -> None:
        bar.update(1)
        bar.set_postfix({k: f"{v:.4f}" for k, v in info.items() if k in ("loss", "mae", "iou05")})

    model, hist = train_contactnet(train, val, infos, objects, cfg, step)
    bar.close()
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    final: dict = {}
    if val is not None and val.size:  # the loop always scores its last step: reuse that, it is the same weights
        last_scored = hist["val"] and hist["val"][-1][0] == iters
        final = hist["val"][-1][1] if last_scored else evaluate_contactnet(model, val, infos, objects)
    first = hist["val"][0][1] if hist["val"] else {}
    metrics = {
        "val_subjects": val_subj,
        "train_subjects": train_subj,
        "train_frames": train.size,
        "val_frames": val.size if val is not None else 0,
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
    training = {k: metrics[k] for k in ("val_subjects", "train_subjects", "iters", "val_mae", "val_iou05")}
    save_contactnet(model, out, {"training": training, "data": str(root.data_root)})
    (out / "metrics.json").write_text(json.dumps(metrics, indent=2))
    (out / "history.json").write_text(json.dumps({"train_loss": hist["train_loss"], "val": hist["val"]}))
    save_contactnet_curve(out / "curve.png", hist)
    return metrics


def variant_seed(seed: int, sequence: str, variant: int) -> int:
    """Seed of one (sequence, variant) of a pose bank: 31 bits of ``SeedSequence([seed,
    crc32(sequence), variant])`` for the ``"sid/seq"`` id, so no two (sequence, variant)
    pairs share their draws and a sequence draws the same whatever other sequences are
    selected (the per-batch seeds inside :func:`~hogsa_loader.pom.pipeline.augment` add at
    most the sequence's frame count to it)."""
    key = zlib.crc32(str(sequence).encode("utf-8"))
    return int(np.random.SeedSequence([int(seed), key, int(variant)]).generate_state(1)[0] >> 1)


def build_pose_bank(
    data: PathLike,
    contactnet: PathLike,
    out: PathLike,
    *,
    per_sequence: int = 16,
    variants: int = 1,
    subjects: Optional[Sequence[str]] = None,
    sequences: Optional[Sequence[str]] = None,
    iters: int = 200,
    batch: int = 16,
    seed: int = 0,
    keep_rejected: bool = False,
    perturbation: Optional[PerturbConfig] = None,
    device: str = "cpu",
    progress: bool = True,
) -> dict[str, Any]:
    """Optimise perturbed contact frames of every sequence with POM and save the kept grasps.

    Args:
        data: ARCTIC(-format) data root; contactnet: ContactNet run folder; out: bank folder.
        per_sequence: contact frames taken per sequence (evenly spaced).
        variants: perturbations per frame.
        subjects: restrict to these subjects (default all).
        sequences: restrict to these ``"sid/seq"`` ids (default all).
        iters: POM iterations; batch: samples optimised at once.
        seed: base seed; each (sequence, variant) draws from its own seed derived from
            ``(seed, sequence id, variant)`` (:func:`variant_seed`).
        keep_rejected: also keep grasps that fail acceptance.
        perturbation: the start perturbation; default :data:`KEEP_ARTICULATION` (the paper's
            ranges, annotated θ kept, so the bank's θ follows the data's).

    Returns:
        a summary (``bank``, ``entries``, ``optimised``, ``dropped`` by reason, ``seconds``).

    Raises:
        ValueError: no contact frame was found.
    """
    from tqdm import tqdm

    from hogsa_loader.pom.bank import save_pose_bank
    from hogsa_loader.pom.contactnet import load_contactnet
    from hogsa_loader.pom.hands import hand_infos
    from hogsa_loader.pom.metrics import grasp_metrics
    from hogsa_loader.pom.objects import ObjectSet
    from hogsa_loader.pom.optimize import POMConfig
    from hogsa_loader.pom.pipeline import augment, contact_frames
    from hogsa_loader.pom.state import GraspState

    root = ArcticRoot(data)
    net = load_contactnet(contactnet, device)
    seqs = root.sequences()
    if subjects:
        seqs = [s for s in seqs if s.split("/")[0] in set(subjects)]
    if sequences:
        seqs = [s for s in seqs if s in set(sequences)]
    infos = hand_infos(root.mano_layers())
    objects = ObjectSet(root.object_templates(load_texture=False))
    cfg = POMConfig(iters=iters)
    pert = KEEP_ARTICULATION if perturbation is None else perturbation
    states, sources = [], []
    metrics: dict[str, list[np.ndarray]] = {k: [] for k in ("penetration_depth", "intersection", "contact_ratio", "accept")}
    dropped = {"nonfinite": 0, "implausible": 0, "penetration": 0, "rejected": 0}
    total, t0 = 0, time.perf_counter()
    for seq in tqdm(seqs, disable=not progress, desc="pose bank"):
        frames = contact_frames(root, [seq], infos, objects, per_sequence=per_sequence)
        if frames.state.batch == 0:
            continue
        for v in range(variants):
            aug = augment(frames, infos, objects, net, cfg, seed=variant_seed(seed, seq, v), batch=batch,
                          perturb_config=pert, device=device)
            total += frames.state.batch
            for k, c in aug.dropped.items():
                dropped[k] += c
            m = grasp_metrics(aug.result, infos, objects, frames.active)
            ok = aug.keep.numpy()
            keep = ok & (m["accept"] | keep_rejected)
            if not keep_rejected:
                dropped["rejected"] += int((ok & ~m["accept"]).sum())
            idx = torch.as_tensor(keep.nonzero()[0], dtype=torch.long)
            states.append(aug.result.select(idx))
            sources += [frames.sources[int(i)] for i in idx]
            for k in metrics:
                metrics[k].append(m[k][keep].astype("float32"))
    if not states:
        raise ValueError(f"no contact frame found in {root.data_root} (subjects {subjects or 'all'})")
    state = GraspState.cat(states)
    info = {"data": str(root.data_root), "contactnet": str(contactnet), "per_sequence": per_sequence,
            "variants": variants, "seed": seed, "optimised": total, "dropped": dropped,
            "config": {k: getattr(cfg, k) for k in cfg.__dataclass_fields__}, "perturbation": asdict(pert),
            "seconds": time.perf_counter() - t0}  # fmt: skip
    path = save_pose_bank(out, state, sources, {k: np.concatenate(v) for k, v in metrics.items()}, info)
    return {"bank": str(path.parent), "entries": state.batch, "optimised": total, "dropped": dropped,
            "seconds": info["seconds"]}
