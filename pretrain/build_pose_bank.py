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
import math
import sys
from typing import Optional, Sequence

import torch

from hogsa_loader.cli import checks
from hogsa_loader.errors import HogsaError, UsageError


def parse_args(argv: Optional[Sequence[str]] = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[1])
    p.add_argument("--data", required=True)
    p.add_argument("--contactnet", required=True, help="ContactNet run folder")
    p.add_argument("--out", required=True, help="bank folder")
    p.add_argument("--per-sequence", type=checks.positive_int, default=16)
    p.add_argument("--variants", type=checks.positive_int, default=1, help="perturbations per frame")
    p.add_argument("--subjects", default=None, help="comma-separated subjects (default: all)")
    p.add_argument("--sequences", default=None, help="comma-separated sid/seq ids, e.g. s01/box_grab_01 (default: all)")
    p.add_argument("--iters", type=checks.non_negative_int, default=200)
    p.add_argument("--batch", type=checks.positive_int, default=16)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--keep-rejected", action="store_true")
    p.add_argument("--arti-range", type=float, nargs=2, metavar=("LO", "HI"), default=None,
                   help="draw the articulation angle uniformly in [LO, HI] rad (the paper: 0.0314 0.628) "
                        "instead of keeping the annotated angle")
    p.add_argument("--device", default="cpu", type=checks.torch_device)
    p.add_argument("--threads", type=checks.positive_int, default=None)
    p.add_argument("--quiet", action="store_true")
    checks.one_line_errors(p)
    args = p.parse_args(argv)
    if args.arti_range is not None and not 0.0 <= args.arti_range[0] <= args.arti_range[1] < math.inf:
        p.error(f"argument --arti-range: need finite 0 <= LO <= HI, got {args.arti_range[0]} {args.arti_range[1]}")
    return args


def main(argv: Optional[Sequence[str]] = None) -> int:
    args = parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)
    from hogsa_loader.pom.jobs import build_pose_bank
    from hogsa_loader.pom.perturb import PerturbConfig

    try:
        checks.input_dir(args.data, "--data")
        checks.input_dir(args.contactnet, "--contactnet")
        checks.output_dir(args.out, "--out")
        pert = None if args.arti_range is None else PerturbConfig(arti_range=tuple(args.arti_range))
        summary = build_pose_bank(
            args.data, args.contactnet, args.out, per_sequence=args.per_sequence, variants=args.variants,
            subjects=args.subjects.split(",") if args.subjects else None,
            sequences=args.sequences.split(",") if args.sequences else None, iters=args.iters, batch=args.batch,
            seed=args.seed, keep_rejected=args.keep_rejected, perturbation=pert, device=args.device,
            progress=not args.quiet,
        )  # fmt: skip
    except (HogsaError, OSError) as exc:
        return checks.report("build_pose_bank", exc)
    except ValueError as exc:  # a setting the job refused
        return checks.report("build_pose_bank", UsageError(str(exc)))
    if not args.quiet:
        print(json.dumps(summary, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
