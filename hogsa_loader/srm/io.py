"""SRM checkpoints: ``srm.safetensors`` + ``manifest.json`` (schema version 1), no pickle.

Manifest keys (all required):

==================  ==================================================================
format              ``"hogsa-srm"``
schema_version      1
library_version     writer's ``hogsa_loader.__version__``
architecture        ``"styleunet"``
config              :class:`~hogsa_loader.srm.styleunet.StyleUNetConfig` as JSON
io                  ``{"input": "premultiplied RGB (B,H,W,3) in [0,1] + alpha", "scale": s}``
extra               free-form JSON (training provenance, metrics); ``train_srm.py`` records
                    ``targets``: per HOGS run, subject, object and the views the SRM was
                    trained (``views``) and selected (``val_views``) on (:func:`seen_views`)
tensors             ``{name: {"shape": [...], "dtype": "float32"}}``
tensors_file        ``"srm.safetensors"``
tensors_sha256      sha256 of the tensors file
==================  ==================================================================

Tensors first, manifest last, both atomically (:func:`~hogsa_loader.gaussians.checkpoint.atomic_write`).
:func:`load_srm` validates everything and raises :class:`~hogsa_loader.errors.AssetError`
naming the offending file. It accepts the checkpoint folder itself or a training run folder
(``pretrain/train_srm.py --out RUN`` writes the final EMA generator at ``RUN/``).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Mapping, Optional

import torch

from hogsa_loader.errors import AssetError, PathLike, read_json
from hogsa_loader.gaussians.checkpoint import read_checked_tensors, write_tensors_and_manifest
from hogsa_loader.srm.model import SRM
from hogsa_loader.srm.styleunet import StyleUNetConfig

__all__ = ["SRM_FORMAT", "SRM_SCHEMA_VERSION", "SRM_MANIFEST", "SRM_TENSORS", "save_srm", "read_srm_manifest", "load_srm",
           "seen_views"]

SRM_FORMAT = "hogsa-srm"
SRM_SCHEMA_VERSION = 1
SRM_MANIFEST = "manifest.json"
SRM_TENSORS = "srm.safetensors"

_REQUIRED: dict[str, type | tuple[type, ...]] = {
    "format": str,
    "schema_version": int,
    "library_version": str,
    "architecture": str,
    "config": dict,
    "io": dict,
    "extra": dict,
    "tensors": dict,
    "tensors_file": str,
    "tensors_sha256": str,
}


def save_srm(model: SRM, folder: PathLike, *, extra: Optional[Mapping[str, Any]] = None) -> Path:
    """Write ``model`` to ``folder`` (created if needed) as safetensors + manifest.

    Args:
        model: an :class:`SRM`.
        folder: output folder; existing files are replaced atomically.
        extra: JSON-able provenance (no NaN / infinity).

    Returns:
        the folder.

    Raises:
        ValueError: NaN or infinite weights or metadata; nothing is written then.
    """
    import hogsa_loader

    folder = Path(folder)
    tensors = {k: v.detach().cpu().contiguous() for k, v in model.net.state_dict().items()}
    manifest = {
        "format": SRM_FORMAT,
        "schema_version": SRM_SCHEMA_VERSION,
        "library_version": hogsa_loader.__version__,
        "architecture": "styleunet",
        "config": model.cfg.to_json(),
        "io": {"input": "premultiplied RGB (B,H,W,3) in [0,1] + alpha (B,H,W)", "output": "premultiplied RGB", "scale": model.scale},
        "extra": dict(extra or {}),
        "tensors": {k: {"shape": list(v.shape), "dtype": str(v.dtype).removeprefix("torch.")} for k, v in tensors.items()},
        "tensors_file": SRM_TENSORS,
    }  # (+ tensors_sha256, added by the writer)
    write_tensors_and_manifest(folder, SRM_TENSORS, tensors, SRM_MANIFEST, manifest,
                               metadata={"format": SRM_FORMAT, "schema_version": str(SRM_SCHEMA_VERSION)})
    return folder


def read_srm_manifest(folder: PathLike) -> dict[str, Any]:
    """Read and validate ``folder/manifest.json``.

    Raises:
        AssetError: naming ``manifest.json`` and the problem.
    """
    path = Path(folder) / SRM_MANIFEST
    m = read_json(path, allow_nan=False)
    if not isinstance(m, dict):
        raise AssetError(path, "manifest must be a JSON object")
    if m.get("format") != SRM_FORMAT:
        raise AssetError(path, f"not an SRM checkpoint (format {m.get('format')!r}, expected {SRM_FORMAT!r})")
    for key, typ in _REQUIRED.items():
        if key not in m:
            raise AssetError(path, f"missing key {key!r}")
        if not isinstance(m[key], typ) or (typ is int and isinstance(m[key], bool)):
            raise AssetError(path, f"key {key!r} has type {type(m[key]).__name__}")
    if m["schema_version"] != SRM_SCHEMA_VERSION:
        raise AssetError(path, f"schema_version {m['schema_version']} is not supported (this library reads {SRM_SCHEMA_VERSION})")
    if m["architecture"] != "styleunet":
        raise AssetError(path, f"unknown architecture {m['architecture']!r}")
    return m


def seen_views(manifest: Mapping[str, Any], subject: str, object_name: str) -> Optional[set[int]]:
    """Camera views of (``subject``, ``object_name``) whose ground truth the SRM saw in
    training or checkpoint selection, from ``manifest["extra"]["targets"]``.

    Returns:
        the set of views (empty when the SRM never saw that subject + object), or ``None``
        when the manifest does not record its targets (SRMs written before they were).
    """
    targets = manifest.get("extra", {}).get("targets")
    if not isinstance(targets, list):
        return None
    seen: set[int] = set()
    for t in targets:
        if isinstance(t, dict) and (t.get("subject"), t.get("object")) == (subject, object_name):
            seen.update(int(v) for v in list(t.get("views") or []) + list(t.get("val_views") or []))
    return seen


def load_srm(folder: PathLike, device: Optional[torch.device | str] = None, *, dtype: torch.dtype = torch.float32) -> SRM:
    """Load an SRM checkpoint folder (or a ``train_srm.py`` run folder) in eval mode.

    Args:
        folder: folder with ``manifest.json`` + ``srm.safetensors``.
        device: where to put it (default CPU).

    Returns:
        :class:`SRM` with ``.refine(rgb (B,H,W,3), alpha (B,H,W)) -> (B,sH,sW,3)``.

    Raises:
        AssetError: missing/malformed manifest or tensors file, checksum mismatch, tensors
            that do not fit the configured architecture (names the file).
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise AssetError(folder, "SRM checkpoint folder is missing")
    m = read_srm_manifest(folder)
    mpath = folder / SRM_MANIFEST
    try:
        cfg = StyleUNetConfig.from_json(m["config"])
        model = SRM(cfg)
    except (TypeError, ValueError) as exc:
        raise AssetError(mpath, f"bad StyleUNet config ({exc})") from None
    tensors = read_checked_tensors(folder / m["tensors_file"], m, mpath)  # (tensors_sha256 is required here)
    tpath = folder / m["tensors_file"]
    want = model.net.state_dict()
    missing, unexpected = sorted(set(want) - set(tensors)), sorted(set(tensors) - set(want))
    if missing or unexpected:
        raise AssetError(tpath, f"tensors do not fit the configured StyleUNet: missing {missing[:4]}, unexpected {unexpected[:4]}")
    bad = [k for k in want if tuple(tensors[k].shape) != tuple(want[k].shape)]
    if bad:
        raise AssetError(tpath, f"tensor shapes do not fit the configured StyleUNet: {bad[:4]}")
    for k, spec in m["tensors"].items():
        if k in tensors and list(tensors[k].shape) != list(spec.get("shape", [])):
            raise AssetError(mpath, f"tensor {k!r} shape {list(tensors[k].shape)} differs from the manifest {spec.get('shape')}")
    model.net.load_state_dict(tensors)
    model = model.to(device=device or "cpu", dtype=dtype)
    return model.eval()
