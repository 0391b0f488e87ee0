"""Argument checks shared by every ``hogsa`` command and ``python -m hogsa_loader.cli.*`` script.

Checks run before any work starts. The argparse converters (``type=``) :func:`positive_int`, :func:`non_negative_int`,
:func:`positive_float`, :func:`non_negative_float`, :func:`unit_float` and :func:`torch_device` raise
``argparse.ArgumentTypeError``, and the parser reports ``PROG: error: argument --x: ...``. The checks of whole paths
and combinations of arguments, :func:`output_dir`, :func:`output_file`, :func:`input_dir`, :func:`input_file`,
:func:`multiple_of` and :func:`data_root_pairs`, raise
:class:`~hogsa_loader.errors.UsageError` naming the argument and the problem. :func:`one_line_errors` makes a parser
(and its sub-commands) print argparse's errors as one ``PROG: error: ...`` line without the usage block;
:func:`report` prints any :class:`~hogsa_loader.errors.HogsaError` or ``OSError`` in that form and returns the exit
status (2 for a usage error, 1 for a problem met while working).
"""

from __future__ import annotations

import argparse
import math
import os
from pathlib import Path
from typing import Iterable, Optional

import torch

from hogsa_loader.assets.arctic import ArcticRoot
from hogsa_loader.cli.parsing import one_line_errors, report
from hogsa_loader.errors import HogsaError, PathLike, UsageError
from hogsa_loader.io.atomic import creation_problem

__all__ = [
    "positive_int",
    "non_negative_int",
    "positive_float",
    "non_negative_float",
    "unit_float",
    "torch_device",
    "output_dir",
    "output_file",
    "input_dir",
    "input_file",
    "multiple_of",
    "data_root_pairs",
    "one_line_errors",
    "report",
    "UsageError",
]


# --------------------------------------------------------------------------------------
# argparse converters
# --------------------------------------------------------------------------------------


def _number(text: str, kind: type, minimum: float, strict: bool) -> float:
    try:
        value = kind(text)
    except (TypeError, ValueError):
        raise argparse.ArgumentTypeError(
            f"expected {'an integer' if kind is int else 'a number'}, got {text!r}"
        ) from None
    if kind is float and value != value:  # NaN
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}")
    if value < minimum or (strict and value == minimum):
        raise argparse.ArgumentTypeError(f"must be {'>' if strict else '>='} {minimum:g}, got {text}")
    return value


def positive_int(text: str) -> int:
    """argparse ``type=``: an integer > 0."""
    return int(_number(text, int, 0, strict=True))


def non_negative_int(text: str) -> int:
    """argparse ``type=``: an integer >= 0."""
    return int(_number(text, int, 0, strict=False))


def positive_float(text: str) -> float:
    """argparse ``type=``: a finite number > 0."""
    value = float(_number(text, float, 0.0, strict=True))
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"expected a finite number > 0, got {text!r}")
    return value


def non_negative_float(text: str) -> float:
    """argparse ``type=``: a finite number >= 0."""
    value = float(_number(text, float, 0.0, strict=False))
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"expected a finite number >= 0, got {text!r}")
    return value


def unit_float(text: str) -> float:
    """argparse ``type=``: a number in [0, 1]."""
    value = non_negative_float(text)
    if value > 1.0:
        raise argparse.ArgumentTypeError(f"must be <= 1, got {text}")
    return value


def torch_device(text: str) -> str:
    """argparse ``type=``: a torch device string this machine has (``cpu``, ``cuda``, ``cuda:N``, ``mps``)."""
    try:
        dev = torch.device(text)
    except (RuntimeError, TypeError, ValueError):
        raise argparse.ArgumentTypeError(f"not a device: {text!r} (cpu, cuda, cuda:N)") from None
    if dev.type == "cuda":
        if not torch.cuda.is_available():
            raise argparse.ArgumentTypeError(f"{text!r}: CUDA is not available on this machine")
        if dev.index is not None and dev.index >= torch.cuda.device_count():
            raise argparse.ArgumentTypeError(f"{text!r}: this machine has {torch.cuda.device_count()} CUDA device(s)")
    elif dev.type == "mps":
        if not (getattr(torch.backends, "mps", None) and torch.backends.mps.is_available()):
            raise argparse.ArgumentTypeError(f"{text!r}: MPS is not available on this machine")
    elif dev.type != "cpu":
        raise argparse.ArgumentTypeError(f"unsupported device {text!r} (cpu, cuda, cuda:N)")
    return text


