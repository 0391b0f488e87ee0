"""Checkpoints as a safetensors file plus a JSON manifest, no pickle.

Every checkpoint kind of the library (Gaussian parts, light, SRM, ContactNet, pose bank)
writes the same header into its ``manifest.json``, described by a :class:`ManifestFormat`
(its docstring lists the keys). Each kind adds its own keys and checks. Both files are written
atomically, tensors first and manifest last (:func:`save_checkpoint`,
:func:`write_tensors_and_manifest`); :func:`read_manifest` and :func:`read_tensors` validate
them and raise :class:`~hogsa_loader.errors.AssetError` naming the offending file and the problem.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal, Mapping, Optional

import torch
from safetensors.torch import load as st_load
from safetensors.torch import save as st_save
from torch import Tensor

from hogsa_loader import __version__
from hogsa_loader.errors import AssetError, PathLike, read_json
from hogsa_loader.io.atomic import atomic_write

__all__ = [
    "MANIFEST_FILE",
    "ManifestFormat",
    "canonical_safetensors",
    "dtype_name",
    "write_tensors_and_manifest",
    "read_checked_tensors",
    "save_checkpoint",
    "check_header",
    "read_manifest",
    "read_tensors",
]

MANIFEST_FILE = "manifest.json"


def dtype_name(dtype: torch.dtype) -> str:
    """``"float32"`` for ``torch.float32``."""
    return str(dtype).removeprefix("torch.")


@dataclass(frozen=True)
class ManifestFormat:
    """The shared manifest header of one checkpoint kind, with the key names it uses on disk.

    Attributes:
        name: the kind's name, stored under ``name_key`` (``"hogsa-gaussians"``).
        version: the schema version this library writes and reads.
        title: the kind in words for errors, with its article (``"an SRM checkpoint"``).
        tensors_file: the tensors file name, stored under ``file_key``; None for a
            manifest without tensors (a bundle).
        name_key: ``"format"`` or ``"schema"``.
        file_key: ``"tensors_file"``, ``"tensor_file"`` or ``"weights"``.
        specs: how ``tensors`` lists each tensor: ``"shape_dtype"`` (``{"shape", "dtype"}``),
            ``"shape"`` (the shape list) or None (not listed).
        library_version: whether the manifest records the writer's library version.
        header_metadata: whether the tensors file's own header repeats ``format`` and
            ``schema_version``.
        manifest_file: the manifest file name.

    Header keys:

    =====================  ===============================================================
    key                    value
    =====================  ===============================================================
    ``format``/``schema``  the kind's name (``"hogsa-srm"``, ``"hogsa.pose_bank"``...)
    schema_version         the kind's schema version (an int)
    library_version        ``hogsa_loader.__version__`` of the writer (kinds that record it)
    tensors                ``{name: {"shape": [...], "dtype": "float32"}}`` or ``{name: [...]}``
    tensors file key       the tensors file name (``tensors_file``, ``tensor_file`` or ``weights``)
    tensors_sha256         sha256 of the tensors file (a torn or mismatched pair is refused)
    =====================  ===============================================================
    """

    name: str
    version: int
    title: str
    tensors_file: Optional[str] = None
    name_key: str = "format"
    file_key: str = "tensors_file"
    specs: Optional[Literal["shape_dtype", "shape"]] = "shape_dtype"
    library_version: bool = True
    header_metadata: bool = False
    manifest_file: str = MANIFEST_FILE

    def head(self) -> dict[str, Any]:
        """The header keys that open a manifest: name, schema version (, library version)."""
        out: dict[str, Any] = {self.name_key: self.name, "schema_version": self.version}
        if self.library_version:
            out["library_version"] = __version__
        return out

    def tensor_entries(self, tensors: Mapping[str, Tensor]) -> dict[str, Any]:
        """The header keys that describe the tensors file: ``tensors`` (when listed), file name."""
        out: dict[str, Any] = {}
        if self.specs == "shape_dtype":
            out["tensors"] = {n: {"shape": list(t.shape), "dtype": dtype_name(t.dtype)} for n, t in tensors.items()}
        elif self.specs == "shape":
            out["tensors"] = {n: list(t.shape) for n, t in tensors.items()}
        out[self.file_key] = self.tensors_file
        return out


# --------------------------------------------------------------------------------------
# Writing
# --------------------------------------------------------------------------------------


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


def write_tensors_and_manifest(
    folder: Path,
    tensors_file: str,
    tensors: Mapping[str, Tensor],
    manifest_file: str,
    manifest: Mapping[str, Any],
    indent: Optional[int] = 1,
    metadata: Optional[Mapping[str, str]] = None,
    allow_nan: bool = False,
) -> Path:
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
    folder = Path(folder)
    bad = [k for k, v in tensors.items() if v.is_floating_point() and not bool(torch.isfinite(v).all())]
    if bad:
        raise ValueError(f"{folder / tensors_file}: tensors {bad[:3]} contain NaN or infinity; not saved")
    blob = canonical_safetensors(st_save(dict(tensors), metadata=dict(metadata) if metadata else None))
    try:
        text = (
            json.dumps(
                {**manifest, "tensors_sha256": hashlib.sha256(blob).hexdigest()}, indent=indent, allow_nan=allow_nan
            )
            + "\n"
        )
    except ValueError as exc:
        raise ValueError(
            f"{folder / manifest_file}: the manifest would hold NaN or infinity ({exc}); not saved"
        ) from None
    folder.mkdir(parents=True, exist_ok=True)
    atomic_write(folder / tensors_file, blob)
    atomic_write(folder / manifest_file, text.encode("utf-8"))
    return folder / manifest_file


def save_checkpoint(
    folder: PathLike,
    fmt: ManifestFormat,
    tensors: Mapping[str, Tensor],
    fields: Mapping[str, Any],
    *,
    indent: Optional[int] = 1,
) -> Path:
    """Write a checkpoint of kind ``fmt``: the manifest is the shared header around the kind's
    own ``fields`` (:meth:`ManifestFormat.head`, ``fields``, :meth:`ManifestFormat.tensor_entries`,
    ``tensors_sha256``).

    Args:
        folder: output folder (created); existing files are replaced atomically.
        fmt: the checkpoint kind.
        tensors: ``{name: tensor}`` on the CPU, contiguous, no shared storage.
        fields: the kind's own manifest keys (JSON, no NaN / infinity).
        indent: manifest indentation.

    Returns:
        the manifest path.

    Raises:
        ValueError: non-finite tensors or fields; nothing is written then.
    """
    manifest = {**fmt.head(), **fields, **fmt.tensor_entries(tensors)}
    metadata = {fmt.name_key: fmt.name, "schema_version": str(fmt.version)} if fmt.header_metadata else None
    return write_tensors_and_manifest(
        Path(folder), str(fmt.tensors_file), tensors, fmt.manifest_file, manifest, indent=indent, metadata=metadata
    )


# --------------------------------------------------------------------------------------
# Reading and validation
# --------------------------------------------------------------------------------------


def _check_specs(raw: Mapping[str, Any], path: Path, fmt: ManifestFormat) -> None:
    """``tensors`` must list each tensor in the kind's spec style."""
    if not isinstance(raw.get("tensors"), dict):
        raise AssetError(path, "required key 'tensors' is missing or not a JSON object")
    for name, entry in raw["tensors"].items():
        if fmt.specs == "shape_dtype" and not (
            isinstance(entry, dict) and isinstance(entry.get("shape"), list) and isinstance(entry.get("dtype"), str)
        ):
            raise AssetError(
                path, f"tensors[{name!r}] must be an object with a 'shape' list and a 'dtype' string, got {entry!r}"
            )
        if fmt.specs == "shape" and not isinstance(entry, list):
            raise AssetError(path, f"tensors[{name!r}] must be a shape list, got {entry!r}")


