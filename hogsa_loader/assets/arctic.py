"""Reader of a real ARCTIC data root.

Start with :class:`ArcticRoot` (its docstring shows the folder layout it reads), which exposes
every sequence as a dataset-independent :class:`~hogsa_loader.assets.types.SequenceData`
(metres, axis-angle, ``p_cam = R p_world + T``). Every missing or malformed file raises
:class:`~hogsa_loader.errors.AssetError` naming the file and the problem.
"""

from __future__ import annotations

import math
import os
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping, Optional, Sequence, Union

import numpy as np
import torch

from hogsa_loader.assets.conventions import ALLO_VIEWS, CROPPED_SIZE, EGO_IMAGE_SCALE, EGO_IMAGE_SIZE, EGO_VIEW
from hogsa_loader.assets.hands.mano import MANOLayer
from hogsa_loader.assets.hands.mano_io import load_mano
from hogsa_loader.assets.objects.articulated import ArticulatedObjectLayer
from hogsa_loader.assets.objects.template import ObjectTemplates
from hogsa_loader.assets.types import CameraTrack, HandTrack, ObjectTrack, SequenceData
from hogsa_loader.errors import AssetError, PathLike, read_json
from hogsa_loader.io.npy import NpyUnpickler, read_npy
from hogsa_loader.io.pickle_caps import nested_shape

__all__ = [
    "ARCTIC_SUBDIR",
    "MANO_SUBDIR",
    "PROTOCOL_VIEWS",
    "SPLIT_NAMES",
    "WORLD_META_FILE",
    "ArcticRoot",
    "NpyUnpickler",
    "RawSequence",
    "SubjectMisc",
    "WorldMeta",
    "canonical_split",
    "protocol_views",
    "read_npy",
]

#: Where ARCTIC's data lives below ``data_root`` (``./data``).
ARCTIC_SUBDIR = Path("arctic_data") / "data"
#: Where the MANO model files live below ``data_root`` (common/body_models.py).
MANO_SUBDIR = Path("body_models") / "mano"
#: Optional project file written by the world generator, below ``arctic_data/data``.
WORLD_META_FILE = Path("meta") / "hogsa_world.json"
#: Views used by each protocol (src/arctic/split.py ``get_selected_views``).
PROTOCOL_VIEWS: dict[str, tuple[int, ...]] = {
    "p1": tuple(ALLO_VIEWS),
    "p1a": tuple(ALLO_VIEWS),
    "p2": (EGO_VIEW,),
    "p2a": (EGO_VIEW,),
}
#: Split names after the ``mini``/``tiny``/``small`` prefixes are stripped.
SPLIT_NAMES: tuple[str, ...] = ("train", "val", "test")
#: Number of allocentric cameras in ``misc.json`` (views 1..8).
NUM_ALLO = len(ALLO_VIEWS)
#: Tolerance of the rotation-matrix checks (orthonormality, determinant).
ROTATION_TOL = 1e-3
GENDERS = ("male", "female", "neutral")
_SEQ_ID = re.compile(r"^[A-Za-z0-9_.\-]+/[A-Za-z0-9_.\-]+$")


# ----------------------------------------------------------------------------------------
# Validation helpers
# ----------------------------------------------------------------------------------------
def _shape_str(spec: Sequence[Union[int, str]]) -> str:
    inner = ", ".join(str(s) for s in spec)
    return f"({inner},)" if len(spec) == 1 else f"({inner})"


def _check_nested_shape(
    value: Any, path: Path, key: str, spec: Sequence[Union[int, str]], frames: Optional[int]
) -> None:
    """Refuse nested lists whose shape, read along their first elements, is not ``spec``,
    before converting them (a list of shared references may expand to millions of numbers)."""
    shape = nested_shape(value)
    want = [frames if s == "F" and frames is not None else s for s in spec]
    if len(shape) != len(spec) or any(isinstance(w, int) and w != n for w, n in zip(want, shape, strict=True)):
        extra = f" with F = {frames}" if frames is not None and "F" in spec else ""
        got = "x".join(map(str, shape))
        raise AssetError(path, f"{key} is a nested list of shape {got}, expected {_shape_str(spec)}{extra}")


def _numeric(
    value: Any, path: Path, key: str, spec: Sequence[Union[int, str]], frames: Optional[int] = None
) -> np.ndarray:
    """Check that ``value`` is a finite real numeric array of shape ``spec``.

    Args:
        value: the loaded value (array or nested list of numbers).
        path: file it came from (for the error).
        key: dotted key inside the file (for the error).
        spec: expected shape; the string ``"F"`` stands for the frame count.
        frames: the frame count ``F`` (None: any, but all ``"F"`` entries equal).

    Returns:
        a float64 copy.
    """
    if isinstance(value, (str, bytes, dict)) or value is None:
        raise AssetError(path, f"{key} is a {type(value).__name__}, expected a numeric array {_shape_str(spec)}")
    if isinstance(value, np.ndarray):
        arr = value
    else:
        if isinstance(value, (list, tuple)):
            _check_nested_shape(value, path, key, spec, frames)
        try:
            arr = np.asarray(value)
        except Exception:  # ragged nested lists
            raise AssetError(path, f"{key} is not a numeric array") from None
    if arr.dtype.kind not in "fiu":
        raise AssetError(path, f"{key} has dtype {arr.dtype}, expected real numbers (float or int)")
    want = tuple(frames if s == "F" and frames is not None else s for s in spec)
    ok = arr.ndim == len(spec) and all(
        (w == "F" and arr.shape[i] == arr.shape[spec.index("F")]) or w == arr.shape[i] for i, w in enumerate(want)
    )
    if not ok:
        extra = f" with F = {frames}" if frames is not None and "F" in spec else ""
        raise AssetError(path, f"{key} has shape {arr.shape}, expected {_shape_str(spec)}{extra}")
    out = arr.astype(np.float64)
    bad = int(np.size(out) - np.count_nonzero(np.isfinite(out)))
    if bad:
        raise AssetError(path, f"{key} contains NaN or inf ({bad} values)")
    return out


