"""End-to-end throughput of the synthetic loader, per stage, next to the real ARCTIC loader.

Two measurements in one run, each through a ``torch.utils.data.DataLoader`` with the
default collate and the same batch size:

1. **synthetic** — :class:`hogsa_loader.sample.dataset.HOGSADataset` over ``--bundle``
   and ``--data`` (pose sampling → [POM] → one batched render into the crop → [SRM] →
   background compositing → ARCTIC augmentation + targets). Images/s are counted over
   ``--seconds`` of wall clock after ``--warmup`` batches (model loading, background pool,
   first-call overheads). Per-stage seconds are read from the dataset's ``stats``
   (``pose``, ``pom``, ``render``, ``srm``, ``composite``, ``targets``; CUDA stages are
   synchronised) together with the attempted / kept / dropped counts. With
   ``--num-workers 0`` (the only choice on CUDA: workers never touch CUDA) the stages are
   those of the timed run. With CPU workers, ``timed_worker_stats`` / ``timed_worker_stages``
   are the workers' own counts and seconds over the timed window (from the dataset's
   shared-memory table, :meth:`~hogsa_loader.sample.dataset.HOGSADataset.total_stats`;
   seconds summed over workers), and ``stats`` / ``stages`` come from a separate
   single-process pass of ``--stage-seconds``, which shows the stage costs without
   contention between workers.
2. **real** — :class:`hogsa_loader.sample.arctic_dataset.ArcticDataset` over
   ``--real-data`` (default ``--data``), split ``--real-split``: JPEG decode + blur + crop
   warp + augmentation + targets, the reference a training loop would otherwise run at
   (``real_loader_images_per_s``), plus a small single-process breakdown (read+decode vs
   the rest) in ``real_loader.stages_ms_per_image``.

Without ``--bundle`` only the real loader is measured (``images_per_s`` is null).

Usage::

    python benchmarks/throughput.py --bundle B --data ROOT --device cpu|cuda --seconds T --json OUT \\
        [--batch-size 8] [--srm/--no-srm] [--poses perturb|bank|online] [--num-workers 0] \\
        [--coco-root C] [--real-data ROOT2] [--real-seconds T2]

Memory (same conventions as ``benchmarks/_timing.py``): ``peak_memory_mb`` is
``torch.cuda.max_memory_allocated`` on CUDA, the process's
peak RSS (``resource.getrusage(RUSAGE_SELF).ru_maxrss``; DataLoader workers'
``RUSAGE_CHILDREN`` peak reported separately) on the CPU.
"""

from __future__ import annotations

import argparse
import json
import platform
import resource
import sys
import time
import warnings
from pathlib import Path
from typing import Any, Iterable, Optional

import torch
from torch.utils.data import DataLoader

from hogsa_loader.sample.arctic_dataset import ArcticDataset
from hogsa_loader.sample.config import with_options
from hogsa_loader.sample.dataset import HOGSADataset
from hogsa_loader.sample.synth import SynthStats
from hogsa_loader.system import available_cores

STAGES = ("pose", "pom", "render", "srm", "composite", "targets")


def device_name(device: str) -> str:
    """GPU name, or CPU model with core and torch thread counts."""
    if device.startswith("cuda"):
        return torch.cuda.get_device_name(torch.device(device))
    model = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo", "r", encoding="utf-8") as fh:
            for line in fh:
                if line.startswith("model name"):
                    model = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    n = available_cores()
    return f"{model} ({n} cores available, torch threads {torch.get_num_threads()})"


def peak_memory(device: str) -> dict[str, Any]:
    """Peak memory of this process (and of finished DataLoader workers on the CPU)."""
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    child = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024.0
    out: dict[str, Any] = {"cpu_rss_peak_mb": round(rss, 1), "workers_rss_peak_mb": round(child, 1)}
    if device.startswith("cuda"):
        out["peak_memory_mb"] = round(torch.cuda.max_memory_allocated() / 2**20, 1)
        out["memory"] = "torch.cuda.max_memory_allocated"
    else:
        out["peak_memory_mb"] = round(rss, 1)
        out["memory"] = "ru_maxrss (process peak RSS)"
    return out


