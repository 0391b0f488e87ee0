"""Facts about the machine the code runs on, and the process-wide allocator setting."""

from __future__ import annotations

import ctypes
import multiprocessing
import os
import platform
import sys
import threading
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from typing import Any, Callable, Optional, Sequence

__all__ = [
    "available_cores",
    "can_fork",
    "run_forked",
    "keep_allocator_memory",
    "allocator_status",
    "KEEP_MEMORY_ENV",
    "process_slot",
    "rank_device",
]

#: Set to ``0`` to leave the C allocator as the process found it.
KEEP_MEMORY_ENV = "HOGSA_KEEP_MEMORY"
#: glibc ``mallopt`` parameter numbers (``malloc.h``) and the values set by :func:`keep_allocator_memory`:
#: blocks up to 32 MiB (the ceiling of glibc's dynamic mmap threshold on 64-bit) come from the heap instead of a
#: fresh ``mmap``, freed memory is kept (trim threshold 2 GiB), and the heap grows 512 MiB at a time
#: (address space only; pages are backed when first touched).
GLIBC_SETTINGS = {
    "M_MMAP_THRESHOLD": (-3, 32 * 2**20),
    "M_TRIM_THRESHOLD": (-1, 2**31 - 1),
    "M_TOP_PAD": (-2, 512 * 2**20),
}
#: Environment variables through which a user configures glibc's allocator himself; any of them set
#: means :func:`keep_allocator_memory` leaves it alone.
GLIBC_ENV = ("MALLOC_MMAP_THRESHOLD_", "MALLOC_TRIM_THRESHOLD_", "MALLOC_TOP_PAD_", "MALLOC_MMAP_MAX_")
#: Allocators a user may preload instead of glibc's.
OTHER_ALLOCATORS = ("tcmalloc", "jemalloc", "mimalloc")

_lock = threading.Lock()
_status: Optional[str] = None
if hasattr(os, "register_at_fork"):  # a child forked while another thread held the lock must not deadlock
    os.register_at_fork(after_in_child=lambda: globals().__setitem__("_lock", threading.Lock()))