#: Largest |translation| component (metres) of a hand, an object or the egocentric camera:
#: ARCTIC's capture volume is a few metres across.
MAX_TRANSLATION_M = 100.0
#: Largest axis-angle norm (radians) of a rotation or a pose parameter triple (16 turns; the
#: fits stay within a few radians).
MAX_ROTATION_RAD = 100.0


def _check_bounds(x: np.ndarray, path: Path, key: str, limit: float, unit: str, norm: bool = False) -> None:
    """Refuse finite but physically impossible values (``norm``: of the rows' 3-vectors)."""
    v = np.linalg.norm(x.reshape(-1, 3), axis=1) if norm else np.abs(x)
    if v.size and float(v.max()) > limit:
        worst = float(v.max())
        raise AssetError(path, f"{key} reaches {worst:.3g} {unit}, beyond any real capture (limit {limit:g} {unit})")


def _check_rotations(R: np.ndarray, path: Path, key: str) -> None:
    """(..., 3, 3) must be proper rotations within :data:`ROTATION_TOL`."""
    eye = np.eye(3)
    err = np.abs(np.einsum("...ij,...kj->...ik", R, R) - eye).max(axis=(-1, -2))
    det = np.linalg.det(R)
    bad = np.flatnonzero((err > ROTATION_TOL) | (np.abs(det - 1.0) > ROTATION_TOL))
    if bad.size:
        raise AssetError(
            path, f"{key}[{int(bad[0])}] is not a rotation matrix (R R^T != I or det != 1; {bad.size} bad)"
        )


def _check_intrinsics(K: np.ndarray, path: Path, key: str) -> None:
    """(..., 3, 3) pinhole matrices with positive focal lengths and last row (0, 0, 1)."""
    last = K[..., 2, :]
    ok = (
        np.all(np.abs(last - np.array([0.0, 0.0, 1.0])) < 1e-9, axis=-1)
        & (K[..., 0, 0] > 0)
        & (K[..., 1, 1] > 0)
        & (np.abs(K[..., 1, 0]) < 1e-9)
    )
    bad = np.flatnonzero(~np.asarray(ok).reshape(-1))
    if bad.size:
        raise AssetError(
            path, f"{key}[{int(bad[0])}] is not a pinhole intrinsics matrix (need fx, fy > 0 and last row (0, 0, 1))"
        )


def _plain_data(value: Any, path: Path, key: str, depth: int = 0, seen: Optional[set[int]] = None) -> None:
    """Unused keys may hold strings/numbers/arrays/lists/dicts only (no other objects).

    Each container is checked once however often it is referenced (``seen``: ids of the
    containers checked, all alive through ``value``), so the cost follows the file, not what
    shared references expand to.
    """
    if depth > 16:
        raise AssetError(path, f"{key} is nested too deeply")
    if value is None or isinstance(value, (str, bytes, int, float, np.generic)):
        return
    if not isinstance(value, (np.ndarray, list, tuple, dict)):
        raise AssetError(path, f"{key} holds a {type(value).__name__}, expected plain data")
    seen = set() if seen is None else seen
    if id(value) in seen:
        return
    seen.add(id(value))
    if isinstance(value, np.ndarray):
        if value.dtype.hasobject:
            for i, item in enumerate(value.reshape(-1)[:10000]):
                _plain_data(item, path, f"{key}[{i}]", depth + 1, seen)
    elif isinstance(value, dict):
        for k, item in value.items():
            _plain_data(item, path, f"{key}.{k}", depth + 1, seen)
    else:
        for i, item in enumerate(value):
            if isinstance(item, (np.ndarray, list, tuple, dict)) or not isinstance(
                item, (str, bytes, int, float, np.generic, type(None))
            ):
                _plain_data(item, path, f"{key}[{i}]", depth + 1, seen)


def _json_int(value: Any) -> Optional[int]:
    """An int from JSON (ints, or floats with an integral value); None otherwise."""
    if isinstance(value, bool):
        return None
    if isinstance(value, int):
        return value
    if isinstance(value, float) and math.isfinite(value) and value == int(value):
        return int(value)
    return None


def canonical_split(split: str) -> str:
    """ARCTIC's split-file name: strip the ``mini``/``tiny``/``small`` sub-sampling prefixes.

    ``"minitrain" -> "train"``, ``"tinyval" -> "val"``, ``"smalltest" -> "test"``
    (``src/datasets/arctic_dataset.py`` ``_load_data``). The sub-sampling itself is the
    dataset's job.
    """
    short = split.replace("mini", "").replace("tiny", "").replace("small", "")
    if short not in SPLIT_NAMES:
        raise ValueError(f"unknown split {split!r}: expected [mini|tiny|small]{{train,val,test}}")
    return short


def protocol_views(protocol: str) -> tuple[int, ...]:
    """Views of a protocol: p1 → allocentric 1..8, p2 → egocentric 0."""
    try:
        return PROTOCOL_VIEWS[protocol]
    except KeyError:
        raise ValueError(f"unknown protocol {protocol!r}; known: {sorted(PROTOCOL_VIEWS)}") from None


# ----------------------------------------------------------------------------------------
# Data classes
# ----------------------------------------------------------------------------------------
@dataclass(frozen=True)
class SubjectMisc:
    """One subject's entry of ``meta/misc.json``, validated.

    Attributes:
        sid: subject id (``"s01"``).
        world2cam: (8, 4, 4) float64 world→camera extrinsics of views 1..8 (index = view − 1).
        intris_mat: (8, 3, 3) float64 full-resolution intrinsics of views 1..8.
        image_size: (9, 2) int64 image (width, height) per view 0..8.
        ioi_offset: image file number = GT frame index + ``ioi_offset``.
        gender: ``"male"``/``"female"``/``"neutral"`` (SMPL-X model choice).
    """

    sid: str
    world2cam: np.ndarray
    intris_mat: np.ndarray
    image_size: np.ndarray
    ioi_offset: int
    gender: str


