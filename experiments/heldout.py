#!/usr/bin/env python
"""Finished downstream models on a larger held-out set, with the uncertainty over its clips.

A generated world's validation split holds few clips (one subject, sequence and camera view
each): a paired difference of 1-2 mm between two arms of ``experiments/downstream.py`` can come
from one clip on which one of them fails. This script evaluates the saved models of downstream
runs on the held-out splits of another ARCTIC-format root made by the same generator with more
held-out sequences (``hogsa world --preset small_styles_heldout`` for models trained on
``small_styles``: the same bodies and training files, five times the held-out sequences, a
test subject), and reports ARCTIC's per-frame metrics per run and, against a reference, the
paired difference per seed with its 95 % interval over clips and its range with one clip left
out (:func:`~hogsa_loader.baselines.clips.clip_uncertainty`), per split and over all of them,
for MPJPE_h and CDev_ho and for each hand's MPJPE (a change that helps one hand and costs the
other shows there).

Every model must have been trained with the MANO layers and object templates of the root it
is evaluated on (checked against its training root when that still exists). Each (model file,
root, split) is evaluated once; the result is cached in ``OUT/cache``.

Outputs in ``--out``: ``heldout.json`` and ``heldout.md``.

Usage::

    hogsa world --out runs/world_heldout --preset small_styles_heldout
    python experiments/heldout.py --data runs/world_heldout/arctic_data/data --reference real \\
        --runs real=runs/downstream/runs/real,hogsa=runs/downstream/runs/hogsa
"""

from __future__ import annotations

import argparse
import dataclasses
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

from hogsa_loader.assets.arctic import ArcticRoot
from hogsa_loader.assets.hands.mano_io import load_mano
from hogsa_loader.baselines.arcticnet_sf import load_saved_model
from hogsa_loader.baselines.clips import (
    CLIP_METRICS,
    ClipSums,
    clip_mean,
    clip_sums,
    clip_uncertainty,
    interval_text,
    left_out_text,
)
from hogsa_loader.baselines.engine import BodyLayers, evaluate, temporal_order
from hogsa_loader.cli.dataclass_args import add_dataclass_arguments, dataclass_from_args
from hogsa_loader.compose.plates import data_fingerprint
from hogsa_loader.errors import AssetError, read_json
from hogsa_loader.io.atomic import atomic_write_json
from hogsa_loader.io.hashing import sha256_file
from hogsa_loader.sample.arctic_dataset import ArcticDataset
from hogsa_loader.sample.augment import ArcticConfig
from hogsa_loader.system import available_cores

#: Per-frame metrics reported (ARCTIC's names).
METRICS = {
    "mpjpe/ra/h": "MPJPE_h (mm)",
    "mpjpe/ra/r": "MPJPE right (mm)",
    "mpjpe/ra/l": "MPJPE left (mm)",
    "cdev/ho": "CDev_ho (mm)",
    "mrrpe/r/l": "MRRPE_rl (mm)",
    "aae": "AAE (°)",
    "success_rate/0.05": "Success (%)",
}
#: Each hand's MPJPE (ARCTIC's per-hand terms of MPJPE_h), paired per clip like MPJPE_h.
HAND_METRICS = ("mpjpe/ra/r", "mpjpe/ra/l")
#: The metrics kept per clip and paired against the reference.
PAIRED_METRICS = CLIP_METRICS + HAND_METRICS
CACHE_VERSION = 2
#: Run settings that may differ between the seeds of one label.
PER_SEED = ("seed", "init_sha256")


