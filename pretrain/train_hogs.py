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
held-out views) and ``curves.png`` into ``--out``; ``--resume`` continues the run there,
``--overwrite`` starts it again from step 0 (a folder holding checkpoints is refused without
one of them). Every argument is checked before the data is read.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Optional, Sequence

from hogsa_loader.cli import checks
from hogsa_loader.errors import AssetError, HogsaError, UsageError
from hogsa_loader.objects.h2o_meshes import find_h2o_mesh
from hogsa_loader.train import HogsConfig, HogsTrainer
from hogsa_loader.train.run_folder import check_run_folder, config_defaults, latest_checkpoint, read_trainer_state


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


def _ints(p: argparse.ArgumentParser, flag: str, text: Optional[str]) -> Optional[list[int]]:
    try:
        out = [int(v) for v in text.split(",") if v] if text else None
    except ValueError:
        p.error(f"{flag} expects comma-separated integers, got {text!r}")
    if out is not None and any(v < 0 for v in out):
        p.error(f"{flag} expects view numbers >= 0, got {text!r}")
    return out


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
    p.add_argument("--iters", type=checks.non_negative_int, default=2000)
    p.add_argument("--gaussians", default="mesh", choices=["mesh", "free"])
    p.add_argument("--device", default="cpu", type=checks.torch_device)
    p.add_argument("--resume", action="store_true", help="continue from the run folder's latest checkpoint")
    p.add_argument("--overwrite", action="store_true",
                   help="start again from step 0 in a run folder that holds checkpoints (they are deleted)")
    p.add_argument("--eval-every", type=checks.non_negative_int, default=500)
    p.add_argument("--ckpt-every", type=checks.non_negative_int, default=500)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--batch-size", type=checks.positive_int, default=1)
    p.add_argument("--image-size", type=checks.positive_int, default=None, help="training resolution (default: ARCTIC cropped size, H2O 256)")
    p.add_argument("--views", default=None, help="comma-separated camera views used (default: ARCTIC 1-8, H2O 0-3; 4 = H2O ego)")
    p.add_argument("--eval-views", default=None, help="comma-separated held-out views (default: ARCTIC 8, H2O 3)")
    p.add_argument("--eval-every-frame", type=checks.positive_int, default=8, help="hold out one frame in N")
    p.add_argument("--frame-stride", type=checks.positive_int, default=1)
    p.add_argument("--max-eval", type=checks.positive_int, default=8)
    p.add_argument("--k", type=checks.positive_int, default=2, help="Gaussians per face")
    p.add_argument("--sh-degree", type=int, default=3, choices=range(4))
    p.add_argument("--sh-warmup", type=checks.non_negative_int, default=1000, help="raise the SH degree every N steps")
    p.add_argument("--object-subdivide", type=int, default=None, choices=range(3), help="0-2 (default: until >= 8000 faces)")
    p.add_argument("--hand-subdivide", type=int, default=0, choices=range(3))
    p.add_argument("--margin", type=checks.non_negative_int, default=4, help="mask dilation of the loss region (px of the cropped image)")
    p.add_argument("--lambda-ssim", type=checks.non_negative_float, default=0.2)
    p.add_argument("--lambda-r", type=checks.non_negative_float, default=0.5)
    p.add_argument("--lambda-alpha", type=checks.non_negative_float, default=1.0, help="weight of alpha -> 0 outside the loss region")
    p.add_argument("--lambda-alpha-in", type=checks.non_negative_float, default=1.0,
                   help="weight of alpha -> 1 inside the (eroded) mask; 0 = off (silhouettes may stay translucent)")
    p.add_argument("--lr-scale", type=checks.positive_float, default=1.0, help="multiply every learning rate except the position ones (offsets, means)")
    p.add_argument("--lr", action="append", default=[], metavar="NAME=VALUE",
                   help="learning rate of one parameter (e.g. opacity_logits=0.01); repeatable")
    p.add_argument("--shading", default="lambert", choices=["lambert", "none"],
                   help="lambert (default): learn one directional light in the world frame with the Gaussians; none: unshaded SH colours as in the paper")
    p.add_argument("--max-minutes", type=checks.positive_float, default=None, help="training-time budget; the run ends early when it is used up")
    p.add_argument("--opacity-warmup", type=checks.non_negative_int, default=0, help="keep opacities frozen for the first N steps")
    p.add_argument("--strip-views", type=checks.positive_int, default=4, help="held-out views in strip.png")
    p.add_argument("--quiet", action="store_true")
    checks.one_line_errors(p)
    a = p.parse_args(argv)
    views, eval_views = _ints(p, "--views", a.views), _ints(p, "--eval-views", a.eval_views)
    cfg = HogsConfig(
        data=a.data, subject=a.subject, object=a.object, out=a.out, dataset=a.dataset, mano_dir=a.mano_dir,
        object_mesh_dir=a.object_mesh_dir, masks=a.masks, window=a.window, views=views,
        sequences=[s for s in a.sequences.split(",") if s] if a.sequences else None,
        iters=a.iters, gaussians=a.gaussians, device=a.device, seed=a.seed, batch_size=a.batch_size,
        image_size=a.image_size, eval_views=eval_views,
        eval_every_frame=a.eval_every_frame, frame_stride=a.frame_stride, max_eval=a.max_eval,
        eval_every=a.eval_every, ckpt_every=a.ckpt_every, k=a.k, sh_degree=a.sh_degree, sh_warmup=a.sh_warmup,
        hand_subdivide=a.hand_subdivide, object_subdivide=a.object_subdivide, margin=a.margin,
        lambda_ssim=a.lambda_ssim, lambda_r=a.lambda_r, lambda_alpha=a.lambda_alpha, lambda_alpha_in=a.lambda_alpha_in, lr_scale=a.lr_scale,
        strip_views=a.strip_views, lr_overrides=_lr_overrides(p, a.lr), opacity_warmup=a.opacity_warmup,
        shading=a.shading, max_minutes=a.max_minutes,
    )  # fmt: skip
    cfg.resume = a.resume  # type: ignore[attr-defined]
    cfg.overwrite = a.overwrite  # type: ignore[attr-defined]
    cfg.quiet = a.quiet  # type: ignore[attr-defined]
    return cfg


