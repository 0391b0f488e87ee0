#!/usr/bin/env python
"""Finished downstream models on a larger held-out set, with the uncertainty over its clips.

A generated world's validation split holds few clips (one subject, sequence and camera view
each): a paired difference of 1-2 mm between two arms of ``benchmarks/downstream.py`` can come
from one clip on which one of them fails. This script evaluates the saved models of downstream
runs on the held-out splits of another ARCTIC-format root made by the same generator with more
held-out sequences (``hogsa world --preset small_styles_heldout`` for models trained on
``small_styles``: the same bodies and training files, five times the held-out sequences, a
test subject), and reports ARCTIC's per-frame metrics per run and, against a reference, the
paired difference per seed with its 95 % interval over clips and its range with one clip left
out (:func:`~hogsa_loader.baselines.clips.clip_uncertainty`), per split and over all of them.

Every model must have been trained with the MANO layers and object templates of the root it
is evaluated on (checked against its training root when that still exists). Each (model file,
root, split) is evaluated once; the result is cached in ``OUT/cache``.

Outputs in ``--out``: ``heldout.json`` and ``heldout.md``.

Usage::

    hogsa world --out runs/world_heldout --preset small_styles_heldout
    python benchmarks/heldout.py --data runs/world_heldout/arctic_data/data --reference real \\
        --runs real=runs/downstream/runs/real hogsa=runs/downstream/runs/hogsa
"""

from __future__ import annotations

import argparse
import hashlib
import json
import sys
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Optional

import numpy as np
import torch
from torch.utils.data import DataLoader, Subset
from tqdm import tqdm

from hogsa_loader.baselines.arcticnet_sf import ArcticNetSF, load_arctic_checkpoint
from hogsa_loader.baselines.clips import ClipSums, clip_sums, clip_uncertainty
from hogsa_loader.baselines.engine import BodyLayers, evaluate, temporal_order
from hogsa_loader.cli.dataclass_args import add_dataclass_arguments, dataclass_from_args
from hogsa_loader.compose.plates import data_fingerprint
from hogsa_loader.datasets.arctic import ArcticRoot
from hogsa_loader.datasets.arctic_dataset import ArcticDataset
from hogsa_loader.datasets.augment import ArcticConfig
from hogsa_loader.errors import AssetError, read_json
from hogsa_loader.io.hashing import sha256_file
from hogsa_loader.system import available_cores

#: Per-frame metrics reported (ARCTIC's names) and those kept per clip for the intervals.
METRICS = {
    "mpjpe/ra/h": "MPJPE_h (mm)",
    "cdev/ho": "CDev_ho (mm)",
    "mrrpe/r/l": "MRRPE_rl (mm)",
    "aae": "AAE (°)",
    "success_rate/0.05": "Success (%)",
}
CLIP_METRICS = ("mpjpe/ra/h", "cdev/ho")
CACHE_VERSION = 1


@dataclass
class HeldoutConfig:
    """One evaluation of finished runs on a held-out root."""

    data: str = field(
        default="",
        metadata={"help": "ARCTIC-format root (…/arctic_data/data) whose held-out splits are read", "required": True},
    )
    runs: tuple[str, ...] = field(
        default=(),
        metadata={
            "help": "LABEL=FOLDER, FOLDER holding seed<N>/model.safetensors (a downstream run)",
            "required": True,
        },
    )
    reference: str = field(default="real", metadata={"help": "label of the runs the others are paired with"})
    splits: tuple[str, ...] = field(default=("p1_val", "p1_test"), metadata={"help": "held-out splits of --data"})
    out: str = field(default="runs/heldout", metadata={"help": "output folder (cache in OUT/cache)"})
    batch_size: int = field(default=32, metadata={"help": "frames per evaluation batch", "type": "positive_int"})
    threads: int = field(default=0, metadata={"help": "torch threads (0: every core)", "type": "non_negative_int"})


def parse_runs(items: tuple[str, ...]) -> dict[str, dict[int, Path]]:
    """``LABEL=FOLDER`` items → label → seed → model file (every ``seed<N>/model.safetensors``)."""
    runs: dict[str, dict[int, Path]] = {}
    for item in items:
        label, sep, folder = item.partition("=")
        if not sep or not label or not folder:
            raise SystemExit(f"heldout: error: --runs takes LABEL=FOLDER, got {item!r}")
        if label in runs:
            raise SystemExit(f"heldout: error: label {label!r} given twice")
        seeds = {}
        for path in sorted(Path(folder).glob("seed*/model.safetensors")):
            suffix = path.parent.name[len("seed") :]
            if suffix.isdigit():
                seeds[int(suffix)] = path
        if not seeds:
            raise SystemExit(f"heldout: error: no seed<N>/model.safetensors in {folder} ({label})")
        runs[label] = seeds
    return runs


