#!/usr/bin/env python
"""Train one HOGS model (right hand, left hand, object Gaussians) per subject + object.

Example::

    python pretrain/train_hogs.py --data ./hogsa_world --dataset arctic --subject s01 \
        --object box --out runs/s01_box --iters 2000
    python pretrain/train_hogs.py --dataset h2o --data H2O_ROOT --mano-dir MANO_DIR \
        --object-mesh-dir H2O_ROOT/object --subject subject1 --object book --out runs/h2o_s1_book

ARCTIC uses the root's ``masks/`` when present (the generated world) and renders the part
masks from the annotated meshes otherwise (``--masks``); H2O always renders them, crops
every full frame around the annotated hands and object, trains on the static cameras 0-3
and holds out camera 3 (``--views``, ``--eval-views``).

Writes the part checkpoints, ``metrics.json``, ``strip.png`` (GT | render | |error| on
held-out views) and ``curves.png`` into ``--out``; ``--resume`` continues the run there.
"""

from __future__ import annotations

import argparse
import json
import sys
from typing import Optional, Sequence

from hogsa_loader.train import HogsConfig, HogsTrainer


def _lr_overrides(p: argparse.ArgumentParser, items: Sequence[str]) -> dict[str, float]:
    out = {}
    for item in items:
        name, sep, val = item.partition("=")
        try:
            out[name.strip()] = float(val)
        except ValueError:
            sep = ""
        if not sep:
            p.error(f"--lr expects NAME=VALUE, got {item!r}")
    return out


def _ints(text: Optional[str]) -> Optional[list[int]]:
    return [int(v) for v in text.split(",") if v] if text else None


