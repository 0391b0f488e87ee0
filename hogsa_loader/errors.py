"""Typed errors shared by every reader and writer of the project.

Every error that comes from bad input names the file and says what is wrong with it.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Union

PathLike = Union[str, "os.PathLike[str]"]


class HogsaError(Exception):
    """Base class of every error raised on purpose by hogsa-loader."""


class AssetError(HogsaError, ValueError):
    """A file on disk is missing, malformed or inconsistent.

    Args:
        path: the offending file (or folder).
        problem: what is wrong, in words a user can act on.
    """

    def __init__(self, path: PathLike, problem: str) -> None:
        self.path = os.fspath(path)
        self.problem = problem
        super().__init__(f"{self.path}: {problem}")


class UnsafePickleError(AssetError):
    """A pickle asked for a global (class or function) outside the allow-list."""


class UsageError(HogsaError, ValueError):
    """A command-line argument or setting is invalid; the message names it and says why.

    Raised by the argument checks (:mod:`hogsa_loader.cli.checks`) before any work starts;
    the command line reports it as one ``PROG: error: MESSAGE`` line (exit status 2).
    """


def read_json(path: PathLike, allow_nan: bool = True) -> "object":
    """Parse a JSON file; :class:`AssetError` naming it when missing, unreadable or malformed.

    ``allow_nan=False`` also refuses ``NaN`` / ``Infinity`` (not JSON values; Python's
    reader accepts them): for this library's own manifests, whose writer never emits them.
    """

    def reject(name: str) -> "object":
        raise ValueError(f"malformed JSON: {name} is not a JSON value")

    path = Path(path)
    if not path.is_file():
        raise AssetError(path, "file is missing")
    try:
        with open(path, "r", encoding="utf-8") as fh:
            return json.load(fh) if allow_nan else json.load(fh, parse_constant=reject)
    except json.JSONDecodeError as exc:
        raise AssetError(path, f"malformed JSON ({exc.msg} at line {exc.lineno})") from None
    except (OSError, UnicodeDecodeError, RecursionError) as exc:
        raise AssetError(path, f"cannot read file ({type(exc).__name__}: {exc})") from None
    except ValueError as exc:  # NaN / Infinity refused
        raise AssetError(path, str(exc)) from None
