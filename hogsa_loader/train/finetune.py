"""``hogsa finetune``: ArcticNet-SF trained on real ARCTIC batches with HOGSA samples mixed in,
on one process or several (torchrun, srun), resumable.

:func:`finetune` runs it from a :class:`FinetuneConfig`. Under torchrun or srun every process
is one DDP rank (gloo on the CPU, NCCL on ``cuda:LOCAL_RANK``): the real half of each batch comes
from a ``DistributedSampler``, the synthetic half from the rank's own share of the stream
(disjoint across ranks, a function of the seed), both set to the epoch. Rank 0 writes the
checkpoints, the model and ARCTIC's metrics on the validation split; every rank logs its batches
to ``OUT/log.rank<R>.jsonl``.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Iterator, Literal, Optional

import torch
from torch.utils.data import DataLoader, DistributedSampler

from hogsa_loader.assets.arctic import ArcticRoot
from hogsa_loader.assets.protocol import training_subjects
from hogsa_loader.baselines.arcticnet_sf import ArcticNetSF, load_arctic_checkpoint
from hogsa_loader.baselines.engine import BodyLayers, evaluate, temporal_order, training_step
from hogsa_loader.errors import AssetError, UsageError
from hogsa_loader.integrations.arctic import wrap_train_loader
from hogsa_loader.io.atomic import atomic_write
from hogsa_loader.io.locks import writer_lock
from hogsa_loader.io.tensors import write_tensors_and_manifest
from hogsa_loader.sample.arctic_dataset import ArcticDataset
from hogsa_loader.sample.augment import ArcticConfig
from hogsa_loader.sample.mixing import MixedLoader
from hogsa_loader.sample.synth import is_synthetic
from hogsa_loader.system import process_slot, rank_device
from hogsa_loader.train.config import field_options as _opt
from hogsa_loader.train.run_folder import (
    commit_checkpoint,
    load_network_and_adam,
    network_and_adam_tensors,
    read_latest_trainer_state,
    save_trainer_state,
)

__all__ = ["FinetuneConfig", "finetune", "weights_digest"]


@dataclass
class FinetuneConfig:
    """Every setting of ``hogsa finetune`` (batch size and steps are per process)."""

    data: str = field(default="", metadata=_opt("ARCTIC data root", required=True))
    out: str = field(default="", metadata=_opt("run folder", required=True))
    bundle: Optional[str] = field(default=None, metadata=_opt("HOGSA bundle (none: real batches only)"))
    ratio: float = field(default=0.5, metadata=_opt("synthetic share of each batch", "unit_float"))
    method: Literal["hogsa", "no_pom", "no_srm", "views_only"] = field(
        default="hogsa",
        metadata=_opt(
            "hogsa: pose-bank grasps refined by the SRM (the paper); no_pom: perturbed annotated grasps; "
            "no_srm: unrefined; views_only: the annotated grasps unchanged"
        ),
    )
    split: str = field(default="p1_train", metadata=_opt("real training split"))
    allow_held_out: Optional[tuple[str, ...]] = field(
        default=None,
        metadata=_opt("held-out subjects the training split and the bundle may hold (recorded, with a warning)"),
    )
    val_split: str = field(default="p1_val", metadata=_opt("split ARCTIC's metrics are computed on"))
    max_val: int = field(default=256, metadata=_opt("validation frames (0: none)", "non_negative_int"))
    backbone: Literal["resnet18", "resnet50"] = field(default="resnet50", metadata=_opt("ArcticNet-SF backbone"))
    img_res: int = field(default=224, metadata=_opt("patch side (px)", "positive_int"))
    init: Optional[str] = field(default=None, metadata=_opt("ARCTIC's released ArcticNet-SF checkpoint to start from"))
    steps: int = field(default=1000, metadata=_opt("optimisation steps", "positive_int"))
    batch_size: int = field(default=64, metadata=_opt("samples per batch per process", "positive_int"))
    lr: float = field(default=1e-5, metadata=_opt("Adam learning rate", "positive_float"))
    log_weights: bool = field(
        default=False, metadata=_opt("log a digest of the weights after every step (hashes every parameter)")
    )
    ckpt_every: int = field(default=100, metadata=_opt("checkpoint every N steps", "positive_int"))
    workers: int = field(default=0, metadata=_opt("DataLoader workers of the real half", "non_negative_int"))
    seed: int = field(default=0, metadata=_opt("seed of the model, the real order and the synthetic stream"))
    device: str = field(
        default="cpu", metadata=_opt("torch device (cuda: cuda:LOCAL_RANK per process)", "torch_device")
    )


def weights_digest(model: torch.nn.Module) -> str:
    """16 hex digits of the sha256 of the model's parameters (equal on every DDP rank after a
    step; the batch-norm statistics are rank 0's only after the next forward)."""
    h = hashlib.sha256()
    for k, v in sorted(model.named_parameters()):
        h.update(k.encode())
        h.update(v.detach().cpu().contiguous().numpy().tobytes())
    return h.hexdigest()[:16]


