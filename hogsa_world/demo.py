"""``hogsa demo``: the whole pipeline on the embedded default world, cached stage by stage.

:func:`run_demo` builds (or reuses) the world, the HOGS models, ContactNet, the pose bank, the
SRM and the bundle (:func:`build_bundle_stages`), streams synthetic samples through a
DataLoader and writes ``samples.png``, ``batch.npz`` and ``demo.json``.
"""

from __future__ import annotations

import json
import os
import shutil
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any, Callable, Optional, Sequence

import cv2
import numpy as np
import torch
from torch.utils.data import DataLoader

from hogsa_loader.assets.arctic import ArcticRoot
from hogsa_loader.assets.protocol import training_subjects
from hogsa_loader.errors import PathLike
from hogsa_loader.io.atomic import atomic_write
from hogsa_loader.io.hashing import keyed_settings, settings_key
from hogsa_loader.models.bundle import BUNDLE_SCHEMA_VERSION, write_bundle
from hogsa_loader.models.pom.perturb import KEEP_ARTICULATION
from hogsa_loader.render.gaussians import warm_up_compositor
from hogsa_loader.sample.arctic_dataset import ArcticDataset
from hogsa_loader.sample.config import LoaderConfig, with_options
from hogsa_loader.sample.dataset import HOGSADataset
from hogsa_loader.sample.mixing import MixedLoader
from hogsa_loader.system import available_cores, can_fork, run_forked
from hogsa_loader.train import HogsConfig, HogsDataConfig, HogsModelConfig, HogsOptimConfig, HogsRunConfig, HogsTrainer
from hogsa_loader.train.pom_config import (
    BankDataConfig,
    BankPOMConfig,
    BankRunConfig,
    ContactNetDataConfig,
    ContactNetJobConfig,
    ContactNetOptimConfig,
    ContactNetRunConfig,
    PoseBankConfig,
)
from hogsa_loader.train.pom_jobs import build_pose_bank, fit_contactnet
from hogsa_loader.train.srm_config import (
    SRMDataConfig,
    SRMLossConfig,
    SRMModelConfig,
    SRMOptimConfig,
    SRMRunConfig,
    SRMTrainConfig,
)
from hogsa_loader.train.srm_trainer import SRMTrainer
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


def _key(*parts: Any) -> str:
    return settings_key(parts)


class _Stages:
    """Stage records in ``OUT/stages/``: run a stage unless its key is unchanged."""

    def __init__(self, out: Path, say: Callable[[str], None]) -> None:
        self.dir = out / "stages"
        self.dir.mkdir(parents=True, exist_ok=True)
        self.say = say
        self.seconds: dict[str, float] = {}
        self.reused: list[str] = []

    def is_cached(self, name: str, key: str, outputs: Sequence[Path]) -> bool:
        """Whether :meth:`run` would reuse ``name`` (its record has ``key`` and its outputs exist)."""
        rec = self._record(name)
        return rec is not None and rec.get("key") == key and all(p.exists() for p in outputs)

    def _record(self, name: str) -> Optional[dict]:
        """The stage's record, or None (absent or unreadable: a build interrupted mid-write)."""
        rec_path = self.dir / f"{name.replace('/', '_')}.json"
        try:
            rec = json.loads(rec_path.read_text()) if rec_path.is_file() else None
        except (OSError, ValueError):
            return None
        return rec if isinstance(rec, dict) else None

    def run(self, name: str, key: str, outputs: Sequence[Path], fn: Callable[[], Any], resumable: bool = False) -> Any:
        """Run ``fn`` unless a record of ``name`` with ``key`` exists and its outputs do. Stale
        outputs are removed first — but a ``resumable`` stage's outputs with no record (an
        interrupted build) are left for ``fn`` to resume from."""
        rec_path = self.dir / f"{name.replace('/', '_')}.json"
        rec = self._record(name)
        if rec is not None and rec.get("key") == key and all(p.exists() for p in outputs):
            self.say(f"[{name}] cached ({rec['seconds']:.0f} s when built)")
            self.reused.append(name)
            self.seconds[name] = 0.0
            return rec.get("result")
        for p in outputs if rec is not None or not resumable else ():  # stale: rebuild from scratch
            if p.is_dir():
                shutil.rmtree(p)
            elif p.exists():
                p.unlink()
        if rec_path.exists():  # an interruption of the rebuild leaves no stale record behind
            rec_path.unlink()
        self.say(f"[{name}] building ...")
        t0 = time.perf_counter()
        result = fn()
        dt = time.perf_counter() - t0
        self.seconds[name] = dt
        # atomic: a record is whole or absent
        atomic_write(
            rec_path, json.dumps({"key": key, "seconds": dt, "result": result}, indent=1, default=str).encode()
        )
        self.say(f"[{name}] done in {dt:.0f} s")
        return result


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


