#!/usr/bin/env python
"""Held-out rendering quality of trained HOGS runs: PSNR / SSIM / LPIPS, side by side.

Evaluates one or more runs of ``hogsa train hogs`` (e.g. ``--model-gaussians mesh`` and
``--model-gaussians free`` of the same subject + object) on the held-out camera views × held-out
frames of their own split (read from each run's ``config.json``), inside the foreground
box as the paper crops (:mod:`hogsa_loader.train.hogs_eval`). With ``--srm RUN`` the first
run is also scored after SRM refinement (``without_srm`` / ``with_srm``). An SRM whose
manifest records that it was trained or selected on one of the scored views of that
subject + object is refused (``--allow-seen-views`` scores it anyway, marked not held-out).

Example::

    python experiments/render_quality.py --data ./hogsa_world/arctic_data/data \
        --run runs/s01_box_mesh --run runs/s01_box_free --json quality.json --png quality.png
    python experiments/render_quality.py --dataset h2o --data H2O_ROOT --mano-dir MANO_DIR \
        --object-mesh-dir H2O_ROOT/object --run runs/h2o_s1_book --json quality.json

``--data``, ``--mano-dir`` and ``--object-mesh-dir`` default to the paths in each run's
``config.json``; the dataset (ARCTIC or H2O) is the run's (``--dataset`` checks it).

JSON: ``psnr``, ``ssim``, ``lpips`` (null when unavailable, with ``lpips_note``) and
``per_view`` of the first run; ``runs`` (every run's metrics, labelled by its Gaussians
variant); with ``--srm``: ``without_srm``, ``with_srm`` and ``srm_views_check`` (held-out,
not held-out, or unchecked for SRMs that do not record their training views).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Any, Optional, Sequence

import numpy as np
import torch

from hogsa_loader.models.gaussians.hogs_model import HogsModel
from hogsa_loader.train.hogs_data import HogsData, ViewSample
from hogsa_loader.train.hogs_eval import evaluate_samples, load_lpips
from hogsa_loader.train.hogs_source import HogsSource, load_run_data


def parse_args(argv: Optional[Sequence[str]] = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument(
        "--data", default=None, help="dataset root the runs were trained on (default: the runs' config.json)"
    )
    p.add_argument("--dataset", default=None, choices=["arctic", "h2o"], help="check that the runs are of this dataset")
    p.add_argument("--mano-dir", default=None, help="H2O: MANO folder (default: the run's)")
    p.add_argument("--object-mesh-dir", default=None, help="H2O: object mesh folder (default: the run's)")
    p.add_argument(
        "--run",
        type=lambda text: [t for t in text.split(",") if t],
        required=True,
        help="HOGS run folders, comma-separated (several: side by side)",
    )
    p.add_argument("--json", required=True, help="output JSON")
    p.add_argument("--png", default=None, help="side-by-side PNG: GT | run 1 | run 2 | ... (| SRM)")
    p.add_argument("--srm", default=None, help="SRM run folder: also score the first run after refinement")
    p.add_argument(
        "--srm-tta",
        type=int,
        default=1,
        choices=[1, 2, 4, 8],
        help="SRM test-time augmentation: symmetric copies averaged (SRM.refine(tta=...))",
    )
    p.add_argument(
        "--allow-seen-views",
        action="store_true",
        help="score an SRM even on views it was trained or selected on (the figure is then not held-out)",
    )
    p.add_argument("--max-eval", type=int, default=64, help="at most this many held-out images (evenly spaced)")
    p.add_argument("--png-rows", type=int, default=4)
    p.add_argument("--device", default="cpu")
    return p.parse_args(argv)


def load_split(a: argparse.Namespace, run: str, cfg: dict[str, Any]) -> tuple[HogsSource, HogsData]:
    """The run's dataset and held-out split, rebuilt from its ``config.json`` settings."""
    dataset = cfg.get("dataset", "arctic")
    if a.dataset is not None and a.dataset != dataset:
        raise SystemExit(f"render_quality: run {run} was trained on {dataset!r}, not {a.dataset!r}")
    return load_run_data(cfg, data=a.data, mano_dir=a.mano_dir, object_mesh_dir=a.object_mesh_dir, max_eval=a.max_eval)


