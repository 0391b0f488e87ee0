"""``hogsa demo``: the whole pipeline on the embedded default world, cached stage by stage.

:func:`run_demo` builds (or reuses) the world, the HOGS models, ContactNet, the pose bank, the
SRM and the bundle (:func:`build_bundle_stages`), streams synthetic samples through a
DataLoader and writes ``samples.png``, ``batch.npz`` and ``demo.json``.
"""

from __future__ import annotations

import json
import os
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any, Callable, Literal, Optional

import cv2
import numpy as np
import torch
from torch.utils.data import DataLoader

from hogsa_loader.errors import PathLike
from hogsa_loader.sample.arctic_dataset import ArcticDataset
from hogsa_loader.sample.config import LoaderConfig, with_options
from hogsa_loader.sample.dataset import HOGSADataset
from hogsa_loader.sample.mixing import MixedLoader
from hogsa_loader.train.build import BuildConfig, BuildDataConfig, BuildRunConfig, build
from hogsa_loader.train.stages import StageRecords, stage_key
from hogsa_loader.view import ViewConfig, run_view
from hogsa_loader.view.grid import sample_grid
from hogsa_loader.view.pictures import demo_photographs
from hogsa_world import generate_world, get_preset

__all__ = ["DemoConfig", "run_demo", "build_bundle_stages", "demo_photographs", "unbatch"]


@dataclass
class DemoConfig:
    """Settings of :func:`run_demo` (defaults: the ``demo`` world and brief training on 2 CPU cores).

    Attributes:
        preset, seed: the world.
        data: an existing ARCTIC(-format) data root to use instead of building the world.
        pairs: (subject, object) HOGS models to train (training split only).
        hogs_iters, hogs_k, hogs_object_subdivide, hogs_image_size, hogs_sh_degree,
            hogs_frame_stride: brief HOGS training (1 Gaussian per face of the unsubdivided
            meshes: half the cost per step of the library default, so twice the steps).
        hogs_window: ``"fg"`` trains on a window around the hands and object of each frame
            (on average 1.35× the linear resolution on them at the same cost; ``"crop"``:
            whole cropped images).
        contactnet_iters: ContactNet steps; bank_per_sequence: POM frames per sequence;
            bank_variants: perturbed starts per frame (``BankDataConfig.variants``);
            bank_finger_scale: finger noise of the pose bank's starts (``BankPOMConfig.finger_scale``);
            bank_frames: ``"contact"`` (grasps only) or ``"all"`` (frames without contact keep
            their share; ``BankDataConfig.frames``).
        srm_iters, srm_crop, srm_augment: brief SRM training (crop = training window side;
            augment: ``none``/``flip``/``d4``); srm_gan: weight of its adversarial term
            (StyleUNet's conditional discriminator; 0: L1 and perceptual terms only, a
            regression to the mean image of a render). Its coarse renders are cached in
            ``OUT/cache/srm`` (keyed by the HOGS weights and labels), so a rebuild of the SRM
            stage alone does not render again; entries the build did not use (older HOGS
            weights) are deleted after it.
        samples: synthetic samples streamed; batch_size; num_workers: DataLoader workers
            (CPU rendering in the workers, one torch thread each); render_batch: samples
            per render call.
        grid_rows, grid_cols: synthetic rows × columns in ``samples.png`` (+ one real row).
        backgrounds, coco_root, coco_ann: background images (see module docstring).
        orbit_views, orbit_size: the 360° orbit of the first pair's model written to
            ``OUT/view/`` (:func:`~hogsa_loader.view.job.run_view`; 0 views: none),
            rendered again on every run (no stage).
    """

    preset: str = "demo"
    seed: int = 0
    data: Optional[str] = None
    pairs: tuple[tuple[str, str], ...] = (("s01", "box"), ("s02", "notebook"))
    hogs_iters: int = 400
    hogs_k: int = 1
    hogs_object_subdivide: int = 0
    hogs_image_size: int = 128
    hogs_sh_degree: int = 1
    hogs_frame_stride: int = 2
    hogs_window: str = "fg"
    contactnet_iters: int = 120
    bank_per_sequence: int = 6
    bank_variants: int = 1
    bank_finger_scale: float = 0.0
    bank_frames: str = "contact"
    srm_iters: int = 400
    srm_crop: int = 64
    srm_augment: str = (
        "none"  # 400 steps on the small world: +0.24 dB without, +0.06 dB with d4 (d4 pays off only in long runs)
    )
    srm_gan: float = 0.0
    samples: int = 64
    batch_size: int = 8
    num_workers: int = 2
    render_batch: int = 8
    grid_rows: int = 2
    grid_cols: int = 8
    backgrounds: Optional[str] = None
    coco_root: Optional[str] = None
    coco_ann: Optional[str] = None
    orbit_views: int = 16
    orbit_size: int = 192
    progress: bool = field(default=True, compare=False)


