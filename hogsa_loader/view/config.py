"""Settings of ``hogsa view`` (:class:`ViewConfig`; the CLI derives its flags from it) and
the checks that need no file loaded. Importing this module stays cheap (no torch)."""

# ruff: noqa: UP045  (Optional[...] fields: hogsa_loader.cli.dataclass_args reads typing.Optional)

from __future__ import annotations

import importlib.util
import math
import os
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal, Optional

from hogsa_loader.errors import UsageError
from hogsa_loader.io.atomic import creation_problem

__all__ = ["ViewConfig", "ViewError", "check_view_config", "parse_item"]

_ITEM = re.compile(r"^(?P<name>[^:]+):(?P<index>-?\d+)$")


class ViewError(UsageError):
    """A ``hogsa view`` request that cannot be served (reported as one line)."""


@dataclass
class ViewConfig:
    """Settings of ``hogsa view`` (:func:`~hogsa_loader.view.job.run_view`); one flag per field."""

    bundle: Optional[str] = field(default=None, metadata={"help": "bundle folder", "required": True})
    data: Optional[str] = field(
        default=None, metadata={"help": "ARCTIC(-format) data root of the bundle", "required": True}
    )
    subject: Optional[str] = field(
        default=None, metadata={"help": "subject of the HOGS model to show", "required": True}
    )
    object: Optional[str] = field(default=None, metadata={"help": "object of the HOGS model to show", "required": True})
    out: Optional[str] = field(default=None, metadata={"help": "output folder", "required": True})
    frame: tuple[str, ...] = field(
        default=(),
        metadata={"help": "pose sources SEQ:IDX: annotated frame IDX of the subject's sequence SEQ (one or more)"},
    )
    pose_bank: tuple[str, ...] = field(
        default=(), metadata={"help": "pose sources NAME:I: row I of the bundle's pose bank NAME (one or more)"}
    )
    orbit: int = field(default=16, metadata={"help": "views on the 360° orbit (0: no orbit)"})
    elevation: float = field(default=20.0, metadata={"help": "orbit elevation above the horizontal (degrees)"})
    distance: Optional[float] = field(
        default=None,
        metadata={"help": "orbit camera distance (m); none: the median distance of the subject's dataset cameras"},
    )
    size: int = field(default=256, metadata={"help": "side of every rendered view (px)"})
    transfer_to: tuple[str, ...] = field(
        default=(),
        metadata={"help": "target subjects: the same poses on their hand models (their betas, wrists re-solved)"},
    )
    srm: bool = field(default=True, metadata={"help": "also show the views refined by the bundle's SRM"})
    background: Literal["neutral", "photo"] = field(default="neutral", metadata={"help": "background of the pictures"})
    backgrounds: Optional[str] = field(
        default=None,
        metadata={
            "help": "image folder for --background photo; none: the photographs shipped with scikit-image",
            "name": "background_folder",
        },
    )
    keypoints: bool = field(
        default=False, metadata={"help": "draw the 2D hand joints and object keypoints in transfer.png"}
    )
    video: Literal["gif", "mp4", "none"] = field(
        default="gif", metadata={"help": "animated orbit (mp4 needs the imageio-ffmpeg package)"}
    )
    fps: float = field(default=8.0, metadata={"help": "frames per second of the animation"})
    regrasp_steps: int = field(
        default=20, metadata={"help": "wrist re-solve steps of a transfer (0: wrists only aligned)"}
    )
    contact_voxel: float = field(
        default=0.002, metadata={"help": "SDF grid spacing (m) of the object for the re-solve and the contact figures"}
    )
    device: str = field(default="cpu", metadata={"help": "cpu or cuda"})
    backend: Literal["auto", "torch", "gsplat"] = field(default="auto", metadata={"help": "renderer backend"})
    seed: int = field(default=0, metadata={"help": "seed of the photo backgrounds"})
    threads: int = field(default=0, metadata={"help": "torch CPU threads (0 = default)"})
    quiet: bool = field(default=False, metadata={"help": "no messages"})


def parse_item(value: str, flag: str, what: str) -> tuple[str, int]:
    """``"NAME:I"`` → ``(NAME, I)`` (I ≥ 0); :class:`ViewError` naming ``flag`` otherwise."""
    m = _ITEM.match(value)
    if not m:
        raise ViewError(f"{flag} expects {what}, got {value!r}")
    idx = int(m.group("index"))
    if idx < 0:
        raise ViewError(f"{flag}: the index must be >= 0, got {value!r}")
    return m.group("name"), idx


