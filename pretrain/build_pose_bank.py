#!/usr/bin/env python
"""Build a POM pose bank: perturb annotated contact frames and optimise them.

Example::

    python pretrain/build_pose_bank.py --data ./hogsa_world --contactnet runs/contactnet \
        --out banks/small --per-sequence 16

For every sequence (or those of ``--subjects``), ``--per-sequence`` contact frames (evenly
spaced) are perturbed ``--variants`` times each (different seeds) and optimised; samples
the optimiser drops are left out, and so are those failing GraspTTA's acceptance unless
``--keep-rejected``. Writes ``poses.safetensors`` + ``manifest.json`` (read with
:func:`hogsa_loader.pom.load_pose_bank`).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from typing import Optional, Sequence

import torch


def parse_args(argv: Optional[Sequence[str]] = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[1])
    p.add_argument("--data", required=True)
    p.add_argument("--contactnet", required=True, help="ContactNet run folder")
    p.add_argument("--out", required=True, help="bank folder")
    p.add_argument("--per-sequence", type=int, default=16)
    p.add_argument("--variants", type=int, default=1, help="perturbations per frame")
    p.add_argument("--subjects", default=None, help="comma-separated subjects (default: all)")
    p.add_argument("--iters", type=int, default=200)
    p.add_argument("--batch", type=int, default=16)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--keep-rejected", action="store_true")
    p.add_argument("--device", default="cpu")
    p.add_argument("--threads", type=int, default=None)
    p.add_argument("--quiet", action="store_true")
    return p.parse_args(argv)


def main(argv: Optional[Sequence[str]] = None) -> int:
    args = parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)
    from tqdm import tqdm

    from hogsa_loader.datasets import ArcticRoot
    from hogsa_loader.pom.bank import save_pose_bank
    from hogsa_loader.pom.contactnet import load_contactnet
    from hogsa_loader.pom.hands import hand_infos
    from hogsa_loader.pom.metrics import grasp_metrics
    from hogsa_loader.pom.objects import ObjectSet
    from hogsa_loader.pom.optimize import POMConfig
    from hogsa_loader.pom.pipeline import augment, contact_frames
    from hogsa_loader.pom.state import GraspState

    root = ArcticRoot(args.data)
    net = load_contactnet(args.contactnet, args.device)
    seqs = root.sequences()
    if args.subjects:
        seqs = [s for s in seqs if s.split("/")[0] in set(args.subjects.split(","))]
    infos = hand_infos(root.mano_layers())
    objects = ObjectSet(root.object_templates(load_texture=False))
    cfg = POMConfig(iters=args.iters)
    states, sources, metrics = [], [], {k: [] for k in ("penetration_depth", "intersection", "contact_ratio", "accept")}
    dropped = {"nonfinite": 0, "implausible": 0, "penetration": 0, "rejected": 0}
    total, t0 = 0, time.perf_counter()
    for seq in tqdm(seqs, disable=args.quiet, desc="sequences"):
        frames = contact_frames(root, [seq], infos, objects, per_sequence=args.per_sequence)
        if frames.state.batch == 0:
            continue
        for v in range(args.variants):
            aug = augment(frames, infos, objects, net, cfg, seed=args.seed + 1000 * v + total,
                          batch=args.batch, device=args.device)
            total += frames.state.batch
            for k, c in aug.dropped.items():
                dropped[k] += c
            m = grasp_metrics(aug.result, infos, objects, frames.active)
            keep = aug.keep.numpy() & (m["accept"] | args.keep_rejected)
            dropped["rejected"] += int((aug.keep.numpy() & ~m["accept"]).sum()) if not args.keep_rejected else 0
            idx = torch.as_tensor(keep.nonzero()[0], dtype=torch.long)
            states.append(aug.result.select(idx))
            sources += [frames.sources[int(i)] for i in idx]
            for k in metrics:
                metrics[k].append(m[k][keep].astype("float32"))
    import numpy as np

    if not states:
        print("error: no contact frame found", file=sys.stderr)
        return 2
    state = GraspState.cat(states)
    info = {"data": str(root.data_root), "contactnet": str(args.contactnet), "per_sequence": args.per_sequence,
            "variants": args.variants, "seed": args.seed, "optimised": total, "dropped": dropped,
            "config": {k: getattr(cfg, k) for k in cfg.__dataclass_fields__},
            "seconds": time.perf_counter() - t0}
    path = save_pose_bank(args.out, state, sources, {k: np.concatenate(v) for k, v in metrics.items()}, info)
    if not args.quiet:
        print(json.dumps({"bank": str(path.parent), "entries": state.batch, "optimised": total,
                          "dropped": dropped, "seconds": info["seconds"]}, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