@dataclass
class HeldoutConfig:
    """One evaluation of finished runs on a held-out root."""

    data: str = field(
        default="",
        metadata={"help": "ARCTIC-format root (…/arctic_data/data) whose held-out splits are read", "required": True},
    )
    runs: tuple[str, ...] = field(
        default=(),
        metadata={"help": "LABEL=FOLDER, FOLDER holding seed<N>/ of finished downstream runs", "required": True},
    )
    reference: str = field(default="real", metadata={"help": "label of the runs the others are paired with"})
    splits: tuple[str, ...] = field(default=("p1_val", "p1_test"), metadata={"help": "held-out splits of --data"})
    out: str = field(default="runs/heldout", metadata={"help": "output folder (cache in OUT/cache)"})
    batch_size: int = field(default=32, metadata={"help": "frames per evaluation batch", "type": "positive_int"})
    device: str = field(default="cpu", metadata={"help": "where the models run", "type": "torch_device"})
    threads: int = field(default=0, metadata={"help": "torch threads (0: every core)", "type": "non_negative_int"})


@dataclass
class _Context:
    """What every evaluation of one command shares."""

    cfg: HeldoutConfig
    root: ArcticRoot
    layers: BodyLayers
    fingerprints: dict[str, str]  # split -> sha256 of the root's cameras, world record and split file
    datasets: dict[tuple[str, int], ArcticDataset] = field(default_factory=dict)
    bodies: dict[str, str] = field(default_factory=dict)  # root path -> bodies_digest
    unchecked: list[str] = field(default_factory=list)  # models whose training root is gone


def _comparable(settings: dict[str, Any]) -> dict[str, Any]:
    """A run's settings without those that differ from seed to seed."""
    out = {k: v for k, v in settings.items() if k not in PER_SEED}
    if isinstance(out.get("model"), dict):
        out["model"] = {k: v for k, v in out["model"].items() if k not in PER_SEED}
    return out


def finished_models(label: str, folder: Path) -> dict[int, Path]:
    """seed → model file of the finished runs in ``folder`` (``seed<N>/``): a model counts when
    its run finished (``result.json`` without ``diverged``) with the settings its ``model.json``
    records and that manifest describes these weights (``tensors_sha256``), and every seed's run
    has the same settings but for the seed and its start file.

    Raises:
        SystemExit: naming the folder when it holds no finished run or runs of other settings.
    """
    seeds: dict[int, Path] = {}
    settings: dict[int, dict[str, Any]] = {}
    for path in sorted(folder.glob("seed*/model.safetensors")):
        suffix = path.parent.name[len("seed") :]
        result = path.with_name("result.json")
        if not suffix.isdigit() or not result.is_file():
            continue
        if not path.with_name("model.json").is_file():
            continue
        res, manifest = read_json(result), read_json(path.with_name("model.json"))
        if res.get("diverged") or res.get("settings") != manifest.get("settings"):  # type: ignore[union-attr]
            continue
        if manifest.get("tensors_sha256") not in (None, sha256_file(path)):  # type: ignore[union-attr]
            continue  # a manifest of other weights (a save torn between its two files)
        seeds[int(suffix)] = path
        settings[int(suffix)] = _comparable(manifest["settings"])  # type: ignore[index]
    if not seeds:
        raise SystemExit(f"heldout: error: no finished run (seed<N>/ with model and result) in {folder} ({label})")
    first = next(iter(settings.values()))
    if any(v != first for v in settings.values()):
        raise SystemExit(f"heldout: error: the runs in {folder} ({label}) differ in settings beyond their seeds")
    return seeds


def parse_runs(items: tuple[str, ...]) -> dict[str, dict[int, Path]]:
    """``LABEL=FOLDER`` items → label → seed → model file (:func:`finished_models`)."""
    runs: dict[str, dict[int, Path]] = {}
    for item in items:
        label, sep, folder = item.partition("=")
        if not sep or not label or not folder:
            raise SystemExit(f"heldout: error: --runs takes LABEL=FOLDER, got {item!r}")
        if label in runs:
            raise SystemExit(f"heldout: error: label {label!r} given twice")
        runs[label] = finished_models(label, Path(folder))
    return runs


def _digest_arrays(h: Any, prefix: str, record: Any, skip: tuple[str, ...] = ()) -> None:
    for f in dataclasses.fields(record):
        if f.name.startswith(skip):
            continue
        value = getattr(record, f.name)
        h.update(f"{prefix}.{f.name}".encode())
        if isinstance(value, np.ndarray):
            h.update(f"{value.dtype}{value.shape}".encode() + np.ascontiguousarray(value).tobytes())
        else:
            h.update(repr(value).encode())


