"""Bundles: everything the synthetic loader needs, in one validated folder.

:func:`write_bundle` (used by ``hogsa_loader/cli/build_bundle.py``) writes a bundle; :func:`load_bundle`
validates one and returns a :class:`Bundle`, which
:class:`~hogsa_loader.sample.dataset.HOGSADataset` reads. :class:`Bundle` describes the folder
layout and the ``manifest.json`` keys. :func:`load_bundle` checks every entry and raises **one**
:class:`~hogsa_loader.errors.AssetError` listing every problem it found.
"""

from __future__ import annotations

import json
import os
import shutil
import tempfile
from dataclasses import dataclass, field
from pathlib import Path, PurePosixPath
from typing import Any, Mapping, Optional, Sequence, Union

from hogsa_loader.assets.arctic import ArcticRoot
from hogsa_loader.assets.h2o_io import H2O_CROP_SIZE
from hogsa_loader.assets.h2o_poses import H2OPoseRoot
from hogsa_loader.errors import AssetError, PathLike, read_json
from hogsa_loader.io.atomic import atomic_write_json
from hogsa_loader.io.hashing import sha256_file
from hogsa_loader.io.locks import writer_lock
from hogsa_loader.io.tensors import ManifestFormat, check_header
from hogsa_loader.models.gaussians.checkpoint import MANIFEST_FILE, TENSORS_FILE, read_manifest
from hogsa_loader.models.gaussians.hogs_model import LIGHT_DIR, HogsModel
from hogsa_loader.models.gaussians.parts import template_hash
from hogsa_loader.models.gaussians.shading import LIGHT_MANIFEST, LIGHT_TENSORS
from hogsa_loader.models.pom.bank import load_pose_bank
from hogsa_loader.models.pom.contactnet import load_contactnet
from hogsa_loader.models.srm.io import read_srm_manifest

__all__ = [
    "BUNDLE_FORMAT",
    "BUNDLE_SCHEMA_VERSION",
    "MANIFEST_NAME",
    "Bundle",
    "HogsEntry",
    "ExtraEntry",
    "write_bundle",
    "load_bundle",
    "bundle_dataset",
]

BUNDLE_FORMAT = "hogsa-bundle"
BUNDLE_SCHEMA_VERSION = 2
MANIFEST_NAME = "manifest.json"
_PARTS = ("hand_right", "hand_left", "object")
#: The shared manifest header of a bundle (no tensors file of its own).
BUNDLE_HEADER = ManifestFormat(BUNDLE_FORMAT, BUNDLE_SCHEMA_VERSION, "a bundle", manifest_file=MANIFEST_NAME)
#: A data root as the bundle functions take it: an ARCTIC(-format) root folder, an opened
#: :class:`ArcticRoot`, or an H2O root with its MANO and mesh folders (:class:`H2OPoseRoot`).
DataRoot = Union[PathLike, ArcticRoot, H2OPoseRoot]
#: ``{"tensors": file name, "manifest": file name}`` of a run's light folder (``LIGHT_DIR``).
_LIGHT_FILES = {"tensors": LIGHT_TENSORS, "manifest": LIGHT_MANIFEST}


# --------------------------------------------------------------------------------------
# Records
# --------------------------------------------------------------------------------------


@dataclass(frozen=True)
class HogsEntry:
    """One HOGS run of a bundle.

    Attributes:
        subject: subject id (``"s01"``).
        object: object name (``"box"``).
        path: absolute path of the run folder inside the bundle.
        num_gaussians: total Gaussians of the three parts.
        parts: ``{part: {"template_hash", "tensors_sha256", "manifest_sha256"}}``.
        light: ``{"tensors_sha256", "manifest_sha256"}`` of the run's learned light, or None.
    """

    subject: str
    object: str
    path: Path
    num_gaussians: int
    parts: Mapping[str, Mapping[str, str]]
    light: Optional[Mapping[str, str]] = None

    @property
    def key(self) -> tuple[str, str]:
        """``(subject, object)``."""
        return (self.subject, self.object)


@dataclass(frozen=True)
class ExtraEntry:
    """An optional checkpoint / pose bank: its absolute path and file hashes."""

    name: str
    path: Path
    files: Mapping[str, str]


