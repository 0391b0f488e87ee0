"""Checkpoints of Gaussian parts: safetensors tensors plus a JSON manifest, no pickle.

A checkpoint is a folder::

    <folder>/gaussians.safetensors   the part's learnable state (``part.splats.state_dict()``)
    <folder>/manifest.json           what the tensors are and what they belong to

Manifest (schema version 1), every key required:

==================  ==================================================================
key                 value
==================  ==================================================================
format              ``"hogsa-gaussians"``
schema_version      1
library_version     ``hogsa_loader.__version__`` of the writer
part_type           ``"hand_right"``, ``"hand_left"`` or ``"object"``
variant             ``"games"``, ``"avatars"`` or ``"free"``
k, sh_degree        Gaussians per face, SH degree
num_verts,          binding-mesh vertices / faces, number of Gaussians
num_faces,
num_gaussians
template_hash       sha256 of the caller's template mesh (float32 vertices then int64
                    faces, little endian; :func:`~hogsa_loader.gaussians.parts.template_hash`)
binding_hash        the same hash of the binding mesh the Gaussians live on
binding_mesh        how the binding mesh was made (e.g. ``"subdivide_model levels=1"``)
config              the part's constructor settings (rebuilds it in :func:`load_part`)
source              ``{"dataset", "subject", "sequence"}`` (strings or null)
extra               free-form JSON object
tensors             ``{name: {"shape": [...], "dtype": "float32"}}``
tensors_file        ``"gaussians.safetensors"``
tensors_sha256      sha256 of the tensors file (detects a torn or mismatched pair)
==================  ==================================================================

Both files are written atomically (temporary file in the same folder, fsync,
``os.replace``), tensors first and manifest last. Loading validates everything and raises
:class:`~hogsa_loader.errors.AssetError` naming the offending file and the problem.
"""

from __future__ import annotations

import hashlib
import json
import os
import uuid
from pathlib import Path
from typing import Any, Mapping, Optional, Union

import torch
from torch import Tensor

from hogsa_loader.errors import AssetError, PathLike, read_json
from hogsa_loader.gaussians.parts import (
    ALL_VARIANTS,
    PART_TYPES,
    GaussianPart,
    HandGaussians,
    ObjectGaussians,
)
from hogsa_loader.hands.mano import MANOLayer
from hogsa_loader.hands.mano_io import ManoModelData
from hogsa_loader.objects.template import ObjectTemplate

__all__ = [
    "FORMAT",
    "SCHEMA_VERSION",
    "MANIFEST_FILE",
    "TENSORS_FILE",
    "save_part",
    "canonical_safetensors",
    "read_manifest",
    "load_state",
    "load_part",
]

FORMAT = "hogsa-gaussians"
SCHEMA_VERSION = 1
MANIFEST_FILE = "manifest.json"
TENSORS_FILE = "gaussians.safetensors"

_REQUIRED: dict[str, type | tuple[type, ...]] = {
    "format": str,
    "schema_version": int,
    "library_version": str,
    "part_type": str,
    "variant": str,
    "k": int,
    "sh_degree": int,
    "num_verts": int,
    "num_faces": int,
    "num_gaussians": int,
    "template_hash": str,
    "binding_hash": str,
    "binding_mesh": str,
    "config": dict,
    "source": dict,
    "extra": dict,
    "tensors": dict,
    "tensors_file": str,
    "tensors_sha256": str,
}
_SOURCE_KEYS = ("dataset", "subject", "sequence")


# --------------------------------------------------------------------------------------
# Writing
# --------------------------------------------------------------------------------------


