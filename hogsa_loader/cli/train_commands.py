"""``hogsa train hogs|srm|contactnet|bank FLAGS``: the training jobs of :mod:`hogsa_loader.cli.train`.

The job's flags follow its name and are parsed by the job itself (``hogsa train hogs --help``).
"""

from __future__ import annotations

import argparse
from typing import Any

from hogsa_loader.cli.registry import HELP

__all__ = ["TRAIN_JOBS", "add_train_commands", "run_train_command"]

#: job name -> what it does
TRAIN_JOBS = {
    "hogs": "train one HOGS model (right hand, left hand, object Gaussians) per subject + object",
    "srm": "train the SRM (StyleUNet refinement of HOGS renders) on every finished HOGS run of a folder",
    "contactnet": "train POM's ContactNet on the annotated frames of an ARCTIC-format or H2O dataset",
    "bank": "build a POM pose bank: optimise perturbed contact frames of every sequence",
}


def add_train_commands(subparsers: Any) -> None:
    """Add ``hogsa train JOB FLAGS`` to ``subparsers`` (the ``add_subparsers`` action of the
    ``hogsa`` parser); its handler is ``args.func(args)``."""
    t = subparsers.add_parser(
        "train",
        help=HELP["train"],
        description="Training jobs; each job's flags are derived from its config (see its --help).",
    )
    t.add_argument("job", choices=sorted(TRAIN_JOBS), help="; ".join(f"{k}: {v}" for k, v in TRAIN_JOBS.items()))
    t.add_argument("job_args", nargs=argparse.REMAINDER, help="the job's flags (JOB --help lists them)")
    t.set_defaults(func=run_train_command)


def run_train_command(args: argparse.Namespace) -> int:
    """Run the ``hogsa train`` job ``args.job`` with ``args.job_args``; its exit status."""
    from hogsa_loader.cli.train import JOBS  # deferred: the training modules, only when a job runs

    return JOBS[args.job](args.job_args)
