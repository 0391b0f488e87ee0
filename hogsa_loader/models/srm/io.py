"""SRM checkpoints: ``srm.safetensors`` + ``manifest.json``, no pickle.

:func:`save_srm` writes one (its docstring lists the manifest keys); :func:`load_srm` validates
everything and raises :class:`~hogsa_loader.errors.AssetError` naming the offending file. It
accepts the checkpoint folder itself or a training run folder (``hogsa train srm --out
RUN`` writes the final EMA generator at ``RUN/``). :func:`seen_views` reads the views an SRM saw.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Mapping, Optional

import torch

from hogsa_loader.errors import AssetError, PathLike
from hogsa_loader.io.tensors import ManifestFormat, read_manifest, read_tensors, save_checkpoint
from hogsa_loader.models.srm.model import SRM
from hogsa_loader.models.srm.styleunet import StyleUNetConfig

__all__ = [
    "SRM_FORMAT",
    "SRM_SCHEMA_VERSION",
    "SRM_MANIFEST",
    "SRM_TENSORS",
    "SRM_CHECKPOINT",
    "save_srm",
    "read_srm_manifest",
    "load_srm",
    "seen_views",
]

SRM_FORMAT = "hogsa-srm"
SRM_SCHEMA_VERSION = 1
SRM_MANIFEST = "manifest.json"
SRM_TENSORS = "srm.safetensors"
#: The shared checkpoint header of an SRM.
SRM_CHECKPOINT = ManifestFormat(
    SRM_FORMAT, SRM_SCHEMA_VERSION, "an SRM checkpoint", SRM_TENSORS, manifest_file=SRM_MANIFEST, header_metadata=True
)

#: The SRM's own manifest keys and their JSON types.
_REQUIRED: dict[str, type | tuple[type, ...]] = {"architecture": str, "config": dict, "io": dict, "extra": dict}


def save_srm(model: SRM, folder: PathLike, *, extra: Optional[Mapping[str, Any]] = None) -> Path:
    """Write ``model`` to ``folder`` (created if needed) as safetensors + manifest.

    The manifest is the shared checkpoint header (:mod:`hogsa_loader.io.tensors`: ``format``
    ``"hogsa-srm"``, ``schema_version`` 1, ``library_version``, ``tensors``, ``tensors_file``,
    ``tensors_sha256``) plus these keys, every one required:

    ==================  ==================================================================
    architecture        ``"styleunet"``
    config              :class:`~hogsa_loader.models.srm.styleunet.StyleUNetConfig` as JSON
    io                  ``{"input": "premultiplied RGB (B,H,W,3) in [0,1] + alpha", "scale": s}``
    extra               free-form JSON (training provenance, metrics); ``train_srm.py`` records
                        ``targets``: per HOGS run, subject, object and the views the SRM was
                        trained (``views``) and selected (``val_views``) on (:func:`seen_views`)
    ==================  ==================================================================

    Args:
        model: an :class:`SRM`.
        folder: output folder; existing files are replaced atomically.
        extra: JSON-able provenance (no NaN / infinity).

    Returns:
        the folder.

    Raises:
        ValueError: NaN or infinite weights or metadata; nothing is written then.
    """
    folder = Path(folder)
    tensors = {k: v.detach().cpu().contiguous() for k, v in model.net.state_dict().items()}
    fields = {
        "architecture": "styleunet",
        "config": model.cfg.to_json(),
        "io": {
            "input": "premultiplied RGB (B,H,W,3) in [0,1] + alpha (B,H,W)",
            "output": "premultiplied RGB",
            "scale": model.scale,
        },
        "extra": dict(extra or {}),
    }
    save_checkpoint(folder, SRM_CHECKPOINT, tensors, fields)
    return folder


def read_srm_manifest(folder: PathLike) -> dict[str, Any]:
    """Read and validate ``folder/manifest.json``.

    Raises:
        AssetError: naming ``manifest.json`` and the problem.
    """
    m = read_manifest(folder, SRM_CHECKPOINT)
    path = Path(folder) / SRM_MANIFEST
    for key, typ in _REQUIRED.items():
        if key not in m:
            raise AssetError(path, f"missing key {key!r}")
        if not isinstance(m[key], typ):
            raise AssetError(path, f"key {key!r} has type {type(m[key]).__name__}")
    if m["architecture"] != "styleunet":
        raise AssetError(path, f"unknown architecture {m['architecture']!r}")
    return m


def seen_views(manifest: Mapping[str, Any], subject: str, object_name: str) -> Optional[set[int]]:
    """Camera views of (``subject``, ``object_name``) whose ground truth the SRM saw in
    training or checkpoint selection, from ``manifest["extra"]["targets"]``.

    Returns:
        the set of views (empty when the SRM never saw that subject + object), or ``None``
        when the manifest does not record its targets (an SRM saved without them).
    """
    targets = manifest.get("extra", {}).get("targets")
    if not isinstance(targets, list):
        return None
    seen: set[int] = set()
    for t in targets:
        if isinstance(t, dict) and (t.get("subject"), t.get("object")) == (subject, object_name):
            seen.update(int(v) for v in list(t.get("views") or []) + list(t.get("val_views") or []))
    return seen


def load_srm(
    folder: PathLike, device: Optional[torch.device | str] = None, *, dtype: torch.dtype = torch.float32
) -> SRM:
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
    m = read_srm_manifest(folder)
    mpath = folder / SRM_MANIFEST
    try:
        cfg = StyleUNetConfig.from_json(m["config"])
        model = SRM(cfg)
    except (TypeError, ValueError) as exc:
        raise AssetError(mpath, f"bad StyleUNet config ({exc})") from None
    tensors = read_tensors(folder, m, SRM_CHECKPOINT)
    tpath = folder / SRM_TENSORS
    want = model.net.state_dict()
    missing, unexpected = sorted(set(want) - set(tensors)), sorted(set(tensors) - set(want))
    if missing or unexpected:
        raise AssetError(
            tpath, f"tensors do not fit the configured StyleUNet: missing {missing[:4]}, unexpected {unexpected[:4]}"
        )
    bad = [k for k in want if tuple(tensors[k].shape) != tuple(want[k].shape)]
    if bad:
        raise AssetError(tpath, f"tensor shapes do not fit the configured StyleUNet: {bad[:4]}")
    model.net.load_state_dict(tensors)
    model = model.to(device=device or "cpu", dtype=dtype)
    return model.eval()