def unbatch(batch: Any, i: int) -> Any:
    """Sample ``i`` of a default-collated batch (tensors indexed, lists of scalars indexed)."""
    if isinstance(batch, torch.Tensor):
        return batch[i]
    if isinstance(batch, dict):
        return {k: unbatch(v, i) for k, v in batch.items()}
    if isinstance(batch, (list, tuple)):
        if batch and isinstance(batch[0], (torch.Tensor, dict, list, tuple)):
            return (
                type(batch)(unbatch(v, i) for v in batch)
                if isinstance(batch, tuple)
                else [unbatch(v, i) for v in batch]
            )
        return batch[i]
    raise TypeError(f"cannot unbatch a {type(batch).__name__}")


def _flatten_batch(batch: Any) -> dict[str, np.ndarray]:
    out: dict[str, np.ndarray] = {}
    for name, part in zip(("inputs", "targets", "meta_info"), batch):
        for k, v in part.items():
            if isinstance(v, torch.Tensor):
                out[f"{name}/{k}"] = v.detach().cpu().numpy()
            elif isinstance(v, (list, tuple)) and v and isinstance(v[0], torch.Tensor):
                out[f"{name}/{k}"] = np.stack([x.detach().cpu().numpy() for x in v], axis=1)
            else:
                out[f"{name}/{k}"] = np.asarray(v)
    return out


def _worker_init(_: int) -> None:
    torch.set_num_threads(1)


def _world_stage(cfg: DemoConfig, out: Path, stages: StageRecords, say: Callable[[str], None]) -> tuple[Path, str]:
    """Build (or reuse) the world in ``out/world`` unless ``cfg.data`` names one; its data root and key."""
    if cfg.data is not None:
        data = Path(os.path.abspath(cfg.data))
        return data, stage_key("data", str(data))  # (the seed also drives every training stage)
    world = out / "world"
    data = world / "arctic_data" / "data"
    preset = get_preset(cfg.preset)
    k_world = stage_key("world", cfg.preset, cfg.seed)
    stages.run(
        "world",
        k_world,
        [world],
        lambda: {
            "sequences": len(
                generate_world(world, preset, seed=cfg.seed, progress=cfg.progress, log=say, resume=True)["sequences"]
            )
        },
        resumable=True,
    )
    return data, k_world