@dataclass(frozen=True)
class WorldMeta:
    """``meta/hogsa_world.json`` (written by the project's world generator) or ARCTIC defaults.

    Attributes:
        schema_version: file schema version (0 when the file is absent).
        cropped_size: side of the allocentric cropped images (ARCTIC: 1000).
        ego_image_scale: ego cropped image = full ego image × this (ARCTIC: 0.3).
        ego_image_size: full-resolution ego image (width, height) (ARCTIC: (2800, 2000)).
        mask_ids: label name → pixel value of the ``masks/`` images (empty for ARCTIC).
        present: whether the file exists.
        extra: any other keys of the file, as stored.
    """

    schema_version: int = 0
    cropped_size: int = CROPPED_SIZE
    ego_image_scale: float = EGO_IMAGE_SCALE
    ego_image_size: tuple[int, int] = EGO_IMAGE_SIZE
    mask_ids: Mapping[str, int] = field(default_factory=dict)
    present: bool = False
    extra: Mapping[str, Any] = field(default_factory=dict)

    @property
    def arctic_sized(self) -> bool:
        """Whether the image files have the sizes ARCTIC's own loader hard-codes (1000-px
        allocentric crops, the 2800×2000 ego image × 0.3)."""
        return (self.cropped_size, self.ego_image_scale, tuple(self.ego_image_size)) == (
            CROPPED_SIZE,
            EGO_IMAGE_SCALE,
            EGO_IMAGE_SIZE,
        )


@dataclass
class RawSequence:
    """The validated contents of one sequence's ``raw_seqs`` files, float64.

    Attributes:
        sid, seq: subject id and sequence name.
        object_name: the part of ``seq`` before the first ``_``.
        mano: ``{"right"|"left": {"rot" (F,3), "pose" (F,45), "trans" (F,3) m,
            "shape" (10,), "fitting_err" (F,)}}`` (world frame, pose relative to the mean).
        shape_layout: per side, how ``shape`` was stored: ``"(10,)"`` (ARCTIC) or
            ``"(F, 10)"`` (accepted when all rows are equal; ``shape`` is then row 0).
        object: (F, 7) [θ rad, axis-angle (3), translation (3) **mm**], world frame.
        R_ego: (F, 3, 3) world→ego rotation; T_ego: (F, 3) world→ego translation (m).
        K_ego: (3, 3) ego intrinsics (full-res); dist8: (8,) OpenCV rational distortion.
        egocam_extra: the other keys of ``.egocam.dist.npy`` as stored (markers, R0, T0...).
        paths: ``{"mano"|"object"|"egocam": file}``.
    """

    sid: str
    seq: str
    object_name: str
    mano: dict[str, dict[str, np.ndarray]]
    shape_layout: dict[str, str]
    object: np.ndarray
    R_ego: np.ndarray
    T_ego: np.ndarray
    K_ego: np.ndarray
    dist8: np.ndarray
    egocam_extra: dict[str, Any]
    paths: dict[str, Path]

    @property
    def num_frames(self) -> int:
        return int(self.object.shape[0])

    @property
    def world2ego(self) -> np.ndarray:
        """(F, 4, 4) ``[[R, T], [0, 0, 0, 1]]``."""
        F = self.num_frames
        out = np.zeros((F, 4, 4))
        out[:, :3, :3] = self.R_ego
        out[:, :3, 3] = self.T_ego
        out[:, 3, 3] = 1.0
        return out


