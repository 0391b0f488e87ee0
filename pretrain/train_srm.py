#!/usr/bin/env python
"""Train the SRM (StyleUNet refinement of HOGS renders) on every finished HOGS run of a folder.

Example::

    python pretrain/train_srm.py --data ./hogsa_world --hogs runs/hogs --out runs/srm --iters 4000

Pairs the frozen HOGS renders of each run's *training* views/frames (same split as its HOGS
training; held-out views and frames are never used) with the masked ground-truth crops and
trains one StyleUNet for all of them with ``5·L1 + 0.03·VGG19 + GAN`` (without
``--vgg-weights`` a Laplacian-pyramid L1 substitutes for VGG, weight 1.0, with a warning).
Writes the final EMA generator (``manifest.json`` + ``srm.safetensors``, read by
``hogsa_loader.srm.load_srm(RUN)``), ``metrics.json`` (held-out PSNR/SSIM without vs with
SRM, per view), ``samples.png`` (coarse | refined | GT) and ``curves.png`` into ``--out``;
``--resume`` continues exactly from the latest checkpoint. ``--cross-hogs FOLDS`` adds
inputs rendered by view-fold runs that never saw the sample's view; ``--val-views V`` keeps
those training views out and saves the checkpoint that scores best on them (early stopping
without looking at the held-out views). A folder holding checkpoints is refused unless
``--resume`` or ``--overwrite`` (start again from step 0) is given; every argument is checked
before the runs are read.
"""

from __future__ import annotations

import argparse
import json
import sys
from typing import Optional, Sequence

import torch

from hogsa_loader.cli import checks
from hogsa_loader.errors import HogsaError, UsageError
from hogsa_loader.srm.train import SRMTrainConfig, SRMTrainer
from hogsa_loader.train.run_folder import check_run_folder


def parse_args(argv: Optional[Sequence[str]] = None) -> tuple[SRMTrainConfig, argparse.Namespace]:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--data", required=True, help="dataset root (ARCTIC ./data) the HOGS runs were trained on")
    p.add_argument("--hogs", required=True, help="folder of finished HOGS runs (or one run folder)")
    p.add_argument("--out", required=True, help="SRM run folder")
    p.add_argument("--runs", default=None, help="comma-separated run folder names to use (default: all finished)")
    p.add_argument("--pairs", default=None, choices=["own", "cross", "both"],
                   help="training inputs: each run's renders of its own training views (own), renders by "
                        "view-fold runs that did not see the view (cross), or both (default: both with "
                        "--cross-hogs, else own)")
    p.add_argument("--cross-hogs", default=None,
                   help="folder of view-fold HOGS runs: same subject/object, trained on subsets of the "
                        "training views (e.g. --views 1,3,5,7,8 and 2,4,6,8 with --eval-views 8)")
    p.add_argument("--val-views", default=None,
                   help="comma-separated training views kept out of SRM training to pick the best checkpoint "
                        "(their fold renders when --cross-hogs is given); the saved model is the best one")
    p.add_argument("--max-val", type=checks.positive_int, default=32, help="validation samples per run (evenly spaced)")
    p.add_argument("--augment", default="d4", choices=["none", "flip", "d4"],
                   help="random flips (and 90° turns with d4) of each training window, input and target alike "
                        "(default d4: +0.36 dB held-out against +0.13 dB without, small world)")
    p.add_argument("--cache", default=None,
                   help="folder for the coarse HOGS renders, shareable between SRM runs (default: OUT/cache)")
    p.add_argument("--iters", type=checks.non_negative_int, default=4000)
    p.add_argument("--batch-size", type=checks.positive_int, default=4)
    p.add_argument("--image-size", type=checks.positive_int, default=None, help="output / GT resolution (default: the runs' image size)")
    p.add_argument("--crop", type=checks.non_negative_int, default=128, help="training window at the output resolution (0: full images)")
    p.add_argument("--scale", type=int, default=1, choices=[1, 2], help="output resolution factor (renders at image-size/scale)")
    p.add_argument("--channels", default="32,64,128,128,128", help="StyleUNet widths per level, top (H/2) first")
    p.add_argument("--plain-skips", action="store_true", help="plain RGB skips instead of Haar-wavelet skips")
    p.add_argument("--lr", type=checks.positive_float, default=0.002)
    p.add_argument("--lambda-l1", type=checks.non_negative_float, default=5.0)
    p.add_argument("--lambda-perc", type=checks.non_negative_float, default=None, help="default 0.03 with VGG, 1.0 with the substitute")
    p.add_argument("--lambda-gan", type=checks.non_negative_float, default=1.0, help="0 disables the discriminator")
    p.add_argument("--r1-gamma", type=checks.non_negative_float, default=10.0)
    p.add_argument("--r1-every", type=checks.positive_int, default=16)
    p.add_argument("--ema-decay", type=checks.unit_float, default=0.999)
    p.add_argument("--vgg-weights", default=None, help="local torchvision vgg19 state dict (.pth or .safetensors)")
    p.add_argument("--device", default="cpu", type=checks.torch_device)
    p.add_argument("--threads", type=checks.positive_int, default=None, help="torch CPU threads (default: torch's)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--eval-every", type=checks.non_negative_int, default=500)
    p.add_argument("--ckpt-every", type=checks.non_negative_int, default=500)
    p.add_argument("--strip-views", type=checks.positive_int, default=4)
    p.add_argument("--resume", action="store_true", help="continue from the run folder's latest checkpoint")
    p.add_argument("--overwrite", action="store_true",
                   help="start again from step 0 in a run folder that holds checkpoints (they are deleted)")
    p.add_argument("--quiet", action="store_true")
    checks.one_line_errors(p)
    a = p.parse_args(argv)
    cfg = SRMTrainConfig(
        data=a.data, hogs=a.hogs, out=a.out, iters=a.iters, batch_size=a.batch_size, image_size=a.image_size,
        crop=a.crop, scale=a.scale, channels=[int(c) for c in a.channels.split(",") if c], wavelet=not a.plain_skips,
        lr=a.lr, lambda_l1=a.lambda_l1, lambda_perc=a.lambda_perc, lambda_gan=a.lambda_gan, r1_gamma=a.r1_gamma,
        r1_every=a.r1_every, ema_decay=a.ema_decay, vgg_weights=a.vgg_weights, device=a.device, seed=a.seed,
        eval_every=a.eval_every, ckpt_every=a.ckpt_every, strip_views=a.strip_views,
        runs=[r for r in a.runs.split(",") if r] if a.runs else None,
        pairs=a.pairs or ("both" if a.cross_hogs else "own"), cross_hogs=a.cross_hogs,
        val_views=[int(v) for v in a.val_views.split(",") if v] if a.val_views else None, max_val=a.max_val,
        augment=a.augment, cache=a.cache,
    )  # fmt: skip
    return cfg, a


