"""The GPU path in one command: CUDA tests, the synthetic stream, a fine-tune with and without
the synthetic half, and HOGS training steps, on one GPU, in a few minutes.

Every step is timed and recorded, and a failing step does not stop the others:

1. ``env`` — torch, CUDA, the device; gsplat's extension built (JIT on first use) and timed.
2. ``cuda_tests`` — ``pytest -m cuda`` on the renderer and MANO tests (gsplat against the
   PyTorch rasteriser, CUDA against CPU).
3. ``world`` / ``bundle`` — the ``tiny`` generated world (256-px crops) and an untrained bundle
   of one (subject, object) with ``--gaussians-per-face`` Gaussians per face and an untrained
   SRM (same architecture and cost as a trained one); backgrounds: the demo's photographs.
4. ``stream`` — :class:`~hogsa_loader.sample.dataset.HOGSADataset` on the device at
   ``--render-size`` with the SRM, batches of ``--batch-size``, timed over ``--seconds``:
   images/s and seconds per stage (CUDA-synchronised).
5. ``finetune`` — ArcticNet-SF (``--backbone``, patches of ``--img-res``) trained with AdamW
   for ``--steps`` timed steps on real batches of ``--batch-size`` alone, then on the same
   batch size with half of it synthetic (``MixedLoader``, rendered in this process): steps/s,
   peak GPU memory, and how much the synthetic half slows a step.
6. ``hogs_train`` — ``hogsa train hogs`` on the world's training pair with the gsplat
   backend for ``--hogs-iters`` steps: iterations/s from the run's own timings.

Usage::

    python benchmarks/gpu_check.py --out runs/gpu_check            # on a CUDA machine (~8 min)
    python benchmarks/gpu_check.py --out /tmp/gc --dry-run         # the same steps on the CPU, tiny sizes

Writes ``gpu_check.json`` (every step's figures, errors and seconds) and prints a table.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
import traceback
from pathlib import Path
from typing import Any, Callable, Optional

import torch

ROOT = Path(__file__).resolve().parents[1]
CUDA_TEST_FILES = ("tests/test_render_api.py", "tests/test_render_gaussians.py", "tests/test_mano_layer.py")


def _sync(device: str) -> None:
    if device.startswith("cuda"):
        torch.cuda.synchronize()


def step_env(args: argparse.Namespace, ctx: dict[str, Any]) -> dict[str, Any]:
    """Versions, the device, and the first gsplat render (its JIT build)."""
    out: dict[str, Any] = {"torch": torch.__version__, "cuda": torch.version.cuda, "device": args.device}
    if args.device.startswith("cuda"):
        out["device_name"] = torch.cuda.get_device_name(0)
        out["memory_gib"] = round(torch.cuda.get_device_properties(0).total_memory / 2**30, 1)
    from hogsa_loader.render import render

    t0 = time.perf_counter()
    n = 64
    g = torch.Generator().manual_seed(0)
    means = (torch.rand(1, n, 3, generator=g) - 0.5) * 0.2 + torch.tensor([0.0, 0.0, 0.6])
    quats = torch.nn.functional.normalize(torch.randn(1, n, 4, generator=g), dim=-1)
    scales = torch.full((1, n, 3), 0.01)
    opac, cols = torch.full((1, n), 0.8), torch.rand(1, n, 3, generator=g)
    K = torch.tensor([[[[100.0, 0.0, 32.0], [0.0, 100.0, 32.0], [0.0, 0.0, 1.0]]]])  # (B, C, 3, 3)
    tensors = [t.to(args.device) for t in (means, quats, scales, opac, cols, torch.eye(4)[None, None], K)]
    backend = "gsplat" if args.device.startswith("cuda") else "torch"
    res = render(*tensors, width=64, height=64, backend=backend)
    _sync(args.device)
    out["first_render_backend"] = backend
    out["first_render_s"] = round(time.perf_counter() - t0, 2)
    out["first_render_alpha_mean"] = float(res.alpha.mean())
    return out


def step_cuda_tests(args: argparse.Namespace, ctx: dict[str, Any]) -> dict[str, Any]:
    """``pytest -m cuda`` on the CUDA comparisons (collected only, in a dry run)."""
    cmd = [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-m", "cuda", *CUDA_TEST_FILES]
    if args.dry_run:
        cmd.append("--collect-only")
    run = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=args.test_timeout)
    lines = [ln for ln in run.stdout.splitlines() if ln.strip()]
    failed = [ln for ln in lines if ln.startswith("FAILED")]
    return {"returncode": run.returncode, "summary": lines[-1] if lines else "", "failed": failed}


def step_world(args: argparse.Namespace, ctx: dict[str, Any]) -> dict[str, Any]:
    """The ``tiny`` world (reused when present)."""
    from hogsa_world import generate_world, get_preset

    world = Path(args.out) / "world"
    data = world / "arctic_data" / "data"
    if not (data / "splits").is_dir():
        generate_world(world, get_preset("tiny"), seed=0, progress=False, log=lambda m: None)
    ctx["world"] = world
    return {"world": str(world)}


def step_bundle(args: argparse.Namespace, ctx: dict[str, Any]) -> dict[str, Any]:
    """An untrained bundle of the world's training pair with an untrained SRM."""
    from hogsa_loader.models.bundle import load_bundle
    from hogsa_loader.models.srm import SRM
    from hogsa_loader.models.srm.io import save_srm
    from hogsa_loader.view.pictures import demo_photographs
    from hogsa_world.untrained import write_untrained_bundle

    out = Path(args.out) / "bundle_src"
    srm = out / "srm"
    if not (srm / "manifest.json").is_file():
        save_srm(SRM(), srm)
    bundle = out / "bundle"
    if not bundle.is_dir():
        write_untrained_bundle(ctx["world"], out, srm=srm, gaussians_per_face=args.gaussians_per_face)
    ctx["bundle"] = bundle
    ctx["backgrounds"] = demo_photographs(Path(args.out) / "backgrounds")
    b = load_bundle(bundle, ctx["world"])
    return {"bundle": str(bundle), "models": [list(k) for k in b.keys]}


