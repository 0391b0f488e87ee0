"""``hogsa build``: flags derived from :class:`~hogsa_loader.train.build.BuildConfig`, a TOML file
(``--config``), ``--print-config`` and ``--status``.

Settings come from the defaults, then the ``--config`` file, then the flags. Each stage's flags
are those of its ``hogsa train`` job behind the stage's name (``--hogs-optim-iters``,
``--srm-batch-size``); the data, output, seed and device are the build's own (``--data``,
``--out``, ``--seed``, ``--device``).

``--gpus 0,1,…`` starts one build process per listed GPU on this machine (each maps ``--device
cuda`` to ``cuda:<id>``; with another device the ids only count the processes); they share the
stages as processes from torchrun or srun do.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from typing import Any, Optional, Sequence

from hogsa_loader.cli import checks
from hogsa_loader.cli.dataclass_args import CommaList, add_dataclass_arguments, apply_field_checks, dataclass_from_args
from hogsa_loader.cli.registry import HELP
from hogsa_loader.errors import HogsaError, UsageError
from hogsa_loader.system import process_slot
from hogsa_loader.train.build import SET_BY_BUILD, BuildConfig, build, build_status, config_toml, read_config

__all__ = ["add_build_command", "build_parser", "run_build_command"]

_FLAGS = (
    (
        "--config",
        dict(default=None, metavar="FILE", help="TOML file of settings (hogsa build --print-config writes one)"),
    ),
    ("--print-config", dict(action="store_true", help="print the settings as TOML and exit")),
    ("--status", dict(action="store_true", help="print what is built and what is left, and exit")),
    ("--quiet", dict(action="store_true", help="no progress bars or messages")),
    (
        "--gpus",
        dict(
            default=None,
            type=CommaList(int),
            metavar="ID,...",
            help="one build process per listed GPU of this machine, sharing the stages",
        ),
    ),
)


def _add_flags(p: argparse.ArgumentParser, default: Optional[Any] = None) -> argparse.ArgumentParser:

    for flag, kw in _FLAGS:
        p.add_argument(flag, **kw)
    add_dataclass_arguments(p, BuildConfig, default=default, skip=SET_BY_BUILD)
    apply_field_checks(p, BuildConfig)
    for action in p._actions:  # --data and --out come from the file or the flags: checked after parsing
        action.required = False
    checks.one_line_errors(p)
    return p


def build_parser(default: Optional[Any] = None) -> argparse.ArgumentParser:
    """The flags of ``hogsa build`` (defaults from ``default``, a BuildConfig)."""
    return _add_flags(argparse.ArgumentParser(prog="hogsa build", description=HELP["build"]), default)


def add_build_command(subparsers: Any) -> None:
    """Add ``hogsa build`` with its flags (the defaults; ``--config`` is applied when it runs)."""
    p = _add_flags(subparsers.add_parser("build", help=HELP["build"], description=HELP["build"]))
    p.set_defaults(func=run_build_command)


def parse_build_args(argv: Optional[Sequence[str]] = None) -> tuple[Any, argparse.Namespace]:
    """The :class:`~hogsa_loader.train.build.BuildConfig` of a command line (defaults, then
    ``--config``, then flags) and the namespace."""

    argv = list(sys.argv[1:] if argv is None else argv)
    pre = argparse.ArgumentParser(add_help=False)
    pre.add_argument("--config", default=None)
    given, _ = pre.parse_known_args(argv)
    base = read_config(given.config) if given.config else BuildConfig()
    a = build_parser(base).parse_args(argv)
    return dataclass_from_args(BuildConfig, a, default=base), a


def run_build_command(args: argparse.Namespace) -> int:
    """``hogsa build`` from ``hogsa``'s command line (parsed again: the ``--config`` file's values
    come before the flags); the exit status."""
    argv = list(args.argv)
    return main(argv[argv.index("build") + 1 :])


def main(argv: Optional[Sequence[str]] = None) -> int:
    """Run ``hogsa build`` with ``argv``; 0, 1 (a stage failed), 2 (bad arguments)."""

    try:
        cfg, a = parse_build_args(argv)
        if a.print_config:
            sys.stdout.write(config_toml(cfg))
            return 0
        if a.status:
            rows = build_status(cfg)
            for r in rows:
                took = f"{r['seconds']:.0f} s" if r["seconds"] is not None else "-"
                print(f"{r['name']:24s} {r['state']:6s} {took:>8s} {r['bytes'] / 2**20:9.1f} MiB")
            left = [r["name"] for r in rows if r["state"] != "done"]
            tail = f"; left: {', '.join(left)}" if left else ""
            print(f"{len(rows) - len(left)} of {len(rows)} stages done{tail}")
            return 0
        if a.gpus:
            return _launch(list(argv if argv is not None else sys.argv[1:]), a.gpus)
        bundle, seconds = build(cfg, log=None if a.quiet else print)
    except (HogsaError, OSError) as exc:  # a bad setting (exit status 2), a problem met while building (1)
        return checks.report("hogsa build", exc)
    if not a.quiet:
        print(json.dumps({"bundle": str(bundle), "stage_seconds": {k: round(v, 1) for k, v in seconds.items()}}))
    return 0


def _without_gpus(argv: list[str]) -> list[str]:
    out, skip = [], False
    for arg in argv:
        if skip:
            skip = False
        elif arg == "--gpus":
            skip = True
        elif not arg.startswith("--gpus="):
            out.append(arg)
    return out


def _launch(argv: list[str], gpus: list[int]) -> int:
    """Run the build in one process per GPU of ``gpus`` (``RANK``, ``WORLD_SIZE`` and
    ``LOCAL_RANK`` = the GPU id, as torchrun sets them); the first non-zero exit status."""
    if process_slot()[1] > 1:
        raise UsageError("--gpus starts its own processes: not under torchrun or srun")
    if len(set(gpus)) != len(gpus) or min(gpus) < 0:
        raise UsageError(f"--gpus must list distinct GPU ids >= 0, got {gpus}")
    base = {k: v for k, v in os.environ.items() if not k.startswith("SLURM_")}
    cmd = [sys.executable, "-m", "hogsa_loader.cli.build", *_without_gpus(argv)]
    procs = []
    try:
        for rank, gpu in enumerate(gpus):
            env = {**base, "RANK": str(rank), "WORLD_SIZE": str(len(gpus)), "LOCAL_RANK": str(gpu)}
            procs.append(subprocess.Popen(cmd, env=env))
        codes = [p.wait() for p in procs]
    finally:
        for p in procs:
            if p.poll() is None:
                p.terminate()
    return next((c for c in codes if c), 0)


if __name__ == "__main__":
    raise SystemExit(main())