def _child_cfg(cfg: DemoConfig) -> DemoConfig:
    """The settings a stage builds with: those of the stage process (no progress bars), else ``cfg``."""
    return _CHILD_CFG or cfg


def _world_stage(cfg: DemoConfig, out: Path, stages: _Stages, say: Callable[[str], None]) -> tuple[Path, str]:
    """Build (or reuse) the world in ``out/world`` unless ``cfg.data`` names one; its data root and key."""
    if cfg.data is not None:
        data = Path(os.path.abspath(cfg.data))
        return data, _key("data", str(data), cfg.seed)  # (the seed also drives every training stage)
    world = out / "world"
    data = world / "arctic_data" / "data"
    preset = get_preset(cfg.preset)
    k_world = _key("world", cfg.preset, cfg.seed)
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


def _hogs_nodes(cfg: DemoConfig, out: Path, data: Path, k_world: str) -> list[_StageNode]:
    """One HOGS training stage per (subject, object) pair, into ``out/runs/hogs/<sid>_<obj>``."""
    nodes: list[_StageNode] = []
    for sid, obj in cfg.pairs:
        run = out / "runs" / "hogs" / f"{sid}_{obj}"
        k = _key(
            "hogs",
            k_world,
            sid,
            obj,
            cfg.hogs_iters,
            cfg.hogs_image_size,
            cfg.hogs_sh_degree,
            cfg.hogs_frame_stride,
            cfg.hogs_k,
            cfg.hogs_object_subdivide,
            cfg.hogs_window,
        )
        nodes.append(
            _StageNode(
                f"hogs/{sid}_{obj}",
                k,
                [run],
                lambda sid=sid, obj=obj, run=run: _train_hogs(_child_cfg(cfg), data, sid, obj, run),
            )
        )
    return nodes


def _contactnet_node(cfg: DemoConfig, cn: Path, data: Path, k_world: str) -> _StageNode:
    """The ContactNet training stage, into ``cn``."""

    def contactnet() -> dict[str, Any]:
        c = _child_cfg(cfg)
        job = ContactNetJobConfig(
            data=ContactNetDataConfig(root=str(data)),
            optim=ContactNetOptimConfig(iters=c.contactnet_iters, seed=c.seed),
            run=ContactNetRunConfig(out=str(cn), val_every=c.contactnet_iters),
        )
        m = fit_contactnet(job, progress=c.progress)
        return {k: m[k] for k in ("val_mae", "val_iou05")}

    subjects = {"subjects": training_subjects(ArcticRoot(data), stage="ContactNet")}  # what it is trained on
    return _StageNode("contactnet", _key("contactnet", k_world, cfg.contactnet_iters, subjects), [cn], contactnet)


#: SRM settings keyed only when they hold other values than these.
_SRM_UNKEYED = {"gan": 0.0}
#: Pose-bank settings keyed only when they hold other values than these.
_BANK_UNKEYED = {"finger_scale": 0.0, "variants": 1, "frames": "contact"}