#: Settings a run can change when resumed (more steps, other checkpoint or validation sizes).
_RESUMABLE = ("out", "steps", "ckpt_every", "max_val", "val_split", "workers")


def _run_key(cfg: FinetuneConfig, world: int) -> str:
    """What a checkpoint must have been trained with to be resumed: the settings but the resumable
    ones, and the number of processes (each rank's share of the data depends on it)."""
    kept = {k: v for k, v in asdict(cfg).items() if k not in _RESUMABLE}
    return hashlib.sha256(json.dumps({**kept, "world": world}, sort_keys=True).encode()).hexdigest()


def _checks(cfg: FinetuneConfig) -> None:
    """Refuse bad settings before anything is read: missing folders, a training split with a
    subject the dataset's protocol holds out (unless named in ``allow_held_out``)."""
    if not cfg.data or not cfg.out:
        raise UsageError("--data and --out are required")
    root = ArcticRoot(cfg.data)
    setup, _, name = cfg.split.partition("_")
    if root.protocol_path(setup).is_file():
        listed = root.protocol(setup).get(name)
        if listed is None:
            raise UsageError(f"--split {cfg.split}: {root.protocol_path(setup)} has no {name!r} split")
        training_subjects(
            root, sorted({s.split("/", 1)[0] for s in listed}), cfg.allow_held_out or (), "hogsa finetune"
        )
    if cfg.bundle is not None and not (Path(cfg.bundle) / "manifest.json").is_file():
        raise UsageError(f"--bundle {cfg.bundle}: not a bundle (no manifest.json)")
    if cfg.init is not None and not Path(cfg.init).is_file():
        raise UsageError(f"--init {cfg.init}: no such file")


def _save(out: Path, step: int, model: ArcticNetSF, opt: torch.optim.Optimizer, state: dict) -> None:
    """``checkpoints/step_N``: the network, Adam's moments and ``state``."""
    ck = out / "checkpoints" / f"step_{step:07d}"
    save_trainer_state(ck, network_and_adam_tensors(model, opt), {**state, "step": step})
    commit_checkpoint(ck, step)


def _step_seed(seed: int, rank: int, step: int) -> int:
    """The torch seed of training step ``step`` on ``rank`` (its dropout masks), so that a resumed
    run draws what an uninterrupted one draws."""
    return int.from_bytes(hashlib.sha256(f"{seed}/{rank}/{step}".encode()).digest()[:8], "little") >> 1


def _resume(out: Path, key: str, model: ArcticNetSF, opt: torch.optim.Optimizer) -> Optional[dict[str, Any]]:
    """Restore the last checkpoint into ``model`` and ``opt``; its state (None without one).

    Raises:
        AssetError: the checkpoint belongs to a run with other settings, or is damaged.
    """
    found = read_latest_trainer_state(out, required=())
    if found is None:
        return None
    latest, state, tensors = found
    if state.get("key") != key:
        raise AssetError(latest, "belongs to a run with other settings (start again in another --out)")
    load_network_and_adam(latest, tensors, model, opt)
    return state