def model_settings(path: Path) -> tuple[str, int, dict[str, Any]]:
    """Backbone, patch side and settings of the model saved at ``path`` (its ``model.json``).

    Raises:
        AssetError: naming the file when the manifest lacks the model settings.
    """
    manifest = read_json(path.with_name("model.json"))
    try:
        settings = manifest["settings"]  # type: ignore[index]
        return str(settings["model"]["backbone"]), int(settings["model"]["img_res"]), settings
    except (KeyError, TypeError, ValueError) as exc:
        raise AssetError(path.with_name("model.json"), f"no settings.model.backbone / img_res ({exc!r})") from exc


def bodies_digest(root: ArcticRoot) -> str:
    """sha256 over the MANO model files and the object templates of a root (what the model's
    layers and its targets are built from)."""
    h = hashlib.sha256()
    for folder in (root.mano_dir, root.meta_dir / "object_vtemplates"):
        for path in sorted(p for p in folder.rglob("*") if p.is_file()):
            h.update(str(path.relative_to(folder)).encode())
            h.update(sha256_file(path).encode())
    return h.hexdigest()


def check_bodies(settings: dict[str, Any], root: ArcticRoot, path: Path, checked: dict[str, str]) -> None:
    """Refuse a model whose training root has other MANO models or object templates than the
    evaluated ``root`` (a training root no longer on disk is not checked).

    Args:
        settings: the model's settings (``data``: its training root).
        root: the evaluated root.
        path: the model file (named in the error).
        checked: digests computed so far, by root path (filled in).
    """
    try:
        train = ArcticRoot(str(settings.get("data", ""))).data_root
    except AssetError:
        return
    for r in (root.data_root, train):
        if str(r) not in checked:
            checked[str(r)] = bodies_digest(ArcticRoot(r))
    if checked[str(train)] != checked[str(root.data_root)]:
        raise SystemExit(
            f"heldout: error: {path} was trained on {train}, whose MANO models or object templates differ from --data's"
        )


def evaluate_model(path: Path, split: str, cfg: HeldoutConfig, ctx: dict[str, Any]) -> dict[str, Any]:
    """ARCTIC's per-frame metrics of one model on one split (cached by file digest, root, split)."""
    digest = sha256_file(path)
    cache = Path(cfg.out) / "cache" / f"{digest[:16]}-{ctx['fingerprint'][:12]}-{split}.json"
    if cache.is_file():
        rec = json.loads(cache.read_text())
        if rec.get("version") == CACHE_VERSION and rec.get("model_sha256") == digest:
            return rec
    backbone, img_res, settings = model_settings(path)
    layers = ctx["layers"]
    check_bodies(settings, ctx["root"], path, ctx["checked"])
    model = ArcticNetSF(backbone, layers.mano_r, layers.mano_l, layers.objects, focal_length=1000.0, img_res=img_res)
    load_arctic_checkpoint(model, path)
    ds = ctx["datasets"].get((split, img_res))
    if ds is None:
        ds = ArcticDataset(cfg.data, split=split, seed=0, augment=False, config=ArcticConfig(img_res=img_res))
        ctx["datasets"][(split, img_res)] = ds
    loader = DataLoader(Subset(ds, temporal_order(ds.imgnames)), batch_size=cfg.batch_size)
    with tqdm(total=len(ds), desc=f"{path.parent.parent.name}/{path.parent.name} {split}", unit="frame") as bar:
        ev = evaluate(model.eval(), loader, layers, img_res, "cpu", temporal=False, on_batch=bar.update)
    rec = {
        "version": CACHE_VERSION,
        "model": str(path),
        "model_sha256": digest,
        "split": split,
        "frames": ev["frames"],
        "summary": {k: float(ev["summary"][k]) for k in METRICS if k in ev["summary"]},
        "clips": clip_sums(ev, CLIP_METRICS),
    }
    cache.parent.mkdir(parents=True, exist_ok=True)
    cache.write_text(json.dumps(rec))
    return rec


def merged(recs: list[dict[str, Any]]) -> dict[str, Any]:
    """One run's results on several splits as one: the clip metrics formed again over all
    clips (frame-weighted), the other metrics left out."""
    clips: ClipSums = {c: v for r in recs for c, v in r["clips"].items()}
    summary = {}
    for m in CLIP_METRICS:
        n = sum(v[m][1] for v in clips.values())
        summary[m] = sum(v[m][0] for v in clips.values()) / n if n else float("nan")
    return {"frames": sum(r["frames"] for r in recs), "summary": summary, "clips": clips}


def _mean_std(vals: list[float]) -> dict[str, Optional[float]]:
    vals = [v for v in vals if np.isfinite(v)]
    return {
        "mean": float(np.mean(vals)) if vals else None,
        "std": float(np.std(vals, ddof=1)) if len(vals) > 1 else None,
    }


