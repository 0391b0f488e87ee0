"""Speed / memory benchmark of the Gaussian rasteriser, through the entry point
``hogsa_loader.render.render`` (backend "torch" = hogsa_loader.render.gaussians on the CPU,
backend "gsplat" = gsplat's CUDA rasterization, unpacked).

Scene (as in the CPU rasteriser calibration): N Gaussians uniformly in a ball of radius
0.1 m at z = 0.6 m in front of the camera, random unit quaternions, scales log-U[1, 6] mm,
opacities U[0.3, 1], random RGB, focal length f = 2.1 W, principal point at the image
centre, black background.

Timings: median of ``--repeats`` runs after ``--warmup`` runs; "fwd" under
``torch.no_grad()``, "fwd_bwd" = forward + ``(img * Wrand).sum().backward()`` with
gradients for means, quats, scales, opacities and colours.

Memory: every (backend, N, resolution) row runs in its own child process. On CPU,
``peak_mb`` is that process's peak resident set size (``resource.getrusage(RUSAGE_SELF)
.ru_maxrss``, so it includes the Python / torch baseline, reported as ``base_mb``,
measured after imports and scene creation). On CUDA it is
``torch.cuda.max_memory_allocated()`` over the timed runs.

Allocators: ``--malloc`` runs every row once per allocator, side by side: "default" (glibc
as the library sets it on the first CPU render, keeping its working memory:
:func:`hogsa_loader.system.keep_allocator_memory`), "glibc" (glibc untouched,
``HOGSA_KEEP_MEMORY=0``) and "tcmalloc" (``LD_PRELOAD`` of libtcmalloc_minimal, found in the
system's library folders or given by ``--tcmalloc``).

Page faults: ``fwd_faults`` / ``fwd_bwd_faults`` are the minor page faults of the child
process per timed call (memory given back and faulted in again shows here);
``fwd_warmup_faults`` / ``fwd_bwd_warmup_faults`` are the warm-up's faults in total (mostly
the first touches of a fresh process, paid once). Faults come in bursts (the heap growing to
its plateau over tens of calls, or an allocator returning memory every so many calls), so
with more than one allocator the defaults are 10 warm-up and 100 / 40 timed calls. Timing on
a shared or virtual machine drifts: ``--rounds`` repeats every row, allocators interleaved
(default 3 with more than one allocator), and reports median times and mean faults.

The torch backend's compositor (``--compositor``): ``auto`` (the default, the compiled
kernels on the CPU), ``torch`` (vectorised PyTorch), ``numba``, or ``both`` (a row each).

Usage::

    python benchmarks/render_speed.py --json OUT.json [--backend torch|gsplat|all] [--quick] [--compositor both]
    python benchmarks/render_speed.py --quick --malloc default,glibc,tcmalloc --json OUT.json
"""

from __future__ import annotations

import argparse
import json
import math
import os
import statistics
import subprocess
import sys
from typing import Any, Callable

import torch
from _timing import bench_threads, time_render

CONFIGS = [(50_000, 224), (50_000, 512), (150_000, 224), (150_000, 512)]
QUICK_CONFIGS = [(50_000, 224)]
MALLOCS = ("default", "glibc", "tcmalloc")
TCMALLOC_PATHS = tuple(
    f"/usr/{d}/libtcmalloc_minimal.so.4" for d in ("lib/x86_64-linux-gnu", "lib/aarch64-linux-gnu", "lib64", "lib")
)


def malloc_env(name: str, tcmalloc: str | None) -> dict[str, str]:
    """Environment of a child row for allocator ``name`` (one of :data:`MALLOCS`)."""
    env = {k: v for k, v in os.environ.items() if k not in ("LD_PRELOAD", "HOGSA_KEEP_MEMORY")}
    if name == "glibc":
        env["HOGSA_KEEP_MEMORY"] = "0"
    elif name == "tcmalloc":
        path = tcmalloc or next((p for p in TCMALLOC_PATHS if os.path.isfile(p)), None)
        if path is None or not os.path.isfile(path):
            raise SystemExit(
                f"render_speed: tcmalloc not found (looked in {list(TCMALLOC_PATHS)}); "
                "install libtcmalloc-minimal4 or pass --tcmalloc PATH"
            )
        env["LD_PRELOAD"] = path
    return env


