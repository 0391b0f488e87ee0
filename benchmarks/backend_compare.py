"""Compare the renderer backends of ``hogsa_loader.render.render`` (speed, memory, agreement).

Scene (deterministic, no random numbers): N Gaussians on a sphere of radius 8 cm centred
0.5 m in front of the camera, at Fibonacci-sphere points; each is a disc tangent to the
sphere (standard deviations 0.6 d, 0.6 d, 0.05 d with d = sqrt(4 pi r^2 / N), the mean
spacing), rotated so that its thin axis is the sphere normal; opacity 0.9; colour from a
texture: an 8 x 16 latitude / longitude checkerboard modulating a smooth colour ramp.
Part ids: 0 for the upper hemisphere (world y < 0), 1 for the lower one. Camera at the
origin looking down +z, f = 2.5 W, principal point at the image centre, black background.

Backends: "torch" on the scene device (CUDA when available, else CPU) and "gsplat"
(gsplat 1.5.3 CUDA ``rasterization``, packed mode) when usable; a backend that cannot
run is listed under ``skipped`` with the reason.

Timings: median of ``--repeats-*`` runs after ``--warmup`` runs, render_mode "RGB";
"fwd" under ``torch.no_grad()``, "fwd_bwd" = forward + ``(rgb * Wrand).sum().backward()``
with gradients for means, quats, scales, opacities and colours. Every row runs in its own
child process. ``peak_mb``: on CUDA ``torch.cuda.max_memory_allocated()`` over the timed
runs; on CPU the child's peak resident set size (``ru_maxrss``, which includes the
Python / torch baseline, given as ``base_mb``).

Agreement (``psnr_torch_vs_gsplat``, per image size, only when both run on CUDA): one
render of each backend with render_mode "RGB+ED" and the two part channels; RGB PSNR
(data range 1), alpha / part-alpha max and mean absolute differences, and the mean / max
absolute depth difference over pixels with alpha > 0.5 in both.

Usage::

    python benchmarks/backend_compare.py --json OUT.json [--n 50000] [--size 224,512]
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
from typing import Any

import torch
from _timing import bench_threads, time_render

from hogsa_loader.system import available_cores


def make_scene(n: int, width: int, device: str) -> dict[str, Any]:
    """The textured-sphere scene (batched as B = C = 1), see the module docstring."""
    dt = torch.float64
    radius, centre = 0.08, torch.tensor([0.0, 0.0, 0.5], dtype=dt)
    i = torch.arange(n, dtype=dt)
    y = 1.0 - (2.0 * i + 1.0) / n  # in (-1, 1), never +-1
    ring = torch.sqrt(1.0 - y * y)
    phi = i * math.pi * (3.0 - math.sqrt(5.0))  # golden angle
    normal = torch.stack([ring * torch.cos(phi), y, ring * torch.sin(phi)], -1)  # unit
    means = centre + radius * normal
    # quaternion (wxyz) of the shortest rotation taking the local z axis onto the normal
    quats = torch.stack([1.0 + normal[:, 2], -normal[:, 1], normal[:, 0], torch.zeros_like(y)], -1)
    quats = quats / quats.norm(dim=-1, keepdim=True)
    d = math.sqrt(4.0 * math.pi * radius**2 / n)
    scales = torch.tensor([0.6 * d, 0.6 * d, 0.05 * d], dtype=dt).expand(n, 3)
    opac = torch.full((n,), 0.9, dtype=dt)
    lat = torch.asin(y.clamp(-1, 1))  # [-pi/2, pi/2]
    lon = torch.atan2(normal[:, 2], normal[:, 0])  # (-pi, pi]
    checker = ((torch.floor(lat / math.pi * 8) + torch.floor(lon / math.pi * 8)) % 2 == 0).to(dt)
    ramp = torch.stack([0.5 + 0.5 * torch.cos(lon), 0.5 + 0.5 * torch.sin(2 * lat), 0.5 + 0.5 * torch.sin(lon)], -1)
    cols = ramp * (0.35 + 0.65 * checker[:, None])
    part_ids = (normal[:, 1] >= 0).long()  # world y points down (OpenCV): 0 = upper half
    f = 2.5 * width
    K = torch.tensor([[f, 0.0, width / 2], [0.0, f, width / 2], [0.0, 0.0, 1.0]], dtype=dt)
    wrand = torch.rand(1, 1, width, width, 3, generator=torch.Generator().manual_seed(0))
    t = dict(means=means, quats=quats, scales=scales, opacities=opac, colors=cols)
    s: dict[str, Any] = {k: v[None].float().contiguous().to(device) for k, v in t.items()}
    s["viewmats"] = torch.eye(4)[None, None].to(device)
    s["Ks"] = K.float()[None, None].to(device)
    s["part_ids"] = part_ids[None].to(device)
    s["wrand"] = wrand.to(device)
    s["width"] = width
    return s


def _render(s: dict[str, Any], backend: str, **kw: Any):
    from hogsa_loader.render import render

    return render(
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
        **kw,
    )


def run_row(backend: str, device: str, n: int, width: int, warmup: int, rep_fwd: int, rep_bwd: int) -> dict[str, Any]:
    if device == "cpu":
        torch.set_num_threads(bench_threads())
    s = make_scene(n, width, device)
    t = time_render(lambda sc: _render(sc, backend).rgb, s, device, warmup, rep_fwd, rep_bwd)
    with torch.no_grad():
        alpha_mean = float(_render(s, backend).alpha.mean())
    return {
        "backend": backend,
        "device": torch.cuda.get_device_name() if device == "cuda" else f"cpu x{torch.get_num_threads()} threads",
        "N": n,
        "width": width,
        "height": width,
        "fwd_ms": round(t["fwd_ms"], 2),
        "fwd_bwd_ms": round(t["fwd_bwd_ms"], 2),
        "peak_mb": round(t["peak_mb"], 1),
        "base_mb": round(t["base_mb"], 1) if t["base_mb"] is not None else None,
        "memory": t["memory"],
        "alpha_mean": round(alpha_mean, 4),
    }


def agreement(n: int, width: int) -> dict[str, Any]:
    """torch vs gsplat backend on CUDA for one image size."""
    s = make_scene(n, width, "cuda")
    kw = dict(render_mode="RGB+ED", part_ids=s["part_ids"], num_parts=2)
    with torch.no_grad():
        t = _render(s, "torch", **kw)
        g = _render(s, "gsplat", **kw)
    mse = float(((t.rgb.double() - g.rgb.double()) ** 2).mean())
    hit = (t.alpha > 0.5) & (g.alpha > 0.5)
    dd = (t.depth - g.depth).abs()[hit]
    da = (t.alpha - g.alpha).abs()
    dp = (t.part_alpha - g.part_alpha).abs()
    return {
        "rgb_psnr_db": None if mse == 0 else round(10 * math.log10(1.0 / mse), 2),
        "rgb_max_abs": float((t.rgb - g.rgb).abs().max()),
        "alpha_max_abs": float(da.max()),
        "alpha_mean_abs": float(da.mean()),
        "part_alpha_max_abs": float(dp.max()),
        "depth_mean_abs_alpha_gt_0.5": float(dd.mean()) if dd.numel() else None,
        "depth_max_abs_alpha_gt_0.5": float(dd.max()) if dd.numel() else None,
        "pixels_alpha_gt_0.5": int(hit.sum()),
    }


def _child(args: list[str]) -> dict[str, Any] | str:
    cmd = [sys.executable, os.path.abspath(__file__), *args]
    res = subprocess.run(cmd, capture_output=True, text=True)
    if res.returncode != 0:
        return f"failed: {res.stderr.strip()[-2000:]}"
    return json.loads(res.stdout.strip().splitlines()[-1])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--json", help="write the result to this file")
    ap.add_argument("--n", type=int, default=50_000, help="number of Gaussians")
    ap.add_argument(
        "--size",
        type=lambda t: [int(x) for x in t.split(",")],
        default=[224, 512],
        help="square image sizes, comma-separated",
    )
    ap.add_argument("--warmup", type=int, default=2)
    ap.add_argument("--repeats-fwd", type=int, default=7)
    ap.add_argument("--repeats-bwd", type=int, default=5)
    ap.add_argument("--row", help=argparse.SUPPRESS)  # internal: backend,device,N,width
    ap.add_argument("--agree", help=argparse.SUPPRESS)  # internal: N,width
    a = ap.parse_args()

    if a.row:
        backend, device, n, w = a.row.split(",")
        print(json.dumps(run_row(backend, device, int(n), int(w), a.warmup, a.repeats_fwd, a.repeats_bwd)))
        return
    if a.agree:
        n, w = a.agree.split(",")
        print(json.dumps(agreement(int(n), int(w))))
        return

    from hogsa_loader.render.gsplat_backend import gsplat_unavailable_reason

    device = "cuda" if torch.cuda.is_available() else "cpu"
    # on CUDA this may JIT-build gsplat's extension once (the children then load it)
    gs_reason = gsplat_unavailable_reason(torch.device(device), torch.float32)
    backends = [("torch", device)]
    skipped = []
    if gs_reason is None:
        backends.append(("gsplat", "cuda"))
    else:
        skipped.append({"backend": "gsplat", "reason": gs_reason})
        print(f"gsplat backend skipped: {gs_reason}")

    rows = []
    for backend, dev in backends:
        for w in a.size:
            r = _child(
                [
                    "--row",
                    f"{backend},{dev},{a.n},{w}",
                    "--warmup",
                    str(a.warmup),
                    "--repeats-fwd",
                    str(a.repeats_fwd),
                    "--repeats-bwd",
                    str(a.repeats_bwd),
                ]
            )
            if isinstance(r, str):
                print(f"{backend} N={a.n} {w}x{w}: {r}")
                skipped.append({"backend": backend, "N": a.n, "width": w, "reason": r})
                continue
            rows.append(r)
            print(
                f"{r['backend']:7s} {r['device']:24s} N={r['N']:>7d} {r['width']:>4d}x{r['height']:<4d} "
                f"fwd {r['fwd_ms']:9.2f} ms  fwd+bwd {r['fwd_bwd_ms']:9.2f} ms  peak {r['peak_mb']:8.1f} MB "
                f"(base {r['base_mb']}) alpha_mean {r['alpha_mean']}",
                flush=True,
            )

    psnr: dict[str, Any] | None = None
    psnr_reason = None
    if gs_reason is not None:
        psnr_reason = f"gsplat backend unavailable: {gs_reason}"
    else:
        psnr = {}
        for w in a.size:
            r = _child(["--agree", f"{a.n},{w}"])
            psnr[f"{w}x{w}"] = r
            print(f"torch vs gsplat {w}x{w}: {r}", flush=True)

    result = {
        "device": torch.cuda.get_device_name() if device == "cuda" else f"cpu ({available_cores()} cores available)",
        "torch": torch.__version__,
        "scene": f"textured sphere, N={a.n}, r=0.08 m at z=0.5 m, f=2.5W, render_mode RGB for timings",
        "rows": rows,
        "skipped": skipped,
        "psnr_torch_vs_gsplat": psnr,
        "psnr_reason": psnr_reason,
    }
    if a.json:
        with open(a.json, "w") as fh:
            json.dump(result, fh, indent=1)


if __name__ == "__main__":
    sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    main()