@dataclass
class Bundle:
    """A validated bundle; build it with :func:`load_bundle`.

    Attributes:
        path: bundle folder.
        manifest: the parsed ``manifest.json``.
        hogs: ``{(subject, object): HogsEntry}``.
        srm, contactnet: optional checkpoint folders.
        pose_banks: ``{name: ExtraEntry}``.

    The bundle folder (what :class:`~hogsa_loader.sample.dataset.HOGSADataset` reads)::

        BUNDLE/
          manifest.json
          hogs/<subject>_<object>/{hand_right,hand_left,object}/   one HOGS run per (subject, object)
          hogs/<subject>_<object>/light/   the run's learned light, when it was trained with one
          srm/<name>/               optional SRM checkpoint folder (save_srm / a train_srm.py run)
          contactnet/<name>/        optional ContactNet checkpoint folder
          pose_banks/<name>/        optional pose-bank folders

    Of a folder, only its top-level files are copied (manifest, tensors, metrics): a training
    run's ``checkpoints/`` history and caches stay behind.

    ``manifest.json`` (the shared header of :mod:`hogsa_loader.io.tensors`, without tensors):

    ================  =========================================================================
    key               value
    ================  =========================================================================
    format            ``"hogsa-bundle"``
    schema_version    2
    library_version   ``hogsa_loader.__version__`` of the writer
    dataset           ``{"name": "arctic" | "h2o", "root": str, "subjects": [...],
                      "cropped_size": int}``, H2O also ``"mano_dir"`` and ``"object_mesh_dir"``
                      (the folders are informational: the loader takes the data root as an
                      argument)
    hand_model        ``{"source": str, "right": {"template_hash", "num_verts"},
                      "left": {...}}`` — the MANO(-schema) models the hands were trained on
    objects           ``{name: {"template_hash", "num_verts"}}`` — the object templates used
    hogs              list of ``{"subject", "object", "path", "num_gaussians",
                      "parts": {part: {"template_hash", "tensors_sha256", "manifest_sha256"}},
                      "light": null | {"tensors_sha256", "manifest_sha256"}}``
    srm, contactnet   ``null`` or ``{"path", "files": {relative path: sha256}}``
    pose_banks        list of ``{"name", "path", "files": {relative path: sha256}}`` (unique names)
    ================  =========================================================================
    """

    path: Path
    manifest: dict[str, Any]
    hogs: dict[tuple[str, str], HogsEntry]
    srm: Optional[ExtraEntry] = None
    contactnet: Optional[ExtraEntry] = None
    pose_banks: dict[str, ExtraEntry] = field(default_factory=dict)

    @property
    def dataset(self) -> str:
        """The dataset the bundle was built on (``"arctic"`` or ``"h2o"``)."""
        return str(self.manifest["dataset"].get("name", "arctic"))

    @property
    def keys(self) -> list[tuple[str, str]]:
        """Sorted ``(subject, object)`` pairs that have a HOGS run."""
        return sorted(self.hogs)

    def load_hogs(
        self,
        key: tuple[str, str],
        mano_layers: Mapping[str, Any],
        object_templates: Mapping[str, Any],
        device: Any = None,
    ) -> Any:
        """Load the :class:`~hogsa_loader.models.gaussians.hogs_model.HogsModel` of ``key``.

        Args:
            key: ``(subject, object)``.
            mano_layers: ``{"right", "left"}`` MANO layers of the data root.
            object_templates: ``{name: ObjectTemplate}`` of the data root.
            device: where to put the parameters.
        """
        if key not in self.hogs:
            raise KeyError(f"bundle {self.path} has no HOGS run for {key}; it has {self.keys}")
        return HogsModel.from_run(self.hogs[key].path, mano_layers, object_templates, device=device).eval()

    def check_data_root(self, data_root: DataRoot) -> None:
        """Raise one :class:`AssetError` if ``data_root``'s hand model or object templates
        differ from the ones the bundle was built with."""
        problems = _check_root(self.manifest, data_root)
        if problems:
            raise _bundle_error(self.path, problems)


# --------------------------------------------------------------------------------------
# Hashing helpers
# --------------------------------------------------------------------------------------


def _hash_tree(path: Path) -> dict[str, str]:
    """``{relative posix path: sha256}`` of a file or of every file under a folder."""
    if path.is_file():
        return {path.name: sha256_file(path)}
    out = {}
    for p in sorted(path.rglob("*")):
        if p.is_file():
            out[p.relative_to(path).as_posix()] = sha256_file(p)
    return out


def _hand_hashes(mano_layers: Mapping[str, Any]) -> dict[str, dict[str, Any]]:
    out = {}
    for side in ("right", "left"):
        data = mano_layers[side].data
        out[side] = {
            "template_hash": template_hash(data.v_template, data.faces),
            "num_verts": int(len(data.v_template)),
        }
    return out