def _synthetic(args: argparse.Namespace, ctx: dict[str, Any], seed: int = 0) -> Any:
    from hogsa_loader.sample.augment import ArcticConfig
    from hogsa_loader.sample.config import LoaderConfig, with_options
    from hogsa_loader.sample.dataset import HOGSADataset

    config = with_options(
        LoaderConfig(),
        arctic=ArcticConfig(img_res=args.img_res),
        device=args.device,
        batch_size=args.batch_size,
        seed=seed,
        srm=True,
        render_size=args.render_size,
        background_folder=str(ctx["backgrounds"]),
    )
    return HOGSADataset(ctx["bundle"], ctx["world"], config)


def step_stream(args: argparse.Namespace, ctx: dict[str, Any]) -> dict[str, Any]:
    """Synthetic images/s on the device with the SRM, and seconds per stage."""
    ds = _synthetic(args, ctx)
    it = iter(ds)
    for _ in range(args.batch_size):  # warm-up: models, backgrounds, first kernels
        next(it)
    ds.stats.reset()
    _sync(args.device)
    t0, n = time.perf_counter(), 0
    while time.perf_counter() - t0 < args.seconds:
        next(it)
        n += 1
    _sync(args.device)
    dt = time.perf_counter() - t0
    st = ds.stats
    per_image = {k: round(1e3 * v / max(st.attempted, 1), 2) for k, v in st.seconds.items() if v}
    ctx["gaussians"] = getattr(ds, "num_gaussians", None)
    return {
        "images_per_s": round(n / dt, 2),
        "images": n,
        "seconds": round(dt, 1),
        "ms_per_image_by_stage": per_image,
        "kept": st.kept,
        "dropped": st.num_dropped,
        "render_size": ds.render_size,
    }