def bodies_digest(root: ArcticRoot) -> str:
    """sha256 over what a model's layers and targets are built from: both MANO models' arrays
    (not their file path, metadata or vertex colours) and every object template's geometry,
    parts, keypoints and diameter (not its texture)."""
    h = hashlib.sha256()
    for side in ("right", "left"):
        _digest_arrays(h, f"mano.{side}", load_mano(root.mano_dir, side=side), skip=("source", "meta", "vertex_colors"))
    for name, template in sorted(root.object_templates(load_texture=False).items()):
        _digest_arrays(h, name, template, skip=("tex",))
    return h.hexdigest()


def check_bodies(settings: dict[str, Any], path: Path, ctx: _Context) -> None:
    """Refuse a model whose training root (``settings["data"]``) has other MANO models or
    object templates than the evaluated root; a model whose training root (or its bodies) is not
    on disk is listed in ``ctx.unchecked`` instead.

    Raises:
        SystemExit: naming the model file and its training root.
    """
    try:
        train = ArcticRoot(str(settings["data"])).data_root if settings.get("data") else None
        if train is not None and str(train) not in ctx.bodies:
            ctx.bodies[str(train)] = bodies_digest(ArcticRoot(train))
    except AssetError:
        train = None
    if train is None:
        if str(path) not in ctx.unchecked:
            ctx.unchecked.append(str(path))
        return
    if ctx.bodies[str(train)] != ctx.bodies[str(ctx.root.data_root)]:
        raise SystemExit(
            f"heldout: error: {path} was trained on {train}, whose MANO models or object templates differ from --data's"
        )


def _finite(x: Any) -> Optional[float]:
    x = float(x)
    return x if np.isfinite(x) else None


def _read_cache(path: Path, digest: str, fingerprint: str) -> Optional[dict[str, Any]]:
    try:
        rec = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    ok = rec.get("version") == CACHE_VERSION and rec.get("model_sha256") == digest
    return rec if ok and rec.get("data_fingerprint") == fingerprint else None


def evaluate_model(path: Path, split: str, ctx: _Context) -> dict[str, Any]:
    """ARCTIC's per-frame metrics of one model on one split, cached in ``OUT/cache`` by the
    model file's sha256 and the split's fingerprint (the root's cameras, world record, MANO
    models, object templates and split file); the model's bodies are checked on every call.

    Returns:
        ``{"version", "model", "model_sha256", "split", "data_fingerprint", "frames",
        "summary": {metric: value or None}, "clips": clip_sums}``.
    """
    digest, fingerprint = sha256_file(path), ctx.fingerprints[split]
    check_bodies(dict(read_json(path.with_name("model.json"))["settings"]), path, ctx)  # type: ignore[index]
    cache = Path(ctx.cfg.out) / "cache" / f"{digest[:16]}-{fingerprint[:16]}-{split}.json"
    rec = _read_cache(cache, digest, fingerprint)
    if rec is not None:
        return rec
    model, settings = load_saved_model(path, ctx.layers.mano_r, ctx.layers.mano_l, ctx.layers.objects)
    img_res = int(settings["model"]["img_res"])
    ds = ctx.datasets.get((split, img_res))
    if ds is None:
        ds = ArcticDataset(ctx.cfg.data, split=split, seed=0, augment=False, config=ArcticConfig(img_res=img_res))
        ctx.datasets[(split, img_res)] = ds
    loader = DataLoader(Subset(ds, temporal_order(ds.imgnames)), batch_size=ctx.cfg.batch_size)
    with tqdm(total=len(ds), desc=f"{path.parent.parent.name}/{path.parent.name} {split}", unit="frame") as bar:
        layers = ctx.layers.to(ctx.cfg.device)
        ev = evaluate(
            model.to(ctx.cfg.device), loader, layers, img_res, ctx.cfg.device, temporal=False, on_batch=bar.update
        )
    rec = {
        "version": CACHE_VERSION,
        "model": str(path),
        "model_sha256": digest,
        "split": split,
        "data_fingerprint": fingerprint,
        "frames": ev["frames"],
        "summary": {k: _finite(ev["summary"][k]) for k in METRICS if k in ev["summary"]},
        "clips": clip_sums(ev, PAIRED_METRICS),
    }
    cache.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_json(cache, rec, indent=None, allow_nan=False)
    return rec