def _object_hashes(templates: Mapping[str, Any]) -> dict[str, dict[str, Any]]:
    return {
        name: {"template_hash": template_hash(t.verts, t.faces), "num_verts": int(len(t.verts))}
        for name, t in sorted(templates.items())
    }


def _bundle_error(path: Path, problems: Sequence[str]) -> AssetError:
    lines = "\n".join(f"  - {p}" for p in problems)
    n = len(problems)
    return AssetError(path, f"invalid bundle ({n} problem{'s' if n != 1 else ''}):\n{lines}")


def _opened(data_root: DataRoot) -> Union[ArcticRoot, H2OPoseRoot]:
    """``data_root`` opened: a folder as an :class:`ArcticRoot`; an opened root as it is."""
    return data_root if isinstance(data_root, (ArcticRoot, H2OPoseRoot)) else ArcticRoot(data_root)


def _dataset_of(root: Union[ArcticRoot, H2OPoseRoot]) -> str:
    return "h2o" if isinstance(root, H2OPoseRoot) else "arctic"


def _objects_dir(root: Union[ArcticRoot, H2OPoseRoot]) -> Path:
    return root.object_mesh_dir if isinstance(root, H2OPoseRoot) else root.meta_dir


def _check_root(manifest: Mapping[str, Any], data_root: DataRoot) -> list[str]:
    """Problems of ``data_root`` against the manifest's dataset, hand model and object hashes."""
    problems: list[str] = []
    built_on = manifest.get("dataset", {}).get("name", "arctic")
    if built_on == "h2o" and not isinstance(data_root, H2OPoseRoot):
        return [
            f"the bundle was built on h2o: check it against H2OPoseRoot(root, mano_dir, object_mesh_dir), "
            f"not {data_root}"
        ]
    try:
        root = _opened(data_root)
        if built_on != _dataset_of(root):
            return [f"the bundle was built on {built_on}, the data root {root.data_root} is {_dataset_of(root)}"]
        hands = _hand_hashes(root.mano_layers())
        templates = root.object_templates(load_texture=False)
        objects = _object_hashes({n: templates[n] for n in manifest.get("objects", {}) if n in templates})
    except AssetError as exc:
        return [f"data root {data_root}: {exc}"]
    for side in ("right", "left"):
        want = manifest.get("hand_model", {}).get(side, {}).get("template_hash")
        if want != hands[side]["template_hash"]:
            problems.append(
                f"hand model ({side}) of the data root {root.mano_dir} hashes to "
                f"{hands[side]['template_hash'][:16]}..., "
                f"the bundle was built with {str(want)[:16]}..."
            )
    for name, rec in manifest.get("objects", {}).items():
        if name not in objects:
            problems.append(
                f"object template {name!r} used by the bundle is missing from the data root {_objects_dir(root)}"
            )
        elif objects[name]["template_hash"] != rec.get("template_hash"):
            problems.append(
                f"object template {name!r} of the data root hashes to {objects[name]['template_hash'][:16]}..., "
                f"the bundle was built with {str(rec.get('template_hash'))[:16]}..."
            )
    return problems


# --------------------------------------------------------------------------------------
# Writing
# --------------------------------------------------------------------------------------


def _copy(src: Path, dst: Path) -> None:
    """Copy a file, or the *top-level files* of a folder: a checkpoint folder keeps its
    manifest and tensors there, while a run folder's sub-folders (``checkpoints/`` history,
    render caches) are not part of the checkpoint and stay behind. Copying a path onto
    itself (rebuilding a bundle from its own contents) leaves it as it is."""
    if dst.exists() and os.path.samefile(src, dst):
        return
    if dst.exists():
        shutil.rmtree(dst) if dst.is_dir() else dst.unlink()
    dst.parent.mkdir(parents=True, exist_ok=True)
    if src.is_dir():
        dst.mkdir()
        for f in sorted(src.iterdir()):
            if f.is_file():
                shutil.copy2(f, dst / f.name)
    else:
        shutil.copy2(src, dst)


def _checkpoint_problems(srm: Optional[Path], contactnet: Optional[Path], banks: Sequence[Path]) -> list[str]:
    """Read the SRM, ContactNet and pose banks as checkpoints; their problems, if any."""
    checks = [("SRM checkpoint", srm, read_srm_manifest), ("ContactNet checkpoint", contactnet, load_contactnet)]
    checks += [("pose bank", b, load_pose_bank) for b in banks]
    problems = []
    for what, path, read in checks:
        if path is None:
            continue
        if not path.is_dir():
            problems.append(f"{what} {path} must be a checkpoint folder")
            continue
        try:
            read(path)
        except AssetError as exc:
            problems.append(f"{what}: {exc}")
    return problems