def _finetune(args: argparse.Namespace, ctx: dict[str, Any], batches: Any, steps: int) -> dict[str, Any]:
    from hogsa_loader.assets.arctic import ArcticRoot
    from hogsa_loader.baselines.arcticnet_sf import ArcticNetSF
    from hogsa_loader.baselines.engine import BodyLayers, training_step

    layers = BodyLayers.from_root(ArcticRoot(ctx["world"])).to(args.device)
    torch.manual_seed(0)
    model = ArcticNetSF(args.backbone, layers.mano_r, layers.mano_l, layers.objects, img_res=args.img_res)
    model = model.to(args.device)
    opt = torch.optim.AdamW(model.parameters(), lr=1e-5)
    if args.device.startswith("cuda"):
        torch.cuda.reset_peak_memory_stats()
    it = iter(batches)
    warm = 3
    times, sizes = [], []
    for i in range(warm + steps):
        _sync(args.device)
        t0 = time.perf_counter()
        batch = next(it)
        training_step(model, batch, layers, opt, args.img_res, device=args.device)
        _sync(args.device)
        if i >= warm:
            times.append(time.perf_counter() - t0)
            sizes.append(int(batch[0]["img"].shape[0]))
    out = {"steps_per_s": round(len(times) / sum(times), 3), "batch": sizes[0], "steps": len(times)}
    if args.device.startswith("cuda"):
        out["peak_memory_gib"] = round(torch.cuda.max_memory_allocated() / 2**30, 2)
    return out


def _forever(loader: Any):
    while True:
        yield from loader


def step_finetune(args: argparse.Namespace, ctx: dict[str, Any]) -> dict[str, Any]:
    """Steps/s on real batches alone, then with half of each batch synthetic."""
    from torch.utils.data import DataLoader

    from hogsa_loader.sample.arctic_dataset import ArcticDataset
    from hogsa_loader.sample.augment import ArcticConfig
    from hogsa_loader.sample.mixing import MixedLoader

    real = ArcticDataset(ctx["world"], split="p1_train", config=ArcticConfig(img_res=args.img_res), seed=0)
    workers = min(8, os.cpu_count() or 1) if not args.dry_run else 0
    loader = DataLoader(
        real, batch_size=args.batch_size, shuffle=True, drop_last=True, num_workers=workers, pin_memory=True
    )
    alone = _finetune(args, ctx, _forever(loader), args.steps)
    mixed = MixedLoader(loader, _synthetic(args, ctx, seed=1), ratio=0.5)
    half = _finetune(args, ctx, _forever(mixed), args.steps)
    slowdown = alone["steps_per_s"] / half["steps_per_s"] - 1.0
    return {"real": alone, "real_plus_synthetic": half, "slowdown": round(slowdown, 3)}


def step_hogs_train(args: argparse.Namespace, ctx: dict[str, Any]) -> dict[str, Any]:
    """``hogsa train hogs`` for ``--hogs-iters`` steps; iterations/s from the run's metrics."""
    run = Path(args.out) / "hogs_run"
    data = Path(ctx["world"]) / "arctic_data" / "data"
    cmd = [sys.executable, "-m", "hogsa_loader.cli.main", "train", "hogs", "--data", str(data)]
    cmd += ["--subject", "s01", "--object", "box", "--out", str(run), "--device", args.device]
    cmd += ["--optim-iters", str(args.hogs_iters), "--overwrite", "--quiet"]
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=args.test_timeout)
    wall = time.perf_counter() - t0
    if proc.returncode:
        raise RuntimeError(f"train hogs exited {proc.returncode}: {proc.stderr[-1500:]}")
    metrics = json.loads((run / "metrics.json").read_text())
    train_s = metrics.get("timings", {}).get("train_s")
    return {
        "iters": args.hogs_iters,
        "train_s": train_s,
        "iters_per_s": round(args.hogs_iters / train_s, 2) if train_s else None,
        "wall_s": round(wall, 1),
        "psnr": metrics.get("psnr"),
    }


STEPS: dict[str, Callable[[argparse.Namespace, dict[str, Any]], dict[str, Any]]] = {
    "env": step_env,
    "cuda_tests": step_cuda_tests,
    "world": step_world,
    "bundle": step_bundle,
    "stream": step_stream,
    "finetune": step_finetune,
    "hogs_train": step_hogs_train,
}