def _validation(cfg: FinetuneConfig, model: ArcticNetSF, layers: BodyLayers, device: Any) -> dict[str, Any]:
    """ARCTIC's metrics on ``cfg.max_val`` frames of the validation split, evenly spaced in temporal
    order (the temporal metrics MDev and ACC only when every frame is evaluated)."""
    ds = ArcticDataset(
        cfg.data, split=cfg.val_split, seed=cfg.seed, augment=False, config=ArcticConfig(img_res=cfg.img_res)
    )
    order = temporal_order(ds.imgnames)
    every = order if cfg.max_val >= len(order) else order[:: max(1, len(order) // cfg.max_val)][: cfg.max_val]
    loader = DataLoader(torch.utils.data.Subset(ds, every), batch_size=min(cfg.batch_size, 32))
    with torch.no_grad():
        res = evaluate(model, loader, layers, cfg.img_res, device, temporal=len(every) == len(order))
    summary = {k: float(v) if math.isfinite(float(v)) else None for k, v in res["summary"].items()}
    return {"frames": res["frames"], "summary": summary}  # None: no frame the metric applies to


def _process(cfg: FinetuneConfig) -> tuple[int, int, torch.device]:
    """This process's rank, the world size and its device; the process group joined (several)."""
    rank, world = process_slot()
    device = torch.device(rank_device(cfg.device))
    if world > 1 and not torch.distributed.is_initialized():
        os.environ.setdefault("RANK", str(rank))  # srun: torch.distributed reads its rank from these
        os.environ.setdefault("WORLD_SIZE", str(world))
        if device.type == "cuda":
            torch.cuda.set_device(device)
        torch.distributed.init_process_group("nccl" if device.type == "cuda" else "gloo")
    return rank, world, device


def _loaders(cfg: FinetuneConfig, rank: int, world: int, device: torch.device) -> tuple[Any, DistributedSampler, Any]:
    """The real loader (this rank's share, ``DistributedSampler``), its sampler, and the synthetic
    stream of ``cfg.method`` (this rank's share; None without a bundle)."""
    real_ds = ArcticDataset(cfg.data, split=cfg.split, seed=cfg.seed, config=ArcticConfig(img_res=cfg.img_res))
    sampler = DistributedSampler(real_ds, num_replicas=world, rank=rank, shuffle=True, seed=cfg.seed, drop_last=True)
    real = DataLoader(
        real_ds,
        batch_size=cfg.batch_size,
        sampler=sampler,
        drop_last=True,
        num_workers=cfg.workers,
        generator=torch.Generator().manual_seed(cfg.seed),  # the workers' seeds (the global generator untouched)
    )
    if len(real) == 0:
        raise UsageError(
            f"--split {cfg.split}: {len(real_ds)} frames make no batch of --batch-size {cfg.batch_size} "
            f"on each of {world} process(es)"
        )
    if cfg.bundle is None:
        return real, sampler, None
    mixed = wrap_train_loader(
        real,
        cfg.bundle,
        cfg.ratio,
        seed=cfg.seed,
        device=str(device),
        method=cfg.method,
        allow_held_out=cfg.allow_held_out,
    )
    return real, sampler, mixed.synthetic


def _batches(state: dict[str, Any], real: Any, sampler: Any, mixed: Optional[MixedLoader]) -> Iterator[Any]:
    """``(epoch, index in epoch, batch)`` from where ``state`` left off: each epoch sets the real
    sampler, the real dataset and the synthetic stream to it and restarts the synthetic stream.
    Resumed mid-epoch, the mixed loader continues from the saved stream states (the
    synthetic samples already trained on are not rendered again; the real batches before are
    loaded and passed over)."""
    epoch, skip = int(state.get("epoch", 0)), int(state.get("epoch_batches", 0))
    stream = state.get("stream")
    while True:
        if mixed is None:
            sampler.set_epoch(epoch)
            real.dataset.set_epoch(epoch)
            batches = enumerate(real)
        elif skip and stream:
            mixed.load_state_dict(stream)  # this epoch, each rank from its own place in it
            batches = enumerate(mixed, start=skip)
            skip = 0
        else:
            mixed.set_epoch(epoch)  # the real sampler and dataset, and the synthetic stream from its start
            batches = enumerate(mixed)
        for i, batch in batches:
            if i >= skip:  # (resumed mid-epoch without a stream state: the batches before are drawn again)
                yield epoch, i, batch
        epoch, skip = epoch + 1, 0


def _log_row(step: int, losses: dict[str, float], batch: Any, model: Optional[torch.nn.Module]) -> str:
    """One log line: the step, its loss, its samples and (``model`` given) the weights' digest."""
    names = list(batch[2]["imgname"])
    row = {
        "step": step,
        "loss": losses["loss"],
        "synthetic": [n for n in names if is_synthetic(n)],
        "real": [n for n in names if not is_synthetic(n)],
    }
    if model is not None:
        row["weights"] = weights_digest(model)
    return json.dumps(row) + "\n"


def _truncated_log(path: Path, step: int) -> None:
    """Keep the log lines of the steps up to ``step`` (those after it are trained again; a line
    torn by a killed process is dropped)."""
    kept = []
    for line in path.read_text().splitlines() if path.is_file() else []:
        try:
            row = json.loads(line)
        except ValueError:
            continue
        if isinstance(row, dict) and isinstance(row.get("step"), int) and row["step"] <= step:
            kept.append(line + "\n")
    atomic_write(path, "".join(kept).encode())


def _finish(cfg: FinetuneConfig, out: Path, model: ArcticNetSF, layers: BodyLayers, device: Any, result: dict) -> None:
    """Rank 0: the model (``model.safetensors`` + ``model.json``), ARCTIC's validation metrics, ``result.json``."""
    net = {k: v.detach().cpu().contiguous() for k, v in model.network_state_dict().items()}
    settings = {"model": {"backbone": cfg.backbone, "img_res": cfg.img_res}, "finetune": asdict(cfg)}
    write_tensors_and_manifest(
        out, "model.safetensors", net, "model.json", {"kind": "arcticnet_sf", "settings": settings}
    )
    if cfg.max_val:
        result["metrics"] = _validation(cfg, model, layers, device)
    atomic_write(out / "result.json", (json.dumps(result, indent=1) + "\n").encode())


def finetune(cfg: FinetuneConfig, log: Any = print) -> dict[str, Any]:
    """Train, resuming from ``cfg.out``'s last checkpoint of the same settings; the result record.

    Returns:
        ``{"steps", "loss", "weights"}`` and, on rank 0, ``"metrics"`` (ARCTIC's on ``val_split``).
    """
    say = log or (lambda s: None)
    _checks(cfg)
    rank, world, device = _process(cfg)
    out = Path(os.path.abspath(cfg.out))
    out.mkdir(parents=True, exist_ok=True)
    key = _run_key(cfg, world)
    torch.manual_seed(cfg.seed)  # the same initial weights on every rank
    layers = BodyLayers.from_root(ArcticRoot(cfg.data)).to(device)
    model = ArcticNetSF(cfg.backbone, layers.mano_r, layers.mano_l, layers.objects, img_res=cfg.img_res).to(device)
    if cfg.init is not None:
        load_arctic_checkpoint(model, cfg.init)
    opt = torch.optim.Adam(model.parameters(), lr=cfg.lr)
    with writer_lock(out, f".rank-{rank}.lock", what=f"rank {rank} of this run"):
        state = _resume(out, key, model, opt)
        state = state or {"key": key, "history": [], "evals": [], "train_time_s": 0.0}
        net = torch.nn.parallel.DistributedDataParallel(model) if world > 1 else model
        real, sampler, synthetic = _loaders(cfg, rank, world, device)
        mixed = None if synthetic is None else MixedLoader(real, synthetic, cfg.ratio)
        step = int(state.get("step", 0))
        log_path = out / f"log.rank{rank}.jsonl"
        _truncated_log(log_path, step)
        say(f"[finetune] rank {rank} of {world} on {device}, from step {step}")
        t0 = time.perf_counter()
        with open(log_path, "a") as fh:
            for epoch, i, batch in _batches(state, real, sampler, mixed) if step < cfg.steps else ():
                torch.manual_seed(_step_seed(cfg.seed, rank, step))  # dropout: a function of (seed, rank, step)
                losses = training_step(net, batch, layers, opt, cfg.img_res, device=device)
                step += 1
                fh.write(_log_row(step, losses, batch, model if cfg.log_weights else None))
                fh.flush()
                state["history"].append({"step": step, "loss": losses["loss"]})
                if step % cfg.ckpt_every == 0 or step == cfg.steps:
                    state["train_time_s"] = float(state["train_time_s"]) + time.perf_counter() - t0
                    t0 = time.perf_counter()
                    stream = None if mixed is None else mixed.state_dict()  # (collective: every rank)
                    if rank == 0:
                        place = {"epoch": epoch, "epoch_batches": i + 1, "stream": stream}
                        _save(out, step, model, opt, {**state, **place})
                    if world > 1:
                        torch.distributed.barrier()  # a checkpoint is whole before any rank goes on
                if step >= cfg.steps:
                    break
        result: dict[str, Any] = {"steps": step, "loss": state["history"][-1]["loss"] if state["history"] else None}
        result["weights"] = weights_digest(model)
        if rank == 0:
            _finish(cfg, out, model, layers, device, result)
        if world > 1:
            torch.distributed.barrier()
    return result