def _check_extras(srm: Optional[PathLike], contactnet: Optional[PathLike], pose_banks: Sequence[PathLike]) -> list[str]:
    """Problems of the optional checkpoints given to :func:`write_bundle` (before copying)."""
    problems = []
    for what, p in [("SRM checkpoint", srm), ("ContactNet checkpoint", contactnet)] + [
        ("pose bank", b) for b in pose_banks
    ]:
        if p is not None and not Path(p).exists():
            problems.append(f"{what} {p} is missing")
    if problems:
        return problems
    names = [Path(b).name for b in pose_banks]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        problems.append(
            f"pose banks must have distinct folder names (they are copied to pose_banks/<name>): {dup} repeated"
        )
    return problems + _checkpoint_problems(
        Path(srm) if srm else None, Path(contactnet) if contactnet else None, [Path(b) for b in pose_banks]
    )


def _extra(src: Optional[PathLike], out: Path, rel: str, what: str) -> Optional[dict[str, Any]]:
    if src is None:
        return None
    src = Path(src)
    if not src.exists():
        raise AssetError(src, f"{what} is missing")
    rel = f"{rel}/{src.name}"
    dst = out / rel
    _copy(src, dst)
    return {"path": rel, "files": _hash_tree(dst)}


def _collect_runs(
    hogs_runs: Sequence[PathLike], layers: Mapping[str, Any], templates: Mapping[str, Any]
) -> tuple[list[tuple[str, str, Path, int]], list[str]]:
    """Load every HOGS run against the data root's models: ``[(subject, object, run, num_gaussians)]``
    and the problems found (unfinished or mismatched runs, two runs of one (subject, object))."""
    problems: list[str] = []
    runs: list[tuple[str, str, Path, int]] = []
    for run in map(Path, hogs_runs):
        try:
            model = HogsModel.from_run(run, layers, templates)
        except AssetError as exc:
            problems.append(f"HOGS run {run}: {exc}")
            continue
        subject = read_manifest(run / "object").get("source", {}).get("subject")
        if not subject:
            problems.append(f"HOGS run {run}: its object manifest records no subject")
            continue
        runs.append((str(subject), str(model.object_name), run, int(model.num_gaussians)))
    seen: dict[tuple[str, str], Path] = {}
    for sid, obj, run, _ in runs:
        if (sid, obj) in seen:
            problems.append(f"two HOGS runs for ({sid}, {obj}): {seen[(sid, obj)]} and {run}")
        seen[(sid, obj)] = run
    if not runs and not problems:
        problems.append("no HOGS run given")
    return runs, problems


def _copy_run(run: Path, out: Path, rel: str) -> tuple[dict[str, dict[str, str]], Optional[dict[str, str]]]:
    """Copy a HOGS run's part checkpoints (and its light) to ``out / rel``: their hashes
    ``{part: {"template_hash", "tensors_sha256", "manifest_sha256"}}`` and the light's (or None)."""
    parts = {}
    for part in _PARTS:
        _copy(run / part, out / rel / part)
        man = json.loads((out / rel / part / MANIFEST_FILE).read_text(encoding="utf-8"))
        parts[part] = {
            "template_hash": man["template_hash"],
            "tensors_sha256": sha256_file(out / rel / part / TENSORS_FILE),
            "manifest_sha256": sha256_file(out / rel / part / MANIFEST_FILE),
        }
    light = None
    if (run / LIGHT_DIR).is_dir():  # the learned light the run's colours were fitted under
        _copy(run / LIGHT_DIR, out / rel / LIGHT_DIR)
        light = {f"{k}_sha256": sha256_file(out / rel / LIGHT_DIR / f) for k, f in _LIGHT_FILES.items()}
    elif (out / rel / LIGHT_DIR).exists():
        shutil.rmtree(out / rel / LIGHT_DIR)
    return parts, light