def batch_len(batch: Any) -> int:
    """Samples in a default-collated ``(inputs, targets, meta_info)`` batch."""
    return int(batch[0]["img"].shape[0])


def warmup_batches(warmup: int, workers: int) -> int:
    """Batches to consume before the clock starts: at least two per DataLoader worker.

    Workers start together, so their first batches arrive in one burst; a clock started
    after one batch would count the rest of that burst as free (measured with stand-in
    workers of 1 img/s each: 8 workers read 10.3 img/s over 3 s instead of 8.0).
    """
    return max(int(warmup), 2 * int(workers))


def timed_iteration(
    batches: Iterable[Any], seconds: float, warmup: int, on_warm: Optional[Any] = None, sync: Any = None
) -> dict[str, Any]:
    """Consume ``batches`` for ``seconds`` after ``warmup`` batches; count images.

    Args:
        batches: iterable of collated batches.
        seconds: timed duration (the batch running when it ends is finished and counted).
        warmup: batches consumed before the clock starts.
        on_warm: called once when the clock starts (e.g. reset counters).
        sync: called before reading the clock (CUDA synchronise).
    """
    sync = sync or (lambda: None)
    it = iter(batches)
    t0 = time.perf_counter()
    for _ in range(warmup):
        if next(it, None) is None:  # (fewer batches than the warm-up: nothing left to time)
            break
    sync()
    warm_s = time.perf_counter() - t0
    if on_warm is not None:
        on_warm()
    n_img = n_batch = 0
    start = time.perf_counter()
    elapsed = 0.0
    for batch in it:
        n_img += batch_len(batch)
        n_batch += 1
        sync()
        elapsed = time.perf_counter() - start
        if elapsed >= seconds:
            break
    return {
        "images": n_img,
        "batches": n_batch,
        "seconds": round(elapsed, 3),
        "warmup_seconds": round(warm_s, 3),
        "images_per_s": (n_img / elapsed) if elapsed > 0 else None,
    }


def stage_report(stats: Any) -> dict[str, Any]:
    """Per-stage seconds, ms per kept image and share of the stage total."""
    secs = {k: float(stats.seconds.get(k, 0.0)) for k in STAGES}
    total = sum(secs.values())
    kept = max(1, int(stats.kept))
    return {
        k: {
            "seconds": round(v, 4),
            "ms_per_image": round(1000.0 * v / kept, 3),
            "fraction": round(v / total, 4) if total > 0 else 0.0,
        }
        for k, v in secs.items()
    }


# --------------------------------------------------------------------------------------


def make_synth(args: argparse.Namespace, device: str):
    kw: dict[str, Any] = dict(
        coco_root=args.coco_root,
        coco_ann=args.coco_ann,
        srm=args.srm,
        device=device,
        batch_size=args.render_batch or args.batch_size,
        seed=args.seed,
    )
    if args.background_folder:
        kw["background_folder"] = args.background_folder
    if args.poses:
        kw["poses"] = args.poses
    if args.render_size:
        kw["render_size"] = args.render_size
    return HOGSADataset(args.bundle, args.data, with_options(**kw))