def parse_args(argv: Optional[Sequence[str]] = None) -> HogsConfig:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--data", required=True, help="dataset root (ARCTIC ./data, or the H2O root)")
    p.add_argument("--dataset", default="arctic", choices=["arctic", "h2o"])
    p.add_argument("--mano-dir", default=None, help="H2O: folder with MANO_RIGHT.pkl / MANO_LEFT.pkl")
    p.add_argument("--object-mesh-dir", default=None, help="H2O: folder of the object meshes (<name>/<name>.obj|.ply)")
    p.add_argument("--window", default="crop", choices=["crop", "fg"],
                   help="train on the whole cropped image (crop) or on a window around the posed hands and "
                        "object of each frame (fg: more pixels on them at the same resolution; ARCTIC only)")
    p.add_argument("--masks", default="auto", choices=["auto", "files", "render"],
                   help="part masks: the dataset's files, or rendered from the annotated meshes (auto: files if present)")
    p.add_argument("--subject", required=True)
    p.add_argument("--object", required=True)
    p.add_argument("--out", required=True, help="run folder")
    p.add_argument("--sequences", default=None,
                   help="comma-separated sequence names, H2O as scene/seq (default: all with the object)")
    p.add_argument("--iters", type=int, default=2000)
    p.add_argument("--gaussians", default="mesh", choices=["mesh", "free"])
    p.add_argument("--device", default="cpu")
    p.add_argument("--resume", action="store_true", help="continue from the run folder's latest checkpoint")
    p.add_argument("--eval-every", type=int, default=500)
    p.add_argument("--ckpt-every", type=int, default=500)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--batch-size", type=int, default=1)
    p.add_argument("--image-size", type=int, default=None, help="training resolution (default: ARCTIC cropped size, H2O 256)")
    p.add_argument("--views", default=None, help="comma-separated camera views used (default: ARCTIC 1-8, H2O 0-3; 4 = H2O ego)")
    p.add_argument("--eval-views", default=None, help="comma-separated held-out views (default: ARCTIC 8, H2O 3)")
    p.add_argument("--eval-every-frame", type=int, default=8, help="hold out one frame in N")
    p.add_argument("--frame-stride", type=int, default=1)
    p.add_argument("--max-eval", type=int, default=8)
    p.add_argument("--k", type=int, default=2, help="Gaussians per face")
    p.add_argument("--sh-degree", type=int, default=3)
    p.add_argument("--sh-warmup", type=int, default=1000, help="raise the SH degree every N steps")
    p.add_argument("--object-subdivide", type=int, default=None, help="0-2 (default: until >= 8000 faces)")
    p.add_argument("--hand-subdivide", type=int, default=0)
    p.add_argument("--margin", type=int, default=4, help="mask dilation of the loss region (px of the cropped image)")
    p.add_argument("--lambda-ssim", type=float, default=0.2)
    p.add_argument("--lambda-r", type=float, default=0.5)
    p.add_argument("--lambda-alpha", type=float, default=1.0, help="weight of alpha -> 0 outside the loss region")
    p.add_argument("--lambda-alpha-in", type=float, default=1.0,
                   help="weight of alpha -> 1 inside the (eroded) mask; 0 = off (silhouettes may stay translucent)")
    p.add_argument("--lr-scale", type=float, default=1.0, help="multiply every learning rate except the position ones (offsets, means)")
    p.add_argument("--lr", action="append", default=[], metavar="NAME=VALUE",
                   help="learning rate of one parameter (e.g. opacity_logits=0.01); repeatable")
    p.add_argument("--shading", default="lambert", choices=["lambert", "none"],
                   help="lambert (default): learn one directional light in the world frame with the Gaussians; none: unshaded SH colours as in the paper")
    p.add_argument("--max-minutes", type=float, default=None, help="training-time budget; the run ends early when it is used up")
    p.add_argument("--opacity-warmup", type=int, default=0, help="keep opacities frozen for the first N steps")
    p.add_argument("--strip-views", type=int, default=4, help="held-out views in strip.png")
    p.add_argument("--quiet", action="store_true")
    a = p.parse_args(argv)
    cfg = HogsConfig(
        data=a.data, subject=a.subject, object=a.object, out=a.out, dataset=a.dataset, mano_dir=a.mano_dir,
        object_mesh_dir=a.object_mesh_dir, masks=a.masks, window=a.window, views=_ints(a.views),
        sequences=[s for s in a.sequences.split(",") if s] if a.sequences else None,
        iters=a.iters, gaussians=a.gaussians, device=a.device, seed=a.seed, batch_size=a.batch_size,
        image_size=a.image_size, eval_views=_ints(a.eval_views),
        eval_every_frame=a.eval_every_frame, frame_stride=a.frame_stride, max_eval=a.max_eval,
        eval_every=a.eval_every, ckpt_every=a.ckpt_every, k=a.k, sh_degree=a.sh_degree, sh_warmup=a.sh_warmup,
        hand_subdivide=a.hand_subdivide, object_subdivide=a.object_subdivide, margin=a.margin,
        lambda_ssim=a.lambda_ssim, lambda_r=a.lambda_r, lambda_alpha=a.lambda_alpha, lambda_alpha_in=a.lambda_alpha_in, lr_scale=a.lr_scale,
        strip_views=a.strip_views, lr_overrides=_lr_overrides(p, a.lr), opacity_warmup=a.opacity_warmup,
        shading=a.shading, max_minutes=a.max_minutes,
    )  # fmt: skip
    cfg.resume = a.resume  # type: ignore[attr-defined]
    cfg.quiet = a.quiet  # type: ignore[attr-defined]
    return cfg


def main(argv: Optional[Sequence[str]] = None) -> int:
    cfg = parse_args(argv)
    resume, quiet = cfg.resume, cfg.quiet  # type: ignore[attr-defined]
    try:
        trainer = HogsTrainer(cfg, progress=not quiet)
    except ValueError as exc:
        print(f"train_hogs: error: {exc}", file=sys.stderr)
        return 2
    if resume and trainer.resume() and not quiet:
        print(f"resumed {cfg.out} at step {trainer.step}")
    m = trainer.train()
    if not quiet:
        print(json.dumps({k: m[k] for k in ("psnr", "ssim", "iters")} | {"s_per_iter": m["timings"]["s_per_iter"]}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
