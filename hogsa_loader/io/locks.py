"""One writer per output: an advisory lock held while a job writes a folder.

:func:`writer_lock` takes an exclusive ``flock`` on a lock file in the folder and records the
holder's pid in it. A second writer is refused at once with an error naming the folder and
the holder's pid. The lock goes with the process that holds it (the kernel releases a
``flock`` when its holder exits or is killed), so a lock file left by a dead writer is taken
over without any clean-up.
"""

from __future__ import annotations

import contextlib
import os
from pathlib import Path
from typing import Iterator

from hogsa_loader.errors import HogsaError, PathLike

__all__ = ["FolderBusyError", "writer_lock"]


class FolderBusyError(HogsaError, RuntimeError):
    """Another live process is writing the same output."""


@contextlib.contextmanager
def writer_lock(
    folder: PathLike, name: str = ".hogsa-writer.lock", what: str = "this folder", wait: bool = False
) -> Iterator[None]:
    """Hold the writer lock ``folder/name`` for the ``with`` block.

    Args:
        folder: the output folder (it must exist).
        name: the lock file (one per unit that has one writer, e.g. an export rank).
        what: what the lock guards, for the message (``"rank 0 of this export"``).
        wait: wait for the holder to finish instead of refusing (for short critical sections
            that several writers take in turn, e.g. rebuilding an export's index).

    Raises:
        FolderBusyError: a live process holds the lock (its pid is named); never with ``wait``.
    """
    try:
        import fcntl  # deferred: POSIX only (elsewhere no lock is taken)
    except ImportError:  # pragma: no cover - non-POSIX
        yield
        return
    path = Path(folder) / name
    fd = os.open(path, os.O_RDWR | os.O_CREAT | getattr(os, "O_NOFOLLOW", 0) | getattr(os, "O_CLOEXEC", 0), 0o644)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX if wait else fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.pread(fd, 32, 0).decode("ascii", "replace").strip() or "unknown"
            raise FolderBusyError(f"{Path(folder)}: {what} is being written by process {holder}") from None
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
        try:
            yield
        finally:
            os.ftruncate(fd, 0)
            fcntl.flock(fd, fcntl.LOCK_UN)
    finally:
        os.close(fd)
