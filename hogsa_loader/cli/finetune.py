"""``hogsa finetune``: flags derived from :class:`~hogsa_loader.train.finetune.FinetuneConfig`."""

from __future__ import annotations

import argparse
import json
import sys
from typing import Any, Optional, Sequence

from hogsa_loader.cli import checks
from hogsa_loader.cli.dataclass_args import add_dataclass_arguments, apply_field_checks, dataclass_from_args
from hogsa_loader.cli.main import main as hogsa
from hogsa_loader.cli.registry import HELP
from hogsa_loader.train.finetune import FinetuneConfig, finetune

__all__ = ["add_finetune_command", "main"]


def _add_flags(p: argparse.ArgumentParser) -> argparse.ArgumentParser:

    add_dataclass_arguments(p, FinetuneConfig)
    apply_field_checks(p, FinetuneConfig)
    p.add_argument("--quiet", action="store_true", help="no messages")
    checks.one_line_errors(p)
    return p


def add_finetune_command(subparsers: Any) -> None:
    """Add ``hogsa finetune`` with its flags."""
    p = _add_flags(subparsers.add_parser("finetune", help=HELP["finetune"], description=HELP["finetune"]))
    p.set_defaults(func=run_finetune_command)


def run_finetune_command(args: argparse.Namespace) -> int:
    """``hogsa finetune`` from ``hogsa``'s parsed arguments; the exit status."""

    result = finetune(dataclass_from_args(FinetuneConfig, args), log=None if args.quiet else print)
    if not args.quiet:
        print(json.dumps({k: v for k, v in result.items() if k != "metrics"} | {"metrics": result.get("metrics")}))
    return 0


def main(argv: Optional[Sequence[str]] = None) -> int:
    """``python -m hogsa_loader.cli.finetune`` (what torchrun and srun launch): ``hogsa finetune``."""
    return hogsa(["finetune", *(sys.argv[1:] if argv is None else argv)])


if __name__ == "__main__":
    raise SystemExit(main())
