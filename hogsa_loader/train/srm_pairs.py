"""SRM training pairs: HOGS renders (inputs) and ground-truth crops (targets) of each run.

Start with :func:`find_runs` (the finished HOGS runs of a folder), :func:`fold_runs` (their
view-fold runs) and :func:`load_pairs`, which returns a run's :class:`PairSet`; its docstring
describes how samples are selected, where the inputs come from (``mode``) and validation.
"""

from __future__ import annotations

import hashlib
import json
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Optional, Sequence

import numpy as np
import torch
from safetensors.torch import load_file, save
from torch import Tensor

import hogsa_loader
from hogsa_loader.errors import AssetError
from hogsa_loader.io.atomic import atomic_write
from hogsa_loader.models.gaussians.hogs_model import LIGHT_DIR, PART_NAMES, HogsModel
from hogsa_loader.models.gaussians.shading import LIGHT_TENSORS
from hogsa_loader.train.hogs_data import HogsData, ViewSample
from hogsa_loader.train.hogs_source import HogsSource, load_run_data

__all__ = ["PAIR_MODES", "PairSet", "find_runs", "load_pairs", "fold_runs"]

PAIR_MODES = ("own", "cross", "both")


def find_runs(runs_dir: str | Path, names: Optional[Sequence[str]] = None) -> list[Path]:
    """Finished HOGS runs: ``runs_dir`` itself if it is one, else its sub-folders that are
    (sorted by name). Unfinished ones (missing part manifests) are skipped."""
    runs_dir = Path(runs_dir)
    if not runs_dir.is_dir():
        raise AssetError(runs_dir, "HOGS runs folder is missing")
    cands = [runs_dir] if HogsModel.is_run(runs_dir) else sorted(p for p in runs_dir.iterdir() if p.is_dir())
    runs = [p for p in cands if HogsModel.is_run(p) and (p / "config.json").is_file()]
    if names:
        runs = [p for p in runs if p.name in set(names)]
    if not runs:
        raise AssetError(
            runs_dir, f"no finished HOGS run (folders with {', '.join(PART_NAMES)} manifests and config.json)"
        )
    return runs


#: Part of every render-cache key: bump it whenever the rasteriser or how a HOGS checkpoint
#: is posed and rendered changes, so caches made by older code are never served (2: seam
#: welding and its ``weld_seams`` setting).
RENDER_CACHE_VERSION = 2


def _run_hash(run: Path) -> str:
    """Hash of a run's weights and part settings, the library version and
    :data:`RENDER_CACHE_VERSION`."""
    h = hashlib.sha256(f"{hogsa_loader.__version__}/{RENDER_CACHE_VERSION}".encode())
    for name in PART_NAMES:
        m = json.loads((run / name / "manifest.json").read_text())
        h.update(m["tensors_sha256"].encode() + json.dumps(m.get("config"), sort_keys=True).encode())
    light = run / LIGHT_DIR / LIGHT_TENSORS
    if light.is_file():
        h.update(hashlib.sha256(light.read_bytes()).digest())
    return h.hexdigest()[:16]


def _inputs_hash(source: HogsSource, object_name: str, data: HogsData, parts: dict[str, Sequence[ViewSample]]) -> str:
    """Hash of everything a render depends on besides the weights: the MANO layers, the
    object template, each sample's annotated poses and camera, so a shared cache never
    serves renders of other labels (e.g. the same run on a ``world-noise`` copy), other
    cameras or another body model."""
    h = hashlib.sha256()
    for side in sorted(source.mano_layers):
        for k, v in sorted(source.mano_layers[side].named_buffers()):  # (the MANO buffers are non-persistent)
            h.update(f"{side}.{k}".encode() + v.detach().cpu().contiguous().numpy().tobytes())
    tpl = source.object_templates.get(object_name)
    if tpl is not None:
        for arr in (tpl.verts, tpl.faces, tpl.parts):
            h.update(np.ascontiguousarray(np.asarray(arr)).tobytes())
    for name in sorted(parts):
        samples = parts[name]
        h.update(name.encode())
        if not samples:
            continue
        for k, v in sorted(data.poses(samples, dtype=torch.float64).items()):
            h.update(k.encode() + v.numpy().tobytes())
        for s in samples:
            h.update(np.ascontiguousarray(s.world2cam, dtype=np.float64).tobytes())
            h.update(np.ascontiguousarray(s.K, dtype=np.float64).tobytes())
    return h.hexdigest()[:16]