def make_scene(n: int, width: int, device: str, seed: int = 0) -> dict[str, Any]:
    """The calibration ball scene, batched as B = C = 1."""
    g = torch.Generator().manual_seed(seed)
    d = torch.randn(n, 3, generator=g)
    d = d / d.norm(dim=-1, keepdim=True) * torch.rand(n, 1, generator=g) ** (1.0 / 3.0) * 0.1
    means = d + torch.tensor([0.0, 0.0, 0.6])
    quats = torch.randn(n, 4, generator=g)
    quats = quats / quats.norm(dim=-1, keepdim=True)
    scales = torch.exp(torch.empty(n, 3).uniform_(math.log(1e-3), math.log(6e-3), generator=g))
    opac = torch.empty(n).uniform_(0.3, 1.0, generator=g)
    cols = torch.rand(n, 3, generator=g)
    f = 2.1 * width
    K = torch.tensor([[f, 0.0, width / 2], [0.0, f, width / 2], [0.0, 0.0, 1.0]])
    wrand = torch.rand(1, 1, width, width, 3, generator=g)
    t = dict(means=means, quats=quats, scales=scales, opacities=opac, colors=cols)
    scene = {k: v[None].to(device) for k, v in t.items()}
    scene["viewmats"] = torch.eye(4)[None, None].to(device)
    scene["Ks"] = K[None, None].to(device)
    scene["wrand"] = wrand.to(device)
    scene["width"] = width
    return scene


def _render_fn(backend: str, compositor: str) -> Callable[[dict[str, Any]], torch.Tensor]:
    """Both backends go through the public entry point ``hogsa_loader.render.render``
    (render_mode "RGB"; gsplat unpacked as in the original gsplat rows, the torch backend
    ignores ``packed``; ``compositor`` is the torch backend's)."""
    if backend not in ("torch", "gsplat"):
        raise ValueError(backend)
    from hogsa_loader.render import render

    opts = {"compositor": compositor} if backend == "torch" else {}

    def fn(s: dict[str, Any]) -> torch.Tensor:
        out = render(
            s["means"],
            s["quats"],
            s["scales"],
            s["opacities"],
            s["colors"],
            s["viewmats"],
            s["Ks"],
            s["width"],
            s["width"],
            backend=backend,
            render_mode="RGB",
            packed=False,
            **opts,
        )
        return out.rgb

    return fn


def _compositor_used(compositor: str, s: dict[str, Any]) -> str:
    """The compositor ``render_gaussians`` runs for ``compositor`` on this scene."""
    from hogsa_loader.render.raster_kernels import use_kernels

    return (
        "numba"
        if use_kernels("compositor", compositor, [s["means"], s["colors"], s["opacities"]], differentiable=True)
        else "torch"
    )


def run_row(
    backend: str, n: int, width: int, warmup: int, rep_fwd: int, rep_bwd: int, compositor: str = "auto"
) -> dict[str, Any]:
    from hogsa_loader.system import allocator_status

    device = "cuda" if backend == "gsplat" else "cpu"
    torch.set_num_threads(bench_threads())
    fn = _render_fn(backend, compositor)
    s = make_scene(n, width, device)
    t = time_render(fn, s, device, warmup, rep_fwd, rep_bwd)
    with torch.no_grad():
        n_isects = None
        if backend == "torch":
            from hogsa_loader.render import render

            n_isects = render(
                s["means"],
                s["quats"],
                s["scales"],
                s["opacities"],
                s["colors"],
                s["viewmats"],
                s["Ks"],
                width,
                width,
                backend="torch",
            ).meta["n_isects"]
    return {
        "backend": backend,
        "compositor": _compositor_used(compositor, s) if backend == "torch" else None,
        "device": torch.cuda.get_device_name() if device == "cuda" else f"cpu x{torch.get_num_threads()} threads",
        "N": n,
        "width": width,
        "height": width,
        "fwd_ms": round(t["fwd_ms"], 1),
        "fwd_bwd_ms": round(t["fwd_bwd_ms"], 1),
        "peak_mb": round(t["peak_mb"], 1),
        "base_mb": round(t["base_mb"], 1) if t["base_mb"] is not None else None,
        "memory": t["memory"],
        "n_isects": n_isects,
        "fwd_faults": round(t["fwd_faults"], 1),
        "fwd_bwd_faults": round(t["fwd_bwd_faults"], 1),
        "fwd_warmup_faults": t["fwd_warmup_faults"],
        "fwd_bwd_warmup_faults": t["fwd_bwd_warmup_faults"],
        "malloc": allocator_status(),
        "ld_preload": os.environ.get("LD_PRELOAD", ""),
    }


