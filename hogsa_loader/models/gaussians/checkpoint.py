"""Checkpoints of Gaussian parts: safetensors tensors plus a JSON manifest, no pickle.

:func:`save_part` writes a part's checkpoint folder (its docstring lists the files and the
manifest keys); :func:`load_part` rebuilds a part from one, :func:`load_state` loads one into
an existing part and :func:`read_manifest` reads the manifest alone. Loading validates
everything and raises :class:`~hogsa_loader.errors.AssetError` naming the offending file and
the problem.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Mapping, Optional, Union

import torch
from torch import Tensor

from hogsa_loader.assets.hands.mano import MANOLayer
from hogsa_loader.assets.hands.mano_io import ManoModelData
from hogsa_loader.assets.objects.template import ObjectTemplate
from hogsa_loader.errors import AssetError, PathLike
from hogsa_loader.io.tensors import ManifestFormat, read_tensors, save_checkpoint
from hogsa_loader.io.tensors import read_manifest as read_checkpoint_manifest
from hogsa_loader.models.gaussians.binding import ALL_VARIANTS, BindingConfig
from hogsa_loader.models.gaussians.parts import PART_TYPES, GaussianPart, HandGaussians, ObjectGaussians

__all__ = [
    "FORMAT",
    "SCHEMA_VERSION",
    "MANIFEST_FILE",
    "TENSORS_FILE",
    "GAUSSIANS_FORMAT",
    "save_part",
    "read_manifest",
    "load_state",
    "load_part",
]

FORMAT = "hogsa-gaussians"
SCHEMA_VERSION = 1
MANIFEST_FILE = "manifest.json"
TENSORS_FILE = "gaussians.safetensors"
#: The shared checkpoint header of a Gaussian part.
GAUSSIANS_FORMAT = ManifestFormat(
    FORMAT,
    SCHEMA_VERSION,
    "a Gaussian part checkpoint",
    TENSORS_FILE,
    manifest_file=MANIFEST_FILE,
    header_metadata=True,
)

#: The part's own manifest keys and their JSON types.
_REQUIRED: dict[str, type | tuple[type, ...]] = {
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
}
_SOURCE_KEYS = ("dataset", "subject", "sequence")


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

    A checkpoint is a folder::

        <folder>/gaussians.safetensors   the part's learnable state (``part.splats.state_dict()``)
        <folder>/manifest.json           what the tensors are and what they belong to

    The manifest is the shared checkpoint header (:mod:`hogsa_loader.io.tensors`: ``format``
    ``"hogsa-gaussians"``, ``schema_version`` 1, ``library_version``, ``tensors``,
    ``tensors_file``, ``tensors_sha256``) plus these keys, every one required:

    ==================  ==================================================================
    key                 value
    ==================  ==================================================================
    part_type           ``"hand_right"``, ``"hand_left"`` or ``"object"``
    variant             ``"games"``, ``"avatars"`` or ``"free"``
    k, sh_degree        Gaussians per face, SH degree
    num_verts,          binding-mesh vertices / faces, number of Gaussians
    num_faces,
    num_gaussians
    template_hash       sha256 of the caller's template mesh (float32 vertices then int64
                        faces, little endian; :func:`~hogsa_loader.models.gaussians.parts.template_hash`)
    binding_hash        the same hash of the binding mesh the Gaussians live on
    binding_mesh        how the binding mesh was made (e.g. ``"subdivide_model levels=1"``)
    config              the part's constructor settings, flat: its
                        :class:`~hogsa_loader.models.gaussians.binding.BindingConfig` (without
                        ``init_opacity``) then its own (rebuilds it in :func:`load_part`)
    source              ``{"dataset", "subject", "sequence"}`` (strings or null)
    extra               free-form JSON object
    ==================  ==================================================================

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
    folder = Path(folder)
    tensors = {name: t.detach().cpu().contiguous() for name, t in part.splats.state_dict().items()}
    fields: dict[str, Any] = {
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
    }
    save_checkpoint(folder, GAUSSIANS_FORMAT, tensors, fields)
    return folder


# --------------------------------------------------------------------------------------
# Reading and validation
# --------------------------------------------------------------------------------------


def read_manifest(folder: PathLike) -> dict[str, Any]:
    """Read and validate ``manifest.json`` on its own (shared header, types, known values).

    Raises:
        AssetError: naming ``manifest.json`` (or the folder) and the problem.
    """
    raw = read_checkpoint_manifest(folder, GAUSSIANS_FORMAT)
    path = Path(folder) / MANIFEST_FILE
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
    return raw


def _check_template(raw: Mapping[str, Any], part: GaussianPart, path: Path) -> None:
    """The checkpoint's part type and template hash vs the part the caller built."""
    if raw["part_type"] != part.part_type:
        raise AssetError(path, f"checkpoint is for part_type {raw['part_type']!r}, the model is {part.part_type!r}")
    if raw["template_hash"] != part.template_hash:
        hint = ""
        if part.part_type.startswith("hand"):
            hint = (
                "; a hand part is bound to its hand model's vertices in their order, so a different MANO file "
                "(e.g. another version of the synthetic hand, see its 'generator' metadata) needs the part "
                "trained again"
            )
        raise AssetError(
            path,
            f"template hash mismatch: the checkpoint was made for template {raw['template_hash'][:16]}..., "
            f"the given template hashes to {part.template_hash[:16]}...{hint}",
        )