def _trained_views(cfg: dict) -> set[int]:
    return {int(v) for v in cfg.get("views") or []} - {int(v) for v in cfg.get("eval_views") or []}


def fold_runs(run: Path, candidates: Sequence[Path]) -> list[Path]:
    """The view-fold runs among ``candidates`` for ``run``: same data, subject and object,
    trained on a strict subset of the run's training views and none of its held-out views.

    Raises:
        AssetError: a candidate of the same (subject, object) trained on a held-out view of
            ``run`` (its renders would leak the held-out views into SRM training).
    """
    rc = json.loads((run / "config.json").read_text())
    own = _trained_views(rc)
    held = {int(v) for v in rc.get("eval_views") or []}
    out = []
    for f in candidates:
        if f.resolve() == run.resolve():
            continue
        fc = json.loads((f / "config.json").read_text())
        if (fc.get("subject"), fc.get("object")) != (rc.get("subject"), rc.get("object")):
            continue
        seen = _trained_views(fc)
        if seen & held:
            raise AssetError(
                f / "config.json", f"view fold trained on held-out view(s) {sorted(seen & held)} of {run.name}"
            )
        if seen < own:
            out.append(f)
    return out


@dataclass
class PairSet:
    """Coarse renders and targets of one HOGS run.

    Attributes:
        name: run folder name; data: its :class:`HogsData` (GT at ``image_size``).
        train_rgb: (N, h, w, 3) uint8 premultiplied renders at ``image_size/scale``;
        train_alpha: (N, h, w) uint8; train_rows: (N,) long, the ``data.train`` sample of
            each render (a sample can appear twice in mode ``"both"``);
        eval_rgb / eval_alpha: float32 renders of the held-out samples by the run itself.
        margin_px: HOGS loss-region dilation at ``image_size``.
        sources: where the training renders come from (run names and counts).
        val_rgb / val_alpha / val_rows: validation renders (uint8) and their ``data.train``
            samples (empty without ``val_views``).
        cache_files: the render-cache files these renders were read from or written to.

    For every finished HOGS run (``find_runs``) the training (frame, view) samples are selected
    exactly as its HOGS training did (its ``config.json`` rebuilt by
    :func:`~hogsa_loader.train.hogs_source.load_run_data`: views, masks, window, frames), so
    held-out views and frames are never seen. Inputs are frozen renders (final SH degree,
    premultiplied on black + alpha) at ``image_size / scale``, cached under ``cache_dir`` keyed
    by the checkpoints' hashes.

    Where the inputs come from (``mode``):

    * ``"own"`` — the run renders its own training views. Those are views the HOGS model was
      fitted to, so their errors are far smaller than on views it never saw (the small world:
      42.8 dB vs 38.3 dB full-image PSNR), and an SRM trained on them learns almost nothing
      that transfers to novel views (measured: +0.01 dB held-out after 1000 steps).
    * ``"cross"`` — *view folds*: extra HOGS runs of the same (subject, object) trained on
      subsets of the training views (``cross_runs``, e.g. views {1,3,5,7} and {2,4,6}). Each
      training sample is rendered by a fold that did **not** see its view, so the inputs carry
      genuine novel-view errors — the situation the loader is in when it renders new
      viewpoints. A fold that trained on one of the run's held-out views is refused.
    * ``"both"`` — the two sets together.

    Validation (``val_views``): training views whose pairs are kept out of SRM training and used
    only to choose the SRM's training length (best checkpoint) — the run's held-out views must
    stay unseen, so they cannot serve. Validation inputs are the fold renders of those views
    (novel-view errors, like the held-out renders) when folds are used, else the run's own.
    """

    name: str
    data: HogsData
    train_rgb: Tensor
    train_alpha: Tensor
    train_rows: Tensor
    eval_rgb: Tensor
    eval_alpha: Tensor
    margin_px: int
    sources: dict[str, int]
    val_rgb: Tensor = field(default_factory=lambda: torch.zeros(0, 0, 0, 3, dtype=torch.uint8))
    val_alpha: Tensor = field(default_factory=lambda: torch.zeros(0, 0, 0, dtype=torch.uint8))
    val_rows: Tensor = field(default_factory=lambda: torch.zeros(0, dtype=torch.long))
    cache_files: list[Path] = field(default_factory=list)