def build_config(cfg: DemoConfig, data: Path, out: Path) -> BuildConfig:
    """The :class:`~hogsa_loader.train.build.BuildConfig` of the demo's settings: brief CPU
    training of its pairs on every sequence of each (1 Gaussian per face of the unsubdivided
    meshes, learning rates ×10, SH raised every third of the steps)."""
    base = BuildConfig()
    hogs = replace(
        base.hogs,
        data=replace(
            base.hogs.data,
            image_size=cfg.hogs_image_size,
            max_eval=4,
            frame_stride=cfg.hogs_frame_stride,
            window=cfg.hogs_window,
        ),
        model=replace(
            base.hogs.model, sh_degree=cfg.hogs_sh_degree, k=cfg.hogs_k, object_subdivide=cfg.hogs_object_subdivide
        ),
        optim=replace(base.hogs.optim, iters=cfg.hogs_iters, sh_warmup=max(1, cfg.hogs_iters // 3), lr_scale=10.0),
        run=replace(base.hogs.run, eval_every=cfg.hogs_iters, ckpt_every=cfg.hogs_iters, strip_views=2),
    )
    contactnet = replace(
        base.contactnet,
        optim=replace(base.contactnet.optim, iters=cfg.contactnet_iters),
        run=replace(base.contactnet.run, val_every=cfg.contactnet_iters),
    )
    bank = replace(
        base.bank,
        data=replace(
            base.bank.data, per_sequence=cfg.bank_per_sequence, variants=cfg.bank_variants, frames=cfg.bank_frames
        ),
        pom=replace(base.bank.pom, finger_scale=cfg.bank_finger_scale),
    )
    srm = replace(
        base.srm,
        data=replace(base.srm.data, crop=cfg.srm_crop, augment=cfg.srm_augment),
        model=replace(base.srm.model, channels=(16, 32, 64, 64, 64)),
        loss=replace(base.srm.loss, lambda_gan=float(cfg.srm_gan)),
        optim=replace(base.srm.optim, iters=cfg.srm_iters),
        run=replace(base.srm.run, eval_every=cfg.srm_iters, ckpt_every=cfg.srm_iters, strip_views=2),
    )
    return BuildConfig(
        data=BuildDataConfig(root=str(data), pairs=tuple(f"{s}/{o}" for s, o in cfg.pairs), sequences_like=None),
        run=BuildRunConfig(out=str(out), seed=cfg.seed),
        hogs=hogs,
        contactnet=contactnet,
        bank=bank,
        srm=srm,
    )


def build_bundle_stages(
    out: PathLike,
    config: DemoConfig = DemoConfig(),
    log: Optional[Callable[[str], None]] = print,
    gaussians: Literal["mesh", "free"] = "mesh",
) -> tuple[Path, Path, dict[str, float]]:
    """Build (or reuse) the demo's world and, from it, every stage up to the bundle
    (:func:`hogsa_loader.train.build.build`, settings :func:`build_config`), each cached in
    ``out`` by its settings.

    Stages: ``world`` (``OUT/world/``, the ``demo`` world; none when ``config.data`` names a
    root), then those of ``hogsa build`` into ``OUT``: ``hogs/<sid>_<obj>`` (``OUT/runs/hogs/``),
    ``contactnet``, ``bank`` (``OUT/runs/pose_bank``), ``srm`` and ``bundle`` (``OUT/bundle``).
    A stage whose key is unchanged is reused, so a second run only streams.

    Args:
        gaussians: ``"free"``: HOGS runs of plain 3D Gaussians (not bound to the meshes), and
            every stage of ``hogsa build`` with otherwise the same settings, in ``OUT/free/``
            (the world is the same).

    Returns:
        ``(data_root, bundle_folder, stage_seconds)``.
    """
    say = log or (lambda s: None)
    out = Path(os.path.abspath(out))
    out.mkdir(parents=True, exist_ok=True)
    stages = StageRecords(out, say)
    data, k_world = _world_stage(config, out, stages, say)
    settings = build_config(config, data, out if gaussians == "mesh" else out / "free")
    model = replace(settings.hogs.model, gaussians=gaussians)
    settings = replace(settings, hogs=replace(settings.hogs, model=model))
    bundle, seconds = build(settings, log=log, data_key=k_world, progress=config.progress)
    return data, bundle, {**stages.seconds, **seconds}


def _orbit(out: Path, bundle: Path, data: Path, cfg: DemoConfig, say: Callable[[str], None]) -> dict[str, Any] | None:
    """The 360° orbit (with and without SRM) of the first pair's model in ``out/view/``."""
    if cfg.orbit_views <= 0:
        return None
    sid, obj = cfg.pairs[0]
    vc = ViewConfig(
        bundle=str(bundle),
        data=str(data),
        subject=sid,
        object=obj,
        out=str(out / "view"),
        orbit=cfg.orbit_views,
        size=cfg.orbit_size,
        quiet=True,
    )
    rec = run_view(vc, log=None)
    orbit = rec["orbits"][sid]
    say(
        f"[view] 360° orbit of {sid}/{obj} ({cfg.orbit_views} views, with and without SRM) in "
        f"{rec['seconds']['total']:.1f} s: {orbit['png']}"
    )
    return {"png": orbit["png"], "video": orbit.get("video"), "pose": orbit["pose"], "seconds": rec["seconds"]["total"]}


def _background_options(config: DemoConfig, out: Path) -> dict[str, Any]:
    """The loader's background options: COCO when given, else an image folder (default: the demo photographs)."""
    if config.coco_root or config.coco_ann:
        return dict(coco_root=config.coco_root, coco_ann=config.coco_ann)
    return dict(background_folder=config.backgrounds or demo_photographs(out / "backgrounds"))


def _demo_dataset(bundle: Path, data: Path, bg: dict[str, Any], **options: Any) -> HOGSADataset:
    """A CPU :class:`HOGSADataset` with the bundle's SRM, backgrounds ``bg`` and loader ``options``."""
    return HOGSADataset(bundle, data, with_options(LoaderConfig(), **bg, srm=True, device="cpu", **options))


def _stream(ds: HOGSADataset, config: DemoConfig, say: Callable[[str], None]) -> tuple[list[Any], dict[str, Any]]:
    """Stream ``ds`` through a DataLoader; the samples (one by one) and the throughput record."""
    loader = DataLoader(
        ds,
        batch_size=config.batch_size,
        num_workers=config.num_workers,
        worker_init_fn=_worker_init if config.num_workers else None,
    )
    t0 = time.perf_counter()
    t_first: Optional[float] = None
    syn: list[Any] = []
    first_batch = None
    for batch in loader:
        if t_first is None:
            t_first = time.perf_counter()
            first_batch = batch
        syn.extend(unbatch(batch, i) for i in range(len(batch[2]["imgname"])))
    t_end = time.perf_counter()
    n = len(syn)
    steady = n - (len(first_batch[2]["imgname"]) if first_batch is not None else 0)
    ips = n / (t_end - t0) if n else 0.0
    ips_steady = steady / (t_end - t_first) if t_first is not None and steady > 0 and t_end > t_first else None
    say(
        f"[stream] {n} samples kept of {config.samples} in {t_end - t0:.1f} s: {ips:.2f} img/s end to end"
        + (f", {ips_steady:.2f} img/s after the first batch" if ips_steady else "")
    )
    rec = {
        "samples_requested": config.samples,
        "samples_kept": n,
        "dropped": config.samples - n,
        "seconds": round(t_end - t0, 2),
        "images_per_s": round(ips, 2),
        "images_per_s_after_first_batch": None if ips_steady is None else round(ips_steady, 2),
        "num_workers": config.num_workers,
        "batch_size": config.batch_size,
    }
    return syn, rec


def _grid_rows(
    syn: list[Any], real: list[Any], bundle: Path, data: Path, bg: dict[str, Any], config: DemoConfig
) -> list[tuple[str, list[Any]]]:
    """Rows of the sample sheet: streamed samples, perturbed annotated grasps, real samples."""
    n = len(syn)
    pick = np.linspace(0, n - 1, min(n, config.grid_cols)).round().astype(int) if n else []
    rows = [
        (
            "synthetic: POM pose bank + SRM + photo background (samples spread over the stream)",
            [syn[int(i)] for i in pick],
        )
    ]
    if config.grid_rows > 1:  # annotated grasps, lightly perturbed, for comparison
        per = _demo_dataset(
            bundle,
            data,
            bg,
            poses="perturb",
            batch_size=config.grid_cols,
            seed=config.seed + 2,
            num_samples=config.grid_cols * (config.grid_rows - 1),
        )
        more = [per.to_sample(f) for g in range(per.num_batches or 0) for f in per.frames(g) if f is not None]
        for r in range(config.grid_rows - 1):
            rows.append(
                (
                    f"synthetic: perturbed annotated grasps + SRM + photo background, row {r + 1}",
                    more[r * config.grid_cols : (r + 1) * config.grid_cols],
                )
            )
    return [r for r in rows if r[1]] + [("real (ARCTIC-format world, same augmentation)", real)]


def _write_grids(out: Path, rows: list[tuple[str, list[Any]]], ds: HOGSADataset) -> Path:
    """``samples.png`` (2D labels drawn) and ``samples_clean.png`` (pixels only)."""
    grid_path = out / "samples.png"
    grid = sample_grid(rows, ds.cfg, cell=ds.cfg.img_res)
    cv2.imwrite(str(grid_path), cv2.cvtColor(grid, cv2.COLOR_RGB2BGR))
    clean = sample_grid(rows, ds.cfg, cell=ds.cfg.img_res, labels=False)  # the same samples, pixels only
    cv2.imwrite(str(out / "samples_clean.png"), cv2.cvtColor(clean, cv2.COLOR_RGB2BGR))
    return grid_path


def run_demo(
    out: PathLike, config: DemoConfig = DemoConfig(), log: Optional[Callable[[str], None]] = print
) -> dict[str, Any]:
    """Build (or reuse) everything, stream synthetic samples, write the pictures.

    ``samples.png``: a row of streamed synthetic samples (pose bank), rows of synthetic samples
    of perturbed annotated grasps, each with its 2D labels (right hand red, left hand blue,
    object keypoints yellow), above a row of real samples of the same world;
    ``samples_clean.png``: the same without labels.
    ``batch.npz``: one mixed batch (``MixedLoader``, half synthetic) flattened to
    ``inputs/<key>``, ``targets/<key>``, ``meta_info/<key>`` arrays.

    Backgrounds: ``coco_root``/``coco_ann`` or ``backgrounds`` (an image folder) when given,
    else the colour photographs shipped inside scikit-image's wheel (astronaut, cat, coffee,
    rocket, motorcycle) — real photographs without any download.

    Args:
        out: demo folder (created).
        config: :class:`DemoConfig`.
        log: line printer (None: silent).

    Returns:
        the ``demo.json`` record: stage seconds, reused stages, throughput, dropped counts,
        output paths.
    """
    say = log or (lambda s: None)
    t_start = time.perf_counter()
    out = Path(os.path.abspath(out))
    out.mkdir(parents=True, exist_ok=True)
    data, bundle, stage_seconds = build_bundle_stages(out, config, log)

    bg = _background_options(config, out)
    ds = _demo_dataset(
        bundle, data, bg, poses="bank", batch_size=config.render_batch, seed=config.seed, num_samples=config.samples
    )
    say(f"[stream] {config.samples} synthetic samples, models {ds.keys}, {config.num_workers} workers")
    syn, stream = _stream(ds, config, say)

    real_ds = ArcticDataset(data, split="p1_train", seed=config.seed)
    rng = np.random.default_rng(config.seed)
    real_idx = rng.choice(len(real_ds), size=min(config.grid_cols, len(real_ds)), replace=False)
    real = [real_ds[int(i)] for i in real_idx]
    grid_path = _write_grids(out, _grid_rows(syn, real, bundle, data, bg, config), ds)

    real_loader = DataLoader(
        real_ds, batch_size=config.batch_size, shuffle=True, generator=torch.Generator().manual_seed(config.seed)
    )
    syn_single = _demo_dataset(bundle, data, bg, poses="bank", batch_size=config.render_batch, seed=config.seed + 1)
    mixed = next(iter(MixedLoader(real_loader, syn_single, ratio=0.5)))
    npz_path = out / "batch.npz"
    np.savez_compressed(npz_path, **_flatten_batch(mixed))
    orbit = _orbit(out, bundle, data, config, say)

    record = {
        "config": {k: v for k, v in asdict(config).items() if k != "progress"},
        "stage_seconds": {k: round(v, 1) for k, v in stage_seconds.items()},
        "reused_stages": sorted(k for k, v in stage_seconds.items() if v == 0.0),
        "stream": {**stream, "models": [list(k) for k in ds.keys], "backgrounds": str(bg)},
        "outputs": {
            "grid": str(grid_path),
            "grid_clean": str(out / "samples_clean.png"),
            "batch": str(npz_path),
            "bundle": str(bundle),
            "data": str(data),
            "orbit": orbit,
        },
        "total_seconds": round(time.perf_counter() - t_start, 1),
    }
    (out / "demo.json").write_text(json.dumps(record, indent=1))
    say(
        f"[demo] samples.png: {grid_path}\n[demo] batch.npz:   {npz_path}\n"
        f"[demo] total {record['total_seconds']:.0f} s; synthetic loader {stream['images_per_s']:.2f} img/s on "
        f"{config.num_workers} CPU worker(s)"
    )
    return record