def _bank_node(cfg: DemoConfig, bank: Path, data: Path, cn: Path, k_cn: str) -> _StageNode:
    """The pose-bank stage (after ContactNet ``cn``) over the sequences of ``cfg.pairs``, into ``bank``."""
    root = ArcticRoot(data)
    seqs = [s for sid, obj in cfg.pairs for s in root.sequences(sid) if s.split("/", 1)[1].split("_", 1)[0] == obj]
    late = keyed_settings(
        {"finger_scale": cfg.bank_finger_scale, "variants": cfg.bank_variants, "frames": cfg.bank_frames}, _BANK_UNKEYED
    )
    bank_cfg = PoseBankConfig(
        data=BankDataConfig(
            root=str(data),
            contactnet=str(cn),
            sequences=tuple(seqs),
            per_sequence=cfg.bank_per_sequence,
            variants=cfg.bank_variants,
            frames=cfg.bank_frames,
        ),
        pom=BankPOMConfig(finger_scale=cfg.bank_finger_scale),
        run=BankRunConfig(out=str(bank), seed=cfg.seed),
    )
    start = [asdict(KEEP_ARTICULATION)] + ([late] if late else [])  # the start perturbations
    margin = {"frame_margin": bank_cfg.data.frame_margin}  # which frames a bank may start from
    k_bank = _key("bank", k_cn, cfg.bank_per_sequence, seqs, margin, *start)
    return _StageNode(
        "bank",
        k_bank,
        [bank],
        lambda: build_pose_bank(bank_cfg, progress=_child_cfg(cfg).progress),
        needs=("contactnet",),
    )


def _srm_node(cfg: DemoConfig, out: Path, data: Path, hogs: list[_StageNode]) -> _StageNode:
    """The SRM stage (after the HOGS stages ``hogs``) into ``OUT/runs/srm``."""
    late = keyed_settings({"gan": float(cfg.srm_gan)}, _SRM_UNKEYED)  # 1 and 1.0 key alike
    k_hogs = [n.key for n in hogs]
    srm = out / "runs" / "srm"
    return _StageNode(
        "srm",
        _key("srm", k_hogs, cfg.srm_iters, cfg.srm_crop, cfg.srm_augment, *([late] if late else [])),
        [srm],
        lambda: _train_srm(_child_cfg(cfg), data, out / "runs" / "hogs", srm, out / "cache" / "srm"),
        needs=tuple(n.name for n in hogs),
    )


def _build(cfg: DemoConfig, out: Path, stages: _Stages, say: Callable[[str], None]) -> tuple[Path, Path]:
    """Build (or reuse) world, HOGS runs, ContactNet, pose bank, SRM and bundle; the data root and bundle."""
    data, k_world = _world_stage(cfg, out, stages, say)
    # the stages between the world and the bundle
    hogs = _hogs_nodes(cfg, out, data, k_world)
    runs, k_hogs = [n.outputs[0] for n in hogs], [n.key for n in hogs]
    cn, bank = out / "runs" / "contactnet", out / "runs" / "pose_bank"
    cn_node = _contactnet_node(cfg, cn, data, k_world)
    bank_node = _bank_node(cfg, bank, data, cn, cn_node.key)
    srm_node = _srm_node(cfg, out, data, hogs)
    srm, k_srm = srm_node.outputs[0], srm_node.key
    _run_stage_graph(stages, [*hogs, cn_node, bank_node, srm_node], cfg, say)

    bundle = out / "bundle"
    k_bundle = _key("bundle", k_hogs, cn_node.key, bank_node.key, k_srm, BUNDLE_SCHEMA_VERSION)
    stages.run(
        "bundle",
        k_bundle,
        [bundle],
        lambda: str(write_bundle(bundle, data, runs, srm=srm, contactnet=cn, pose_banks=[bank])),
    )
    return data, bundle


@dataclass
class _StageNode:
    """A stage of the build graph: :meth:`_Stages.run` arguments and the stages it needs."""

    name: str
    key: str
    outputs: list[Path]
    build: Callable[[], Any]
    needs: tuple[str, ...] = ()