def merged(recs: list[dict[str, Any]]) -> dict[str, Any]:
    """One run's results on several splits as one: the clip metrics formed again over all
    clips (frame-weighted), the other metrics left out."""
    clips: ClipSums = {c: v for r in recs for c, v in r["clips"].items()}
    summary = {m: clip_mean(clips, m) for m in PAIRED_METRICS}
    return {"frames": sum(r["frames"] for r in recs), "summary": summary, "clips": clips}


def _mean_std(vals: list[Optional[float]]) -> dict[str, Optional[float]]:
    xs = [v for v in vals if v is not None]
    return {"mean": float(np.mean(xs)) if xs else None, "std": float(np.std(xs, ddof=1)) if len(xs) > 1 else None}


def report(results: dict[str, dict[int, dict[str, Any]]], reference: str) -> dict[str, Any]:
    """Mean ± std per label and the paired differences against ``reference`` of one split."""
    rows = {
        label: {m: _mean_std([r["summary"].get(m) for r in by_seed.values()]) for m in METRICS}
        for label, by_seed in results.items()
    }
    paired = {}
    ref = results.get(reference, {})
    for label, by_seed in results.items():
        if label == reference:
            continue
        seeds = sorted(set(by_seed) & set(ref))
        paired[label] = {}
        for m in PAIRED_METRICS:
            d = {
                s: by_seed[s]["summary"][m] - ref[s]["summary"][m]
                for s in seeds
                if None not in (by_seed[s]["summary"][m], ref[s]["summary"][m])
            }
            paired[label][m] = {
                "per_seed": d,
                **_mean_std(list(d.values())),
                "clips": clip_uncertainty([(by_seed[s]["clips"], ref[s]["clips"]) for s in seeds], m),
            }
    frames = next((r["frames"] for by_seed in results.values() for r in by_seed.values()), 0)
    clips = next((len(r["clips"]) for by_seed in results.values() for r in by_seed.values()), 0)
    return {"frames": frames, "clips": clips, "arms": rows, "paired": paired}


def _cell(row: dict[str, Optional[float]], sign: bool = False) -> str:
    if row["mean"] is None:
        return "n/a"
    fmt = "+.2f" if sign else ".2f"
    return f"{row['mean']:{fmt}}" + (f" ± {row['std']:.2f}" if row["std"] is not None else "")


def _head(cells: list[str]) -> list[str]:
    """A blank line, then a Markdown table's header row of ``cells`` and its rule."""
    return ["", "| " + " | ".join(cells) + " |", "|" + "---|" * len(cells)]


def _per_seed(d: dict[str, Any]) -> str:
    return ", ".join(f"{v:+.2f}" for v in d["per_seed"].values()) or "n/a"


def markdown(reports: dict[str, dict[str, Any]], reference: str) -> str:
    """One section per split: the runs' metrics, then each label against the reference."""
    lines = []
    for split, rep in reports.items():
        metrics = [m for m in METRICS if any(rep["arms"][a][m]["mean"] is not None for a in rep["arms"])]
        lines.append(f"**{split}** ({rep['frames']} frames, {rep['clips']} clips), mean ± std over seeds")
        lines += _head(["run", *(METRICS[m] for m in metrics)])
        lines += [f"| {a} | " + " | ".join(_cell(row[m]) for m in metrics) + " |" for a, row in rep["arms"].items()]
        interval = "95 % interval over clips"
        lines += _head(
            [f"− {reference}", "ΔMPJPE_h per seed", "mean ± std", interval, "one clip left out", "ΔCDev_ho mean ± std"]
            + [interval]
        )
        for label, d in rep["paired"].items():
            h, c = d["mpjpe/ra/h"], d["cdev/ho"]
            lines.append(
                f"| {label} | {_per_seed(h)} | {_cell(h, True)} | {interval_text(h['clips'])}"
                f" | {left_out_text(h['clips'])} | {_cell(c, True)} | {interval_text(c['clips'])} |"
            )
        lines += _head(
            [f"− {reference}, per hand", "ΔMPJPE right per seed", "mean ± std", interval]
            + ["ΔMPJPE left per seed", "mean ± std", interval]
        )
        for label, d in rep["paired"].items():
            cells = [f"{_per_seed(d[m])} | {_cell(d[m], True)} | {interval_text(d[m]['clips'])}" for m in HAND_METRICS]
            lines.append(f"| {label} | " + " | ".join(cells) + " |")
        lines.append("")
    return "\n".join(lines)


