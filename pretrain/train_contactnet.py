#!/usr/bin/env python
"""Train POM's ContactNet on the annotated frames of an ARCTIC-format dataset.

Example::

    python pretrain/train_contactnet.py --data ./hogsa_world --out runs/contactnet \
        --iters 1500 --val-subjects s05

Held-out subject validation (``--val-subjects``; default: the last subject). Writes
``contactnet.safetensors`` + ``manifest.json`` (loaded by
:func:`hogsa_loader.pom.contactnet.load_contactnet`), ``metrics.json`` (validation MAE,
IoU@0.5, BCE, also on unperturbed hands) and ``curve.png`` into ``--out``.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Optional, Sequence

import torch


def parse_args(argv: Optional[Sequence[str]] = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[1])
    p.add_argument("--data", required=True, help="dataset root (ARCTIC ./data)")
    p.add_argument("--out", required=True, help="run folder")
    p.add_argument("--iters", type=int, default=1500)
    p.add_argument("--val-subjects", default=None, help="comma-separated held-out subjects (default: the last one)")
    p.add_argument("--batch", type=int, default=8)
    p.add_argument("--points", type=int, default=512, help="object points per training sample")
    p.add_argument("--lr", type=float, default=1e-3)
    p.add_argument("--val-every", type=int, default=100)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--threads", type=int, default=None, help="torch CPU threads")
    p.add_argument("--quiet", action="store_true")
    return p.parse_args(argv)


def save_curve(path: Path, hist: dict) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    fig, ax = plt.subplots(1, 2, figsize=(10, 3.6))
    tl = np.asarray(hist["train_loss"])
    if len(tl):
        k = max(1, len(tl) // 50)
        smooth = np.convolve(tl, np.ones(k) / k, mode="valid")
        ax[0].plot(np.arange(len(smooth)) + k, smooth, label="train BCE (smoothed)")
    if hist["val"]:
        its = [v[0] for v in hist["val"]]
        ax[0].plot(its, [v[1]["loss"] for v in hist["val"]], "o-", label="val BCE")
        ax[1].plot(its, [v[1]["mae"] for v in hist["val"]], "o-", label="val MAE")
        ax[1].plot(its, [v[1]["iou05"] for v in hist["val"]], "s-", label="val IoU@0.5")
    ax[0].set_xlabel("iteration"); ax[0].legend(); ax[0].set_yscale("log")
    ax[1].set_xlabel("iteration"); ax[1].legend()
    fig.suptitle("ContactNet training")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def main(argv: Optional[Sequence[str]] = None) -> int:
    args = parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)
    from tqdm import tqdm

    from hogsa_loader.datasets import ArcticRoot
    from hogsa_loader.pom.contactnet import save_contactnet
    from hogsa_loader.pom.hands import hand_infos
    from hogsa_loader.pom.objects import ObjectSet
    from hogsa_loader.pom.train import TrainConfig, build_contact_data, evaluate_contactnet, train_contactnet

    root = ArcticRoot(args.data)
    subjects = sorted({s.split("/")[0] for s in root.sequences()})
    val_subj = args.val_subjects.split(",") if args.val_subjects else subjects[-1:]
    train_subj = [s for s in subjects if s not in val_subj]
    if not train_subj:
        print("error: no training subject left after --val-subjects", file=sys.stderr)
        return 2
    infos = hand_infos(root.mano_layers())
    objects = ObjectSet(root.object_templates(load_texture=False))
    t0 = time.perf_counter()
    train = build_contact_data(root, train_subj, infos, objects)
    val = build_contact_data(root, val_subj, infos, objects) if val_subj else None
    prep = time.perf_counter() - t0
    cfg = TrainConfig(iters=args.iters, batch=args.batch, points=args.points, lr=args.lr,
                      val_every=args.val_every, seed=args.seed)
    bar = tqdm(total=args.iters, disable=args.quiet, desc="contactnet")

    def progress(it: int, info: dict) -> None:
        bar.update(1)
        bar.set_postfix({k: f"{v:.4f}" for k, v in info.items() if k in ("loss", "mae", "iou05")})

    model, hist = train_contactnet(train, val, infos, objects, cfg, progress)
    bar.close()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    final = evaluate_contactnet(model, val, infos, objects) if val is not None and val.size else {}
    first = hist["val"][0][1] if hist["val"] else {}
    metrics = {
        "val_subjects": val_subj,
        "train_subjects": train_subj,
        "train_frames": train.size,
        "val_frames": val.size if val is not None else 0,
        "iters": args.iters,
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
    save_contactnet(model, out, {"training": {k: metrics[k] for k in ("val_subjects", "train_subjects", "iters",
                                                                     "val_mae", "val_iou05")},
                                 "data": str(root.data_root)})
    (out / "metrics.json").write_text(json.dumps(metrics, indent=2))
    (out / "history.json").write_text(json.dumps({"train_loss": hist["train_loss"], "val": hist["val"]}))
    save_curve(out / "curve.png", hist)
    if not args.quiet:
        print(json.dumps(metrics, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