def table(results: dict[str, dict[str, Any]]) -> str:
    """The figures a reader compares with the goals, one line each."""
    r = {k: v.get("result", {}) for k, v in results.items()}
    ft = r.get("finetune", {})
    rows = [
        ("device", r.get("env", {}).get("device_name", r.get("env", {}).get("device"))),
        ("gsplat first render (build) s", r.get("env", {}).get("first_render_s")),
        ("CUDA tests", r.get("cuda_tests", {}).get("summary")),
        ("stream images/s with SRM", r.get("stream", {}).get("images_per_s")),
        ("stream ms/image by stage", r.get("stream", {}).get("ms_per_image_by_stage")),
        ("fine-tune steps/s, real", ft.get("real", {}).get("steps_per_s")),
        ("fine-tune steps/s, half synthetic", ft.get("real_plus_synthetic", {}).get("steps_per_s")),
        ("synthetic half slows a step by", ft.get("slowdown")),
        (
            "fine-tune peak GiB (real / mixed)",
            (ft.get("real", {}).get("peak_memory_gib"), ft.get("real_plus_synthetic", {}).get("peak_memory_gib")),
        ),
        ("HOGS iterations/s", r.get("hogs_train", {}).get("iters_per_s")),
    ]
    errors = [f"{k}: {v['error'].splitlines()[-1][:200]}" for k, v in results.items() if v.get("error")]
    lines = ["| figure | value |", "|---|---|", *(f"| {a} | {b} |" for a, b in rows)]
    return "\n".join(lines + ([""] + ["errors:"] + errors if errors else [])) + "\n"


def main(argv: Optional[list[str]] = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--out", required=True, help="results and scratch folder")
    p.add_argument("--dry-run", action="store_true", help="the same steps on the CPU at tiny sizes")
    p.add_argument("--steps", type=int, default=None, help="timed fine-tune steps per arm (default 100; dry 2)")
    p.add_argument("--seconds", type=float, default=None, help="timed seconds of the stream (default 30; dry 5)")
    p.add_argument("--batch-size", type=int, default=None, help="default 64 (dry 4)")
    p.add_argument("--img-res", type=int, default=None, help="patch side (default 224; dry 64)")
    p.add_argument("--render-size", type=int, default=None, help="render side (default 224; dry 64)")
    p.add_argument("--backbone", default=None, choices=["resnet18", "resnet50"], help="default resnet50 (dry resnet18)")
    p.add_argument("--gaussians-per-face", type=int, default=4)
    p.add_argument("--hogs-iters", type=int, default=None, help="default 300 (dry 3)")
    p.add_argument("--test-timeout", type=int, default=240, help="seconds for the CUDA tests and the HOGS run")
    p.add_argument("--only", default=None, help="comma-separated steps to run (the ones they need run too)")
    args = p.parse_args(argv)
    dry = args.dry_run
    defaults = dict(steps=(2, 100), seconds=(5.0, 30.0), batch_size=(4, 64), img_res=(64, 224))
    defaults.update(render_size=(64, 224), backbone=("resnet18", "resnet50"), hogs_iters=(3, 300))
    for name, (small, full) in defaults.items():
        if getattr(args, name) is None:
            setattr(args, name, small if dry else full)
    args.device = "cpu" if dry else "cuda"
    if not dry and not torch.cuda.is_available():
        print("gpu_check: no CUDA device (use --dry-run on the CPU)", file=sys.stderr)
        return 2
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    wanted = set(STEPS) if not args.only else {"env", "world", "bundle", *args.only.split(",")}
    results: dict[str, dict[str, Any]] = {}
    ctx: dict[str, Any] = {}
    for name, fn in STEPS.items():
        if name not in wanted:
            continue
        print(f"[gpu_check] {name} ...", flush=True)
        t0 = time.perf_counter()
        try:
            results[name] = {"result": fn(args, ctx)}
        except Exception:  # noqa: BLE001 - every step is reported, none stops the others
            results[name] = {"error": traceback.format_exc()}
        results[name]["seconds"] = round(time.perf_counter() - t0, 1)
        print(f"[gpu_check] {name}: {results[name]['seconds']} s {'FAILED' if 'error' in results[name] else 'ok'}")
        report = {"dry_run": dry, "config": {k: v for k, v in vars(args).items()}, "steps": results}
        (out / "gpu_check.json").write_text(json.dumps(report, indent=1, default=str))
    print(table(results))
    return 1 if any("error" in v for v in results.values()) else 0


if __name__ == "__main__":
    sys.exit(main())
