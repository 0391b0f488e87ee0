"""Argument-parser helpers that import nothing heavy: one-line errors and error reports."""

from __future__ import annotations

import argparse
import sys

from hogsa_loader.errors import UsageError

__all__ = ["one_line_errors", "report"]


def one_line_errors(parser: argparse.ArgumentParser) -> None:
    """Make ``parser`` and its sub-command parsers report bad arguments as one
    ``PROG: error: ...`` line on stderr (exit status 2), without the usage block."""

    def patch(p: argparse.ArgumentParser) -> None:
        def error(message: str) -> None:
            print(f"{p.prog}: error: {message}", file=sys.stderr)
            sys.exit(2)

        p.error = error  # type: ignore[method-assign]
        for action in p._actions:
            if isinstance(action, argparse._SubParsersAction):
                for sub in action.choices.values():
                    patch(sub)

    patch(parser)


def report(prog: str, exc: BaseException) -> int:
    """Print ``exc`` as one ``PROG: error: ...`` line; the exit status (2 usage, 1 otherwise)."""
    msg = str(exc) if not isinstance(exc, OSError) or not exc.filename else f"{exc.filename}: {exc.strerror}"
    print(f"{prog}: error: {' '.join(msg.split()) if isinstance(exc, UsageError) else msg}", file=sys.stderr)
    return 2 if isinstance(exc, UsageError) else 1
