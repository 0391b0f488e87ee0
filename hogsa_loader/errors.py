"""Typed errors shared by every reader and writer of the project.

Every error that comes from bad input names the file and says what is wrong with it.
"""

from __future__ import annotations

import os
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


def read_json(path: PathLike) -> "object":
    """Parse a JSON file; :class:`AssetError` naming it when missing, unreadable or malformed."""
    import json
    from pathlib import Path

    path = Path(path)
    if not path.is_file():
        raise AssetError(path, "file is missing")
    try:
        with open(path, "r", encoding="utf-8") as fh:
            return json.load(fh)
    except json.JSONDecodeError as exc:
        raise AssetError(path, f"malformed JSON ({exc.msg} at line {exc.lineno})") from None
    except (OSError, UnicodeDecodeError, RecursionError) as exc:
        raise AssetError(path, f"cannot read file ({type(exc).__name__}: {exc})") from None