def bench_synthetic(args: argparse.Namespace, device: str) -> dict[str, Any]:
    ds = make_synth(args, device)
    cuda = device.startswith("cuda")
    workers = 0 if cuda else args.num_workers
    if cuda and args.num_workers:
        print("note: CUDA rendering runs in the main process; --num-workers ignored", file=sys.stderr)
    if cuda:
        torch.cuda.reset_peak_memory_stats()
    sync = (lambda: torch.cuda.synchronize()) if cuda else None
    loader = DataLoader(
        ds,
        batch_size=args.batch_size,
        num_workers=workers,
        persistent_workers=False,
        worker_init_fn=_worker_init if workers else None,
    )
    at_warm: dict[str, Any] = {}

    def on_warm() -> None:
        ds.stats.reset()
        at_warm["workers"] = ds.worker_stats().to_vector()

    res = timed_iteration(loader, args.seconds, warmup_batches(args.warmup, workers), on_warm=on_warm, sync=sync)
    out: dict[str, Any] = {"timed": res, "num_workers": workers}
    if workers and "workers" in at_warm:
        timed = SynthStats.from_vector(ds.worker_stats().to_vector() - at_warm["workers"])
        out["timed_worker_stats"] = timed.as_dict()
        out["timed_worker_stages"] = stage_report(timed)
    if workers == 0:
        out["stats"] = ds.stats.as_dict()
        out["stages"] = stage_report(ds.stats)
        out["stages_from"] = "timed run (main process)"
    else:
        prof = make_synth(args, device)
        loader0 = DataLoader(prof, batch_size=args.batch_size, num_workers=0)
        out["stage_pass"] = timed_iteration(loader0, args.stage_seconds, 1, on_warm=prof.stats.reset)
        out["stats"] = prof.stats.as_dict()
        out["stages"] = stage_report(prof.stats)
        out["stages_from"] = f"separate main-process pass of {args.stage_seconds} s"
        ds = prof
    keys = list(getattr(ds, "keys", []))
    out["gaussians"] = {f"{s}/{o}": int(ds.bundle.hogs[(s, o)].num_gaussians) for s, o in keys}
    pipe = getattr(ds, "_pipe", None)
    models = getattr(pipe, "_models", {}) if pipe is not None else {}
    out["gaussians_loaded"] = {f"{k[0]}/{k[1]}": int(getattr(m, "num_gaussians", 0)) for k, m in models.items()}
    out["render_backend"] = getattr(pipe, "last_backend", None)  # what "auto" resolved to (profile pass)
    out["render_size"] = int(ds.render_size)
    out["render_batch"] = int(ds.batch_size)
    bg = getattr(pipe, "backgrounds", None) if pipe is not None else None
    out["backgrounds"] = repr(bg) if bg is not None else None
    return out


def _worker_init(_: int) -> None:
    torch.set_num_threads(1)


def bench_real(args: argparse.Namespace) -> dict[str, Any]:
    root = args.real_data or args.data
    ds = ArcticDataset(root, split=args.real_split, seed=args.seed)
    g = torch.Generator().manual_seed(args.seed)
    loader = DataLoader(
        ds,
        batch_size=args.batch_size,
        shuffle=True,
        generator=g,
        num_workers=args.num_workers,
        worker_init_fn=_worker_init if args.num_workers else None,
    )
    res = timed_iteration(loader, args.real_seconds or args.seconds, warmup_batches(args.warmup, args.num_workers))
    # single-process breakdown: read + JPEG decode vs blur/warp/augment/targets
    n = min(len(ds), args.real_profile_items)
    idx = torch.randperm(len(ds), generator=torch.Generator().manual_seed(args.seed + 1))[:n].tolist()
    t_read = t_total = 0.0
    for i in idx:
        t0 = time.perf_counter()
        ds._read_image(ds.image_path(ds.imgnames[i]))
        t1 = time.perf_counter()
        ds[i]
        t2 = time.perf_counter()
        t_read += t1 - t0
        t_total += t2 - t1
    stages = {
        "read_decode": round(1000 * t_read / max(n, 1), 3),
        "blur_crop_augment_targets": round(1000 * (t_total - t_read) / max(n, 1), 3),
        "total_single_process": round(1000 * t_total / max(n, 1), 3),
    }
    img = ds._read_image(ds.image_path(ds.imgnames[idx[0]])) if n else None
    return {
        "timed": res,
        "data_root": str(Path(root).resolve()),
        "split": args.real_split,
        "num_images": len(ds),
        "num_workers": args.num_workers,
        "source_image_shape": None if img is None else list(img.shape),
        "stages_ms_per_image": stages,
        "profile_items": n,
        "missing_images_in_profile": len(set(ds.missing_image_paths)),
    }  # (workers' counts stay in the workers)


