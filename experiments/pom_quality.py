#!/usr/bin/env python
"""POM grasp quality and throughput: before vs after optimisation on the same perturbed starts.

Example::

    python experiments/pom_quality.py --data ./hogsa_world --contactnet runs/contactnet \
        --json out/pom_quality.json

Frames: the annotated contact frames of ``--subjects`` (default: the ContactNet run's
held-out validation subjects), ``--per-sequence`` of them per sequence. Each is perturbed
(the paper's ranges, seeded) and optimised. The JSON holds ``original``, ``before``
(perturbed starts) and ``after`` (optimised; every sample, dropped ones included, so a
dropped sample counts as not accepted) and ``after_kept`` blocks with
``penetration_depth_mm`` (mean over samples of the per-sample max depth, ray parity),
``intersection_cm3``, ``contact_ratio``, ``accept_rate``, ``diversity_mm`` (mean pairwise
both-hand joint distance, object frame); ``penetration_reduction``; ``samples_per_s``
(optimisation only, this machine); the dropped counts. Also writes ``<json stem>_tsne.png``
(both-hand joints, original vs augmented) and ``<json stem>_grasps.png`` (original /
perturbed / optimised renders).
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import time
from pathlib import Path
from typing import Optional, Sequence

import torch


def parse_args(argv: Optional[Sequence[str]] = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[1])
    p.add_argument("--data", required=True)
    p.add_argument("--contactnet", required=True, help="ContactNet run folder")
    p.add_argument("--json", required=True, help="output JSON path")
    p.add_argument(
        "--subjects",
        default=None,
        help="comma-separated subjects (default: the run's val subjects, else the dataset's held-out subjects)",
    )
    p.add_argument("--per-sequence", type=int, default=16)
    p.add_argument("--iters", type=int, default=200)
    p.add_argument("--batch", type=int, default=16)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--no-snap", action="store_true", help="paper-pure: no rigid contact projection")
    p.add_argument("--no-final-push", action="store_true")
    p.add_argument("--device", default="cpu")
    p.add_argument("--threads", type=int, default=None)
    p.add_argument("--no-figures", action="store_true")
    return p.parse_args(argv)


def tsne_png(path: Path, orig: torch.Tensor, aug: torch.Tensor) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from hogsa_loader.view.pom_figures import tsne

    X = torch.cat([orig, aug]).reshape(orig.shape[0] + aug.shape[0], -1).numpy()
    Y = tsne(X)
    n = orig.shape[0]
    fig, ax = plt.subplots(figsize=(5.5, 5))
    ax.scatter(Y[:n, 0], Y[:n, 1], s=14, c="tab:blue", label="original")
    ax.scatter(Y[n:, 0], Y[n:, 1], s=14, c="tab:orange", label="augmented (POM)")
    ax.legend()
    ax.set_title("t-SNE of both-hand joints (object frame)")
    ax.set_xticks([])
    ax.set_yticks([])
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv: Optional[Sequence[str]] = None) -> int:
    args = parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)
    from hogsa_loader.assets import ArcticRoot
    from hogsa_loader.assets.protocol import held_out_subjects
    from hogsa_loader.errors import read_json
    from hogsa_loader.models.pom.contactnet import load_contactnet
    from hogsa_loader.models.pom.hands import hand_infos
    from hogsa_loader.models.pom.metrics import both_hand_joints, grasp_metrics, summarize
    from hogsa_loader.models.pom.objects import ObjectSet
    from hogsa_loader.models.pom.optimize import POMConfig
    from hogsa_loader.models.pom.pipeline import augment, contact_frames

    root = ArcticRoot(args.data)
    net = load_contactnet(args.contactnet, args.device)
    if args.subjects:
        subjects = args.subjects.split(",")
    else:
        man = read_json(Path(args.contactnet) / "manifest.json")
        with_sequences = {s.split("/")[0] for s in root.sequences()}
        # ContactNet's validation subjects, else the subjects the dataset holds out (never its training ones)
        subjects = list(man.get("training", {}).get("val_subjects") or []) or sorted(
            set(held_out_subjects(root)) & with_sequences
        )
        if not subjects:
            raise SystemExit(f"pom_quality: {root.data_root} has no held-out subject with sequences; pass --subjects")
    seqs = [s for s in root.sequences() if s.split("/")[0] in subjects]
    infos = hand_infos(root.mano_layers())
    objects = ObjectSet(root.object_templates(load_texture=False))
    t0 = time.perf_counter()
    frames = contact_frames(root, seqs, infos, objects, per_sequence=args.per_sequence)
    for name in sorted(set(frames.state.obj_names)):
        objects.geometry(name)
    prep = time.perf_counter() - t0
    cfg = POMConfig(iters=args.iters, snap=not args.no_snap, final_push=not args.no_final_push)
    # the hands' MANO layers stay on the CPU (perturbation, metrics); the optimisation uses device copies
    aug = augment(frames, infos, objects, net, cfg, seed=args.seed, batch=args.batch, device=args.device)
    N = frames.state.batch
    act = frames.active
    res = {}
    t1 = time.perf_counter()
    for key, st in (("original", frames.state), ("before", aug.start), ("after", aug.result)):
        m = grasp_metrics(st, infos, objects, act)
        res[key] = summarize(m, both_hand_joints(st, infos))
        if key == "after":
            keep = aug.keep.numpy()
            mk = {k: v[keep] for k, v in m.items()}
            res["after_kept"] = summarize(mk, both_hand_joints(aug.result.select(aug.keep), infos))
    metric_s = time.perf_counter() - t1
    before, after = res["before"]["penetration_depth_mm"], res["after"]["penetration_depth_mm"]
    out = {
        **res,
        "penetration_reduction": (before - after) / before if before > 0 else None,
        "diversity_gain_vs_original": res["after"]["diversity_mm"] / res["original"]["diversity_mm"],
        "samples": N,
        "kept": int(aug.keep.sum()),
        "dropped": aug.dropped,
        "samples_per_s": N / aug.seconds,
        "optimise_seconds": aug.seconds,
        "prep_seconds": prep,
        "metric_seconds": metric_s,
        "subjects": subjects,
        "config": {k: getattr(cfg, k) for k in cfg.__dataclass_fields__},
        "device": args.device if args.device == "cpu" else torch.cuda.get_device_name(0),
        "threads": torch.get_num_threads(),
        "cpu": platform.processor() or platform.machine(),
        "contactnet": str(args.contactnet),
    }
    path = Path(args.json)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(out, indent=2))
    if not args.no_figures:
        tsne_png(
            path.with_name(path.stem + "_tsne.png"),
            both_hand_joints(frames.state, infos),
            both_hand_joints(aug.result.select(aug.keep), infos),
        )
        from hogsa_loader.render.mesh_raster import save_png
        from hogsa_loader.view.pom_figures import render_grasps

        pick = torch.linspace(0, N - 1, min(6, N)).round().long()
        sheet = render_grasps(
            [frames.state.select(pick), aug.start.select(pick), aug.result.select(pick)],
            ["original", "perturbed", "optimised"],
            infos,
            objects,
        )
        save_png(path.with_name(path.stem + "_grasps.png"), torch.from_numpy(sheet))
    print(json.dumps(out, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