def _render_all(
    model: HogsModel, data: HogsData, samples: Sequence[ViewSample], size: int, sh_degree: int, batch: int = 4
) -> tuple[Tensor, Tensor]:
    """Render samples at ``size`` (K scaled from the data's resolution): rgb (N,h,w,3), alpha (N,h,w)."""
    s = size / data.image_size
    scale = torch.tensor([[s, 0, 0], [0, s, 0], [0, 0, 1.0]], dtype=torch.float64)
    rgbs, alphas = [], []
    with torch.no_grad():
        for i in range(0, len(samples), batch):
            chunk = samples[i : i + batch]
            poses = data.poses(chunk)
            viewmats = torch.as_tensor(np.stack([c.world2cam for c in chunk]), dtype=torch.float32)[:, None]
            Ks = (scale @ torch.as_tensor(np.stack([c.K for c in chunk]))).float()[:, None]
            out = model.render(poses, viewmats, Ks, size, size, sh_degree=sh_degree, render_mode="RGB")
            rgbs.append(out.rgb[:, 0].clamp(0, 1))
            alphas.append(out.alpha[:, 0, ..., 0].clamp(0, 1))
    if not rgbs:
        return torch.zeros(0, size, size, 3), torch.zeros(0, size, size)
    return torch.cat(rgbs), torch.cat(alphas)


