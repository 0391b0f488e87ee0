"""Shared timing helper of the renderer benchmarks (forward, forward+backward, peak memory)."""

from __future__ import annotations

import os
import resource
import statistics
import time
from typing import Any, Callable

import torch

from hogsa_loader.system import available_cores

PARAMS = ("means", "quats", "scales", "opacities", "colors")


def bench_threads() -> int:
    """Torch CPU threads of a benchmark: ``$BENCH_THREADS`` or :func:`available_cores`."""
    return int(os.environ.get("BENCH_THREADS", available_cores()))


def time_render(
    image_fn: Callable[[dict[str, Any]], torch.Tensor],
    scene: dict[str, Any],
    device: str,
    warmup: int,
    rep_fwd: int,
    rep_bwd: int,
) -> dict[str, Any]:
    """Median forward (no_grad) and forward + ``(img * scene["wrand"]).sum().backward()`` times.

    Page faults come in bursts: a fresh process's heap grows to its plateau over tens of
    calls (pages touched for the first time), and allocators that give memory back do so
    every so many calls; comparing allocators takes on the order of a hundred timed calls.

    Args:
        image_fn: scene dict -> rendered image tensor.
        scene: tensors keyed by :data:`PARAMS` plus ``wrand`` (random loss weights).
        device: "cpu" or "cuda".

    Returns:
        ``fwd_ms``, ``fwd_bwd_ms``, ``peak_mb``, ``base_mb`` (CPU only), ``memory`` (what
        the peak measures), ``fwd_faults`` / ``fwd_bwd_faults``: minor page faults of the
        process per timed call (``ru_minflt``; every thread of the process counts), and
        ``fwd_warmup_faults`` / ``fwd_bwd_warmup_faults``: the warm-up's faults in total
        (the process's first call included when ``warmup`` >= 1).
    """
    sync = torch.cuda.synchronize if device == "cuda" else (lambda: None)
    base_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0

    def fwd() -> None:
        with torch.no_grad():
            image_fn(scene)
        sync()

    def fwd_bwd() -> None:
        for k in PARAMS:
            scene[k] = scene[k].detach().requires_grad_(True)
        (image_fn(scene) * scene["wrand"]).sum().backward()
        sync()

    faults: dict[str, float] = {}
    warm: dict[str, int] = {}

    def minflt() -> int:
        return resource.getrusage(resource.RUSAGE_SELF).ru_minflt

    def timed(f: Callable[[], None], reps: int) -> float:
        f0 = minflt()
        for _ in range(warmup):
            f()
        warm[f.__name__] = minflt() - f0
        ts = []
        f0 = minflt()
        for _ in range(reps):
            t0 = time.perf_counter()
            f()
            ts.append(time.perf_counter() - t0)
        faults[f.__name__] = (minflt() - f0) / max(reps, 1)
        return 1000.0 * statistics.median(ts)

    if device == "cuda":
        torch.cuda.reset_peak_memory_stats()
    fwd_ms = timed(fwd, rep_fwd)
    fwd_bwd_ms = timed(fwd_bwd, rep_bwd)
    if device == "cuda":
        peak_mb, memory = torch.cuda.max_memory_allocated() / 2**20, "torch.cuda.max_memory_allocated"
    else:
        peak_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
        memory = "ru_maxrss (process peak RSS)"
    return {
        "fwd_ms": fwd_ms,
        "fwd_bwd_ms": fwd_bwd_ms,
        "peak_mb": peak_mb,
        "base_mb": base_mb if device == "cpu" else None,
        "memory": memory,
        "fwd_faults": faults["fwd"],
        "fwd_bwd_faults": faults["fwd_bwd"],
        "fwd_warmup_faults": warm["fwd"],
        "fwd_bwd_warmup_faults": warm["fwd_bwd"],
    }