# ----------------------------------------------------------------------------------------
# The root
# ----------------------------------------------------------------------------------------
class ArcticRoot:
    """A real (or generated, same format) ARCTIC data root.

    ``ArcticRoot(data_root)`` takes ARCTIC's ``./data`` folder, i.e. the folder holding::

        data_root/
          arctic_data/data/
            meta/misc.json, meta/object_meta.json, meta/object_vtemplates/<obj>/...
            meta/hogsa_world.json                      (optional, written by our world generator)
            raw_seqs/<sid>/<seq>.{mano,object,egocam.dist}.npy
            splits_json/protocol_<p>.json, splits/<p>_<split>.npy
            cropped_images/<sid>/<seq>/<view>/<frame:05d>.jpg   (optional)
            images/<sid>/<seq>/<view>/<frame:05d>.jpg           (optional)
            masks/<sid>/<seq>/<view>/<frame:05d>.png            (optional, generated worlds)
          body_models/mano/MANO_{RIGHT,LEFT}.pkl

    and exposes every sequence as a dataset-independent :class:`~hogsa_loader.assets.types.SequenceData`
    (metres, axis-angle, ``p_cam = R p_world + T``).

    Every missing or malformed file raises :class:`~hogsa_loader.errors.AssetError` naming the
    file and the problem (``misc.json: subject s02 has 7 world2cam matrices, expected 8``).
    The pickled ``raw_seqs/*.npy`` and ``splits/*.npy`` files are read with
    :func:`~hogsa_loader.io.npy.read_npy` (restricted unpickler, never
    ``np.load(allow_pickle=True)``); the values used are then checked to be numeric arrays of
    the expected shapes and finite.

    Args:
        data_root: ARCTIC's ``./data`` folder (holding ``arctic_data/data`` and
            ``body_models``). The ``arctic_data/data`` folder itself is accepted too.

    Raises:
        AssetError: the folder has no ``arctic_data/data``.
    """

    def __init__(self, data_root: PathLike) -> None:
        root = Path(os.path.abspath(Path(data_root).expanduser()))
        if not (root / ARCTIC_SUBDIR).is_dir() and root.name == "data" and root.parent.name == "arctic_data":
            root = root.parent.parent
        if not (root / ARCTIC_SUBDIR).is_dir():
            raise AssetError(root, f"not an ARCTIC data root: no {ARCTIC_SUBDIR} folder inside")
        self.data_root: Path = root
        self.arctic_dir: Path = root / ARCTIC_SUBDIR
        self.meta_dir: Path = self.arctic_dir / "meta"
        self.raw_dir: Path = self.arctic_dir / "raw_seqs"
        self.mano_dir: Path = root / MANO_SUBDIR
        self._misc: Optional[dict[str, SubjectMisc]] = None
        self._world_meta: Optional[WorldMeta] = None
        self._templates: dict[bool, ObjectTemplates] = {}
        self._object_layer: Any = None
        self._mano_layers: dict[torch.dtype, dict] = {}

    def __repr__(self) -> str:
        return f"ArcticRoot({str(self.data_root)!r})"

    # ------------------------------------------------------------------ paths
    @property
    def misc_path(self) -> Path:
        return self.meta_dir / "misc.json"

    def raw_paths(self, sid: str, seq: str) -> dict[str, Path]:
        """``{"mano"|"object"|"egocam": raw_seqs/<sid>/<seq>.<kind>.npy}``."""
        base = self.raw_dir / sid
        return {
            "mano": base / f"{seq}.mano.npy",
            "object": base / f"{seq}.object.npy",
            "egocam": base / f"{seq}.egocam.dist.npy",
        }

    def image_path(self, sid: str, seq: str, view: int, frame_id: int, cropped: bool = True) -> Path:
        """``{cropped_images|images}/<sid>/<seq>/<view>/<frame_id:05d>.jpg`` (file number = GT + ioi_offset)."""
        folder = "cropped_images" if cropped else "images"
        return self.arctic_dir / folder / sid / seq / str(view) / f"{frame_id:05d}.jpg"

    def mask_path(self, sid: str, seq: str, view: int, frame_id: int) -> Path:
        """``masks/<sid>/<seq>/<view>/<frame_id:05d>.png``."""
        return self.arctic_dir / "masks" / sid / seq / str(view) / f"{frame_id:05d}.png"

    # ------------------------------------------------------------------ misc.json
    def misc(self) -> dict[str, SubjectMisc]:
        """Validated ``meta/misc.json`` (cached): ``{sid: SubjectMisc}``, sorted by sid.

        Raises:
            AssetError: missing file or any malformed entry, e.g.
                ``misc.json: subject s02 has 7 world2cam matrices, expected 8``.
        """
        if self._misc is None:
            self._misc = self._read_misc()
        return self._misc

    def _read_misc(self) -> dict[str, SubjectMisc]:
        path = self.misc_path
        raw = read_json(path)
        if not isinstance(raw, dict) or not raw:
            raise AssetError(path, "expected a non-empty JSON object keyed by subject id")
        out: dict[str, SubjectMisc] = {}
        for sid in sorted(raw):
            entry = raw[sid]
            if not isinstance(entry, dict):
                raise AssetError(path, f"subject {sid}: expected an object, got {type(entry).__name__}")
            for key in ("world2cam", "intris_mat", "image_size", "ioi_offset", "gender"):
                if key not in entry:
                    raise AssetError(path, f"subject {sid} has no '{key}'")

            def mats(key: str, count: int, rows: int, cols: int, what: str, entry=entry, sid=sid) -> np.ndarray:
                val = entry[key]
                if not isinstance(val, list):
                    raise AssetError(path, f"subject {sid}: '{key}' must be a list of {count} {what}")
                if len(val) != count:
                    raise AssetError(path, f"subject {sid} has {len(val)} {key} {what}, expected {count}")
                return _numeric(val, path, f"subject {sid}: '{key}'", (count, rows, cols) if cols else (count, rows))

            w2c = mats("world2cam", NUM_ALLO, 4, 4, "matrices")
            if np.abs(w2c[:, 3] - np.array([0.0, 0.0, 0.0, 1.0])).max() > 1e-9:
                raise AssetError(path, f"subject {sid}: world2cam matrices must end with the row (0, 0, 0, 1)")
            _check_rotations(w2c[:, :3, :3], path, f"subject {sid}: world2cam")
            K = mats("intris_mat", NUM_ALLO, 3, 3, "matrices")
            _check_intrinsics(K, path, f"subject {sid}: intris_mat")
            sizes = mats("image_size", NUM_ALLO + 1, 2, 0, "entries")
            if np.any(sizes <= 0) or np.any(sizes != np.round(sizes)):
                raise AssetError(path, f"subject {sid}: image_size entries must be positive integers [w, h]")
            ioi = _json_int(entry["ioi_offset"])
            if ioi is None:
                raise AssetError(path, f"subject {sid}: ioi_offset must be an integer, got {entry['ioi_offset']!r}")
            gender = entry["gender"]
            if not isinstance(gender, str) or gender.lower() not in GENDERS:
                raise AssetError(path, f"subject {sid}: gender must be one of {GENDERS}, got {gender!r}")
            out[str(sid)] = SubjectMisc(
                sid=str(sid),
                world2cam=w2c,
                intris_mat=K,
                image_size=sizes.astype(np.int64),
                ioi_offset=ioi,
                gender=gender.lower(),
            )
        return out

    def subject_misc(self, sid: str) -> SubjectMisc:
        """One subject of misc.json; AssetError naming misc.json when it is absent."""
        misc = self.misc()
        if sid not in misc:
            raise AssetError(self.misc_path, f"subject {sid} is missing (has {sorted(misc)})")
        return misc[sid]

    def subjects(self) -> list[str]:
        """Subject ids of ``misc.json``, sorted."""
        return sorted(self.misc())

    # ------------------------------------------------------------------ listings
    def sequences(self, subject: Optional[str] = None) -> list[str]:
        """Sorted ``"sid/seq"`` ids of ``raw_seqs`` (one per ``<seq>.mano.npy``).

        Args:
            subject: restrict to one subject.
        """
        if not self.raw_dir.is_dir():
            raise AssetError(self.raw_dir, "raw_seqs folder is missing")
        subs = [subject] if subject is not None else sorted(p.name for p in self.raw_dir.iterdir() if p.is_dir())
        out = []
        for sid in subs:
            folder = self.raw_dir / sid
            if not folder.is_dir():
                raise AssetError(folder, f"no raw_seqs folder for subject {sid}")
            for f in folder.iterdir():
                if f.is_file() and f.name.endswith(".mano.npy"):
                    out.append(f"{sid}/{f.name[: -len('.mano.npy')]}")
        return sorted(out)

    # ------------------------------------------------------------------ models
    def object_templates(self, load_texture: bool = True) -> ObjectTemplates:
        """``{name: ObjectTemplate}`` of ``meta/object_vtemplates`` (metres), each object read when
        first asked for (:class:`~hogsa_loader.assets.objects.template.ObjectTemplates`); one
        mapping per ``load_texture``, kept (the untextured one takes what the textured one read)."""
        if load_texture not in self._templates:
            textured = self._templates.get(True) if not load_texture else None
            self._templates[load_texture] = ObjectTemplates(self.meta_dir, load_texture, textured=textured)
        return self._templates[load_texture]

    def object_layer(self) -> Any:
        """An :class:`~hogsa_loader.assets.objects.articulated.ArticulatedObjectLayer` of every template (cached)."""
        if self._object_layer is None:
            templates = self.object_templates(load_texture=False)
            if not templates:
                raise AssetError(self.meta_dir / "object_vtemplates", "no object template found")
            self._object_layer = ArticulatedObjectLayer(templates)
        return self._object_layer

    def mano_layers(self, dtype: torch.dtype = torch.float32) -> dict:
        """``{"right": MANOLayer, "left": MANOLayer}`` from ``body_models/mano``, ``flat_hand_mean=False`` (ARCTIC)."""
        if dtype not in self._mano_layers:
            if not self.mano_dir.is_dir():
                raise AssetError(
                    self.mano_dir, "MANO model folder is missing (expected MANO_RIGHT.pkl / MANO_LEFT.pkl)"
                )
            self._mano_layers[dtype] = {
                side: MANOLayer(load_mano(self.mano_dir, side=side), flat_hand_mean=False, dtype=dtype).eval()
                for side in ("right", "left")
            }
        return self._mano_layers[dtype]

    # ------------------------------------------------------------------ world meta
    def world_meta(self) -> WorldMeta:
        """``meta/hogsa_world.json`` if present, else ARCTIC's defaults (cached).

        Required keys when the file exists: ``schema_version`` (int ≥ 1), ``cropped_size``
        (int > 0), ``ego_image_scale`` (> 0), ``ego_image_size`` ([w, h] ints > 0),
        ``mask_ids`` (``{name: int ≥ 0}``). Other keys are kept in ``extra``.
        """
        if self._world_meta is None:
            path = self.arctic_dir / WORLD_META_FILE
            self._world_meta = self._read_world_meta(path) if path.exists() else WorldMeta()
        return self._world_meta

    def require_arctic_sizes(self) -> WorldMeta:
        """:meth:`world_meta`, refused unless the image files have ARCTIC's sizes.

        For uses that must see what ARCTIC's own loader sees on these files: it assumes
        1000-px crops and ego × 0.3, so on other sizes its patches show the wrong region and
        its ``meta_info['center']`` is off.

        Raises:
            AssetError: (naming ``meta/hogsa_world.json``) the world has other sizes.
        """
        meta = self.world_meta()
        if not meta.arctic_sized:
            w, h = meta.ego_image_size
            raise AssetError(
                self.arctic_dir / WORLD_META_FILE,
                f"this world has {meta.cropped_size}-px allocentric crops and ego images {w}x{h} × "
                f"{meta.ego_image_scale:g}, but ARCTIC's loader hard-codes {CROPPED_SIZE}-px crops and "
                f"{EGO_IMAGE_SIZE[0]}x{EGO_IMAGE_SIZE[1]} × {EGO_IMAGE_SCALE:g}; generate an ARCTIC-sized world "
                "(hogsa world --preset small or demo) for ARCTIC-exact use",
            )
        return meta

    @staticmethod
    def _read_world_meta(path: Path) -> WorldMeta:
        raw = read_json(path)
        if not isinstance(raw, dict):
            raise AssetError(path, "expected a JSON object")
        for key in ("schema_version", "cropped_size", "ego_image_scale", "ego_image_size", "mask_ids"):
            if key not in raw:
                raise AssetError(path, f"key '{key}' is missing")
        version = _json_int(raw["schema_version"])
        if version is None or version < 1:
            raise AssetError(path, f"schema_version must be an integer >= 1, got {raw['schema_version']!r}")
        size = _json_int(raw["cropped_size"])
        if size is None or size <= 0:
            raise AssetError(path, f"cropped_size must be a positive integer, got {raw['cropped_size']!r}")
        scale = raw["ego_image_scale"]
        if isinstance(scale, bool) or not isinstance(scale, (int, float)) or not (math.isfinite(scale) and scale > 0):
            raise AssetError(path, f"ego_image_scale must be a positive number, got {scale!r}")
        ego = raw["ego_image_size"]
        wh = [_json_int(v) for v in ego] if isinstance(ego, list) and len(ego) == 2 else [None]
        if any(v is None or v <= 0 for v in wh):
            raise AssetError(path, f"ego_image_size must be [width, height] positive integers, got {ego!r}")
        masks = raw["mask_ids"]
        if not isinstance(masks, dict) or any(
            _json_int(v) is None or _json_int(v) < 0
            for v in masks.values()  # type: ignore[operator]
        ):
            raise AssetError(path, "mask_ids must map label names to integers >= 0")
        known = {"schema_version", "cropped_size", "ego_image_scale", "ego_image_size", "mask_ids"}
        return WorldMeta(
            schema_version=version,
            cropped_size=size,
            ego_image_scale=float(scale),
            ego_image_size=(int(wh[0]), int(wh[1])),  # type: ignore[arg-type]
            mask_ids={str(k): int(_json_int(v)) for k, v in masks.items()},  # type: ignore[arg-type]
            present=True,
            extra={k: v for k, v in raw.items() if k not in known},
        )

    # ------------------------------------------------------------------ raw sequences
    def raw_sequence(self, sid: str, seq: str) -> RawSequence:
        """Read and validate ``raw_seqs/<sid>/<seq>.{mano,object,egocam.dist}.npy``.

        Checks: the three files exist and load (restricted unpickler); the MANO file is a
        dict with ``right``/``left`` dicts holding ``rot`` (F,3), ``pose`` (F,45), ``trans``
        (F,3), ``shape`` (10,) or (F,10) with equal rows, ``fitting_err`` (F,); the object
        file is (F,7); the egocam dict has ``R_k_cam_np`` (F,3,3) rotations, ``T_k_cam_np``
        (F,3,1) (or (F,3)), ``intrinsics`` (3,3), ``dist8`` (8,); one F everywhere; every
        used value real and finite.
        """
        paths = self.raw_paths(sid, seq)
        mano = self._read_mano(paths["mano"])
        F = mano["right"]["rot"].shape[0]
        shape_layout = {side: mano[side].pop("_layout") for side in ("right", "left")}

        obj_path = paths["object"]
        obj_raw = read_npy(obj_path)
        if (
            isinstance(obj_raw, np.ndarray)
            and obj_raw.ndim == 2
            and obj_raw.dtype.kind in "fiu"
            and obj_raw.shape[0] != F
        ):
            raise AssetError(obj_path, f"has {obj_raw.shape[0]} frames, but {paths['mano'].name} has {F}")
        obj = _numeric(obj_raw, obj_path, "object parameters", ("F", 7), F)
        _check_bounds(obj[:, 0], obj_path, "object articulation", MAX_ROTATION_RAD, "rad")
        _check_bounds(obj[:, 1:4], obj_path, "object rotation", MAX_ROTATION_RAD, "rad", norm=True)
        _check_bounds(obj[:, 4:7], obj_path, "object translation", MAX_TRANSLATION_M * 1000.0, "mm")

        ego_path = paths["egocam"]
        ego = read_npy(ego_path)
        if not isinstance(ego, dict):
            raise AssetError(ego_path, f"expected a dict (np.save of a dict), found {type(ego).__name__}")
        for key in ("R_k_cam_np", "T_k_cam_np", "intrinsics", "dist8"):
            if key not in ego:
                raise AssetError(ego_path, f"key '{key}' is missing")
        R_raw = ego["R_k_cam_np"]
        if isinstance(R_raw, np.ndarray) and R_raw.ndim == 3 and R_raw.shape[0] != F:
            raise AssetError(ego_path, f"R_k_cam_np has {R_raw.shape[0]} frames, but {paths['mano'].name} has {F}")
        R = _numeric(R_raw, ego_path, "R_k_cam_np", ("F", 3, 3), F)
        _check_rotations(R, ego_path, "R_k_cam_np")
        T_raw = ego["T_k_cam_np"]
        if isinstance(T_raw, np.ndarray) and T_raw.ndim == 2:
            T = _numeric(T_raw, ego_path, "T_k_cam_np", ("F", 3), F)
        else:
            T = _numeric(T_raw, ego_path, "T_k_cam_np", ("F", 3, 1), F)[..., 0]
        _check_bounds(T, ego_path, "T_k_cam_np", MAX_TRANSLATION_M, "m")
        K = _numeric(ego["intrinsics"], ego_path, "intrinsics", (3, 3))
        _check_intrinsics(K, ego_path, "intrinsics")
        dist8 = _numeric(ego["dist8"], ego_path, "dist8", (8,))
        extra = {k: v for k, v in ego.items() if k not in ("R_k_cam_np", "T_k_cam_np", "intrinsics", "dist8")}
        _plain_data(extra, ego_path, "egocam")
        return RawSequence(
            sid=sid,
            seq=seq,
            object_name=seq.split("_")[0],
            mano=mano,
            shape_layout=shape_layout,
            object=obj,
            R_ego=R,
            T_ego=T,
            K_ego=K,
            dist8=dist8,
            egocam_extra=extra,
            paths=paths,
        )

    @staticmethod
    def _read_mano(path: Path) -> dict[str, dict[str, Any]]:
        data = read_npy(path)
        if not isinstance(data, dict):
            raise AssetError(
                path, f"expected a dict with 'right' and 'left' (np.save of a dict), found {type(data).__name__}"
            )
        out: dict[str, dict[str, Any]] = {}
        F: Optional[int] = None
        for side in ("right", "left"):
            hand = data.get(side)
            if not isinstance(hand, dict):
                raise AssetError(path, f"'{side}' is missing or not a dict")
            for key in ("rot", "pose", "trans", "shape", "fitting_err"):
                if key not in hand:
                    raise AssetError(path, f"{side}.{key} is missing")
            rot_raw = hand["rot"]
            if F is None:
                rot = _numeric(rot_raw, path, f"{side}.rot", ("F", 3))
                F = rot.shape[0]
                if F < 1:
                    raise AssetError(path, f"{side}.rot has no frames")
            else:
                rot = _numeric(rot_raw, path, f"{side}.rot", ("F", 3), F)
            d = {
                "rot": rot,
                "pose": _numeric(hand["pose"], path, f"{side}.pose", ("F", 45), F),
                "trans": _numeric(hand["trans"], path, f"{side}.trans", ("F", 3), F),
                "fitting_err": _numeric(hand["fitting_err"], path, f"{side}.fitting_err", ("F",), F),
            }
            _check_bounds(d["rot"], path, f"{side}.rot", MAX_ROTATION_RAD, "rad", norm=True)
            _check_bounds(d["pose"], path, f"{side}.pose", MAX_ROTATION_RAD, "rad", norm=True)
            _check_bounds(d["trans"], path, f"{side}.trans", MAX_TRANSLATION_M, "m")
            shape_raw = hand["shape"]
            if isinstance(shape_raw, np.ndarray) and shape_raw.ndim == 2:
                betas = _numeric(shape_raw, path, f"{side}.shape", ("F", 10), F)
                if np.abs(betas - betas[:1]).max() > 1e-6:
                    raise AssetError(
                        path,
                        f"{side}.shape is stored per frame (F, 10) and varies across frames; "
                        "ARCTIC uses one (10,) vector per sequence and hand",
                    )
                d["shape"] = betas[0].copy()
                d["_layout"] = "(F, 10)"
            else:
                d["shape"] = _numeric(shape_raw, path, f"{side}.shape", (10,))
                d["_layout"] = "(10,)"
            out[side] = d
        return out

    # ------------------------------------------------------------------ SequenceData
    def sequence(self, sid: str, seq: str) -> SequenceData:
        """One sequence as :class:`SequenceData` (metres, world frame).

        Hands: ``rot``/``pose``/``trans`` as stored, ``betas`` (10,), ``fitting_err``.
        Object: θ, axis-angle, translation mm → m. Cameras: views 1..8 static from misc.json
        (``world2cam``/``K`` repeated over F), view 0 egocentric per frame from
        ``.egocam.dist.npy`` with ``dist8`` and K. Image sizes from misc ``image_size``.
        ``frame_ids`` = GT index + ``ioi_offset``. ``image_paths`` (cropped_images),
        ``full_image_paths`` (images) and ``mask_paths`` (masks) per view whose folder
        exists, ``None`` for missing frames.
        """
        misc = self.subject_misc(sid)
        raw = self.raw_sequence(sid, seq)
        F = raw.num_frames
        valid = np.ones(F, dtype=bool)

        def hand(side: str) -> HandTrack:
            h = raw.mano[side]
            return HandTrack(
                rot=h["rot"],
                pose=h["pose"],
                trans=h["trans"],
                betas=h["shape"],
                valid=valid.copy(),
                fitting_err=h["fitting_err"],
            )

        obj = ObjectTrack(
            name=raw.object_name,
            arti=raw.object[:, 0].copy(),
            rot=raw.object[:, 1:4].copy(),
            trans=raw.object[:, 4:7] / 1000.0,
            valid=valid.copy(),
        )
        cams: dict[int, CameraTrack] = {
            EGO_VIEW: CameraTrack(
                view=EGO_VIEW,
                world2cam=raw.world2ego,
                K=np.repeat(raw.K_ego[None], F, axis=0),
                width=int(misc.image_size[EGO_VIEW, 0]),
                height=int(misc.image_size[EGO_VIEW, 1]),
                dist=raw.dist8.copy(),
                egocentric=True,
            )
        }
        for view in ALLO_VIEWS:
            cams[view] = CameraTrack(
                view=view,
                world2cam=np.repeat(misc.world2cam[view - 1][None], F, axis=0),
                K=np.repeat(misc.intris_mat[view - 1][None], F, axis=0),
                width=int(misc.image_size[view, 0]),
                height=int(misc.image_size[view, 1]),
            )
        frame_ids = np.arange(F, dtype=np.int64) + misc.ioi_offset
        views = (EGO_VIEW,) + tuple(ALLO_VIEWS)
        return SequenceData(
            dataset="arctic",
            subject=sid,
            name=seq,
            right=hand("right"),
            left=hand("left"),
            object=obj,
            cameras=cams,
            frame_ids=frame_ids,
            image_paths=self._existing(self.arctic_dir / "cropped_images" / sid / seq, views, frame_ids, ".jpg"),
            full_image_paths=self._existing(self.arctic_dir / "images" / sid / seq, views, frame_ids, ".jpg"),
            mask_paths=self._existing(self.arctic_dir / "masks" / sid / seq, views, frame_ids, ".png"),
            root=self.data_root,
        )

    @staticmethod
    def _existing(
        folder: Path, views: Sequence[int], frame_ids: np.ndarray, ext: str
    ) -> dict[int, list[Optional[Path]]]:
        """view → F paths (None where the file is absent), for views whose folder exists."""
        out: dict[int, list[Optional[Path]]] = {}
        for view in views:
            vdir = folder / str(view)
            if not vdir.is_dir():
                continue
            with os.scandir(vdir) as it:
                names = {e.name for e in it}
            out[view] = [vdir / f"{int(i):05d}{ext}" if f"{int(i):05d}{ext}" in names else None for i in frame_ids]
        return out

    # ------------------------------------------------------------------ protocols and splits
    def protocol_path(self, protocol: str) -> Path:
        return self.arctic_dir / "splits_json" / f"protocol_{protocol}.json"

    def protocol(self, protocol: str) -> dict[str, list[str]]:
        """``splits_json/protocol_<p>.json`` as ``{"train", "val", "test": ["sid/seq", ...]}``.

        As ARCTIC (src/arctic/split.py): val and test must not overlap or repeat; train is
        recomputed as all − val − test, where "all" is the union of the three lists in file
        order (sequences present in ``raw_seqs`` but absent from the file are not added).
        """
        path = self.protocol_path(protocol)
        raw = read_json(path)
        if not isinstance(raw, dict):
            raise AssetError(path, "expected a JSON object with train/val/test lists")
        lists: dict[str, list[str]] = {}
        for key in SPLIT_NAMES:
            val = raw.get(key)
            if not isinstance(val, list):
                raise AssetError(path, f"'{key}' is missing or not a list")
            for item in val:
                if not isinstance(item, str) or not _SEQ_ID.match(item):
                    raise AssetError(path, f"'{key}' holds {item!r}, expected 'sid/seq'")
            lists[key] = list(val)
        for key in ("val", "test"):
            if len(set(lists[key])) != len(lists[key]):
                raise AssetError(path, f"'{key}' lists a sequence twice")
        both = set(lists["val"]) & set(lists["test"])
        if both:
            raise AssetError(path, f"sequences in both val and test: {sorted(both)}")
        held = set(lists["val"]) | set(lists["test"])
        train: list[str] = []
        for s in lists["train"] + lists["val"] + lists["test"]:
            if s not in held and s not in train:
                train.append(s)
        return {"train": train, "val": lists["val"], "test": lists["test"]}

    def split_path(self, protocol: str, split: str) -> Path:
        """``splits/<protocol>_<split>.npy`` with the mini/tiny/small prefix stripped."""
        return self.arctic_dir / "splits" / f"{protocol}_{canonical_split(split)}.npy"

    def load_split(self, name: str, split: Optional[str] = None) -> dict[str, Any]:
        """Load a processed split file (``splits/<protocol>_<split>.npy``).

        Args:
            name: ``"p1_minitrain"``-style name, or the protocol when ``split`` is given.
            split: e.g. ``"train"``, ``"tinyval"``; prefixes are stripped as ARCTIC does
                (the sub-sampling is left to the dataset).

        Returns:
            ``{"data_dict": {"sid/seq": {"cam_coord", "2d", "bbox", "params"}}, "imgnames": [...]}``.

        The file is read with :func:`read_npy` (restricted unpickler, never
        ``np.load(allow_pickle=True)``).
        """
        if split is None:
            protocol, sep, split = name.partition("_")
            if not sep:
                raise ValueError(f"split name {name!r} must look like 'p1_train'")
        else:
            protocol = name
        path = self.split_path(protocol, split)
        data = read_npy(path)
        if not isinstance(data, dict) or "data_dict" not in data or "imgnames" not in data:
            raise AssetError(path, "expected a dict with 'data_dict' and 'imgnames'")
        dd, names = data["data_dict"], data["imgnames"]
        if not isinstance(dd, dict) or not all(isinstance(v, dict) for v in dd.values()):
            raise AssetError(path, "'data_dict' must map 'sid/seq' to dicts")
        if not isinstance(names, list) or not all(isinstance(n, str) for n in names):
            raise AssetError(path, "'imgnames' must be a list of strings")
        for key, seq in dd.items():
            _check_split_sequence(path, key, seq)
        return data