def check_args(cfg: HogsConfig) -> None:
    """Every check that needs no data read: paths, the run folder and, with ``--resume``, the
    run's saved settings and its latest trainer state. Raises UsageError / RunExistsError /
    AssetError (a malformed or corrupt checkpoint) / ValueError (settings that differ)."""
    checks.input_dir(cfg.data, "--data")
    for flag, path in (("--mano-dir", cfg.mano_dir), ("--object-mesh-dir", cfg.object_mesh_dir)):
        if path is not None:
            checks.input_dir(path, flag)
    if cfg.dataset == "h2o" and cfg.object_mesh_dir is not None:
        try:
            find_h2o_mesh(cfg.object_mesh_dir, cfg.object)
        except AssetError as exc:
            raise UsageError(f"--object-mesh-dir {exc}") from exc
    checks.output_dir(cfg.out, "--out")
    check_run_folder(cfg.out, resume=cfg.resume, overwrite=cfg.overwrite)  # type: ignore[attr-defined]
    if cfg.resume:  # type: ignore[attr-defined]
        # the run's settings, its latest checkpoint and the hash-checked trainer state, before any data is
        # read; views and eval views left to the data (None) are compared when the trainer resumes
        given = {k: v for k, v in cfg.to_json().items() if not (k in ("views", "eval_views") and v is None)}
        folder = latest_checkpoint(Path(cfg.out), given, HogsConfig.RESUMABLE, config_defaults(HogsConfig))
        if folder is not None:
            read_trainer_state(folder)


def main(argv: Optional[Sequence[str]] = None) -> int:
    cfg = parse_args(argv)
    resume, overwrite, quiet = cfg.resume, cfg.overwrite, cfg.quiet  # type: ignore[attr-defined]
    try:
        check_args(cfg)
        trainer = HogsTrainer(cfg, progress=not quiet)
        if resume and trainer.resume() and not quiet:
            print(f"resumed {cfg.out} at step {trainer.step}")
    except (HogsaError, OSError) as exc:  # files: exit status 1 (a usage error: 2)
        return checks.report("train_hogs", exc)
    except ValueError as exc:  # a setting the trainer refused (errors during training are not usage errors)
        return checks.report("train_hogs", UsageError(str(exc)))
    try:
        m = trainer.train(overwrite=overwrite)
    except (HogsaError, OSError) as exc:
        return checks.report("train_hogs", exc)
    if not quiet:
        print(json.dumps({k: m[k] for k in ("psnr", "ssim", "iters")} | {"s_per_iter": m["timings"]["s_per_iter"]}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