def check_header(raw: Any, path: Path, fmt: ManifestFormat) -> dict[str, Any]:
    """Check the shared header of a parsed manifest (see :class:`ManifestFormat`).

    Args:
        raw: the parsed JSON.
        path: the manifest, named in errors.
        fmt: the kind it must be.

    Returns:
        ``raw``.

    Raises:
        AssetError: not a JSON object, another kind, another schema version, a header key
            missing or of the wrong type, another tensors file name.
    """
    if not isinstance(raw, dict):
        raise AssetError(path, f"expected a JSON object, got {type(raw).__name__}")
    if raw.get(fmt.name_key) != fmt.name:
        raise AssetError(path, f"not {fmt.title} ({fmt.name_key} is {raw.get(fmt.name_key)!r}, expected {fmt.name!r})")
    version = raw.get("schema_version")
    if not isinstance(version, int) or isinstance(version, bool):
        raise AssetError(path, f"schema_version must be an integer, got {version!r}")
    if version != fmt.version:
        newer = " (written by a newer hogsa-loader)" if version > fmt.version else ""
        older = "; rebuild or retrain it with this version" if version < fmt.version else ""
        raise AssetError(
            path, f"unsupported schema_version {version}{newer}; this reader supports {fmt.version}{older}"
        )
    if fmt.library_version and not isinstance(raw.get("library_version"), str):
        raise AssetError(path, "required key 'library_version' is missing or not a string")
    if fmt.tensors_file is None:
        return raw
    if raw.get(fmt.file_key) != fmt.tensors_file:
        raise AssetError(path, f"{fmt.file_key} is {raw.get(fmt.file_key)!r}, expected {fmt.tensors_file!r}")
    if fmt.specs is not None:
        _check_specs(raw, path, fmt)
    if not isinstance(raw.get("tensors_sha256"), str):
        raise AssetError(path, "required key 'tensors_sha256' is missing or not a string")
    return raw


