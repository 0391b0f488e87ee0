"""Atomic file writes: a temporary file in the target's folder, fsync, ``os.replace``.

A reader never sees a half-written file: it finds the old content or the new one. A failed
write removes its temporary file and leaves the target as it was. The temporary file has an
unguessable name (128 random bits) and is created with ``O_CREAT | O_EXCL | O_NOFOLLOW``, so
a link planted in the folder by another user is never followed: the write fails instead of
overwriting the link's target, and the rename replaces a link at the target path itself, not
what it points to. Every writer of the library goes through :func:`atomic_open`.
:func:`creation_problem` says, before anything is written, why a new output path could not be
created.
"""

from __future__ import annotations

import json
import os
import uuid
from contextlib import contextmanager
from pathlib import Path
from typing import IO, Any, Iterator, Optional

from hogsa_loader.errors import PathLike

__all__ = ["atomic_open", "atomic_write", "atomic_write_json", "creation_problem", "temp_glob"]


def creation_problem(path: Path) -> Optional[str]:
    """Why a path that does not exist yet cannot be created (None when it can): its nearest
    existing ancestor must be a writable folder. Nothing is created.

    Returns:
        ``"cannot be created, <ancestor> is a file"`` / ``"... is not writable"``, or None.
    """
    anc = path.absolute().parent
    while not anc.exists() and anc != anc.parent:
        anc = anc.parent
    if not anc.is_dir():
        return f"cannot be created, {anc} is a file"
    if not os.access(anc, os.W_OK | os.X_OK):
        return f"cannot be created, {anc} is not writable"
    return None


def _temp_name(path: Path) -> Path:
    """A hidden, unguessable temporary file name next to ``path``."""
    return path.with_name(f".{path.name}.{os.getpid()}.{uuid.uuid4().hex}.tmp")


def temp_glob(path: PathLike) -> str:
    """The glob pattern of :func:`atomic_open`'s temporary files for ``path`` (in its folder)."""
    return f".{Path(path).name}.*.tmp"


#: flags of a temporary file: created here, never an existing file, never through a link
_EXCLUSIVE = os.O_WRONLY | os.O_CREAT | os.O_EXCL
_EXCLUSIVE |= getattr(os, "O_NOFOLLOW", 0) | getattr(os, "O_CLOEXEC", 0) | getattr(os, "O_BINARY", 0)


def _fsync_folder(folder: Path) -> None:
    """Make a rename in ``folder`` durable (POSIX); a no-op where folders cannot be opened."""
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


@contextmanager
def atomic_open(
    path: PathLike, mode: str = "wb", encoding: str | None = None, durable: bool = True
) -> Iterator[IO[Any]]:
    """Open a temporary file that replaces ``path`` when the ``with`` block ends without error.

    Args:
        path: the file to write; its folder must exist.
        mode: ``"wb"`` or ``"w"``.
        encoding: text encoding (text mode only).
        durable: fsync the file and its folder (a power cut keeps it); False for bulk files
            that a later step checks (still atomic and never through a link).

    Yields:
        the open temporary file.
    """
    path = Path(path)
    tmp = _temp_name(path)
    fd = os.open(tmp, _EXCLUSIVE, 0o666)  # (the umask applies, as for open())
    try:
        try:
            fh = os.fdopen(fd, mode, encoding=encoding)
        except BaseException:
            os.close(fd)
            raise
        with fh:
            yield fh
            fh.flush()
            if durable:
                os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    if durable:
        _fsync_folder(path.parent)


def atomic_write(path: PathLike, data: bytes, durable: bool = True) -> None:
    """Write ``data`` to ``path`` atomically (see :func:`atomic_open`)."""
    with atomic_open(path, durable=durable) as fh:
        fh.write(data)


def atomic_write_json(path: PathLike, obj: Any, indent: int | None = 1, **dump_kwargs: Any) -> None:
    """Write ``obj`` as JSON (plus a final newline) to ``path`` atomically.

    Args:
        path: the file.
        obj: a JSON-able value.
        indent: as :func:`json.dumps`.
        **dump_kwargs: more :func:`json.dumps` arguments (``allow_nan``, ``default``...).
    """
    atomic_write(path, (json.dumps(obj, indent=indent, **dump_kwargs) + "\n").encode("utf-8"))