_NODES: list[_StageNode] = []  # the stage graph, set in the parent before the stage processes fork
_CHILD_CFG: Optional[DemoConfig] = None  # the settings inside a stage process (no progress bars)
_SAY: Callable[[str], None] = print  # the parent's line printer, inherited by the stage processes
_OUT = Path(".")  # the demo folder, inherited by the stage processes


def _run_node(i: int) -> tuple[float, bool]:
    """Build stage ``i`` in a stage process; returns its seconds and whether it was reused."""
    stages = _Stages(_OUT, _SAY)
    node = _NODES[i]
    stages.run(node.name, node.key, node.outputs, node.build)
    return stages.seconds[node.name], node.name in stages.reused


def _stage_process_init(cfg: DemoConfig) -> None:
    global _CHILD_CFG
    _CHILD_CFG = replace(cfg, progress=False)


def _check_graph(nodes: list[_StageNode]) -> None:
    """Every stage needs only stages listed before it (so list order is a valid build order)."""
    seen: set[str] = set()
    for n in nodes:
        missing = [d for d in n.needs if d not in seen]
        if missing:
            raise ValueError(f"stage {n.name!r} needs {missing}, which are not listed before it")
        seen.add(n.name)


def _run_stage_graph(stages: _Stages, nodes: list[_StageNode], cfg: DemoConfig, say: Callable[[str], None]) -> None:
    """Run the stages, each once the stages it needs are done. Where forking is safe
    (:func:`hogsa_loader.system.can_fork`), with more than one core and more than one stage to
    build, they run on forked processes, side by side where the graph allows (one torch
    thread each, no progress bars; a stage that is the only one able to run builds in this
    process, on all threads); else one after the other in list order. Cached stages are
    reported and skipped in the parent. On an error the other stage processes are stopped
    and the error is raised."""
    global _NODES, _SAY, _OUT, _CHILD_CFG
    _check_graph(nodes)
    todo = [n for n in nodes if not stages.is_cached(n.name, n.key, n.outputs)]
    workers = min(len(todo), available_cores())
    if workers < 2 or not can_fork():
        for n in nodes:
            stages.run(n.name, n.key, n.outputs, n.build)
        return
    for n in nodes:
        if n not in todo:
            stages.run(n.name, n.key, n.outputs, n.build)
    say(f"[stages] building {', '.join(n.name for n in todo)} on up to {workers} processes")
    warm_up_compositor()  # the stage processes inherit the compiled kernels
    index = {n.name: i for i, n in enumerate(todo)}
    needs = [tuple(index[d] for d in n.needs if d in index) for n in todo]  # cached needs are done

    def record(i: int, result: tuple[float, bool]) -> None:
        stages.seconds[todo[i].name] = result[0]
        if result[1]:
            stages.reused.append(todo[i].name)

    _NODES, _SAY, _OUT = todo, say, stages.dir.parent
    try:
        run_forked(_run_node, needs, workers, on_result=record, initializer=_stage_process_init, initargs=(cfg,))
    finally:
        _NODES, _CHILD_CFG = [], None  # (a stage built in this process set the stage settings here)