def write_bundle(
    out: PathLike,
    data_root: DataRoot,
    hogs_runs: Sequence[PathLike],
    *,
    srm: Optional[PathLike] = None,
    contactnet: Optional[PathLike] = None,
    pose_banks: Sequence[PathLike] = (),
) -> Path:
    """Write a bundle folder (layout: :class:`Bundle`) and return its path.

    Every HOGS run is validated against the data root's hand model and object templates
    before anything is copied (its ``(subject, object)`` comes from the object part's
    manifest ``source``); the runs and optional checkpoints are **copied** into the bundle
    so it is self-contained. The bundle is written beside ``out`` and renamed into place when
    whole: an existing bundle at ``out`` is replaced only then (a killed write leaves the old
    one), and one process at a time writes it (a lock beside it).

    Args:
        out: bundle folder (created).
        data_root: the data root the runs were trained on: an ARCTIC(-format) root (a folder
            or an :class:`ArcticRoot`), or an :class:`H2OPoseRoot` (H2O with its MANO and
            mesh folders). The manifest records which.
        hogs_runs: run folders of ``hogsa train hogs`` (each with ``hand_right/``,
            ``hand_left/``, ``object/``).
        srm: optional SRM checkpoint folder.
        contactnet: optional ContactNet checkpoint folder.
        pose_banks: optional pose banks (folders of :func:`~hogsa_loader.models.pom.bank.save_pose_bank`);
            named by their folder name, which must be unique.

    Raises:
        AssetError: a run is not finished, does not match the data root, or two runs have
            the same (subject, object); the SRM, ContactNet or a pose bank is not a readable
            checkpoint; two pose banks have the same name. All problems are listed in one error.
    """
    out = Path(out)
    root = _opened(data_root)
    layers = root.mano_layers()
    templates = root.object_templates()
    runs, problems = _collect_runs(hogs_runs, layers, templates)
    problems += _check_extras(srm, contactnet, pose_banks)
    if problems:
        raise _bundle_error(out, problems)

    given, out = Path(out), Path(os.path.abspath(out))
    out.parent.mkdir(parents=True, exist_ok=True)
    with writer_lock(out.parent, f".{out.name}.bundle.lock", what=f"the writer of bundle {out}"):
        _restore_or_clean(out)
        stage = Path(tempfile.mkdtemp(prefix=f".{out.name}.partial-", dir=out.parent))
        try:
            os.chmod(stage, 0o777 & ~_umask())
            _write_bundle_files(stage, root, runs, layers, templates, srm, contactnet, pose_banks)
            _replace_folder(stage, out)
        except BaseException:
            shutil.rmtree(stage, ignore_errors=True)
            raise
    return given


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def _restore_or_clean(out: Path) -> None:
    """Leftovers of a killed write next to ``out`` (the caller holds the bundle's lock, so no
    one is writing them): an old bundle moved aside is put back when ``out`` is missing, and
    partial and old folders are removed."""
    old = sorted(out.parent.glob(f".{out.name}.old-*"))
    if old and not out.exists():
        os.rename(old.pop(), out)
    for leftover in old + sorted(out.parent.glob(f".{out.name}.partial-*")):
        shutil.rmtree(leftover, ignore_errors=True)


def _replace_folder(new: Path, out: Path) -> None:
    """``new`` renamed to ``out``; a folder at ``out`` is moved aside first and removed after,
    so ``out`` holds either the old or the new bundle, whole."""
    if not out.exists():
        os.rename(new, out)
        return
    aside = out.parent / f".{out.name}.old-{new.name.rsplit('-', 1)[-1]}"
    os.rename(out, aside)
    os.rename(new, out)
    shutil.rmtree(aside, ignore_errors=True)


def _dataset_record(root: Union[ArcticRoot, H2OPoseRoot], subjects: list[str]) -> dict[str, Any]:
    """The manifest's ``dataset`` entry."""
    if isinstance(root, H2OPoseRoot):
        return {
            "name": "h2o",
            "root": str(root.data_root),
            "subjects": subjects,
            "cropped_size": H2O_CROP_SIZE,
            "mano_dir": str(root.mano_dir),
            "object_mesh_dir": str(root.object_mesh_dir),
        }
    return {
        "name": "arctic",
        "root": str(root.data_root),
        "subjects": subjects,
        "cropped_size": int(root.world_meta().cropped_size),
    }


