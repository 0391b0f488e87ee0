"""Checkpoint bookkeeping shared by the trainers (HOGS, SRM).

A run folder keeps ``config.json`` and ``checkpoints/step_NNNNNNN/`` folders; ``checkpoints/
latest.json`` (``{"step", "folder"}``) is written last and atomically, so a run killed at any
moment resumes from a complete checkpoint. A checkpoint's trainer state is a checked pair
(:func:`save_trainer_state`): ``trainer.safetensors`` (optimiser moments, RNG states) and
``trainer.json`` (step, history, the sha256 of the tensors file), verified on resuming.

Starting a run again in a folder that holds checkpoints is refused unless the caller asks to
resume it or to overwrite it (:func:`check_run_folder`, :class:`RunExistsError`): a fresh
run would otherwise delete the old checkpoints at its first save.
"""

from __future__ import annotations

import dataclasses
import json
import re
import shutil
from pathlib import Path
from typing import Any, Mapping, Optional, Sequence

import torch
from torch import Tensor

from hogsa_loader.errors import AssetError, PathLike, UsageError, read_json
from hogsa_loader.io.atomic import atomic_write
from hogsa_loader.io.tensors import read_checked_tensors, write_tensors_and_manifest

__all__ = [
    "load_network_and_adam",
    "network_and_adam_tensors",
    "read_latest_trainer_state",
    "RunExistsError",
    "TRAINER_TENSORS",
    "TRAINER_STATE",
    "check_run_folder",
    "clear_run",
    "start_run",
    "write_json",
    "has_checkpoints",
    "commit_checkpoint",
    "latest_checkpoint",
    "config_defaults",
    "save_trainer_state",
    "read_trainer_state",
]

TRAINER_TENSORS = "trainer.safetensors"
TRAINER_STATE = "trainer.json"
#: Settings that never block a resume: the run folder may be copied or moved.
ALWAYS_RESUMABLE = ("out",)
_STEP_FOLDER = re.compile(r"^step_[0-9]+$")


class RunExistsError(AssetError, UsageError):
    """A fresh run was asked for in a folder that already holds a run's checkpoints."""


def has_checkpoints(out: PathLike) -> bool:
    """Whether the run folder ``out`` holds a complete checkpoint (``checkpoints/latest.json``;
    a ``step_*`` folder without it is a checkpoint torn while being written)."""
    return (Path(out) / "checkpoints" / "latest.json").is_file()


def check_run_folder(out: PathLike, *, resume: bool, overwrite: bool) -> None:
    """Refuse, before any work, a run folder a trainer must not start in.

    Args:
        out: the run folder (may not exist yet).
        resume: the caller will continue the run's latest checkpoint.
        overwrite: the caller will start again from step 0, emptying the folder first.

    Raises:
        AssetError: ``out`` exists and is not a folder.
        RunExistsError: ``out`` holds checkpoints and neither ``resume`` nor ``overwrite``.
        ValueError: both ``resume`` and ``overwrite``.
    """
    out = Path(out)
    if resume and overwrite:
        raise ValueError("--resume and --overwrite exclude each other")
    if out.exists() and not out.is_dir():
        raise AssetError(out, "run folder is a file")
    if not resume and not overwrite and has_checkpoints(out):
        raise RunExistsError(
            out,
            "holds a training run (checkpoints/); pass --resume to continue it or --overwrite "
            "to start it again from step 0 (the folder is emptied)",
        )


def clear_run(out: PathLike) -> None:
    """Empty the run folder (a run started again with ``overwrite``): checkpoints, weights,
    light, metrics and pictures of the old run all go, so nothing of it can be taken for a
    finished run of the new one."""
    out = Path(out)
    if not out.is_dir():
        return
    for entry in out.iterdir():
        if entry.is_dir() and not entry.is_symlink():
            shutil.rmtree(entry)
        else:
            entry.unlink()