def _final_sh(rc: dict) -> int:
    sh_warm = int(rc.get("sh_warmup", 0))
    sh_deg = int(rc.get("sh_degree", 3))
    return sh_deg if sh_warm <= 0 else min(sh_deg, int(rc.get("iters", 0)) // sh_warm)


def _cached_renders(
    run: Path,
    source: HogsSource,
    data: HogsData,
    parts: dict[str, Sequence[ViewSample]],
    lo: int,
    cache_dir: Path,
    log: Callable[[str], None],
) -> tuple[dict[str, Tensor], Path]:
    """``{name}_rgb`` / ``{name}_alpha`` renders of ``run`` for each sample list of ``parts``
    (``train`` lists as uint8, others float32), read from or written to the cache, and the
    cache file."""
    rc = json.loads((run / "config.json").read_text())
    sh = _final_sh(rc)
    key = hashlib.sha256(
        json.dumps(
            [
                _run_hash(run),
                _inputs_hash(source, str(rc.get("object", "")), data, parts),
                data.image_size,
                lo,
                sh,
                {k: [(s.seq_index, s.frame, s.view) for s in v] for k, v in parts.items()},
            ]
        ).encode()
    ).hexdigest()[:16]
    path = cache_dir / f"coarse_{run.name}_{key}.safetensors"
    if path.is_file():
        log(f"[srm] {run.name}: cached renders {path.name} ({', '.join(f'{len(v)} {k}' for k, v in parts.items())})")
        return load_file(str(path)), path
    model = HogsModel.from_run(run, source.mano_layers, source.object_templates)
    t0 = time.perf_counter()
    t: dict[str, Tensor] = {}
    for name, samples in parts.items():
        rgb, a = _render_all(model, data, samples, lo, sh)
        if name.startswith("train"):
            rgb, a = (rgb * 255).round().to(torch.uint8), (a * 255).round().to(torch.uint8)
        t[f"{name}_rgb"], t[f"{name}_alpha"] = rgb.contiguous(), a.contiguous()
    cache_dir.mkdir(parents=True, exist_ok=True)
    atomic_write(path, save(t))  # runs sharing a cache never write the same temporary file
    log(
        f"[srm] {run.name}: rendered {', '.join(f'{len(v)} {k}' for k, v in parts.items())} views at {lo}² "
        f"(SH degree {sh}) in {time.perf_counter() - t0:.0f} s -> {path.name}"
    )
    return t, path


#: (source run name, rgb uint8 (N, h, w, 3), alpha uint8 (N, h, w), rows of ``data.train`` (N,))
_Chunk = tuple[str, Tensor, Tensor, Tensor]


def _check_pair_views(run: Path, rc: dict, data: HogsData, val: set[int], mode: str, folds: Sequence[Path]) -> None:
    """Refuse validation views that are not (or are all) training views of the run, and a
    cross/both pair mode without view-fold runs.

    Raises:
        ValueError: a validation view is not a training view of the run, or they are all.
        AssetError: ``mode`` needs view folds and there are none.
    """
    train_views = {smp.view for smp in data.train}
    if val - train_views:
        raise ValueError(
            f"validation view(s) {sorted(val - train_views)} are not training views of {run.name} "
            f"(training views {sorted(train_views)})"
        )
    if val and val >= train_views:
        raise ValueError(f"validation views {sorted(val)} leave no training view of {run.name}")
    if mode != "own" and not folds:
        raise AssetError(
            run,
            f"pair mode {mode!r} needs view-fold runs of {rc['subject']}/{rc['object']} "
            "(HOGS runs trained on subsets of the training views; --cross-hogs)",
        )


def _fold_chunk(
    fold: Path,
    source: HogsSource,
    data: HogsData,
    val: set[int],
    mode: str,
    lo: int,
    cache_dir: Path,
    log: Callable[[str], None],
    files: list[Path],
) -> Optional[_Chunk]:
    """The renders by view-fold run ``fold`` of the training samples whose view it did not
    see (with ``mode="own"`` only those of validation views), or None when there are none;
    the cache file is appended to ``files``."""
    seen = _trained_views(json.loads((fold / "config.json").read_text()))
    idx = [i for i, smp in enumerate(data.train) if smp.view not in seen]
    if mode == "own":  # folds only serve validation here
        idx = [i for i in idx if data.train[i].view in val]
    if not idx:
        return None
    ft, fold_file = _cached_renders(fold, source, data, {"train": [data.train[i] for i in idx]}, lo, cache_dir, log)
    files.append(fold_file)
    return fold.name, ft["train_rgb"], ft["train_alpha"], torch.as_tensor(idx, dtype=torch.long)


def _assign_chunks(
    chunks: Sequence[_Chunk], run_name: str, data: HogsData, val: set[int], mode: str, has_folds: bool
) -> tuple[tuple[list, list, list], tuple[list, list, list], dict[str, int]]:
    """Split every source's renders into training and validation pairs.

    A source supplies training pairs unless ``mode`` excludes it (``own``: no fold pairs,
    ``cross``: no own pairs); validation pairs come from the folds when there are folds.

    Returns:
        ``((rgbs, alphas, rows), (val rgbs, val alphas, val rows), {source: training pairs})``,
        lists of tensors per source.
    """
    val_from_folds = has_folds and bool(val)  # validation inputs: fold renders when there are folds
    rgbs, alphas, rows, vrgb, valpha, vrows, sources = [], [], [], [], [], [], {}
    for name, rgb, alpha, idx in chunks:
        is_fold = name != run_name
        trains = mode != ("own" if is_fold else "cross")  # this source supplies training pairs
        is_val = torch.as_tensor([data.train[int(i)].view in val for i in idx], dtype=torch.bool)
        keep = ~is_val if trains else torch.zeros_like(is_val)
        use_val = is_val if is_fold == val_from_folds else torch.zeros_like(is_val)
        if keep.any():
            rgbs.append(rgb[keep])
            alphas.append(alpha[keep])
            rows.append(idx[keep])
            sources[name] = int(keep.sum())
        if use_val.any():
            vrgb.append(rgb[use_val])
            valpha.append(alpha[use_val])
            vrows.append(idx[use_val])
    return (rgbs, alphas, rows), (vrgb, valpha, vrows), sources


def load_pairs(
    data_root: str | Path,
    run: Path,
    cache_dir: Path,
    image_size: Optional[int] = None,
    scale: int = 1,
    mode: str = "own",
    folds: Sequence[Path] = (),
    log: Callable[[str], None] = print,
    val_views: Sequence[int] = (),
) -> PairSet:
    """Load one run's split and its coarse renders (made as :class:`PairSet` describes).

    Args:
        data_root: the dataset root the runs were trained on; run: the HOGS run folder;
        cache_dir: render cache; image_size: GT resolution (default: the run's);
        scale: output / input resolution factor; mode: ``"own"``, ``"cross"`` or ``"both"``;
        folds: view-fold runs of this run (:func:`fold_runs`; needed by ``cross``/``both``);
        val_views: training views kept out of training for validation (see :class:`PairSet`).

    Raises:
        ValueError: a validation view is not a training view of the run, or they are all.
    """
    if mode not in PAIR_MODES:
        raise ValueError(f"pair mode must be one of {PAIR_MODES}, got {mode!r}")
    rc = json.loads((run / "config.json").read_text())
    if image_size:
        rc = {**rc, "image_size": int(image_size)}
    source, data = load_run_data(rc, data=data_root)
    size = data.image_size
    if size % scale:
        raise ValueError(f"image size {size} is not divisible by scale {scale}")
    val = {int(v) for v in val_views}
    _check_pair_views(run, rc, data, val, mode, folds)
    lo = size // scale
    own_train = mode != "cross" or (bool(val) and not folds)  # the run's own training renders are used
    own_parts: dict[str, Sequence[ViewSample]] = {"eval": data.eval}
    if own_train:
        own_parts["train"] = data.train
    t, own_file = _cached_renders(run, source, data, own_parts, lo, cache_dir, log)
    files = [own_file]
    chunks: list[_Chunk] = []
    if own_train:
        chunks.append((run.name, t["train_rgb"], t["train_alpha"], torch.arange(len(data.train))))
    for f in folds if mode != "own" or val else ():
        chunk = _fold_chunk(f, source, data, val, mode, lo, cache_dir, log, files)
        if chunk is not None:
            chunks.append(chunk)
    (rgbs, alphas, rows), (vrgb, valpha, vrows), sources = _assign_chunks(
        chunks, run.name, data, val, mode, bool(folds)
    )
    if val and not vrows:
        raise AssetError(run, f"no view fold left out validation view(s) {sorted(val)}: every fold saw them")
    if mode != "own" and sum(sources.get(f.name, 0) for f in folds) == 0:
        raise AssetError(run, "the view folds cover no training view of the run (each fold saw every view)")
    margin = int(round(int(rc.get("margin", 4)) * size / (data.crop_size or size)))
    ps = PairSet(
        run.name,
        data,
        torch.cat(rgbs),
        torch.cat(alphas),
        torch.cat(rows),
        t["eval_rgb"],
        t["eval_alpha"],
        margin,
        sources,
        cache_files=files,
    )
    if vrows:
        ps.val_rgb, ps.val_alpha, ps.val_rows = torch.cat(vrgb), torch.cat(valpha), torch.cat(vrows)
    return ps
