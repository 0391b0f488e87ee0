"""Facts about the machine the code runs on."""

from __future__ import annotations

import os

__all__ = ["available_cores"]


def available_cores() -> int:
    """CPU cores this process may run on: its affinity mask where the OS has one
    (``os.cpu_count()`` counts every core of the host, e.g. 64 inside a 2-core container)."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
