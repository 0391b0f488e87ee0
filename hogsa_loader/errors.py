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