def _check_against_part(raw: Mapping[str, Any], part: GaussianPart, path: Path) -> None:
    """Manifest vs the part the caller built from its template: type, template, settings, config."""
    _check_template(raw, part, path)
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
            raise AssetError(path, f"{key} is {raw[key]!r} in the checkpoint but {val!r} in the model")
    cfg, saved = part.config(), raw["config"]
    for key in sorted(set(cfg) | set(saved)):
        if saved.get(key) != cfg.get(key):
            if key not in saved:
                raise AssetError(
                    path, f"config.{key} is missing from the checkpoint (a pre-1.0 checkpoint: train the part again)"
                )
            raise AssetError(
                path, f"config.{key} is {saved.get(key)!r} in the checkpoint but {cfg.get(key)!r} in the model"
            )


def _read_tensors(folder: Path, raw: Mapping[str, Any], part: GaussianPart) -> dict[str, Tensor]:
    """Read, hash-check and validate the tensors file against the manifest and the part."""
    tpath = folder / TENSORS_FILE
    tensors = read_tensors(folder, raw, GAUSSIANS_FORMAT)  # (listed names, shapes, dtypes; finite)
    model_state = part.splats.state_dict()
    missing = sorted(set(model_state) - set(tensors))
    unexpected = sorted(set(tensors) - set(model_state))
    if missing or unexpected:
        raise AssetError(tpath, f"tensor names do not match the model: missing {missing}, unexpected {unexpected}")
    for name, t in tensors.items():
        want = model_state[name]
        if t.shape != want.shape:
            raise AssetError(tpath, f"tensor {name!r} has shape {tuple(t.shape)}, the model needs {tuple(want.shape)}")
        if t.is_floating_point() != want.is_floating_point():
            raise AssetError(tpath, f"tensor {name!r} has dtype {t.dtype}, the model needs {want.dtype}")
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
    try:
        binding, cfg = BindingConfig.from_recorded(raw["config"])
        if ptype == "object":
            if not isinstance(template, ObjectTemplate):
                raise AssetError(mpath, f"checkpoint is for an object, got a {type(template).__name__} template")
            part: GaussianPart = ObjectGaussians(template, binding, part_id=part_id, dtype=dtype, **cfg)
        else:
            if not isinstance(template, (ManoModelData, MANOLayer)):
                raise AssetError(mpath, f"checkpoint is for a hand, got a {type(template).__name__} template")
            side = template.data.side if isinstance(template, MANOLayer) else template.side
            if f"hand_{side}" != ptype:
                raise AssetError(mpath, f"checkpoint is for part_type {ptype!r}, the given hand model is {side}")
            if isinstance(template, MANOLayer):
                for key in ("flat_hand_mean", "use_pca", "num_pca_comps", "num_betas", "fix_left_shapedirs"):
                    cfg.pop(key, None)
            part = HandGaussians(template, binding, part_id=part_id, dtype=dtype, **cfg)
    except TypeError as exc:  # unknown / missing constructor settings
        raise AssetError(mpath, f"config cannot rebuild the part ({exc})") from exc
    except ValueError as exc:
        if isinstance(exc, AssetError):
            raise
        raise AssetError(mpath, f"config is invalid ({exc})") from exc
    load_state(part, folder)
    return part