def _check_writable(out: Path) -> None:
    """``--out``: a writable folder, or creatable (its nearest existing ancestor a writable folder)."""
    if out.exists() or out.is_symlink():
        if not out.is_dir():
            raise ViewError(f"--out {out}: exists and is not a folder")
        if not os.access(out, os.W_OK | os.X_OK):
            raise ViewError(f"--out {out}: folder is not writable")
        return
    problem = creation_problem(out)
    if problem is not None:
        raise ViewError(f"--out {out}: {problem}")


def check_view_config(cfg: ViewConfig) -> None:
    """Check what can be checked without loading anything (raises :class:`ViewError`)."""
    for name in ("bundle", "data", "subject", "object", "out"):
        if not getattr(cfg, name):
            raise ViewError(f"--{name} is required")
    if not (Path(cfg.bundle) / "manifest.json").is_file():  # type: ignore[arg-type]
        raise ViewError(f"--bundle {cfg.bundle}: not a bundle folder (no manifest.json)")
    if not Path(cfg.data).is_dir():  # type: ignore[arg-type]
        raise ViewError(f"--data {cfg.data}: no such folder")
    if Path(cfg.out).exists() and not Path(cfg.out).is_dir():  # type: ignore[arg-type]
        raise ViewError(f"--out {cfg.out} exists and is not a folder")
    _check_writable(Path(cfg.out))  # type: ignore[arg-type]
    for v in cfg.frame:
        parse_item(v, "--frame", "SEQ:IDX (e.g. box_grab_01:30)")
    for v in cfg.pose_bank:
        parse_item(v, "--pose-bank", "NAME:I (e.g. pose_bank:0)")
    if cfg.orbit < 0 or cfg.orbit > 360:
        raise ViewError(f"--orbit must be in 0..360, got {cfg.orbit}")
    if not -89.0 <= cfg.elevation <= 89.0:
        raise ViewError(f"--elevation must be in [-89, 89] degrees, got {cfg.elevation}")
    if cfg.distance is not None and not (math.isfinite(cfg.distance) and cfg.distance > 0):
        raise ViewError(f"--distance must be a positive number of metres, got {cfg.distance}")
    if not 32 <= cfg.size <= 2048:
        raise ViewError(f"--size must be in 32..2048, got {cfg.size}")
    if not (math.isfinite(cfg.fps) and cfg.fps > 0):
        raise ViewError(f"--fps must be positive, got {cfg.fps}")
    if cfg.regrasp_steps < 0:
        raise ViewError(f"--regrasp-steps must be >= 0, got {cfg.regrasp_steps}")
    if not (math.isfinite(cfg.contact_voxel) and 0.0005 <= cfg.contact_voxel <= 0.02):
        raise ViewError(f"--contact-voxel must be in [0.0005, 0.02] m, got {cfg.contact_voxel}")
    if cfg.threads < 0:
        raise ViewError(f"--threads must be >= 0, got {cfg.threads}")
    if cfg.subject in cfg.transfer_to:
        raise ViewError(f"--transfer-to lists the shown subject {cfg.subject} itself")
    if len(set(cfg.transfer_to)) != len(cfg.transfer_to):
        raise ViewError(f"--transfer-to lists a subject twice: {' '.join(cfg.transfer_to)}")
    if cfg.backgrounds is not None and cfg.background != "photo":
        raise ViewError("--background-folder applies to --background photo")
    if cfg.backgrounds is not None and not Path(cfg.backgrounds).is_dir():
        raise ViewError(f"--background-folder {cfg.backgrounds}: no such folder")
    if cfg.video == "mp4":
        if importlib.util.find_spec("imageio_ffmpeg") is None:
            raise ViewError(
                "--video mp4 needs the imageio-ffmpeg package (pip install imageio-ffmpeg); use --video gif"
            )
    if cfg.device.startswith("cuda"):
        import torch  # deferred: importing this module (``hogsa view --help``) stays free of torch

        if not torch.cuda.is_available():
            raise ViewError(f"--device {cfg.device}: CUDA is not available")
    elif cfg.device != "cpu":
        raise ViewError(f"--device must be cpu or cuda[:N], got {cfg.device!r}")