def report(results: dict[str, dict[int, dict[str, Any]]], reference: str) -> dict[str, Any]:
    """Mean ± std per label and the paired differences against ``reference`` of one split."""
    rows = {
        label: {m: _mean_std([r["summary"].get(m, float("nan")) for r in by_seed.values()]) for m in METRICS}
        for label, by_seed in results.items()
    }
    paired = {}
    ref = results.get(reference, {})
    for label, by_seed in results.items():
        if label == reference:
            continue
        seeds = sorted(set(by_seed) & set(ref))
        paired[label] = {
            m: {
                "per_seed": {s: by_seed[s]["summary"][m] - ref[s]["summary"][m] for s in seeds},
                **_mean_std([by_seed[s]["summary"][m] - ref[s]["summary"][m] for s in seeds]),
                "clips": clip_uncertainty([(by_seed[s]["clips"], ref[s]["clips"]) for s in seeds], m),
            }
            for m in CLIP_METRICS
        }
    frames = next((r["frames"] for by_seed in results.values() for r in by_seed.values()), 0)
    clips = next((len(r["clips"]) for by_seed in results.values() for r in by_seed.values()), 0)
    return {"frames": frames, "clips": clips, "arms": rows, "paired": paired}


def _cell(row: dict[str, Optional[float]], sign: bool = False) -> str:
    if row["mean"] is None:
        return "n/a"
    fmt = "+.2f" if sign else ".2f"
    return f"{row['mean']:{fmt}}" + (f" ± {row['std']:.2f}" if row["std"] is not None else "")


def markdown(reports: dict[str, dict[str, Any]], reference: str) -> str:
    """One section per split: the runs' metrics, then each label against the reference."""
    lines = []
    for split, rep in reports.items():
        metrics = [m for m in METRICS if any(rep["arms"][a][m]["mean"] is not None for a in rep["arms"])]
        lines += [
            f"**{split}** ({rep['frames']} frames, {rep['clips']} clips), mean ± std over seeds",
            "",
            "| run | " + " | ".join(METRICS[m] for m in metrics) + " |",
            "|" + "---|" * (len(metrics) + 1),
        ]
        lines += [f"| {a} | " + " | ".join(_cell(row[m]) for m in metrics) + " |" for a, row in rep["arms"].items()]
        lines += [
            "",
            f"| − {reference} | ΔMPJPE_h per seed | mean ± std | 95 % interval over clips | one clip left out"
            " | ΔCDev_ho mean ± std | 95 % interval over clips |",
            "|---|---|---|---|---|---|---|",
        ]
        for label, d in rep["paired"].items():
            h, c = d["mpjpe/ra/h"], d["cdev/ho"]
            per = ", ".join(f"{v:+.2f}" for v in h["per_seed"].values()) or "n/a"

            def interval(rec: Optional[dict[str, Any]]) -> str:
                return "n/a" if rec is None else f"[{rec['ci95'][0]:+.2f}, {rec['ci95'][1]:+.2f}]"

            loo = (h["clips"] or {}).get("leave_one_out")
            left = (
                f"{loo['min'][0]:+.2f} (without {loo['min'][1]}) … {loo['max'][0]:+.2f} (without {loo['max'][1]})"
                if loo
                else "n/a"
            )
            lines.append(
                f"| {label} | {per} | {_cell(h, True)} | {interval(h['clips'])} | {left}"
                f" | {_cell(c, True)} | {interval(c['clips'])} |"
            )
        lines.append("")
    return "\n".join(lines)


def run(cfg: HeldoutConfig) -> dict[str, Any]:
    """Evaluate every run on every split and write ``heldout.json`` and ``heldout.md``."""
    torch.set_num_threads(cfg.threads or available_cores())
    runs = parse_runs(cfg.runs)
    if not runs:
        raise SystemExit("heldout: error: no runs given (--runs LABEL=FOLDER ...)")
    if cfg.reference not in runs:
        raise SystemExit(f"heldout: error: --reference {cfg.reference!r} is not a label of --runs ({sorted(runs)})")
    root = ArcticRoot(cfg.data)
    for split in cfg.splits:
        setup, short = split.split("_", 1) if "_" in split else ("", "")
        if not root.split_path(setup, short).is_file():
            raise SystemExit(f"heldout: error: {root.split_path(setup, short)} does not exist (split {split!r})")
    ctx = {
        "root": root,
        "layers": BodyLayers.from_root(root),
        "fingerprint": data_fingerprint(root),
        "datasets": {},
        "checked": {},
    }
    per_split = {
        split: {
            label: {s: evaluate_model(p, split, cfg, ctx) for s, p in seeds.items()} for label, seeds in runs.items()
        }
        for split in cfg.splits
    }
    reports = {split: report(res, cfg.reference) for split, res in per_split.items()}
    if len(cfg.splits) > 1:
        every = {
            label: {s: merged([per_split[sp][label][s] for sp in cfg.splits]) for s in seeds}
            for label, seeds in runs.items()
        }
        reports[" + ".join(cfg.splits)] = report(every, cfg.reference)
    out = Path(cfg.out)
    out.mkdir(parents=True, exist_ok=True)
    record = {"config": asdict(cfg), "data_fingerprint": ctx["fingerprint"], "reports": reports}
    (out / "heldout.json").write_text(json.dumps(record, indent=1))
    (out / "heldout.md").write_text(markdown(reports, cfg.reference))
    print((out / "heldout.md").read_text())
    return record


def main(argv: Optional[list[str]] = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_dataclass_arguments(p, HeldoutConfig, HeldoutConfig())
    run(dataclass_from_args(HeldoutConfig, p.parse_args(argv)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