def merge_rounds(rs: list[dict[str, Any]]) -> dict[str, Any]:
    """One row from the rounds of one (allocator, backend, compositor, N, width): median
    times, mean faults, largest peak and base memory; the per-round figures under ``rounds``."""
    out = dict(rs[0])
    for k in ("fwd_ms", "fwd_bwd_ms"):
        out[k] = round(statistics.median(r[k] for r in rs), 1)
    for k in ("fwd_faults", "fwd_bwd_faults", "fwd_warmup_faults", "fwd_bwd_warmup_faults"):
        out[k] = round(statistics.fmean(r[k] for r in rs), 1)
    out["peak_mb"] = max(r["peak_mb"] for r in rs)
    out["base_mb"] = max(r["base_mb"] for r in rs) if rs[0]["base_mb"] is not None else None
    keys = (
        "fwd_ms",
        "fwd_bwd_ms",
        "fwd_faults",
        "fwd_bwd_faults",
        "fwd_warmup_faults",
        "fwd_bwd_warmup_faults",
        "peak_mb",
        "base_mb",
    )
    out["rounds"] = [{k: r[k] for k in keys} for r in rs]
    return out


def print_ratios(rows: list[dict[str, Any]], mallocs: list[str]) -> None:
    """Each allocator's forward time and page faults relative to the last one listed."""
    ref_name = mallocs[-1]
    for r in rows:
        if r["allocator"] == ref_name:
            continue
        ref = next(
            (
                q
                for q in rows
                if q["allocator"] == ref_name
                and (q["backend"], q["compositor"], q["N"], q["width"])
                == (r["backend"], r["compositor"], r["N"], r["width"])
            ),
            None,
        )
        if ref is None:
            continue
        keys = ("fwd_ms", "fwd_bwd_ms", "fwd_faults", "fwd_bwd_faults", "fwd_warmup_faults", "fwd_bwd_warmup_faults")
        ratio = {k: r[k] / ref[k] if ref[k] else float("nan") for k in keys}
        r[f"vs_{ref_name}"] = {k: None if v != v else round(v, 3) for k, v in ratio.items()}  # no ratio to 0
        print(
            f"{r['backend']} ({r['compositor']}) N={r['N']} {r['width']}: {r['allocator']} / {ref_name}: "
            f"fwd time {ratio['fwd_ms']:.2f}x, "
            f"fwd faults {ratio['fwd_faults']:.2f}x, fwd+bwd time {ratio['fwd_bwd_ms']:.2f}x, "
            f"fwd+bwd faults {ratio['fwd_bwd_faults']:.2f}x; warm-up faults fwd {ratio['fwd_warmup_faults']:.2f}x, "
            f"fwd+bwd {ratio['fwd_bwd_warmup_faults']:.2f}x",
            flush=True,
        )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--json", required=False, help="write the rows to this file")
    ap.add_argument("--backend", default="torch", choices=["torch", "gsplat", "all"])
    ap.add_argument(
        "--quick",
        action="store_true",
        help="50k @ 224 only, fewer repeats (1, 3, 2; with several --malloc 10, 100, 40) unless the "
        "repeat flags are given",
    )
    ap.add_argument("--warmup", type=int, default=None, help="default 2 (quick 1; 10 with several --malloc)")
    ap.add_argument("--repeats-fwd", type=int, default=None, help="default 7 (quick 3; 100 with several --malloc)")
    ap.add_argument("--repeats-bwd", type=int, default=None, help="default 5 (quick 2; 40 with several --malloc)")
    ap.add_argument(
        "--malloc",
        default="default",
        help=f"comma-separated allocators, each row run once per allocator: {', '.join(MALLOCS)}",
    )
    ap.add_argument("--tcmalloc", help="path of libtcmalloc_minimal (default: looked up in the library folders)")
    ap.add_argument(
        "--compositor",
        default="auto",
        choices=["auto", "torch", "numba", "both"],
        help="the torch backend's compositor (render_gaussians); both: a row for each of torch, numba",
    )
    ap.add_argument(
        "--rounds",
        type=int,
        default=None,
        help="rounds over the rows, allocators interleaved; median time, mean faults (default 1; "
        "3 with several --malloc)",
    )
    ap.add_argument("--row", help=argparse.SUPPRESS)  # internal: backend,N,width,compositor in a child
    a = ap.parse_args()
    mallocs = [m.strip() for m in a.malloc.split(",") if m.strip()]
    bad = [m for m in mallocs if m not in MALLOCS]
    if not mallocs or bad:
        ap.error(f"--malloc takes a comma-separated list of {list(MALLOCS)}, got {a.malloc!r}")
    if a.rounds is not None and a.rounds < 1:
        ap.error(f"--rounds must be at least 1, got {a.rounds}")

    if a.row:
        backend, n, w, comp = a.row.split(",")
        print(json.dumps(run_row(backend, int(n), int(w), a.warmup, a.repeats_fwd, a.repeats_bwd, comp)))
        return

    backends = ["torch", "gsplat"] if a.backend == "all" else [a.backend]
    if "gsplat" in backends and not torch.cuda.is_available():
        print("gsplat backend skipped: CUDA is not available (gsplat's rasteriser is CUDA-only)")
        backends.remove("gsplat")
    configs = QUICK_CONFIGS if a.quick else CONFIGS
    # fault counts need a long window (they come in bursts; see the module docstring)
    defaults = (10, 100, 40) if len(mallocs) > 1 else (1, 3, 2) if a.quick else (2, 7, 5)
    reps = tuple(
        given if given is not None else default
        for given, default in zip((a.warmup, a.repeats_fwd, a.repeats_bwd), defaults, strict=True)
    )
    envs = {m: malloc_env(m, a.tcmalloc) for m in mallocs}
    compositors = ["torch", "numba"] if a.compositor == "both" else [a.compositor]
    runs = [(b, c) for b in backends for c in (compositors if b == "torch" else ["auto"])]
    rounds = a.rounds if a.rounds is not None else 3 if len(mallocs) > 1 else 1
    runs_by_key: dict[tuple, list[dict[str, Any]]] = {}
    for rnd in range(rounds):  # allocators interleaved, so that a drifting machine affects them alike
        for backend, comp in runs:
            for n, w in configs:
                for m in mallocs:
                    cmd = [
                        sys.executable,
                        os.path.abspath(__file__),
                        "--row",
                        f"{backend},{n},{w},{comp}",
                        "--warmup",
                        str(reps[0]),
                        "--repeats-fwd",
                        str(reps[1]),
                        "--repeats-bwd",
                        str(reps[2]),
                    ]
                    res = subprocess.run(cmd, capture_output=True, text=True, env=envs[m])
                    if res.returncode != 0:
                        print(f"{backend} ({comp}) N={n} {w}x{w} [{m}]: failed\n{res.stderr[-2000:]}")
                        continue
                    r = {"allocator": m, **json.loads(res.stdout.strip().splitlines()[-1])}
                    runs_by_key.setdefault((m, backend, comp, n, w), []).append(r)
                    print(
                        f"[round {rnd + 1}/{rounds}] {r['backend']:7s} {str(r['compositor']):6s} {r['device']:22s} "
                        f"N={r['N']:>7d} {r['width']:>4d}x{r['height']:<4d} "
                        f"fwd {r['fwd_ms']:8.1f} ms  fwd+bwd {r['fwd_bwd_ms']:8.1f} ms  peak {r['peak_mb']:7.1f} MB "
                        f"(base {r['base_mb']}) isects {r['n_isects']} faults/call fwd {r['fwd_faults']:.0f} "
                        f"fwd+bwd {r['fwd_bwd_faults']:.0f} [{m}: {r['malloc']}]",
                        flush=True,
                    )
    rows = [merge_rounds(rs) for rs in runs_by_key.values()]
    if len(mallocs) > 1:
        print_ratios(rows, mallocs)
    if a.json:
        with open(a.json, "w") as fh:
            json.dump(rows, fh, indent=1)


if __name__ == "__main__":
    sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    main()