def start_run(out: Path, *, resumed: bool, overwrite: bool, config: Mapping[str, Any]) -> None:
    """Make ``out`` ready for a training run and write its ``config.json``.

    A folder holding checkpoints that this run did not resume is refused
    (:class:`RunExistsError`), or emptied with ``overwrite``.
    """
    if not resumed and has_checkpoints(out):
        if not overwrite:
            raise RunExistsError(
                out,
                "holds a training run (checkpoints/); resume it (--resume) or "
                "start it again with overwrite (--overwrite)",
            )
        clear_run(out)
    out.mkdir(parents=True, exist_ok=True)
    write_json(out / "config.json", config)


def write_json(path: Path, obj: Any) -> None:
    """Write ``obj`` as indented JSON (no NaN) atomically."""
    atomic_write(path, (json.dumps(obj, indent=1, allow_nan=False) + "\n").encode())


def commit_checkpoint(folder: Path, step: int) -> None:
    """Point ``latest.json`` (next to ``folder``) at the complete checkpoint ``folder``, then
    remove the older ``step_*`` folders."""
    ck = folder.parent
    atomic_write(ck / "latest.json", (json.dumps({"step": step, "folder": folder.name}) + "\n").encode())
    for old in ck.glob("step_*"):
        if old.is_dir() and old.name != folder.name:
            shutil.rmtree(old, ignore_errors=True)


def latest_checkpoint(
    out: Path, config: Mapping[str, Any], resumable: Sequence[str], defaults: Optional[Mapping[str, Any]] = None
) -> Optional[Path]:
    """The latest complete checkpoint folder of run ``out``, or None when there is none.

    A setting missing from the saved ``config.json`` (added to the library after the run
    started) matches when ``config`` has its value from ``defaults``. ``out`` itself never
    has to match: a run folder may be copied or moved and resumed there.

    Raises:
        ValueError: a setting outside ``resumable`` differs from the run's saved ``config.json``.
        AssetError: ``latest.json`` or ``config.json`` is malformed, or names a checkpoint
            folder that is not a ``step_N`` folder of the run.
    """
    out = Path(out)
    latest = out / "checkpoints" / "latest.json"
    if not latest.is_file():
        return None
    saved = read_json(out / "config.json")
    if not isinstance(saved, dict):
        raise AssetError(out / "config.json", f"expected a JSON object, got {type(saved).__name__}")
    defaults = defaults or {}
    free = set(resumable) | set(ALWAYS_RESUMABLE)

    def same(k: str) -> bool:
        if k in saved:
            return saved[k] == config[k]
        return k in defaults and defaults[k] == config[k]

    diff = [k for k in config if k not in free and not same(k)]
    if diff:
        raise ValueError(f"cannot resume {out}: settings {diff} differ from the saved config.json")
    rec = read_json(latest)
    name = rec.get("folder") if isinstance(rec, dict) else None
    if not isinstance(name, str) or not _STEP_FOLDER.match(name):
        raise AssetError(latest, f'must hold {{"step", "folder": "step_N"}}, got {str(rec)[:80]}')
    folder = out / "checkpoints" / name
    if not folder.is_dir():
        raise AssetError(latest, f"points at {name}, which is missing")
    return folder


def save_trainer_state(folder: Path, tensors: Mapping[str, Tensor], state: Mapping[str, Any]) -> None:
    """Write a checkpoint's ``trainer.safetensors`` and ``trainer.json`` (with the tensors'
    sha256), tensors first, each atomically; non-finite tensors are refused (ValueError)."""
    write_tensors_and_manifest(folder, TRAINER_TENSORS, tensors, TRAINER_STATE, state, indent=None, allow_nan=True)