def main(argv: Optional[Sequence[str]] = None) -> int:
    cfg, a = parse_args(argv)
    if a.threads:
        torch.set_num_threads(a.threads)
    try:
        checks.input_dir(cfg.data, "--data")
        checks.input_dir(cfg.hogs, "--hogs")
        if cfg.cross_hogs:
            checks.input_dir(cfg.cross_hogs, "--cross-hogs")
        if cfg.cache:
            checks.output_dir(cfg.cache, "--cache")
        checks.output_dir(cfg.out, "--out")
        check_run_folder(cfg.out, resume=a.resume, overwrite=a.overwrite)
        trainer = SRMTrainer(cfg, progress=not a.quiet)
        if a.resume:
            if trainer.resume():
                print(f"train_srm: resumed {cfg.out} at step {trainer.step}", file=sys.stderr)
            else:
                print(f"train_srm: nothing to resume in {cfg.out}; starting fresh", file=sys.stderr)
    except (HogsaError, OSError) as exc:
        return checks.report("train_srm", exc)
    except ValueError as exc:  # a setting the trainer refused (errors during training are not usage errors)
        return checks.report("train_srm", UsageError(str(exc)))
    try:
        m = trainer.train(overwrite=a.overwrite)
    except (HogsaError, OSError) as exc:
        return checks.report("train_srm", exc)
    if m["selection"]:
        b = m["selection"]["best"]
        print(f"train_srm: selected step {b['step']} (validation views {m['selection']['val_views']}: "
              f"{b['psnr_without_srm']:.2f} -> {b['psnr']:.2f} dB on {b['n']} pairs)", file=sys.stderr)
    print(json.dumps({k: m[k] for k in ("without_srm", "with_srm", "delta_psnr", "delta_ssim")}, indent=1))
    for row in m["per_view"]:
        print(f"{row['run']:>24s} view {row['view']}: n={row['n']} PSNR {row['without_srm']['psnr']:.2f} -> "
              f"{row['with_srm']['psnr']:.2f} dB, SSIM {row['without_srm']['ssim']:.4f} -> {row['with_srm']['ssim']:.4f}")  # fmt: skip
    return 0


if __name__ == "__main__":
    sys.exit(main())
