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
from typing import Optional, Sequence

import torch

from hogsa_loader.cli import checks
from hogsa_loader.errors import HogsaError, UsageError


def parse_args(argv: Optional[Sequence[str]] = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[1])
    p.add_argument("--data", required=True, help="dataset root (ARCTIC ./data)")
    p.add_argument("--out", required=True, help="run folder")
    p.add_argument("--iters", type=checks.non_negative_int, default=1500)
    p.add_argument("--val-subjects", default=None, help="comma-separated held-out subjects (default: the last one)")
    p.add_argument("--batch", type=checks.positive_int, default=8)
    p.add_argument("--points", type=checks.positive_int, default=512, help="object points per training sample")
    p.add_argument("--lr", type=checks.positive_float, default=1e-3)
    p.add_argument("--val-every", type=checks.positive_int, default=100)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--threads", type=checks.positive_int, default=None, help="torch CPU threads")
    p.add_argument("--quiet", action="store_true")
    checks.one_line_errors(p)
    return p.parse_args(argv)


def main(argv: Optional[Sequence[str]] = None) -> int:
    args = parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)
    from hogsa_loader.pom.jobs import fit_contactnet

    try:
        checks.input_dir(args.data, "--data")
        checks.output_dir(args.out, "--out")
        metrics = fit_contactnet(
            args.data, args.out, iters=args.iters,
            val_subjects=args.val_subjects.split(",") if args.val_subjects else None,
            batch=args.batch, points=args.points, lr=args.lr, val_every=args.val_every, seed=args.seed,
            progress=not args.quiet,
        )  # fmt: skip
    except (HogsaError, OSError) as exc:
        return checks.report("train_contactnet", exc)
    except ValueError as exc:  # a setting the job refused
        return checks.report("train_contactnet", UsageError(str(exc)))
    if not args.quiet:
        print(json.dumps(metrics, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