# --------------------------------------------------------------------------------------
# paths and combinations
# --------------------------------------------------------------------------------------


def _writable_parent(p: Path, flag: str) -> None:
    """The nearest existing ancestor of a path to create must be a writable folder."""
    problem = creation_problem(p)
    if problem is not None:
        raise UsageError(f"{flag} {p}: {problem}")


def output_dir(path: PathLike, flag: str = "--out", must_not_exist: bool = False) -> Path:
    """An output folder: an existing writable folder, or creatable (nearest existing
    ancestor a writable folder). Nothing is created.

    Raises:
        UsageError: it is a file, not writable, or (``must_not_exist``) already there.
    """
    p = Path(path)
    if p.exists() or p.is_symlink():
        if not p.is_dir():
            raise UsageError(f"{flag} {p}: exists and is not a folder")
        if must_not_exist:
            raise UsageError(f"{flag} {p}: already exists")
        if not os.access(p, os.W_OK | os.X_OK):
            raise UsageError(f"{flag} {p}: folder is not writable")
        return p
    _writable_parent(p, flag)
    return p


def output_file(
    path: PathLike, flag: str, overwrite: bool = False, suffix: Optional[str] = None, source: Optional[PathLike] = None
) -> Path:
    """An output file: not a folder, not the ``source`` file, with ``suffix`` when given, in a
    writable (or creatable) folder; an existing file only with ``overwrite``.

    Raises:
        UsageError: naming ``flag`` and the problem.
    """
    p = Path(path)
    if suffix is not None and not p.name.endswith(suffix):
        raise UsageError(f"{flag} {p}: must end in {suffix}")
    if source is not None and Path(source).exists() and p.exists() and os.path.samefile(source, p):
        raise UsageError(f"{flag} {p}: is the input file itself")
    if p.is_dir():
        raise UsageError(f"{flag} {p}: is a folder; give a file name")
    if p.exists() or p.is_symlink():
        if not overwrite:
            raise UsageError(f"{flag} {p}: already exists (pass --overwrite to replace it)")
        if not os.access(p.parent, os.W_OK | os.X_OK):
            raise UsageError(f"{flag} {p}: folder {p.parent} is not writable")
        return p
    _writable_parent(p, flag)
    return p


def input_dir(path: PathLike, flag: str) -> Path:
    """An existing, readable folder."""
    p = Path(path)
    if not p.is_dir():
        raise UsageError(f"{flag} {p}: {'is not a folder' if p.exists() else 'no such folder'}")
    if not os.access(p, os.R_OK | os.X_OK):
        raise UsageError(f"{flag} {p}: folder is not readable")
    return p


def input_file(path: PathLike, flag: str) -> Path:
    """An existing, readable file."""
    p = Path(path)
    if not p.is_file():
        raise UsageError(f"{flag} {p}: {'is not a file' if p.exists() else 'no such file'}")
    if not os.access(p, os.R_OK):
        raise UsageError(f"{flag} {p}: file is not readable")
    return p


def multiple_of(value: int, base: int, flag: str, base_flag: str) -> None:
    """``value`` must be a multiple of ``base``."""
    if value % base:
        raise UsageError(f"{flag} {value} must be a multiple of {base_flag} {base}")


def data_root_pairs(data: PathLike, pairs: Iterable[tuple[str, str]], flag: str = "--data") -> None:
    """An ARCTIC(-format) data root that has a sequence of every ``(subject, object)``.

    Reads only ``misc.json`` and the ``raw_seqs`` listing.

    Raises:
        UsageError: not a data root, or a pair without sequences (names them).
    """
    input_dir(data, flag)
    try:
        root = ArcticRoot(data)
        subjects = set(root.subjects())
        missing = []
        for sid, obj in pairs:
            if sid not in subjects:
                missing.append(f"subject {sid}")
            elif not any(s.split("/", 1)[1].split("_", 1)[0] == obj for s in root.sequences(sid)):
                missing.append(f"{sid}/{obj}")
    except HogsaError as exc:
        raise UsageError(f"{flag} {data}: {exc}") from None
    if missing:
        raise UsageError(
            f"{flag} {data}: the data root has no sequence of {', '.join(missing)} "
            f"(subjects: {', '.join(sorted(subjects))})"
        )