def atomic_write(path: Path, data: bytes) -> None:
    """Write ``data`` to ``path`` via a temporary file in the same folder + ``os.replace``."""
    tmp = path.with_name(f".{path.name}.{os.getpid()}.{uuid.uuid4().hex[:8]}.tmp")
    try:
        with open(tmp, "wb") as fh:
            fh.write(data)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    try:  # make the rename durable (POSIX); not possible everywhere
        fd = os.open(path.parent, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def canonical_safetensors(blob: bytes) -> bytes:
    """The same safetensors file with its ``__metadata__`` pairs in sorted key order.

    The safetensors writer emits the metadata pairs in hash-map order, which differs
    between processes; sorting them makes equal tensors and metadata give equal bytes (and
    so equal ``tensors_sha256``). Tensor entries and data are left as they are.
    """
    n = int.from_bytes(blob[:8], "little")
    header = json.loads(blob[8 : 8 + n].decode("utf-8"))
    meta = header.get("__metadata__")
    if not isinstance(meta, dict) or len(meta) < 2:
        return blob
    ordered = {"__metadata__": dict(sorted(meta.items())), **{k: v for k, v in header.items() if k != "__metadata__"}}
    text = json.dumps(ordered, separators=(",", ":"), ensure_ascii=False).encode("utf-8")
    text += b" " * (max(n, len(text) + (-len(text)) % 8) - len(text))  # space padding, as the writer pads
    return len(text).to_bytes(8, "little") + text + blob[8 + n :]


def write_tensors_and_manifest(folder: Path, tensors_file: str, tensors: Mapping[str, Tensor], manifest_file: str,
                               manifest: Mapping[str, Any], indent: Optional[int] = 1,
                               metadata: Optional[Mapping[str, str]] = None, allow_nan: bool = False) -> Path:
    """Write a safetensors file and its JSON manifest into ``folder`` (created), each atomically,
    tensors first. Everything is checked before anything is written: floating tensors must be
    finite and the manifest strict JSON (no NaN / infinity unless ``allow_nan``), so a refused
    save leaves an existing checkpoint as it was. The manifest gets ``tensors_sha256`` (sha256
    of the tensors file), which :func:`read_checked_tensors` verifies. ``metadata``: string
    pairs stored in the safetensors header, in sorted key order (equal inputs give equal
    bytes, :func:`canonical_safetensors`).

    Returns:
        the manifest path.

    Raises:
        ValueError: non-finite tensors or a manifest value that is not JSON (names the file).
    """
    from safetensors.torch import save as st_save

    folder = Path(folder)
    bad = [k for k, v in tensors.items() if v.is_floating_point() and not bool(torch.isfinite(v).all())]
    if bad:
        raise ValueError(f"{folder / tensors_file}: tensors {bad[:3]} contain NaN or infinity; not saved")
    blob = canonical_safetensors(st_save(dict(tensors), metadata=dict(metadata) if metadata else None))
    try:
        text = json.dumps({**manifest, "tensors_sha256": hashlib.sha256(blob).hexdigest()}, indent=indent,
                          allow_nan=allow_nan) + "\n"  # fmt: skip
    except ValueError as exc:
        raise ValueError(f"{folder / manifest_file}: the manifest would hold NaN or infinity ({exc}); not saved") from None
    folder.mkdir(parents=True, exist_ok=True)
    atomic_write(folder / tensors_file, blob)
    atomic_write(folder / manifest_file, text.encode("utf-8"))
    return folder / manifest_file


def read_checked_tensors(tpath: Path, manifest: Mapping[str, Any], manifest_path: Path) -> dict[str, Tensor]:
    """Read the safetensors file of a :func:`write_tensors_and_manifest` pair; its sha256 must
    equal the manifest's ``tensors_sha256`` when the manifest has one (files written before
    it was recorded have none and are read as they are).

    Raises:
        AssetError: missing or unreadable file, checksum mismatch, not safetensors (names the file).
    """
    from safetensors.torch import load as st_load

    tpath = Path(tpath)
    if not tpath.is_file():
        raise AssetError(tpath, f"tensors file is missing (listed in {manifest_path.name})")
    try:
        blob = tpath.read_bytes()
    except OSError as exc:
        raise AssetError(tpath, f"cannot read file ({exc})") from exc
    want = manifest.get("tensors_sha256")
    if want is not None and hashlib.sha256(blob).hexdigest() != want:
        raise AssetError(tpath, f"sha256 does not match {manifest_path.name} (torn write or files from different checkpoints)")
    try:
        return st_load(blob)
    except Exception as exc:  # safetensors raises its own error types on corrupt headers
        raise AssetError(tpath, f"not a valid safetensors file ({exc})") from exc


def _dtype_name(dtype: torch.dtype) -> str:
    return str(dtype).removeprefix("torch.")


def save_part(
    part: GaussianPart,
    folder: PathLike,
    *,
    dataset: Optional[str] = None,
    subject: Optional[str] = None,
    sequence: Optional[str] = None,
    extra: Optional[Mapping[str, Any]] = None,
) -> Path:
    """Write a part's Gaussians as a checkpoint folder (created if needed).

    Args:
        part: a :class:`HandGaussians` or :class:`ObjectGaussians`.
        folder: output folder; existing checkpoint files in it are replaced atomically.
        dataset, subject, sequence: provenance recorded under ``source`` (object parts
            also record their template's ``name`` there as ``object``).
        extra: free-form JSON-able metadata (no NaN / infinity).

    Returns:
        the folder.

    Raises:
        ValueError: NaN or infinite weights or metadata; nothing is written then.
    """
    import hogsa_loader

    folder = Path(folder)
    tensors = {name: t.detach().cpu().contiguous() for name, t in part.splats.state_dict().items()}
    manifest: dict[str, Any] = {
        "format": FORMAT,
        "schema_version": SCHEMA_VERSION,
        "library_version": hogsa_loader.__version__,
        "part_type": part.part_type,
        "variant": part.variant,
        "k": part.k,
        "sh_degree": part.sh_degree,
        **part.binding_counts(),
        "template_hash": part.template_hash,
        "binding_hash": part.binding_hash,
        "binding_mesh": part.binding_mesh,
        "config": part.config(),
        "source": {"dataset": dataset, "subject": subject, "sequence": sequence}
        | ({"object": part.name} if part.part_type == "object" else {}),
        "extra": dict(extra or {}),
        "tensors": {n: {"shape": list(t.shape), "dtype": _dtype_name(t.dtype)} for n, t in tensors.items()},
        "tensors_file": TENSORS_FILE,
    }  # (+ tensors_sha256, added by the writer)
    write_tensors_and_manifest(folder, TENSORS_FILE, tensors, MANIFEST_FILE, manifest,
                               metadata={"format": FORMAT, "schema_version": str(SCHEMA_VERSION)})
    return folder


# --------------------------------------------------------------------------------------
# Reading and validation
# --------------------------------------------------------------------------------------


def read_manifest(folder: PathLike) -> dict[str, Any]:
    """Read and validate ``manifest.json`` on its own (types, schema, known values).

    Raises:
        AssetError: naming ``manifest.json`` (or the folder) and the problem.
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise AssetError(folder, "checkpoint folder is missing")
    path = folder / MANIFEST_FILE
    raw = read_json(path, allow_nan=False)  # (missing, unreadable, malformed, NaN: AssetError naming it)
    if not isinstance(raw, dict):
        raise AssetError(path, f"expected a JSON object, got {type(raw).__name__}")
    if raw.get("format") != FORMAT:
        raise AssetError(path, f"format is {raw.get('format')!r}, expected {FORMAT!r}")
    version = raw.get("schema_version")
    if not isinstance(version, int) or isinstance(version, bool):
        raise AssetError(path, f"schema_version must be an integer, got {version!r}")
    if version != SCHEMA_VERSION:
        newer = " (written by a newer hogsa-loader)" if version > SCHEMA_VERSION else ""
        raise AssetError(path, f"unsupported schema_version {version}{newer}; this reader supports {SCHEMA_VERSION}")
    for key, typ in _REQUIRED.items():
        if key not in raw:
            raise AssetError(path, f"required key {key!r} is missing")
        val = raw[key]
        if not isinstance(val, typ) or (typ is int and isinstance(val, bool)):
            raise AssetError(path, f"{key!r} must be {getattr(typ, '__name__', typ)}, got {type(val).__name__}")
    if raw["part_type"] not in PART_TYPES:
        raise AssetError(path, f"part_type {raw['part_type']!r} is not one of {PART_TYPES}")
    if raw["variant"] not in ALL_VARIANTS:
        raise AssetError(path, f"variant {raw['variant']!r} is not one of {ALL_VARIANTS}")
    for key in _SOURCE_KEYS:
        v = raw["source"].get(key)
        if v is not None and not isinstance(v, str):
            raise AssetError(path, f"source.{key} must be a string or null")
    if raw["tensors_file"] != TENSORS_FILE:
        raise AssetError(path, f"tensors_file is {raw['tensors_file']!r}, expected {TENSORS_FILE!r}")
    for name, entry in raw["tensors"].items():
        if not (isinstance(entry, dict) and isinstance(entry.get("shape"), list) and isinstance(entry.get("dtype"), str)):
            raise AssetError(path, f"tensors[{name!r}] must be an object with a 'shape' list and a 'dtype' string, "
                                   f"got {entry!r}")  # fmt: skip
    return raw


def _check_against_part(raw: Mapping[str, Any], part: GaussianPart, path: Path) -> None:
    """Manifest vs the part the caller built from its template."""
    if raw["part_type"] != part.part_type:
        raise AssetError(path, f"checkpoint is for part_type {raw['part_type']!r}, the model is {part.part_type!r}")
    if raw["template_hash"] != part.template_hash:
        hint = ""
        if part.part_type.startswith("hand"):
            hint = ("; a hand part is bound to its hand model's vertices in their order, so a different MANO file "
                    "(e.g. another version of the synthetic hand, see its 'generator' metadata) needs the part "
                    "trained again")  # fmt: skip
        raise AssetError(
            path,
            f"template hash mismatch: the checkpoint was made for template {raw['template_hash'][:16]}..., "
            f"the given template hashes to {part.template_hash[:16]}...{hint}",
        )
    expect = {
        "variant": part.variant,
        "k": part.k,
        "sh_degree": part.sh_degree,
        "binding_mesh": part.binding_mesh,
        "binding_hash": part.binding_hash,
        **part.binding_counts(),
    }
    for key, val in expect.items():
        if raw[key] != val:
            hint = ""
            if part.part_type == "object" and key in ("binding_hash", "num_verts") and "mesh_tex" in str(part.binding_mesh):
                hint = ("; if the object's mesh_tex.obj has UV seams (several vt per vertex), note that it is now read "
                        "with seam vertices split (correct UVs), so a part trained on the old reading must be retrained")  # fmt: skip
            raise AssetError(path, f"{key} is {raw[key]!r} in the checkpoint but {val!r} in the model{hint}")
    cfg = part.config()
    saved = {"weld_seams": False, **raw["config"]}  # (older checkpoints: unwelded, see load_part)
    for key in sorted(set(cfg) | set(saved)):
        if saved.get(key) != cfg.get(key):
            raise AssetError(
                path, f"config.{key} is {saved.get(key)!r} in the checkpoint but {cfg.get(key)!r} in the model"
            )


def _read_tensors(folder: Path, raw: Mapping[str, Any], part: GaussianPart) -> dict[str, Tensor]:
    """Read, hash-check and validate the tensors file against the manifest and the part."""
    mpath = folder / MANIFEST_FILE
    tpath = folder / TENSORS_FILE
    tensors = read_checked_tensors(tpath, raw, mpath)  # (read_manifest made tensors_sha256 required)
    listed = raw["tensors"]
    if set(listed) != set(tensors):
        raise AssetError(mpath, f"lists tensors {sorted(listed)} but {TENSORS_FILE} holds {sorted(tensors)}")
    model_state = part.splats.state_dict()
    missing = sorted(set(model_state) - set(tensors))
    unexpected = sorted(set(tensors) - set(model_state))
    if missing or unexpected:
        raise AssetError(tpath, f"tensor names do not match the model: missing {missing}, unexpected {unexpected}")
    for name, t in tensors.items():
        want = model_state[name]
        if list(t.shape) != listed[name].get("shape") or _dtype_name(t.dtype) != listed[name].get("dtype"):
            raise AssetError(tpath, f"tensor {name!r} is {tuple(t.shape)} {t.dtype}, {MANIFEST_FILE} says {listed[name]}")
        if t.shape != want.shape:
            raise AssetError(tpath, f"tensor {name!r} has shape {tuple(t.shape)}, the model needs {tuple(want.shape)}")
        if t.is_floating_point() != want.is_floating_point():
            raise AssetError(tpath, f"tensor {name!r} has dtype {t.dtype}, the model needs {want.dtype}")
        if t.is_floating_point() and not bool(torch.isfinite(t).all()):
            bad = int((~torch.isfinite(t)).sum())
            raise AssetError(tpath, f"tensor {name!r} contains {bad} NaN or infinite values")
    if "binding" in tensors:
        b = tensors["binding"]
        n_verts = part.binding_counts()["num_verts"]
        if b.numel() and (int(b.min()) < 0 or int(b.max()) >= n_verts):
            raise AssetError(tpath, f"tensor 'binding' refers to vertices outside [0, {n_verts})")
    return tensors


def load_state(part: GaussianPart, folder: PathLike) -> dict[str, Any]:
    """Validate a checkpoint against ``part`` and load its tensors into it (bit-exact for
    equal dtypes).

    Args:
        part: a part built from the caller's template with the checkpoint's settings.
        folder: checkpoint folder.

    Returns:
        the manifest.

    Raises:
        AssetError: missing files, bad schema, wrong part type, template hash / setting /
            shape mismatch, NaN or infinite values, a torn write.
    """
    folder = Path(folder)
    raw = read_manifest(folder)
    _check_against_part(raw, part, folder / MANIFEST_FILE)
    tensors = _read_tensors(folder, raw, part)
    with torch.no_grad():
        state = part.splats.state_dict()
        part.splats.load_state_dict({n: tensors[n].to(state[n].dtype) for n in state}, strict=True)
    return raw


def load_part(
    folder: PathLike,
    template: Union[ManoModelData, MANOLayer, ObjectTemplate],
    *,
    expected_part_type: Optional[str] = None,
    part_id: Optional[int] = None,
    dtype: torch.dtype = torch.float32,
) -> GaussianPart:
    """Rebuild a part from the manifest's settings on the caller's template and load it.

    Args:
        folder: checkpoint folder.
        template: the hand model/layer or object template the checkpoint was made for
            (its hash is checked).
        expected_part_type: if given, the checkpoint must be of this part type.
        part_id: scene part index (default from the part type).
        dtype: parameter dtype.

    Returns:
        a :class:`HandGaussians` or :class:`ObjectGaussians` holding the checkpoint.
    """
    folder = Path(folder)
    raw = read_manifest(folder)
    mpath = folder / MANIFEST_FILE
    ptype = raw["part_type"]
    if expected_part_type is not None and ptype != expected_part_type:
        raise AssetError(mpath, f"checkpoint is for part_type {ptype!r}, expected {expected_part_type!r}")
    cfg = dict(raw["config"])
    cfg.setdefault("weld_seams", False)  # written before seam welding: per-vertex offsets, as trained
    try:
        if ptype == "object":
            if not isinstance(template, ObjectTemplate):
                raise AssetError(mpath, f"checkpoint is for an object, got a {type(template).__name__} template")
            part: GaussianPart = ObjectGaussians(template, part_id=part_id, dtype=dtype, **cfg)
        else:
            if not isinstance(template, (ManoModelData, MANOLayer)):
                raise AssetError(mpath, f"checkpoint is for a hand, got a {type(template).__name__} template")
            side = template.data.side if isinstance(template, MANOLayer) else template.side
            if f"hand_{side}" != ptype:
                raise AssetError(mpath, f"checkpoint is for part_type {ptype!r}, the given hand model is {side}")
            if isinstance(template, MANOLayer):
                for key in ("flat_hand_mean", "use_pca", "num_pca_comps", "num_betas", "fix_left_shapedirs"):
                    cfg.pop(key, None)
            part = HandGaussians(template, part_id=part_id, dtype=dtype, **cfg)
    except TypeError as exc:  # unknown / missing constructor settings
        raise AssetError(mpath, f"config cannot rebuild the part ({exc})") from exc
    except ValueError as exc:
        if isinstance(exc, AssetError):
            raise
        raise AssetError(mpath, f"config is invalid ({exc})") from exc
    load_state(part, folder)
    return part