def _write_bundle_files(
    out: Path,
    root: Union[ArcticRoot, H2OPoseRoot],
    runs: list,
    layers: Any,
    templates: Any,
    srm: Optional[PathLike],
    contactnet: Optional[PathLike],
    pose_banks: Sequence[PathLike],
) -> None:
    """Copy the checkpoints into the empty folder ``out`` and write its manifest (last)."""
    hogs = []
    for sid, obj, run, n in sorted(runs):
        rel = f"hogs/{sid}_{obj}"
        parts, light = _copy_run(run, out, rel)
        hogs.append({"subject": sid, "object": obj, "path": rel, "num_gaussians": n, "parts": parts, "light": light})
    objects = _object_hashes({name: templates[name] for name in sorted({obj for _, obj, _, _ in runs})})
    manifest = {
        **BUNDLE_HEADER.head(),
        "dataset": _dataset_record(root, sorted({sid for sid, _, _, _ in runs})),
        "hand_model": {"source": str(root.mano_dir), **_hand_hashes(layers)},
        "objects": objects,
        "hogs": hogs,
        "srm": _extra(srm, out, "srm", "SRM checkpoint"),
        "contactnet": _extra(contactnet, out, "contactnet", "ContactNet checkpoint"),
        "pose_banks": [
            {"name": Path(b).name, **_extra(b, out, "pose_banks", "pose bank")}  # type: ignore[dict-item]
            for b in pose_banks
        ],
    }
    atomic_write_json(out / MANIFEST_NAME, manifest, indent=1)


# --------------------------------------------------------------------------------------
# Reading
# --------------------------------------------------------------------------------------


def _inside(base: Path, rel: Any) -> Optional[Path]:
    """``base / rel`` when ``rel`` is a relative POSIX path that stays inside ``base`` (no
    ``..`` part, not absolute, no symbolic link leading out), else None."""
    if not isinstance(rel, str) or not rel or "\\" in rel or "\0" in rel:
        return None
    pure = PurePosixPath(rel)
    if pure.is_absolute() or ".." in pure.parts:
        return None
    path = base / rel
    try:
        if not path.resolve().is_relative_to(base.resolve()):
            return None
    except (OSError, RuntimeError):  # unreadable, or a symbolic-link loop
        return None
    return path


def _check_files(base: Path, what: str, rec: Any, problems: list[str]) -> Optional[ExtraEntry]:
    if not isinstance(rec, dict) or not isinstance(rec.get("path"), str) or not isinstance(rec.get("files"), dict):
        problems.append(f"{what}: entry must be an object with 'path' and 'files'")
        return None
    path = _inside(base, rec["path"])
    if path is None:
        problems.append(f"{what}: path {rec['path']!r} is not a relative path inside the bundle")
        return None
    if not path.exists():
        problems.append(f"{what}: {path} is missing")
        return None
    folder = path if path.is_dir() else path.parent
    for rel, sha in rec["files"].items():
        f = _inside(folder, rel)
        if f is None or not f.resolve().is_relative_to(base.resolve()):
            problems.append(f"{what}: file {rel!r} is not a relative path inside the bundle")
        elif not f.is_file():
            problems.append(f"{what}: file {f} is missing")
        elif sha256_file(f) != sha:
            problems.append(f"{what}: file {f} does not match its sha256 in the manifest")
    return ExtraEntry(name=str(rec.get("name", what)), path=path, files=dict(rec["files"]))


def bundle_dataset(path: PathLike) -> str:
    """The dataset a bundle was built on (``manifest.json``'s ``dataset.name``).

    Raises:
        AssetError: the manifest is missing or malformed.
    """
    return str(_read_bundle_manifest(Path(path))["dataset"].get("name", "arctic"))


def _read_bundle_manifest(path: Path) -> dict[str, Any]:
    """Read ``manifest.json``: shared header, top-level keys of the right JSON types.

    Raises:
        AssetError: the bundle error listing the problems found.
    """
    mpath = path / MANIFEST_NAME
    if not path.is_dir():
        raise _bundle_error(path, ["bundle folder is missing"])
    if not mpath.is_file():
        raise _bundle_error(path, [f"{MANIFEST_NAME} is missing"])
    try:
        manifest = read_json(mpath, allow_nan=False)  # (its writer never emits NaN / Infinity)
    except AssetError as exc:
        raise _bundle_error(path, [f"{MANIFEST_NAME}: {exc.problem}"]) from None
    if not isinstance(manifest, dict):
        raise _bundle_error(path, [f"{MANIFEST_NAME} must hold a JSON object"])
    problems: list[str] = []
    try:
        check_header(manifest, mpath, BUNDLE_HEADER)
    except AssetError as exc:
        problems.append(exc.problem)
    for key, typ in (("dataset", dict), ("hand_model", dict), ("objects", dict), ("hogs", list), ("pose_banks", list)):
        if not isinstance(manifest.get(key), typ):
            problems.append(f"key {key!r} is missing or not a JSON {typ.__name__}")
    if not problems:
        bad = [f"hand_model.{s}" for s in ("right", "left") if not isinstance(manifest["hand_model"].get(s, {}), dict)]
        bad += [f"objects.{k}" for k, v in manifest["objects"].items() if not isinstance(v, dict)]
        if bad:
            problems.append(f"entries {bad[:3]} must be JSON objects")
    if problems:
        raise _bundle_error(path, problems)
    return manifest