#: What the dataset reads from a split's sequence: part -> {key: shape}, "F" = frames.
#: Views: 10 in ``cam_coord`` / ``2d`` points, 9 in rotations, flags and boxes.
_SPLIT_ARRAYS: dict[str, dict[str, tuple[Union[int, str], ...]]] = {
    "cam_coord": {
        "joints.right": ("F", 10, 21, 3),
        "joints.left": ("F", 10, 21, 3),
        "bbox3d": ("F", 10, 16, 3),
        "kp3d": ("F", 10, 32, 3),
        "rot_r_cam": ("F", 9, 3),
        "rot_l_cam": ("F", 9, 3),
        "is_valid": ("F", 9),
        "right_valid": ("F", 9),
        "left_valid": ("F", 9),
    },
    "2d": {
        "joints.right": ("F", 10, 21, 2),
        "joints.left": ("F", 10, 21, 2),
        "bbox3d": ("F", 10, 16, 2),
        "kp3d": ("F", 10, 32, 2),
    },
    "bbox": {"": ("F", 9, 3)},
    "params": {
        "pose_r": ("F", 45),
        "pose_l": ("F", 45),
        "shape_r": ("F", 10),
        "shape_l": ("F", 10),
        "obj_arti": ("F",),
        "dist": ("F", 8),
        "K_ego": ("F", 3, 3),
    },
}
#: Read only by the interaction-field targets; checked when present.
_SPLIT_OPTIONAL = {
    "params": {
        "rot_r": ("F", 3),
        "rot_l": ("F", 3),
        "trans_r": ("F", 3),
        "trans_l": ("F", 3),
        "obj_rot": ("F", 3),
        "obj_trans": ("F", 3),
    }
}