def build_bundle_stages(
    out: PathLike, config: DemoConfig = DemoConfig(), log: Optional[Callable[[str], None]] = print
) -> tuple[Path, Path, dict[str, float]]:
    """Build (or reuse) the demo's stages up to the bundle: world, HOGS runs, ContactNet,
    pose bank, SRM, bundle — each cached in ``out`` by its settings.

    Stages (each writes into ``OUT`` and records ``OUT/stages/<name>.json`` with a key of its
    settings and of the stages it builds on; a stage whose key is unchanged is reused, so a
    second run only streams)::

        world       OUT/world/                the `demo` world (hogsa world --preset demo)
        hogs        OUT/runs/hogs/<sid>_<obj>  HOGS per (subject, object), brief CPU training
        contactnet  OUT/runs/contactnet        ContactNet (the training subjects)
        bank        OUT/runs/pose_bank         POM pose bank of the training subjects
        srm         OUT/runs/srm               SRM on the HOGS renders, brief; its coarse renders
                    OUT/cache/srm              are kept for rebuilds (entries of other HOGS weights
                                               or labels are removed after each SRM build)
        bundle      OUT/bundle                 the bundle the loader reads
        stream      (always)                   HOGSADataset (pose bank, SRM, photo backgrounds)
                                               through a DataLoader; samples.png, batch.npz,
                                               demo.json, throughput on stdout

    Between the world and the bundle the stages form a graph (HOGS per pair and ContactNet need
    the world, the pose bank ContactNet, the SRM every HOGS run): on Linux with more than one
    core and more than one stage to build, each starts on a forked process as soon as the stages
    it needs are done (one torch thread each, no progress bars; a stage that is the only one
    able to run builds in the demo's own process, on all threads).

    Returns:
        ``(data_root, bundle_folder, stage_seconds)``.
    """
    out = Path(os.path.abspath(out))
    out.mkdir(parents=True, exist_ok=True)
    stages = _Stages(out, log or (lambda s: None))
    data, bundle = _build(config, out, stages, log or (lambda s: None))
    return data, bundle, dict(stages.seconds)


def _train_hogs(cfg: DemoConfig, data: Path, sid: str, obj: str, run: Path) -> dict[str, Any]:

    hc = HogsConfig(
        data=HogsDataConfig(
            root=str(data),
            subject=sid,
            object=obj,
            image_size=cfg.hogs_image_size,
            max_eval=4,
            frame_stride=cfg.hogs_frame_stride,
            window=cfg.hogs_window,
        ),
        model=HogsModelConfig(sh_degree=cfg.hogs_sh_degree, k=cfg.hogs_k, object_subdivide=cfg.hogs_object_subdivide),
        optim=HogsOptimConfig(iters=cfg.hogs_iters, sh_warmup=max(1, cfg.hogs_iters // 3), lr_scale=10.0),
        run=HogsRunConfig(
            out=str(run), seed=cfg.seed, eval_every=cfg.hogs_iters, ckpt_every=cfg.hogs_iters, strip_views=2
        ),
    )
    m = HogsTrainer(hc, progress=cfg.progress).train()
    return {"psnr": m["psnr"], "ssim": m["ssim"], "iters": m["iters"]}


def _train_srm(cfg: DemoConfig, data: Path, hogs: Path, out: Path, cache: Path) -> dict[str, Any]:

    sc = SRMTrainConfig(
        data=SRMDataConfig(
            root=str(data), hogs=str(hogs), crop=cfg.srm_crop, augment=cfg.srm_augment, cache=str(cache)
        ),
        model=SRMModelConfig(channels=(16, 32, 64, 64, 64)),
        loss=SRMLossConfig(lambda_gan=cfg.srm_gan),
        optim=SRMOptimConfig(iters=cfg.srm_iters),
        run=SRMRunConfig(
            out=str(out), seed=cfg.seed, eval_every=cfg.srm_iters, ckpt_every=cfg.srm_iters, strip_views=2
        ),
    )
    trainer = SRMTrainer(sc, progress=cfg.progress, log=lambda s: None)
    m = trainer.train()
    used = {f.resolve() for ps in trainer.sets for f in ps.cache_files}
    for stale in cache.glob("coarse_*.safetensors"):  # renders of HOGS weights or labels no longer in use
        if stale.resolve() not in used:
            stale.unlink()
    return {"delta_psnr": m["delta_psnr"], "delta_ssim": m["delta_ssim"]}


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
    stages = _Stages(out, say)
    data, bundle = _build(config, out, stages, say)

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
        "stage_seconds": {k: round(v, 1) for k, v in stages.seconds.items()},
        "reused_stages": stages.reused,
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