def read_trainer_state(
    folder: Path, required: Sequence[str] = ("rng.sampler", "rng.torch")
) -> tuple[dict[str, Any], dict[str, Tensor]]:
    """Read and check a checkpoint's trainer state: ``(trainer.json, trainer.safetensors)``.

    ``trainer.json`` must hold ``step`` (int), ``history`` and ``evals`` (lists) and
    ``train_time_s`` (number); the tensors file must match the recorded sha256, hold the ``required`` tensors
    and only finite floating values.

    Raises:
        AssetError: naming the file and the problem.
    """
    spath, tpath = folder / TRAINER_STATE, folder / TRAINER_TENSORS
    state = read_json(spath)
    if not isinstance(state, dict):
        raise AssetError(spath, f"expected a JSON object, got {type(state).__name__}")
    for key, typ in (("step", int), ("history", list), ("evals", list), ("train_time_s", (int, float))):
        if not isinstance(state.get(key), typ) or isinstance(state.get(key), bool):
            raise AssetError(spath, f"{key!r} is missing or not a {getattr(typ, '__name__', 'number')}")
    if state["step"] < 0:
        raise AssetError(spath, f"step is {state['step']}")
    tensors = read_checked_tensors(tpath, state, spath)
    missing = [k for k in required if k not in tensors]
    if missing:
        raise AssetError(tpath, f"tensors {missing} are missing")
    bad = [k for k, v in tensors.items() if v.is_floating_point() and not bool(torch.isfinite(v).all())]
    if bad:
        raise AssetError(tpath, f"tensors {bad[:3]} contain NaN or infinity (corrupt file)")
    return state, tensors


def config_defaults(cls: type) -> dict[str, Any]:
    """``{field: default}`` of a config dataclass (fields with a default or default factory)."""
    out: dict[str, Any] = {}
    for f in dataclasses.fields(cls):
        if f.default is not dataclasses.MISSING:
            out[f.name] = f.default
        elif f.default_factory is not dataclasses.MISSING:  # type: ignore[misc]
            out[f.name] = f.default_factory()  # type: ignore[misc]
    return out


def network_and_adam_tensors(model: Any, opt: torch.optim.Optimizer) -> dict[str, Tensor]:
    """What a checkpoint holds of a model trained with Adam: ``model.<key>`` for its
    ``network_state_dict()`` and ``adam.<param index>.<name>`` for each parameter's Adam state."""
    tensors = {f"model.{k}": v.detach().cpu().contiguous() for k, v in model.network_state_dict().items()}
    for i, p in enumerate(opt.param_groups[0]["params"]):
        for name, v in opt.state.get(p, {}).items():
            tensors[f"adam.{i}.{name}"] = torch.as_tensor(v).detach().cpu().contiguous()
    return tensors


def read_latest_trainer_state(
    folder: Path, required: Sequence[str]
) -> Optional[tuple[Path, dict[str, Any], dict[str, Tensor]]]:
    """``(latest.json, trainer.json, tensors)`` of ``folder/checkpoints``'s latest checkpoint
    (None: there is none yet).

    Raises:
        AssetError: ``latest.json`` names no ``step_N`` folder, or the state is damaged.
    """
    latest = folder / "checkpoints" / "latest.json"
    if not latest.is_file():
        return None
    rec = read_json(latest)
    name = rec.get("folder") if isinstance(rec, dict) else None
    if not isinstance(name, str) or not re.fullmatch(r"step_[0-9]+", name):
        raise AssetError(latest, f'must hold {{"step", "folder": "step_N"}}, got {str(rec)[:80]}')
    state, tensors = read_trainer_state(folder / "checkpoints" / name, required=required)
    return latest, state, tensors


def load_network_and_adam(latest: Path, tensors: Mapping[str, Tensor], model: Any, opt: torch.optim.Optimizer) -> None:
    """Restore :func:`network_and_adam_tensors` into ``model`` and ``opt``.

    Raises:
        AssetError: naming ``latest`` when the saved network lacks a key of ``model``.
    """
    net = {k.removeprefix("model."): v for k, v in tensors.items() if k.startswith("model.")}
    missing = set(model.network_state_dict()) - set(net)
    if missing:
        raise AssetError(latest, f"the saved network lacks {sorted(missing)[:3]}")
    model.load_state_dict(net, strict=False)
    for i, p in enumerate(opt.param_groups[0]["params"]):
        st = {k.split(".", 2)[2]: v.to(p.device) for k, v in tensors.items() if k.startswith(f"adam.{i}.")}
        if st:
            st["step"] = st["step"].cpu()  # Adam keeps its step count on the CPU
            opt.state[p] = st
