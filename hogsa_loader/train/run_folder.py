"""Checkpoint bookkeeping shared by the trainers (HOGS, SRM).

A run folder keeps ``config.json`` and ``checkpoints/step_NNNNNNN/`` folders; ``checkpoints/
latest.json`` (``{"step", "folder"}``) is written last and atomically, so a run killed at any
moment resumes from a complete checkpoint.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path
from typing import Any, Mapping, Optional, Sequence

from hogsa_loader.gaussians.checkpoint import atomic_write

__all__ = ["commit_checkpoint", "latest_checkpoint", "config_defaults"]


def commit_checkpoint(folder: Path, step: int) -> None:
    """Point ``latest.json`` (next to ``folder``) at the complete checkpoint ``folder``, then
    remove the older ``step_*`` folders."""
    ck = folder.parent
    atomic_write(ck / "latest.json", (json.dumps({"step": step, "folder": folder.name}) + "\n").encode())
    for old in ck.glob("step_*"):
        if old.is_dir() and old.name != folder.name:
            shutil.rmtree(old, ignore_errors=True)


def latest_checkpoint(out: Path, config: Mapping[str, Any], resumable: Sequence[str],
                      defaults: Optional[Mapping[str, Any]] = None) -> Optional[Path]:
    """The latest complete checkpoint folder of run ``out``, or None when there is none.

    A setting missing from the saved ``config.json`` (added to the library after the run
    started) matches when ``config`` has its value from ``defaults``.

    Raises:
        ValueError: a setting outside ``resumable`` differs from the run's saved ``config.json``.
    """
    latest = out / "checkpoints" / "latest.json"
    if not latest.is_file():
        return None
    saved = json.loads((out / "config.json").read_text())
    defaults = defaults or {}

    def same(k: str) -> bool:
        if k in saved:
            return saved[k] == config[k]
        return k in defaults and defaults[k] == config[k]

    diff = [k for k in config if k not in resumable and not same(k)]
    if diff:
        raise ValueError(f"cannot resume {out}: settings {diff} differ from the saved config.json")
    return out / "checkpoints" / json.loads(latest.read_text())["folder"]


def config_defaults(cls: type) -> dict[str, Any]:
    """``{field: default}`` of a config dataclass (fields with a default or default factory)."""
    import dataclasses

    out: dict[str, Any] = {}
    for f in dataclasses.fields(cls):
        if f.default is not dataclasses.MISSING:
            out[f.name] = f.default
        elif f.default_factory is not dataclasses.MISSING:  # type: ignore[misc]
            out[f.name] = f.default_factory()  # type: ignore[misc]
    return out
