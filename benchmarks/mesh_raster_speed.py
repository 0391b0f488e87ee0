"""Speed of the mesh rasteriser's two CPU backends on world-like scenes.

``hogsa_loader.render.mesh_raster.render_meshes`` with ``backend="torch"`` (vectorised
PyTorch over triangle-pixel pairs) and ``backend="numba"`` (the compiled kernels), on the
scenes a generated world renders:

* ``crop``: two vertex-coloured hand-sized ellipsoids (1,280 faces each) beside a textured
  3,072-face box, over a background image (an allocentric crop of ``--size`` px; ARCTIC's
  crops are 1000);
* ``stage``: a textured floor and wall filling a 2800 x 2000 image (the full-resolution
  background of an allocentric view, rendered once per subject and view).

Each row is the median of ``--repeats`` calls after one warm-up call (the first numba call
of a process compiles or loads its kernels from numba's cache). The outputs of the two
backends are compared: part ids, coverage and depth must be equal, colours within 1e-5.

Usage::

    python benchmarks/mesh_raster_speed.py --json OUT.json [--size 1000] [--repeats 5]
"""

from __future__ import annotations

import argparse
import functools
import json
import platform
import statistics
import sys
import time
from pathlib import Path

import torch
import trimesh

from hogsa_loader.render.mesh_raster import MeshPart, intrinsics_from_fov, render_meshes


def _hand(centre: tuple[float, float, float], seed: int) -> MeshPart:
    """An ellipsoid of a hand's size (0.19 x 0.09 x 0.04 m, 1,280 faces), vertex coloured."""
    m = trimesh.creation.icosphere(subdivisions=3)
    v = torch.tensor(m.vertices, dtype=torch.float32) * torch.tensor([0.095, 0.045, 0.02]) + torch.tensor(centre)
    g = torch.Generator().manual_seed(seed)
    colours = 0.6 + 0.2 * torch.rand(v.shape[0], 3, generator=g)
    return MeshPart(v, torch.tensor(m.faces), 1 + seed, vertex_colors=colours)


def _textured(mesh: trimesh.Trimesh, part_id: int, texture: torch.Tensor, scale: float) -> MeshPart:
    """A mesh with planar uv coordinates from its x, y extent."""
    v = torch.tensor(mesh.vertices, dtype=torch.float32)
    lo, hi = v[:, :2].min(0).values, v[:, :2].max(0).values
    uv = (v[:, :2] - lo) / (hi - lo) * scale
    return MeshPart(v, torch.tensor(mesh.faces), part_id, uv=uv % 1.0, texture=texture)


def scene(kind: str, size: int) -> tuple[list[MeshPart], torch.Tensor, torch.Tensor, int, int, torch.Tensor]:
    """(parts, world2cam, K, height, width, background) of a benchmark scene."""
    g = torch.Generator().manual_seed(0)
    texture = torch.rand(512, 512, 3, generator=g)
    w2c = torch.eye(4)
    if kind == "crop":
        box = trimesh.creation.box((0.16, 0.12, 0.1)).subdivide_loop(4)  # 3,072 faces
        box.apply_translation((0.0, 0.0, 0.55))
        parts = [_hand((-0.07, 0.02, 0.5), 0), _hand((0.08, -0.03, 0.52), 1), _textured(box, 3, texture, 3.0)]
        K = intrinsics_from_fov(35.0, size, size)
        return parts, w2c, K, size, size, torch.rand(size, size, 3, generator=g)
    if kind == "stage":
        floor = trimesh.creation.box((4.0, 0.02, 4.0))
        floor.apply_translation((0.0, 0.6, 2.5))
        wall = trimesh.creation.box((4.0, 3.0, 0.02))
        wall.apply_translation((0.0, -0.8, 4.0))
        parts = [_textured(floor, 1, texture, 8.0), _textured(wall, 2, texture, 4.0)]
        W, H = 2800, 2000
        K = intrinsics_from_fov(70.0, W, H)
        return parts, w2c, K, H, W, torch.zeros(H, W, 3)
    raise ValueError(f"unknown scene {kind!r}")


def _time(fn, repeats: int) -> float:
    fn()
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return statistics.median(times)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--json", type=Path, required=True, help="output JSON")
    ap.add_argument("--size", type=int, default=1000, help="crop side in px (default 1000, ARCTIC's)")
    ap.add_argument("--repeats", type=int, default=5, help="timed calls per row (default 5)")
    args = ap.parse_args(argv)
    if args.size < 16 or args.repeats < 1:
        ap.error("--size must be >= 16 and --repeats >= 1")
    rows = []
    for kind in ("crop", "stage"):
        parts, w2c, K, H, W, bg = scene(kind, args.size)
        outs, row = {}, {"scene": kind, "height": H, "width": W, "faces": sum(p.faces.shape[0] for p in parts)}
        for backend in ("torch", "numba"):
            call = functools.partial(render_meshes, parts, w2c, K, H, W, background=bg, backend=backend)
            outs[backend] = call()
            row[f"{backend}_ms"] = 1e3 * _time(call, args.repeats)
        a, b = outs["torch"], outs["numba"]
        row["covered"] = float((a.part_id > 0).float().mean())
        row["equal_part_id_alpha_depth"] = bool(
            torch.equal(a.part_id, b.part_id) and torch.equal(a.alpha, b.alpha) and torch.equal(a.depth, b.depth)
        )
        row["rgb_max_abs_diff"] = float((a.rgb - b.rgb).abs().max())
        row["speedup"] = row["torch_ms"] / row["numba_ms"]
        rows.append(row)
        print(
            f"{kind:6s} {W}x{H} {row['faces']} faces, {row['covered']:.0%} covered: torch {row['torch_ms']:.0f} ms, "
            f"numba {row['numba_ms']:.0f} ms ({row['speedup']:.1f}x); equal {row['equal_part_id_alpha_depth']}, "
            f"rgb max diff {row['rgb_max_abs_diff']:.1e}",
            flush=True,
        )
    out = {
        "rows": rows,
        "repeats": args.repeats,
        "torch": torch.__version__,
        "threads": torch.get_num_threads(),
        "machine": platform.processor() or platform.machine(),
        "python": sys.version.split()[0],
    }
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps(out, indent=1) + "\n")
    ok = all(r["equal_part_id_alpha_depth"] and r["rgb_max_abs_diff"] < 1e-5 for r in rows)
    return 0 if ok else 1


if __name__ == "__main__":
    raise SystemExit(main())