def available_cores() -> int:
    """CPU cores this process may run on: its affinity mask where the OS has one
    (``os.cpu_count()`` counts every core of the host, e.g. 64 inside a 2-core container)."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)


def can_fork() -> bool:
    """Whether work may be forked into processes after torch and OpenCV are loaded: on Linux
    (macOS lists ``fork`` but it is unsafe there with these libraries; Windows has none)."""
    return sys.platform.startswith("linux")


def run_forked(
    fn: Callable[[int], Any],
    needs: Sequence[Sequence[int]],
    workers: int,
    on_result: Callable[[int, Any], None],
    initializer: Optional[Callable[..., None]] = None,
    initargs: tuple = (),
    poll: Optional[Callable[[], None]] = None,
) -> None:
    """Run ``fn(i)`` for every task ``i`` on ``workers`` forked processes, each once the tasks
    in ``needs[i]`` are done. ``fn`` and what it reads are inherited through fork, so they
    need not pickle; results must. ``on_result(i, result)`` runs in the caller as each task
    ends and ``poll()`` about every 0.5 s. The first error (a process that dies, or an
    interrupt of the caller, included) is raised after the results of the tasks that ended
    are reported; the processes still running are terminated first.

    The processes run with one torch thread, set before ``initializer``: GNU OpenMP,
    PyTorch's CPU thread pool on Linux, hangs in the first parallel region of a process
    forked from one that had already run parallel regions, if the child asks for more
    than one thread (its pool's threads do not exist after ``fork``). ``fn`` must not raise
    the thread count either; the processes themselves are the parallelism. A task that is
    ready while no other task runs or is ready (everything left waits for it) runs in the
    caller instead, on all of its threads (``initializer`` is then run in the caller first,
    once).

    Raises:
        ValueError: ``needs`` names a task that is not listed before it.
    """
    for i, deps in enumerate(needs):
        if any(not 0 <= d < i for d in deps):
            raise ValueError(f"task {i} needs {list(deps)}: only tasks listed before it")
    pool = ProcessPoolExecutor(
        workers,
        mp_context=multiprocessing.get_context("fork"),
        initializer=_forked_init,
        initargs=(initializer, initargs),
    )
    error: Optional[BaseException] = None
    caller_ready = False
    try:
        done: set[int] = set()
        waiting, running = list(range(len(needs))), {}
        while (waiting or running) and error is None:
            ready = [i for i in waiting if all(d in done for d in needs[i])]
            if len(ready) == 1 and not running:  # alone: in the caller, whose threads are all usable
                if not caller_ready and initializer is not None:
                    initializer(*initargs)
                caller_ready = True
                waiting.remove(ready[0])
                on_result(ready[0], fn(ready[0]))
                done.add(ready[0])
                continue
            for i in ready:
                waiting.remove(i)
                running[pool.submit(fn, i)] = i
            finished, _ = wait(list(running), timeout=0.5, return_when=FIRST_COMPLETED)
            for f in finished:
                i = running.pop(f)
                if f.exception() is not None:
                    error = error or f.exception()
                else:
                    on_result(i, f.result())
                    done.add(i)
            if poll is not None:
                poll()
    except BaseException as e:  # an interrupt of the caller
        error = e
    finally:
        if error is not None:  # what still runs would write outputs a retry rebuilds
            for proc in list(getattr(pool, "_processes", {}).values()):
                proc.terminate()
        pool.shutdown(wait=True, cancel_futures=True)
    if error is not None:
        raise error


def _forked_init(initializer: Optional[Callable[..., None]], initargs: tuple) -> None:
    """A :func:`run_forked` process: one torch thread (see there), then the caller's setup."""
    import torch  # deferred: system.py stays importable without torch (machine facts, allocator setup)

    torch.set_num_threads(1)
    if initializer is not None:
        initializer(*initargs)


def _skip_reason() -> Optional[str]:
    """Why the allocator is left alone, or None when glibc's may be configured."""
    if os.environ.get(KEEP_MEMORY_ENV, "1") == "0":
        return f"left alone: {KEEP_MEMORY_ENV}=0"
    preload = os.environ.get("LD_PRELOAD", "")
    for name in OTHER_ALLOCATORS:
        if name in preload:
            return f"left alone: {name} preloaded"
    user = [k for k in GLIBC_ENV if k in os.environ]
    if user or "glibc.malloc" in os.environ.get("GLIBC_TUNABLES", ""):
        return f"left alone: set by the environment ({', '.join(user) or 'GLIBC_TUNABLES'})"
    if platform.system() != "Linux" or platform.libc_ver()[0] != "glibc":
        return f"left alone: not glibc on Linux ({platform.system()} {platform.libc_ver()[0] or 'unknown libc'})"
    return None


def keep_allocator_memory() -> str:
    """Make glibc's allocator keep working memory between calls (once per process; idempotent).

    With glibc's defaults, blocks above its (dynamic) mmap threshold get fresh pages from the
    kernel on every allocation and give them back on free, and the top of the heap is trimmed,
    so large temporaries of a CPU render are page-faulted in again on later calls (blocks above
    32 MiB still are with this setting). Each fault costs little on a warm host and much more on
    a freshly booted virtual machine, where each first touch of a page is slow. This
    sets :data:`GLIBC_SETTINGS` through ``mallopt``, the same effect as
    ``MALLOC_MMAP_THRESHOLD_=33554432 MALLOC_TRIM_THRESHOLD_=2147483647 MALLOC_TOP_PAD_=536870912``
    in the environment. The cost: memory freed after a peak stays with the process (its RSS
    does not shrink back), and the heap reserves address space 512 MiB at a time (which counts
    against the commit limit under ``vm.overcommit_memory=2``). It applies to the whole process
    that renders, e.g. a training loop rendering in its main process. Forked children
    (DataLoader workers) inherit the setting.

    The CPU render path calls this; it does nothing when ``HOGSA_KEEP_MEMORY=0``, when another
    allocator is preloaded (tcmalloc, jemalloc, mimalloc keep memory on their own), when the
    user configured glibc's allocator through its environment variables, or off glibc/Linux.

    Returns:
        What was done, as :func:`allocator_status` reports it.
    """
    global _status
    if _status is not None:
        return _status
    with _lock:
        if _status is not None:
            return _status
        reason = _skip_reason()
        if reason is None:
            try:
                libc = ctypes.CDLL("libc.so.6")
                failed = [k for k, (param, value) in GLIBC_SETTINGS.items() if libc.mallopt(param, value) != 1]
            except (OSError, AttributeError) as exc:
                reason = f"left alone: mallopt unavailable ({exc})"
            else:
                reason = f"glibc mallopt failed for {failed}" if failed else "glibc: keeps memory (mallopt)"
        _status = reason
        return _status


def allocator_status() -> str:
    """What :func:`keep_allocator_memory` did in this process ("not configured yet" before its first call)."""
    return _status if _status is not None else "not configured yet"


def process_slot(env: Optional[dict[str, str]] = None) -> tuple[int, int]:
    """``(rank, world_size)`` of this process: torchrun's ``RANK`` / ``WORLD_SIZE``, srun's
    ``SLURM_PROCID`` / ``SLURM_STEP_NUM_TASKS`` (an sbatch script itself, with only
    ``SLURM_NTASKS``, is one process); ``(0, 1)`` alone."""
    env = dict(os.environ) if env is None else env
    if "WORLD_SIZE" in env:
        return int(env.get("RANK", "0")), int(env["WORLD_SIZE"])
    if "SLURM_PROCID" in env and "SLURM_STEP_NUM_TASKS" in env:
        return int(env["SLURM_PROCID"]), int(env["SLURM_STEP_NUM_TASKS"])
    return 0, 1


def rank_device(device: str, env: Optional[dict[str, str]] = None) -> str:
    """``cuda`` made ``cuda:LOCAL_RANK`` (torchrun) or ``cuda:SLURM_LOCALID`` (srun) for a process
    that is one of several on a node; any other device unchanged."""
    env = dict(os.environ) if env is None else env
    local = env.get("LOCAL_RANK", env.get("SLURM_LOCALID"))
    return f"cuda:{int(local)}" if device == "cuda" and local is not None else device
