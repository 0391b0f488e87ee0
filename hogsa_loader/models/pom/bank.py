"""Pose bank: optimised bimanual grasps on disk (safetensors + JSON manifest).

:func:`save_pose_bank` writes a bank folder (its docstring lists the files, the tensors and
their convention); :func:`load_pose_bank` reads and validates one into a :class:`PoseBank`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping, Optional, Sequence

import numpy as np
import torch
from torch import Tensor

from hogsa_loader.errors import AssetError, PathLike
from hogsa_loader.io.tensors import ManifestFormat, read_manifest, read_tensors, save_checkpoint
from hogsa_loader.models.pom.hands import SIDES
from hogsa_loader.models.pom.state import GraspState, HandParams

__all__ = ["BANK_SCHEMA", "BANK_VERSION", "BANK_FORMAT", "PoseBank", "save_pose_bank", "load_pose_bank"]

BANK_SCHEMA = "hogsa.pose_bank"
BANK_VERSION = 1
TENSOR_FILE = "poses.safetensors"
MANIFEST_FILE = "manifest.json"
METRIC_KEYS = ("penetration_depth", "intersection", "contact_ratio", "accept")
_HAND_WIDTH = {"rot": 3, "pose": 45, "trans": 3, "betas": 10}
#: The shared checkpoint header of a pose bank.
BANK_FORMAT = ManifestFormat(
    BANK_SCHEMA,
    BANK_VERSION,
    "a pose bank",
    TENSOR_FILE,
    name_key="schema",
    file_key="tensor_file",
    specs="shape",
    library_version=False,
    manifest_file=MANIFEST_FILE,
)


def _expected_shapes(n: int) -> dict[str, tuple[int, ...]]:
    shapes: dict[str, tuple[int, ...]] = {}
    for s in SIDES:
        for k, w in _HAND_WIDTH.items():
            shapes[f"{s}_{k}"] = (n, w)
    shapes.update({"obj_arti": (n,), "obj_rot": (n, 3), "obj_trans": (n, 3)})
    shapes.update({k: (n,) for k in METRIC_KEYS})
    return shapes


@dataclass
class PoseBank:
    """A loaded pose bank.

    Attributes:
        state: the N grasps as a :class:`GraspState` (float32, CPU).
        sources: N ``(subject, sequence, frame)``.
        metrics: key -> (N,) tensor (see :func:`save_pose_bank`).
        info: the manifest's provenance fields (``config``, ``contactnet``...).
    """

    state: GraspState
    sources: list[tuple[str, str, int]]
    metrics: dict[str, Tensor]
    info: dict = field(default_factory=dict)

    def __len__(self) -> int:
        return self.state.batch

    def tensors(self) -> dict[str, Tensor]:
        """The flat tensor dict written to ``poses.safetensors``."""
        out: dict[str, Tensor] = {}
        for s in SIDES:
            for k in _HAND_WIDTH:
                out[f"{s}_{k}"] = getattr(self.state.hands[s], k)
        out["obj_arti"] = self.state.obj_arti
        out["obj_rot"] = self.state.obj_rot
        out["obj_trans"] = self.state.obj_trans
        for k in METRIC_KEYS:
            out[k] = self.metrics[k]
        # clone: no shared storage (safetensors refuses it)
        return {k: v.detach().to("cpu", torch.float32).clone().contiguous() for k, v in out.items()}


def save_pose_bank(
    path: PathLike,
    state: GraspState,
    sources: Sequence[tuple[str, str, int]],
    metrics: Mapping[str, Any],
    info: Optional[dict] = None,
) -> Path:
    """Write a bank folder.

    A bank is a folder::

        BANK/
          poses.safetensors   tensors, first dimension N (one row per entry)
          manifest.json       the shared checkpoint header (:mod:`hogsa_loader.io.tensors`: schema
                              ``"hogsa.pose_bank"``, schema_version, tensors, tensor_file,
                              tensors_sha256) plus count, convention, entries (sources), info

    Tensors (float32; the same convention as :class:`~hogsa_loader.assets.types.SequenceData`:
    ARCTIC world frame, axis-angle, metres, finger pose relative to the MANO mean,
    ``flat_hand_mean=False``):

    ========================  ========  ==============================================
    key                       shape     meaning
    ========================  ========  ==============================================
    ``right_rot``/``left_rot``    (N, 3)    global orientation
    ``right_pose``/``left_pose``  (N, 45)   articulation (relative to the mean)
    ``right_trans``/...           (N, 3)    MANO ``transl`` (m)
    ``right_betas``/...           (N, 10)   shape
    ``obj_arti``                  (N,)      articulation θ (rad)
    ``obj_rot``                   (N, 3)    object axis-angle
    ``obj_trans``                 (N, 3)    object translation (m)
    ``penetration_depth``         (N,)      metres (ray parity)
    ``intersection``              (N,)      m³ (5 mm voxels)
    ``contact_ratio``             (N,)      fraction of hand vertices within 5 mm
    ``accept``                    (N,)      1.0 / 0.0 GraspTTA acceptance
    ========================  ========  ==============================================

    The manifest's ``entries`` list gives, per row, ``{"subject", "sequence", "frame",
    "object"}`` — the source frame (``frame`` = index into the sequence's GT frames).

    Args:
        path: output folder (created).
        state: N grasps; sources: N ``(subject, sequence, frame)``.
        metrics: per-entry arrays with the keys of :data:`METRIC_KEYS`.
        info: provenance stored in the manifest (JSON-serialisable).

    Returns:
        the manifest path.
    """
    n = state.batch
    if len(sources) != n:
        raise ValueError(f"{len(sources)} sources for {n} grasps")
    m = {k: torch.as_tensor(np.asarray(metrics[k], dtype=np.float32)).reshape(-1) for k in METRIC_KEYS}
    bank = PoseBank(state, list(sources), m, dict(info or {}))
    fields = {
        "count": n,
        "convention": "the dataset's world frame (ARCTIC, H2O) as SequenceData: axis-angle, metres, hand pose "
        "relative to the MANO mean (flat_hand_mean=False); object arti (rad), rot (axis-angle), trans (m)",
        "entries": [
            {"subject": a, "sequence": b, "frame": int(c), "object": state.obj_names[i]}
            for i, (a, b, c) in enumerate(sources)
        ],
        "info": bank.info,
    }
    return save_checkpoint(path, BANK_FORMAT, bank.tensors(), fields)


def _read_entries(man: dict, mpath: Path) -> tuple[list[tuple[str, str, int]], list[str]]:
    """The manifest's ``count`` and ``entries``: N ``(subject, sequence, frame)`` and N object names."""
    n = man.get("count")
    if not isinstance(n, int) or isinstance(n, bool) or n < 0:
        raise AssetError(mpath, f"'count' must be a non-negative integer, got {n!r}")
    entries = man.get("entries")
    if not isinstance(entries, list) or len(entries) != n:
        raise AssetError(mpath, f"'entries' must be a list of {n} sources")
    sources, names = [], []
    for i, e in enumerate(entries):
        if not (
            isinstance(e, dict)
            and isinstance(e.get("subject"), str)
            and isinstance(e.get("sequence"), str)
            and isinstance(e.get("frame"), int)
            and isinstance(e.get("object"), str)
        ):
            raise AssetError(mpath, f"entries[{i}] must have string subject/sequence/object and an int frame")
        sources.append((e["subject"], e["sequence"], e["frame"]))
        names.append(e["object"])
    return sources, names


def load_pose_bank(path: PathLike) -> PoseBank:
    """Read and validate a bank folder (or its ``manifest.json``).

    Raises:
        AssetError: missing or malformed manifest / tensor file, unknown schema or version,
            missing keys, wrong shapes, non-finite values, entries that do not match.
    """
    p = Path(path)
    folder = p.parent if p.is_file() else p
    man = read_manifest(folder, BANK_FORMAT)
    sources, names = _read_entries(man, folder / MANIFEST_FILE)
    tpath = folder / TENSOR_FILE
    t = read_tensors(folder, man, BANK_FORMAT)  # (listed names and shapes; finite)
    for key, shape in _expected_shapes(len(sources)).items():
        if key not in t:
            raise AssetError(tpath, f"tensor '{key}' is missing")
        if tuple(t[key].shape) != shape:
            raise AssetError(tpath, f"tensor '{key}' has shape {tuple(t[key].shape)}, expected {shape}")
        if not t[key].is_floating_point():
            raise AssetError(tpath, f"tensor '{key}' has dtype {t[key].dtype}, expected floating point")
    f = {k: v.float() for k, v in t.items()}
    hands = {s: HandParams(*(f[f"{s}_{k}"] for k in _HAND_WIDTH)) for s in SIDES}
    state = GraspState(hands, names, f["obj_arti"], f["obj_rot"], f["obj_trans"])
    info = man.get("info") if isinstance(man.get("info"), dict) else {}
    return PoseBank(state, sources, {k: f[k] for k in METRIC_KEYS}, info)