def parse_args(argv: Optional[list[str]] = None) -> argparse.Namespace:
    """The benchmark's settings from command-line flags."""
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--bundle", default=None, help="bundle folder; omit to measure the real loader only")
    p.add_argument("--data", required=True, help="ARCTIC(-format) data root")
    p.add_argument("--device", default="cpu", help="cpu or cuda")
    p.add_argument("--seconds", type=float, default=30.0, help="timed seconds of the synthetic loader")
    p.add_argument("--json", required=True, help="output JSON")
    p.add_argument("--batch-size", type=int, default=8, help="DataLoader batch size")
    p.add_argument("--render-batch", type=int, default=None, help="samples per render call (default: batch size)")
    p.add_argument("--srm", action=argparse.BooleanOptionalAction, default=False, help="apply the bundle's SRM")
    p.add_argument("--poses", default=None, help="pose source (perturb, bank, online); default: the loader's")
    p.add_argument("--num-workers", type=int, default=0, help="DataLoader workers (CPU only for the synthetic part)")
    p.add_argument("--warmup", type=int, default=1, help="batches before the clock starts")
    p.add_argument("--stage-seconds", type=float, default=20.0, help="main-process stage pass when workers > 0")
    p.add_argument("--coco-root", default=None)
    p.add_argument("--coco-ann", default=None)
    p.add_argument("--background-folder", default=None)
    p.add_argument("--render-size", type=int, default=None)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--threads", type=int, default=0, help="torch threads in the main process (0 = default)")
    p.add_argument("--real-data", default=None, help="data root of the real loader (default --data)")
    p.add_argument("--real-split", default="p1_train")
    p.add_argument("--real-seconds", type=float, default=None, help="timed seconds of the real loader")
    p.add_argument("--real-profile-items", type=int, default=40, help="items of the real single-process breakdown")
    p.add_argument("--no-real", action="store_true", help="skip the real loader")
    return p.parse_args(argv)


def main(argv: Optional[list[str]] = None) -> int:
    args = parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)
    device = args.device
    if device.startswith("cuda") and not torch.cuda.is_available():
        print("error: --device cuda but CUDA is not available", file=sys.stderr)
        return 2
    warnings.filterwarnings("once")

    report: dict[str, Any] = {
        "benchmark": "throughput",
        "device": device_name(device),
        "device_kind": device,
        "torch": torch.__version__,
        "batch_size": args.batch_size,
        "seconds_requested": args.seconds,
        "config": {k: v for k, v in vars(args).items() if k != "json"},
        "time_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
    }
    if args.bundle:
        syn = bench_synthetic(args, device)
        report["images_per_s"] = syn["timed"]["images_per_s"]
        report["stages"] = syn["stages"]
        report["dropped"] = syn["stats"]["dropped"]
        report["attempted"] = syn["stats"]["attempted"]
        report["kept"] = syn["stats"]["kept"]
        report["gaussians"] = syn["gaussians"]
        report["synthetic"] = syn
    else:
        report["images_per_s"] = None
        report["stages"] = None
    report.update(peak_memory(device))
    if not args.no_real:
        real = bench_real(args)
        report["real_loader_images_per_s"] = real["timed"]["images_per_s"]
        report["real_loader"] = real
    else:
        report["real_loader_images_per_s"] = None
    report["memory_after_real"] = peak_memory(device)
    Path(args.json).parent.mkdir(parents=True, exist_ok=True)
    with open(args.json, "w", encoding="utf-8") as fh:
        json.dump(report, fh, indent=1)
    syn_s = "n/a" if report["images_per_s"] is None else f"{report['images_per_s']:.2f}"
    real_s = "n/a" if report["real_loader_images_per_s"] is None else f"{report['real_loader_images_per_s']:.2f}"
    print(f"synthetic: {syn_s} img/s   real ARCTIC loader: {real_s} img/s   ({report['device']})")
    if report.get("stages"):
        print("stages (ms/img): " + ", ".join(f"{k} {v['ms_per_image']:.1f}" for k, v in report["stages"].items()))
    print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