def _check_part(
    what: str,
    folder: Path,
    want_hash: Any,
    rec_part: Any,
    verify_hashes: bool,
    problems: list[str],
    unlisted: Optional[str] = None,
) -> bool:
    """One part checkpoint of a HOGS run: readable, made for ``want_hash`` (``unlisted``: the
    problem to report instead, when the bundle lists no template for it), files equal to the
    recorded hashes. Appends problems; False when the checkpoint is missing or unreadable."""
    if not (folder / MANIFEST_FILE).is_file():
        problems.append(f"{what}: part checkpoint {folder} is missing")
        return False
    try:
        man = read_manifest(folder)
    except AssetError as exc:
        problems.append(f"{what}: {exc}")
        return False
    if unlisted is not None:
        problems.append(unlisted)
    elif man["template_hash"] != want_hash:
        problems.append(
            f"{what}: part {folder.name} was trained on template {man['template_hash'][:16]}..., "
            f"the bundle records {str(want_hash)[:16]}..."
        )
    if not isinstance(rec_part, dict) or not rec_part:
        problems.append(f"{what}: no hashes recorded for part {folder.name}")
    elif verify_hashes:
        for fname, hkey in ((TENSORS_FILE, "tensors_sha256"), (MANIFEST_FILE, "manifest_sha256")):
            f = folder / fname
            if not f.is_file():
                problems.append(f"{what}: {f} is missing")
            elif sha256_file(f) != rec_part.get(hkey):
                problems.append(f"{what}: {f} does not match its sha256 in the bundle manifest")
    return True


def _check_light(what: str, run: Path, rec: Mapping[str, Any], verify_hashes: bool, problems: list[str]) -> bool:
    """A HOGS run's light entry: null with no light folder, or hashes of its files. Appends
    problems; False when the entry or a light file is missing."""
    light = rec.get("light")
    if "light" not in rec or not (light is None or isinstance(light, dict)):
        problems.append(f"{what}: 'light' must be null or an object of hashes")
        return False
    if light is None:
        if (run / LIGHT_DIR).exists():
            problems.append(f"{what}: {run / LIGHT_DIR} is not listed in the bundle manifest")
        return True
    ok = True
    for k, fname in _LIGHT_FILES.items():
        f = run / LIGHT_DIR / fname
        if not f.is_file():
            problems.append(f"{what}: {f} is missing")
            ok = False
        elif verify_hashes and sha256_file(f) != light.get(f"{k}_sha256"):
            problems.append(f"{what}: {f} does not match its sha256 in the bundle manifest")
    return ok


def _escaping_files(path: Path, rel: str, run: Path) -> list[str]:
    """Checkpoint files of a HOGS run that lead out of the bundle (e.g. a part folder that is a
    symbolic link)."""
    files = [(p, (MANIFEST_FILE, TENSORS_FILE)) for p in _PARTS] + [(LIGHT_DIR, tuple(_LIGHT_FILES.values()))]
    return [
        f"{rel}/{sub}/{f}"
        for sub, names in files
        for f in names
        if (run / sub / f).exists() and _inside(path, f"{rel}/{sub}/{f}") is None
    ]


