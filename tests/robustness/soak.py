"""Soak run: many synthetic samples through ``wrap_train_loader`` with worker processes.

A real ``p1_train`` loader is wrapped with synthetic samples rendered by DataLoader workers
(:func:`~hogsa_loader.integrations.arctic.wrap_train_loader`, ``num_workers``) and iterated
until ``--samples`` synthetic samples have been yielded. A sampler thread records the
resident memory (RSS) of the main process and of every worker over time; the run reports
whether memory stays flat after warm-up, every dropped sample by reason (the workers'
counters, :meth:`~hogsa_loader.sample.dataset.HOGSADataset.total_stats`), and whether any
worker died or was replaced (their process ids are checked at every sample of the RSS).

Usage::

    python tests/robustness/soak.py --out runs/soak                          # 10,000 samples, tiny world
    python tests/robustness/soak.py --out /tmp/soak --samples 500             # a short check
    python tests/robustness/soak.py --out runs/soak_real --data ./data --bundle bundle/

Without ``--data``/``--bundle`` a tiny world and an untrained bundle are generated in
``OUT/setup`` (reused). Writes ``soak.json`` (settings, RSS samples, the fit after warm-up,
drops, workers) and ``soak.png`` (RSS of the main process, the workers and their sum
against samples, warm-up shaded).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import threading
import time
from pathlib import Path
from typing import Any, Optional

import numpy as np
import torch
from torch.utils.data import DataLoader
from tqdm import tqdm

from hogsa_loader.cli.main import main as hogsa
from hogsa_loader.integrations.arctic import wrap_train_loader
from hogsa_loader.sample import is_synthetic
from hogsa_loader.sample.arctic_dataset import ArcticDataset
from hogsa_world.untrained import write_untrained_bundle

#: Share of the run treated as warm-up (caches, allocator pools, first renders).
WARMUP = 0.2
#: The flatness goal: RSS after warm-up stays within this fraction of its mean.
FLAT_TOLERANCE = 0.05


def rss_bytes(pid: int) -> Optional[int]:
    """Resident memory of a process (bytes; Linux ``/proc``), or None when it is gone."""
    try:
        with open(f"/proc/{pid}/status") as fh:
            for line in fh:
                if line.startswith("VmRSS:"):
                    return int(line.split()[1]) * 1024
    except (FileNotFoundError, ProcessLookupError, PermissionError):
        return None
    return None


def child_pids(pid: int) -> list[int]:
    """Direct children of ``pid`` (Linux ``/proc``)."""
    out: list[int] = []
    for entry in os.scandir("/proc"):
        if not entry.name.isdigit():
            continue
        try:
            with open(f"/proc/{entry.name}/stat") as fh:
                stat = fh.read()
        except OSError:
            continue
        fields = stat[stat.rfind(")") + 2 :].split()
        if len(fields) > 1 and int(fields[1]) == pid:
            out.append(int(entry.name))
    return sorted(out)


class RssSampler(threading.Thread):
    """Samples the RSS of this process and its children every ``period`` seconds."""

    def __init__(self, period: float, progress: "list[int]") -> None:
        super().__init__(daemon=True)
        self.period = period
        self.progress = progress
        self.rows: list[dict[str, Any]] = []
        self.worker_pids: set[int] = set()
        self._halt = threading.Event()
        self._t0 = time.perf_counter()

    def sample(self) -> None:
        me = os.getpid()
        kids = child_pids(me)
        self.worker_pids.update(kids)
        workers = [rss_bytes(p) or 0 for p in kids]
        self.rows.append(
            {
                "t": time.perf_counter() - self._t0,
                "samples": self.progress[0],
                "main": rss_bytes(me) or 0,
                "workers": int(sum(workers)),
                "n_workers": len(kids),
            }
        )

    def run(self) -> None:
        while not self._halt.wait(self.period):
            self.sample()

    def stop(self) -> None:
        self._halt.set()
        self.join()
        self.sample()


def flatness(rows: list[dict[str, Any]], total: int) -> dict[str, Any]:
    """Fit of total RSS against samples after warm-up: slope and spread relative to the mean."""
    after = [r for r in rows if r["samples"] >= WARMUP * total]
    if len(after) < 3:
        return {"points": len(after)}
    x = np.array([r["samples"] for r in after], dtype=float)
    y = np.array([r["main"] + r["workers"] for r in after], dtype=float)
    slope, intercept = np.polyfit(x, y, 1) if np.ptp(x) > 0 else (0.0, float(y.mean()))
    mean = float(y.mean())
    return {
        "points": len(after),
        "mean_mib": mean / 2**20,
        "min_mib": float(y.min()) / 2**20,
        "max_mib": float(y.max()) / 2**20,
        "spread": float(np.ptp(y)) / mean,
        "slope_mib_per_1000": float(slope) * 1000 / 2**20,
        "drift_over_run": float(slope) * float(np.ptp(x)) / mean,
        "flat": bool(np.ptp(y) / mean <= FLAT_TOLERANCE),
    }


def plot(rows: list[dict[str, Any]], total: int, path: Path, title: str) -> None:
    import matplotlib  # deferred: the Agg backend is chosen before pyplot loads

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # deferred: after matplotlib.use

    x = np.array([r["samples"] for r in rows])
    main = np.array([r["main"] for r in rows]) / 2**20
    workers = np.array([r["workers"] for r in rows]) / 2**20
    fig, ax = plt.subplots(figsize=(9, 4.5))
    ax.axvspan(0, WARMUP * total, color="0.9", label="warm-up")
    ax.plot(x, main + workers, label="main + workers", lw=2)
    ax.plot(x, main, label="main process")
    ax.plot(x, workers, label="workers (sum)")
    ax.set_xlabel("synthetic samples yielded")
    ax.set_ylabel("RSS (MiB)")
    ax.set_ylim(bottom=0)
    ax.set_title(title, fontsize=10)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def setup(out: Path, data: Optional[str], bundle: Optional[str]) -> tuple[Path, Path]:
    if (data is None) != (bundle is None):
        raise SystemExit("soak: error: --data and --bundle go together")
    if data is not None:
        return Path(data), Path(bundle)  # type: ignore[arg-type]
    world, made = out / "setup" / "world", out / "setup" / "untrained"
    if not (world / "arctic_data" / "data" / "meta" / "hogsa_world.json").is_file():
        print(f"[soak] tiny world -> {world}", flush=True)
        assert hogsa(["world", "--out", str(world), "--preset", "tiny", "--seed", "0", "--quiet"]) == 0
    if not (made / "bundle" / "manifest.json").is_file():
        print(f"[soak] untrained bundle -> {made / 'bundle'}", flush=True)
        write_untrained_bundle(world, made)
    return world, made / "bundle"


def main(argv: Optional[list[str]] = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--out", default="runs/soak", help="results folder")
    p.add_argument("--samples", type=int, default=10_000, help="synthetic samples to draw")
    p.add_argument("--workers", type=int, default=2, help="synthetic DataLoader workers")
    p.add_argument("--batch-size", type=int, default=16, help="real loader batch (half of it synthetic)")
    p.add_argument("--render-size", type=int, default=160, help="side of the rendered crop")
    p.add_argument("--period", type=float, default=2.0, help="seconds between RSS samples")
    p.add_argument("--data", default=None, help="ARCTIC(-format) data root (default: a generated tiny world)")
    p.add_argument("--bundle", default=None, help="bundle built on --data (default: an untrained one)")
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args(argv)
    if args.samples < 10 or args.workers < 1 or args.batch_size < 2 or args.period <= 0 or args.render_size < 32:
        p.error("--samples >= 10, --workers >= 1, --batch-size >= 2, --period > 0 and --render-size >= 32 needed")
    torch.set_num_threads(1)
    out = Path(args.out).resolve()
    out.mkdir(parents=True, exist_ok=True)
    data, bundle = setup(out, args.data, args.bundle)
    real = DataLoader(
        ArcticDataset(data, "p1_train", seed=args.seed),
        batch_size=args.batch_size,
        shuffle=True,
        generator=torch.Generator().manual_seed(args.seed),
    )
    mixed = wrap_train_loader(
        real, bundle, ratio=0.5, num_workers=args.workers, seed=args.seed, render_size=args.render_size, batch_size=8
    )
    syn_ds = mixed.synthetic.dataset  # the HOGSADataset behind the workers' DataLoader
    progress = [0]
    sampler = RssSampler(args.period, progress)
    sampler.sample()
    sampler.start()
    t0 = time.perf_counter()
    error: Optional[str] = None
    real_seen = 0
    bar = tqdm(total=args.samples, desc="soak", unit="sample", dynamic_ncols=True)
    try:
        while progress[0] < args.samples:
            before = progress[0]
            for _, _, meta in mixed:
                n = sum(is_synthetic(name) for name in meta["imgname"])
                progress[0] += n
                real_seen += len(meta["imgname"]) - n
                bar.update(n)
                if progress[0] >= args.samples:
                    break
            if progress[0] == before:
                raise RuntimeError("a whole pass of the mixed loader yielded no synthetic sample")
    except Exception as exc:  # noqa: BLE001 - a dead worker ends the soak; it is the result
        error = f"{type(exc).__name__}: {exc}"
    bar.close()
    seconds = time.perf_counter() - t0
    sampler.stop()
    stats = syn_ds.total_stats()
    workers_seen = sorted(sampler.worker_pids)
    fit = flatness(sampler.rows, args.samples)
    record = {
        "settings": vars(args),
        "data": str(data),
        "bundle": str(bundle),
        "seconds": round(seconds, 1),
        "synthetic_samples": progress[0],
        "real_samples": real_seen,
        "samples_per_s": progress[0] / seconds if seconds else None,
        "error": error,
        "attempted": stats.attempted,
        "kept": stats.kept,
        "dropped": stats.dropped,
        "num_dropped": stats.num_dropped,
        "worker_pids": workers_seen,
        "workers_replaced": max(0, len(workers_seen) - args.workers),
        "fit_after_warmup": fit,
        "rss": sampler.rows,
    }
    (out / "soak.json").write_text(json.dumps(record, indent=1))
    title = (
        f"{progress[0]} synthetic samples, {args.workers} workers, {seconds / 60:.0f} min; after warm-up: "
        f"spread {100 * fit.get('spread', float('nan')):.1f} %, slope {fit.get('slope_mib_per_1000', 0):.2f} "
        "MiB/1000 samples"
    )
    plot(sampler.rows, args.samples, out / "soak.png", title)
    print(f"[soak] {title}", flush=True)
    print(
        f"[soak] attempted {stats.attempted}, kept {stats.kept}, dropped {stats.num_dropped} "
        f"({ {k: v for k, v in stats.dropped.items() if v} }), worker pids {workers_seen}, error {error}",
        flush=True,
    )
    print(f"[soak] {out / 'soak.json'}, {out / 'soak.png'}", flush=True)
    if "flat" not in fit:
        print(f"[soak] too short to judge the memory: {fit['points']} RSS samples after warm-up", flush=True)
    return 0 if error is None and fit.get("flat", True) and record["workers_replaced"] == 0 else 1


if __name__ == "__main__":
    sys.exit(main())