def _check_split_sequence(path: Path, key: str, seq: Any) -> None:
    """Shapes, frame counts, finiteness and flag values of one split sequence (no copies).

    Raises:
        AssetError: naming the split file and e.g. ``data_dict['s05/box_grab_01'].params.K_ego``.
    """
    frames: Optional[int] = None
    for part, arrays in _SPLIT_ARRAYS.items():
        if part not in seq:
            raise AssetError(path, f"data_dict[{key!r}] has no '{part}'")
        for name, spec in {**arrays, **_SPLIT_OPTIONAL.get(part, {})}.items():
            where = f"data_dict[{key!r}].{part}" + (f".{name}" if name else "")
            if name and not isinstance(seq[part], dict):
                raise AssetError(path, f"data_dict[{key!r}].{part} is a {type(seq[part]).__name__}, expected a dict")
            if name and name not in seq[part]:
                if name in _SPLIT_OPTIONAL.get(part, {}):
                    continue
                raise AssetError(path, f"{where} is missing")
            arr = seq[part][name] if name else seq[part]
            if not isinstance(arr, np.ndarray) or arr.dtype.kind not in "fiub":
                raise AssetError(
                    path,
                    f"{where} is a {type(arr).__name__}"
                    f"{'' if not isinstance(arr, np.ndarray) else ' of ' + str(arr.dtype)}, "
                    f"expected a numeric array {_shape_str(spec)}",
                )
            frames = arr.shape[0] if frames is None and arr.ndim else frames
            if (
                arr.ndim != len(spec)
                or any(w != "F" and w != n for w, n in zip(spec, arr.shape))
                or arr.shape[0] != frames
            ):
                raise AssetError(path, f"{where} has shape {arr.shape}, expected {_shape_str(spec)} with F = {frames}")
            if arr.dtype.kind == "f" and not bool(np.isfinite(arr).all()):
                raise AssetError(path, f"{where} contains NaN or inf")
            if name.endswith("valid") and not bool(np.isin(arr, (0, 1)).all()):
                raise AssetError(path, f"{where} holds values other than 0 and 1")
    _check_intrinsics(np.asarray(seq["params"]["K_ego"], dtype=np.float64), path, f"data_dict[{key!r}].params.K_ego")