def _check_hogs_entry(
    path: Path,
    manifest: Mapping[str, Any],
    i: int,
    rec: Any,
    seen: Mapping[tuple[str, str], Any],
    verify_hashes: bool,
    problems: list[str],
) -> Optional[HogsEntry]:
    """``manifest["hogs"][i]``: its record, part checkpoints and light. Appends problems; the
    entry, or None when it is unusable."""
    if not isinstance(rec, dict) or not all(isinstance(rec.get(k), str) for k in ("subject", "object", "path")):
        problems.append(f"hogs[{i}]: entry needs string 'subject', 'object' and 'path'")
        return None
    key = (rec["subject"], rec["object"])
    what = f"HOGS run {key[0]}/{key[1]}"
    if key in seen:
        problems.append(f"{what}: listed twice")
    run = _inside(path, rec["path"])
    if run is None:
        problems.append(f"{what}: path {rec['path']!r} is not a relative path inside the bundle")
        return None
    n_gauss = rec.get("num_gaussians", 0)
    if not isinstance(n_gauss, int) or isinstance(n_gauss, bool) or n_gauss < 0:
        problems.append(f"{what}: num_gaussians must be a non-negative integer, got {n_gauss!r}")
        return None
    escaping = _escaping_files(path, rec["path"], run)
    if escaping:
        problems.append(f"{what}: {escaping[0]} leads out of the bundle")
        return None
    parts = rec.get("parts") if isinstance(rec.get("parts"), dict) else {}
    hand_hash = {s: manifest["hand_model"].get(s, {}).get("template_hash") for s in ("right", "left")}
    ok = True
    for part in _PARTS:
        unlisted = None
        if part != "object":
            want = hand_hash["right" if part == "hand_right" else "left"]
        elif key[1] in manifest["objects"]:
            want = manifest["objects"][key[1]].get("template_hash")
        else:
            want, unlisted = None, f"{what}: object {key[1]!r} is not listed under 'objects'"
        ok &= _check_part(what, run / part, want, parts.get(part, {}), verify_hashes, problems, unlisted)
    ok &= _check_light(what, run, rec, verify_hashes, problems)
    if not ok:
        return None
    light = rec.get("light")
    return HogsEntry(
        subject=key[0],
        object=key[1],
        path=run,
        num_gaussians=n_gauss,
        parts={p: dict(v) for p, v in parts.items() if isinstance(v, dict)},
        light=dict(light) if isinstance(light, dict) else None,
    )


def _check_extra_entries(
    path: Path, manifest: Mapping[str, Any], problems: list[str]
) -> tuple[Optional[ExtraEntry], Optional[ExtraEntry], dict[str, ExtraEntry]]:
    """The SRM, ContactNet and pose-bank entries: files present with their recorded hashes.
    Appends problems; ``(srm, contactnet, {name: pose bank})``."""
    srm = contactnet = None
    if manifest.get("srm") is not None:
        srm = _check_files(path, "SRM checkpoint", manifest["srm"], problems)
    if manifest.get("contactnet") is not None:
        contactnet = _check_files(path, "ContactNet checkpoint", manifest["contactnet"], problems)
    banks: dict[str, ExtraEntry] = {}
    for i, rec in enumerate(manifest["pose_banks"]):
        e = _check_files(path, f"pose bank {i}", rec, problems)
        if e is not None and e.name in banks:
            problems.append(f"pose bank {i}: the name {e.name!r} is used twice")
        elif e is not None:
            banks[e.name] = e
    return srm, contactnet, banks


def load_bundle(path: PathLike, data_root: Optional[DataRoot] = None, *, verify_hashes: bool = True) -> Bundle:
    """Read and validate a bundle.

    Checks: ``manifest.json`` present, valid JSON, format and schema version; every HOGS
    run listed with its three part folders, each part's checkpoint manifest readable,
    its template hash equal to the bundle's hand model / object template, its tensors and
    manifest files (and its light's, when it has one) equal to the recorded sha256
    (``verify_hashes``); optional SRM, ContactNet and pose-bank files present with matching
    sha256 and readable as checkpoints; with ``data_root``, the data root's hand model and
    object templates equal the recorded ones. Every path in the manifest must be relative and
    stay inside the bundle (no ``..``, no absolute path, no symbolic link leading out).

    Args:
        path: bundle folder.
        data_root: optional data root to check against (as :func:`write_bundle` takes it;
            it must be of the dataset the bundle was built on).
        verify_hashes: hash every file (set False to skip the sha256 of large files).

    Returns:
        the :class:`Bundle`.

    Raises:
        AssetError: naming the bundle and listing **every** problem found.
    """
    path = Path(path)
    manifest = _read_bundle_manifest(path)
    problems: list[str] = []
    hogs: dict[tuple[str, str], HogsEntry] = {}
    if not manifest["hogs"]:
        problems.append("the bundle lists no HOGS run")
    for i, rec in enumerate(manifest["hogs"]):
        entry = _check_hogs_entry(path, manifest, i, rec, hogs, verify_hashes, problems)
        if entry is not None:
            hogs[entry.key] = entry
    srm, contactnet, banks = _check_extra_entries(path, manifest, problems)
    if not problems:  # files present and unchanged: read them as checkpoints
        problems += _checkpoint_problems(
            srm.path if srm else None, contactnet.path if contactnet else None, [b.path for b in banks.values()]
        )
    if data_root is not None:
        problems.extend(_check_root(manifest, data_root))
    if problems:
        raise _bundle_error(path, problems)
    return Bundle(path=path, manifest=manifest, hogs=hogs, srm=srm, contactnet=contactnet, pose_banks=banks)