def render_fn(model: HogsModel, data: HogsData, device: torch.device):
    """samples → (rgb, alpha) of the model (all SH bands)."""

    def fn(samples: Sequence[ViewSample]) -> tuple[torch.Tensor, torch.Tensor]:
        poses = {k: v.to(device) for k, v in data.poses(samples).items()}
        vm = torch.as_tensor(np.stack([s.world2cam for s in samples]), dtype=torch.float32, device=device)[:, None]
        K = torch.as_tensor(np.stack([s.K for s in samples]), dtype=torch.float32, device=device)[:, None]
        S = data.image_size
        out = model.render(poses, vm, K, S, S, render_mode="RGB")
        return out.rgb[:, 0], out.alpha[:, 0, ..., 0]

    return fn


def margin_px(cfg: dict[str, Any], data: HogsData) -> int:
    return int(round(cfg.get("margin", 4) * data.image_size / data.crop_size))


def summary(ev: dict[str, Any]) -> dict[str, Any]:
    return {k: ev[k] for k in ("psnr", "ssim", "lpips", "alpha_outside", "num_samples", "per_view")}


def write_png(path: Path, columns: list[list[tuple[torch.Tensor, torch.Tensor]]], labels: list[str]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n = min(len(c) for c in columns)
    rows = []
    for i in range(n):
        gt = columns[0][i][0]
        rows.append(torch.cat([gt] + [c[i][1] for c in columns], 1))
    img = (torch.cat(rows, 0).numpy() * 255).round().astype(np.uint8)
    fig = plt.figure(figsize=(img.shape[1] / 100, img.shape[0] / 100 + 0.3), dpi=100)
    ax = fig.add_axes([0, 0, 1, img.shape[0] / (img.shape[0] + 30)])
    ax.imshow(img)
    ax.axis("off")
    w = img.shape[1] / (len(labels))
    for j, lab in enumerate(labels):
        fig.text(
            (j + 0.5) * w / img.shape[1],
            1 - 0.15 / (img.shape[0] / 100 + 0.3),
            lab,
            ha="center",
            va="center",
            fontsize=10,
        )
    fig.savefig(path)
    plt.close(fig)


def check_srm_views(a: argparse.Namespace, data: HogsData) -> str:
    """Refuse an SRM that was trained or selected on one of the held-out views scored here
    (unless ``--allow-seen-views``); returns a note for the JSON."""
    from hogsa_loader.models.srm import read_srm_manifest, seen_views

    manifest = read_srm_manifest(a.srm)
    seen = seen_views(manifest, data.subject, data.object_name)
    if seen is None:
        note = "unchecked: the SRM manifest does not record its training views"
        print(
            f"render_quality: WARNING {a.srm}: {note}; the with-SRM figure is held-out only if it "
            f"never saw views {list(data.eval_views)} of {data.subject}/{data.object_name}",
            file=sys.stderr,
        )
        return note
    both = sorted(seen & {int(v) for v in data.eval_views})
    if not both:
        return f"held-out: the SRM saw views {sorted(seen)} of {data.subject}/{data.object_name}, none scored here"
    pair = f"{data.subject}/{data.object_name}"
    msg = f"the SRM {a.srm} was trained or selected on view(s) {both} of {pair}, which are scored here"
    if not a.allow_seen_views:
        raise SystemExit(
            f"render_quality: {msg}; its figure would not be held-out (pass --allow-seen-views to score anyway)"
        )
    print(f"render_quality: WARNING {msg}", file=sys.stderr)
    return f"not held-out: {msg}"


def main(argv: Optional[Sequence[str]] = None) -> int:
    a = parse_args(argv)
    device = torch.device(a.device)
    lpips_fn, lpips_note = load_lpips(device)
    keep = a.png_rows if a.png else 0
    runs, columns, labels = [], [], ["GT"]
    first: Optional[tuple[HogsModel, HogsData, int]] = None
    for run in a.run:
        cfg = json.loads((Path(run) / "config.json").read_text())
        source, data = load_split(a, run, cfg)
        model = HogsModel.from_run(run, source.mano_layers, source.object_templates, device=device).eval()
        m = margin_px(cfg, data)
        t0 = time.perf_counter()
        ev = evaluate_samples(
            render_fn(model, data, device),
            data.eval,
            [s.name for s in data.sequences],
            m,
            lpips_fn=lpips_fn,
            device=device,
            keep=keep,
        )
        dt = time.perf_counter() - t0
        label = cfg.get("gaussians", "mesh")
        runs.append(
            {
                "label": label,
                "run": str(run),
                "dataset": source.dataset,
                "subject": cfg["subject"],
                "object": cfg["object"],
                "iters": cfg.get("iters"),
                "image_size": data.image_size,
                "num_gaussians": model.num_gaussians,
                "eval_views": list(data.eval_views),
                "s_per_image": dt / max(1, len(data.eval)),
                **summary(ev),
                "per_sample": ev["per_sample"],
            }
        )
        columns.append(ev.get("images", []))
        labels.append(label)
        if first is None:
            first = (model, data, m)
        print(
            f"{label:5s} {run}: PSNR {ev['psnr']:.2f} dB  SSIM {ev['ssim']:.4f}  LPIPS {ev['lpips']}  "
            f"({ev['num_samples']} held-out images, views {list(data.eval_views)})"
        )
    out: dict[str, Any] = {
        **{k: runs[0][k] for k in ("psnr", "ssim", "lpips", "per_view")},
        "lpips_note": lpips_note,
        "protocol": "held-out camera views x held-out frames of each run's split; foreground box "
        "(bbox of the part mask dilated by the run's margin), GT background black; SSIM kornia 11x11",
        "runs": runs,
    }
    if a.srm:
        from hogsa_loader.models.srm import load_srm

        assert first is not None
        model, data, m = first
        srm = load_srm(a.srm, device=device)
        seen_note = check_srm_views(a, data)
        if srm.scale != 1:  # its output would be scored against boxes of the input size
            raise SystemExit(
                f"render_quality: {a.srm} is a scale-{srm.scale} SRM; only scale-1 SRMs (same-size "
                "refinement, what the loader uses) can be scored here"
            )
        names = [s.name for s in data.sequences]
        ev = evaluate_samples(
            render_fn(model, data, device),
            data.eval,
            names,
            m,
            refine=lambda rgb, alpha: srm.refine(rgb, alpha, tta=a.srm_tta),
            lpips_fn=lpips_fn,
            device=device,
            keep=keep,
        )
        out["without_srm"] = summary({**runs[0], "alpha_outside": runs[0]["alpha_outside"]})
        out["with_srm"] = summary(ev)
        out["srm"] = str(a.srm)
        out["srm_tta"] = a.srm_tta
        out["srm_views_check"] = seen_note
        columns.append(ev.get("images", []))
        labels.append("SRM")
        print(
            f"with SRM: PSNR {ev['psnr']:.2f} dB  SSIM {ev['ssim']:.4f}  (without: {runs[0]['psnr']:.2f} / "
            f"{runs[0]['ssim']:.4f})"
        )
    Path(a.json).parent.mkdir(parents=True, exist_ok=True)
    Path(a.json).write_text(json.dumps(out, indent=1, allow_nan=False) + "\n")
    if a.png:
        write_png(Path(a.png), columns, labels)
    return 0


if __name__ == "__main__":
    sys.exit(main())