def _context(cfg: HeldoutConfig) -> _Context:
    """The root, its layers and the fingerprint of each split (refusing a missing split)."""
    root = ArcticRoot(cfg.data)
    bodies = bodies_digest(root)
    base = f"{data_fingerprint(root)}:{bodies}"
    fingerprints = {}
    for split in cfg.splits:
        protocol, sep, short = split.partition("_")
        if not sep or not protocol or not short:
            raise SystemExit(f"heldout: error: --splits takes names like p1_val, got {split!r}")
        path = root.split_path(protocol, short)
        if not path.is_file():
            raise SystemExit(f"heldout: error: {path} does not exist (split {split!r})")
        fingerprints[split] = hashlib.sha256(f"{base}:{sha256_file(path)}".encode()).hexdigest()
    return _Context(cfg, root, BodyLayers.from_root(root), fingerprints, bodies={str(root.data_root): bodies})


def run(cfg: HeldoutConfig) -> dict[str, Any]:
    """Evaluate every run on every split and write ``heldout.json`` and ``heldout.md``."""
    torch.set_num_threads(cfg.threads or available_cores())
    if len(set(cfg.splits)) != len(cfg.splits):
        raise SystemExit(f"heldout: error: a split is given twice in --splits {list(cfg.splits)}")
    runs = parse_runs(cfg.runs)
    if not runs:
        raise SystemExit("heldout: error: no runs given (--runs LABEL=FOLDER,...)")
    if cfg.reference not in runs:
        raise SystemExit(f"heldout: error: --reference {cfg.reference!r} is not a label of --runs ({sorted(runs)})")
    ctx = _context(cfg)
    per_split = {
        split: {label: {s: evaluate_model(p, split, ctx) for s, p in seeds.items()} for label, seeds in runs.items()}
        for split in cfg.splits
    }
    reports = {split: report(res, cfg.reference) for split, res in per_split.items()}
    if len(cfg.splits) > 1:
        every = {
            label: {s: merged([per_split[sp][label][s] for sp in cfg.splits]) for s in seeds}
            for label, seeds in runs.items()
        }
        reports[" + ".join(cfg.splits)] = report(every, cfg.reference)
    if ctx.unchecked:
        print(f"[heldout] bodies not checked (training root not on disk): {ctx.unchecked}")
    out = Path(cfg.out)
    out.mkdir(parents=True, exist_ok=True)
    record = {"config": asdict(cfg), "fingerprints": ctx.fingerprints, "unchecked": ctx.unchecked, "reports": reports}
    atomic_write_json(out / "heldout.json", record, allow_nan=False)
    (out / "heldout.md").write_text(markdown(reports, cfg.reference))
    print((out / "heldout.md").read_text())
    return record


def parse_args(argv: Optional[list[str]] = None) -> HeldoutConfig:
    """The evaluation's settings from command-line flags."""
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_dataclass_arguments(p, HeldoutConfig, HeldoutConfig())
    return dataclass_from_args(HeldoutConfig, p.parse_args(argv))


def main(argv: Optional[list[str]] = None) -> int:
    run(parse_args(argv))
    return 0


if __name__ == "__main__":
    sys.exit(main())
