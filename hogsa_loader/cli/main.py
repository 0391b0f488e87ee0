"""The ``hogsa`` command line.

:func:`main` runs it; :func:`build_parser` builds the parser (its docstring lists the main
sub-commands). Only the sub-command being run is imported (:mod:`hogsa_loader.cli.registry`
names where each one lives): ``hogsa --help`` and ``hogsa --version`` import neither torch
nor the library.
"""

from __future__ import annotations

import argparse
import importlib
import sys
from typing import Iterable, Optional, Sequence

from hogsa_loader import __version__
from hogsa_loader.cli.parsing import one_line_errors, report
from hogsa_loader.cli.registry import COMMANDS
from hogsa_loader.errors import HogsaError

__all__ = ["main", "build_parser"]


def _add_command(sub: argparse._SubParsersAction, name: str) -> None:
    module, func = COMMANDS[name][1].split(":")
    getattr(importlib.import_module(module), func)(sub)


def build_parser(commands: Optional[Iterable[str]] = None) -> argparse.ArgumentParser:
    """The ``hogsa`` parser; ``commands`` (default: all) get their full flags, the others only
    their name and help (so that ``hogsa --help`` imports no sub-command).

    Among the subcommands::

        hogsa --version
        hogsa assets --out DIR         synthetic MANO-format hands, procedural ARCTIC-format objects,
                                       and PNG previews of both
        hogsa convert-mano SRC DST     one-shot MANO .pkl -> chumpy-free, pickle-free .npz
        hogsa world --out DIR --preset tiny|demo|small|small_styles [--seed N]
                                       a synthetic ARCTIC-format world (raw_seqs, misc, cropped
                                       images, masks, splits) rendered with the mesh rasteriser
        hogsa build --data ROOT --out DIR [--config FILE] [--status] [--print-config]
                                       every model of a dataset root and the bundle: HOGS per
                                       training pair, ContactNet, pose bank, SRM (cached, resumable;
                                       several processes with torchrun or srun)
        hogsa export --bundle B --data ROOT --out DIR --num N --shard-size S [--seed N] [--device D]
                     [--coco-root C] ...
                                       offline synthetic frames as WebDataset tar shards
                                       (resumable; multi-process/GPU with torchrun: RANK, WORLD_SIZE)
        hogsa plates --data ROOT --out DIR [--subjects S,...] [--views V,...]
                                       clean background plates of the static cameras, made from
                                       the dataset's own frames (for --background-folder)
        hogsa view --bundle B --data ROOT --subject S --object O --out DIR [--frame SEQ:IDX ...]
                   [--pose-bank NAME:I ...] [--orbit N] [--transfer-to S2 ...]
                                       360° orbit sheets and animations (with and without SRM)
                                       and a pose-transfer grid of a bundle's models
    """
    wanted = set(COMMANDS) if commands is None else set(commands)
    p = argparse.ArgumentParser(prog="hogsa", description="HOGSA augmentation loader tools")
    p.add_argument("--version", action="version", version=f"hogsa-loader {__version__}")
    sub = p.add_subparsers(dest="command")
    for name, (text, _) in COMMANDS.items():
        if name in wanted:
            _add_command(sub, name)
        else:
            sub.add_parser(name, help=text, add_help=False)
    one_line_errors(p)
    return p


def _command_in(argv: Sequence[str]) -> Optional[str]:
    """The sub-command named in ``argv`` (its first word that is not an option), if any."""
    word = next((a for a in argv if not a.startswith("-")), None)
    return word if word in COMMANDS else None


def main(argv: Optional[Sequence[str]] = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    command = _command_in(argv)
    parser = build_parser([command] if command else [])
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:  # --help / --version exit; a bad argument (one line printed) returns its status
        if not exc.code:
            raise
        return int(exc.code)
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    args.argv = argv  # a command that reads a settings file parses its arguments again
    try:
        return int(args.func(args))
    except (HogsaError, OSError) as exc:  # argument checks (exit status 2), problems with files (1)
        return report(f"hogsa {args.command}", exc)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