def read_manifest(folder: PathLike, fmt: ManifestFormat) -> dict[str, Any]:
    """Read ``folder/<manifest>`` and check its shared header (:func:`check_header`).

    Raises:
        AssetError: missing folder or file, malformed JSON (NaN and infinity included), a bad
            header; naming the file and the problem.
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise AssetError(folder, f"{fmt.title.split(' ', 1)[1]} folder is missing")
    path = folder / fmt.manifest_file
    return check_header(read_json(path, allow_nan=False), path, fmt)


def read_checked_tensors(tpath: Path, manifest: Mapping[str, Any], manifest_path: Path) -> dict[str, Tensor]:
    """Read the safetensors file of a :func:`write_tensors_and_manifest` pair; its sha256 must
    equal the manifest's ``tensors_sha256``.

    Raises:
        AssetError: missing or unreadable file, no or another checksum, not safetensors (names
            the file).
    """
    tpath = Path(tpath)
    want = manifest.get("tensors_sha256")
    if not isinstance(want, str):
        raise AssetError(manifest_path, "required key 'tensors_sha256' is missing or not a string")
    if not tpath.is_file():
        raise AssetError(tpath, f"tensors file is missing (listed in {manifest_path.name})")
    try:
        blob = tpath.read_bytes()
    except OSError as exc:
        raise AssetError(tpath, f"cannot read file ({exc})") from exc
    if hashlib.sha256(blob).hexdigest() != want:
        raise AssetError(
            tpath, f"sha256 does not match {manifest_path.name} (torn write or files from different checkpoints)"
        )
    try:
        return st_load(blob)
    except Exception as exc:  # safetensors raises its own error types on corrupt headers
        raise AssetError(tpath, f"not a valid safetensors file ({exc})") from exc


def _check_listed(tensors: Mapping[str, Tensor], raw: Mapping[str, Any], tpath: Path, fmt: ManifestFormat) -> None:
    """The tensors file holds exactly the tensors the manifest lists, with their shapes (and dtypes)."""
    listed = raw["tensors"]
    missing, unexpected = sorted(set(listed) - set(tensors)), sorted(set(tensors) - set(listed))
    if missing or unexpected:
        raise AssetError(
            tpath,
            f"tensors {missing} listed in {fmt.manifest_file} are missing, tensors {unexpected} are not listed there",
        )
    for name, t in tensors.items():
        spec = listed[name]
        shape, dtype = (spec.get("shape"), spec.get("dtype")) if fmt.specs == "shape_dtype" else (spec, None)
        if list(t.shape) != shape or (dtype is not None and dtype_name(t.dtype) != dtype):
            raise AssetError(
                tpath,
                f"tensor {name!r} has shape {tuple(t.shape)} {dtype_name(t.dtype)}, {fmt.manifest_file} says {spec}",
            )


def read_tensors(
    folder: PathLike, raw: Mapping[str, Any], fmt: ManifestFormat, *, finite: bool = True
) -> dict[str, Tensor]:
    """Read the tensors file of a checkpoint whose manifest ``raw`` passed :func:`read_manifest`.

    Args:
        folder: the checkpoint folder.
        raw: its manifest.
        fmt: its kind.
        finite: refuse NaN or infinite values in floating tensors.

    Returns:
        ``{name: tensor}`` on the CPU.

    Raises:
        AssetError: missing file, checksum mismatch, not safetensors, tensors other than the
            listed ones, NaN or infinite values (naming the tensors file).
    """
    folder = Path(folder)
    tpath = folder / str(fmt.tensors_file)
    tensors = read_checked_tensors(tpath, raw, folder / fmt.manifest_file)
    if fmt.specs is not None:
        _check_listed(tensors, raw, tpath, fmt)
    for name, t in tensors.items():
        if finite and t.is_floating_point() and not bool(torch.isfinite(t).all()):
            bad = int((~torch.isfinite(t)).sum())
            raise AssetError(tpath, f"tensor {name!r} contains {bad} NaN or infinite values")
    return tensors
