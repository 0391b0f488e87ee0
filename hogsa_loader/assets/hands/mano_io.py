"""Reading MANO model files without chumpy.

- :class:`ManoModelData`: the validated arrays of one hand model, plus the metadata the
  project needs (side, fingertip vertices, prior-contact vertices, vertex colours).
- :func:`reorder_vertices`: the same model with its vertices renumbered.
- :func:`load_mano`: ``.pkl`` (restricted unpickler,
  :class:`~hogsa_loader.io.mano_pickle.RestrictedUnpickler`) or ``.npz`` (no pickle allowed).
- :func:`convert_mano_to_npz`: one-shot conversion of a pickle to a chumpy-free ``.npz``.
- :func:`schema_dict`: a model as the MANO release's dictionary of arrays.
"""

from __future__ import annotations

import json
import os
import pickle
from dataclasses import dataclass, field, replace
from typing import Any, Mapping, Optional

import numpy as np
import scipy.sparse as sp

from hogsa_loader.errors import AssetError, PathLike
from hogsa_loader.io.atomic import atomic_open
from hogsa_loader.io.mano_pickle import RestrictedUnpickler, as_array

__all__ = [
    "ARCTIC_TIP_ORDER",
    "MANO_RELEASE_NUM_VERTS",
    "MANO_RELEASE_TIP_IDS",
    "ManoModelData",
    "RestrictedUnpickler",
    "check_npz_destination",
    "convert_mano_to_npz",
    "load_mano",
    "reorder_vertices",
    "schema_dict",
]

#: Order of the five fingertips appended as joints 16..20 (ARCTIC's 21-joint MANO).
ARCTIC_TIP_ORDER = ("thumb", "index", "middle", "ring", "pinky")

#: Vertex count of the official MANO release; only used to recognise it and pick the
#: published fingertip vertices below. Every other count is read from the model file.
MANO_RELEASE_NUM_VERTS = 778

#: Fingertip vertex ids, thumb->pinky: smplx's ``VERTEX_IDS['mano']``, which smplx (and so
#: ARCTIC) appends as joints 16..20 by id on any MANO-schema file.
MANO_RELEASE_TIP_IDS = {"right": (744, 320, 443, 554, 671), "left": (744, 320, 443, 554, 671)}

#: Key under which the project stores its own metadata inside a MANO-schema file.
META_KEY = "hogsa_meta"

_REQUIRED_KEYS = (
    "v_template",
    "shapedirs",
    "posedirs",
    "J_regressor",
    "weights",
    "kintree_table",
    "f",
    "hands_components",
    "hands_mean",
)


# ----------------------------------------------------------------------------------------
# The model container
# ----------------------------------------------------------------------------------------
@dataclass(frozen=True)
class ManoModelData:
    """Validated arrays of one MANO-schema hand model (numpy, float64 where real-valued).

    Attributes:
        v_template: (V, 3) rest vertices, metres.
        shapedirs: (V, 3, S) shape blend shapes.
        posedirs: (V, 3, 9 * (J - 1)) pose-corrective blend shapes.
        J_regressor: (J, V) dense joint regressor.
        weights: (V, J) skinning weights (rows sum to 1).
        parents: (J,) parent joint index, -1 for the root; parents[j] < j.
        faces: (F, 3) int64 triangles.
        hands_components: (C, 45) PCA basis of the articulation (rows = components).
        hands_mean: (45,) mean articulation, added when ``flat_hand_mean=False``.
        hands_coeffs: (N, 45) PCA coefficients of the source poses, or None.
        side: ``"right"`` or ``"left"``.
        tip_vertex_ids: (5,) fingertip vertices in ARCTIC order thumb, index, middle, ring, pinky.
        contact_vertex_ids: named prior-contact vertex sets (finger pads, palm) or empty.
        vertex_colors: (V, 3) albedo in [0, 1] or None.
        meta: free-form JSON-able metadata (generator, units, provenance).
        source: the file it was read from ("" if built in memory).
    """

    v_template: np.ndarray
    shapedirs: np.ndarray
    posedirs: np.ndarray
    J_regressor: np.ndarray
    weights: np.ndarray
    parents: np.ndarray
    faces: np.ndarray
    hands_components: np.ndarray
    hands_mean: np.ndarray
    hands_coeffs: Optional[np.ndarray]
    side: str
    tip_vertex_ids: np.ndarray
    contact_vertex_ids: Mapping[str, np.ndarray] = field(default_factory=dict)
    vertex_colors: Optional[np.ndarray] = None
    meta: Mapping[str, Any] = field(default_factory=dict)
    source: str = ""

    @property
    def num_verts(self) -> int:
        return int(self.v_template.shape[0])

    @property
    def num_joints(self) -> int:
        return int(self.parents.shape[0])

    @property
    def num_betas(self) -> int:
        return int(self.shapedirs.shape[2])

    def replace(self, **changes: Any) -> "ManoModelData":
        """A copy with some fields replaced (validated again)."""
        out = replace(self, **changes)
        validate_model(out)
        return out


def validate_model(m: ManoModelData) -> None:
    """Check every shape and invariant; raise :class:`AssetError` naming the source file."""
    where = m.source or "<in-memory MANO model>"

    def fail(msg: str) -> None:
        raise AssetError(where, msg)

    V = m.v_template.shape[0] if m.v_template.ndim == 2 else -1
    if m.v_template.ndim != 2 or m.v_template.shape[1] != 3 or V < 4:
        fail(f"v_template must be (V, 3), got {m.v_template.shape}")
    J = m.parents.shape[0]
    if m.shapedirs.ndim != 3 or m.shapedirs.shape[:2] != (V, 3):
        fail(f"shapedirs must be ({V}, 3, S), got {m.shapedirs.shape}")
    if m.posedirs.shape != (V, 3, 9 * (J - 1)):
        fail(f"posedirs must be ({V}, 3, {9 * (J - 1)}), got {m.posedirs.shape}")
    if m.J_regressor.shape != (J, V):
        fail(f"J_regressor must be ({J}, {V}), got {m.J_regressor.shape}")
    if m.weights.shape != (V, J):
        fail(f"weights must be ({V}, {J}), got {m.weights.shape}")
    if m.parents[0] != -1 or np.any(m.parents[1:] < 0) or np.any(m.parents[1:] >= np.arange(1, J)):
        fail(f"kintree_table parents must be -1 for the root and < child index, got {m.parents.tolist()}")
    if m.faces.ndim != 2 or m.faces.shape[1] != 3 or m.faces.min() < 0 or m.faces.max() >= V:
        fail(f"faces must be (F, 3) indices into {V} vertices")
    if m.hands_components.ndim != 2 or m.hands_components.shape[1] != 3 * (J - 1):
        fail(f"hands_components must be (C, {3 * (J - 1)}), got {m.hands_components.shape}")
    if m.hands_mean.shape != (3 * (J - 1),):
        fail(f"hands_mean must be ({3 * (J - 1)},), got {m.hands_mean.shape}")
    if m.side not in ("right", "left"):
        fail(f"side must be 'right' or 'left', got {m.side!r}")
    if m.tip_vertex_ids.shape != (5,) or m.tip_vertex_ids.min() < 0 or m.tip_vertex_ids.max() >= V:
        fail(f"tip_vertex_ids must be 5 indices into {V} vertices, got {m.tip_vertex_ids.tolist()}")
    for name, arr in (
        ("v_template", m.v_template),
        ("shapedirs", m.shapedirs),
        ("posedirs", m.posedirs),
        ("J_regressor", m.J_regressor),
        ("weights", m.weights),
        ("hands_components", m.hands_components),
        ("hands_mean", m.hands_mean),
    ):
        if not np.all(np.isfinite(arr)):
            fail(f"{name} contains NaN or inf")
    if np.abs(m.weights.sum(1) - 1.0).max() > 1e-3:
        fail("skinning weights rows must sum to 1")
    if m.vertex_colors is not None and m.vertex_colors.shape != (V, 3):
        fail(f"vertex_colors must be ({V}, 3), got {m.vertex_colors.shape}")
    for key, ids in m.contact_vertex_ids.items():
        if ids.ndim != 1 or (ids.size and (ids.min() < 0 or ids.max() >= V)):
            fail(f"contact_vertex_ids[{key!r}] must be indices into {V} vertices")


def reorder_vertices(model: ManoModelData, order: np.ndarray) -> ManoModelData:
    """The same hand with its vertices renumbered: new vertex ``i`` is old vertex ``order[i]``.

    Every per-vertex array follows (``v_template``, ``shapedirs``, ``posedirs``,
    ``weights``, ``J_regressor`` columns, vertex colours) and every vertex id is remapped
    (faces, fingertips, contact sets), so the posed mesh and the joints are unchanged up to
    the renumbering.

    Args:
        model: the hand.
        order: (V,) a permutation of ``0 .. V-1``.

    Raises:
        ValueError: ``order`` is not a permutation of the model's vertex ids.
    """
    order = np.asarray(order, dtype=np.int64)
    V = model.num_verts
    if order.shape != (V,) or not np.array_equal(np.sort(order), np.arange(V)):
        raise ValueError(f"order must be a permutation of the {V} vertex ids")
    new_id = np.empty(V, dtype=np.int64)
    new_id[order] = np.arange(V)
    colors = model.vertex_colors
    return model.replace(
        v_template=model.v_template[order],
        shapedirs=model.shapedirs[order],
        posedirs=model.posedirs[order],
        J_regressor=model.J_regressor[:, order],
        weights=model.weights[order],
        faces=new_id[model.faces],
        tip_vertex_ids=new_id[model.tip_vertex_ids],
        contact_vertex_ids={k: np.sort(new_id[v]) for k, v in model.contact_vertex_ids.items()},
        vertex_colors=None if colors is None else colors[order],
    )


# ----------------------------------------------------------------------------------------
# Loading
# ----------------------------------------------------------------------------------------
def _side_from_name(path: str) -> Optional[str]:
    base = os.path.basename(path).upper()
    if "RIGHT" in base:
        return "right"
    if "LEFT" in base:
        return "left"
    return None


def _read_pickle(path: str) -> dict:
    try:
        with open(path, "rb") as fh:
            data = RestrictedUnpickler(fh, path).load()
    except AssetError:  # refused global, element / depth caps
        raise
    except (
        pickle.UnpicklingError,
        EOFError,
        ValueError,
        TypeError,
        AttributeError,
        IndexError,
        LookupError,
        RecursionError,
        MemoryError,
    ) as exc:
        raise AssetError(path, f"not a readable MANO pickle ({type(exc).__name__}: {exc})") from None
    if not isinstance(data, dict):
        raise AssetError(path, f"expected a dict of arrays at the top level, found {type(data).__name__}")
    return data


def _read_npz(path: str) -> dict:
    try:
        with np.load(path, allow_pickle=False) as z:
            data = {k: z[k] for k in z.files}
    except ValueError as exc:
        raise AssetError(path, f"npz holds pickled objects, which are not allowed ({exc})") from None
    except (OSError, EOFError) as exc:
        raise AssetError(path, f"not a readable npz file ({exc})") from None
    if META_KEY in data:  # stored as a JSON string inside the npz
        data[META_KEY] = json.loads(str(data[META_KEY]))
    return data


def _meta_arrays(meta: Mapping[str, Any]) -> dict:
    return {k: np.asarray(v, dtype=np.int64) for k, v in (meta.get("contact_vertex_ids") or {}).items()}


def model_from_dict(
    data: Mapping[str, Any],
    source: str = "",
    side: Optional[str] = None,
    tip_vertex_ids: Optional[tuple[int, ...]] = None,
) -> ManoModelData:
    """Build and validate a :class:`ManoModelData` from a MANO-schema dict.

    Args:
        data: the unpickled (or npz) dict: MANO keys, chumpy stubs and sparse allowed.
        source: file name used in error messages.
        side: ``"right"``/``"left"``; default from the metadata, then the file name.
        tip_vertex_ids: override of the fingertip vertices (thumb..pinky).
    """
    where = source or "<MANO dict>"
    try:
        return _model_from_dict(data, where, source, side, tip_vertex_ids)
    except AssetError:
        raise
    # whatever a malformed (or crafted) file makes numpy/scipy raise
    except (ValueError, TypeError, AttributeError, LookupError, RecursionError, MemoryError) as exc:
        raise AssetError(where, f"not a readable MANO model ({type(exc).__name__}: {str(exc)[:200]})") from None


def _model_from_dict(
    data: Mapping[str, Any], where: str, source: str, side: Optional[str], tip_vertex_ids: Optional[tuple[int, ...]]
) -> ManoModelData:
    missing = [k for k in _REQUIRED_KEYS if k not in data]
    if missing:
        raise AssetError(where, f"missing MANO keys {missing}")
    arr = {k: as_array(data[k], f"{where}[{k}]") for k in _REQUIRED_KEYS}
    meta = dict(data.get(META_KEY) or {})
    if not isinstance(meta, dict):
        raise AssetError(where, f"{META_KEY} must be a dict")
    kintree = arr["kintree_table"].astype(np.int64)
    if kintree.ndim != 2 or kintree.shape[0] != 2:
        raise AssetError(where, f"kintree_table must be (2, J), got {kintree.shape}")
    parents = kintree[0].copy()
    parents[0] = -1  # the release stores a large sentinel for the root
    side = side or meta.get("side") or _side_from_name(where)
    if side is None:
        raise AssetError(where, "cannot tell the hand side: name the file *RIGHT*/*LEFT* or pass side=")
    V = arr["v_template"].shape[0]
    if tip_vertex_ids is None:
        if "tip_vertex_ids" in meta:
            tip_vertex_ids = tuple(meta["tip_vertex_ids"])
        elif V == MANO_RELEASE_NUM_VERTS:
            tip_vertex_ids = MANO_RELEASE_TIP_IDS[side]
        else:
            raise AssetError(
                where,
                f"model has {V} vertices and no fingertip metadata ('{META_KEY}.tip_vertex_ids'); "
                "pass tip_vertex_ids=(thumb, index, middle, ring, pinky)",
            )
    coeffs = data.get("hands_coeffs")
    colors = meta.get("vertex_colors")
    model = ManoModelData(
        v_template=arr["v_template"].astype(np.float64),
        shapedirs=arr["shapedirs"].astype(np.float64),
        posedirs=arr["posedirs"].astype(np.float64),
        J_regressor=arr["J_regressor"].astype(np.float64),
        weights=arr["weights"].astype(np.float64),
        parents=parents,
        faces=arr["f"].astype(np.int64),
        hands_components=arr["hands_components"].astype(np.float64),
        hands_mean=arr["hands_mean"].astype(np.float64).reshape(-1),
        hands_coeffs=None if coeffs is None else as_array(coeffs, where).astype(np.float64),
        side=side,
        tip_vertex_ids=np.asarray(tip_vertex_ids, dtype=np.int64),
        contact_vertex_ids=_meta_arrays(meta),
        vertex_colors=None if colors is None else np.asarray(colors, dtype=np.float64),
        meta={k: v for k, v in meta.items() if k not in ("vertex_colors", "contact_vertex_ids")},
        source=source,
    )
    validate_model(model)
    return model


def load_mano(
    path: PathLike, side: Optional[str] = None, tip_vertex_ids: Optional[tuple[int, ...]] = None
) -> ManoModelData:
    """Load a MANO model from a ``.pkl`` (restricted unpickler) or a converted ``.npz``.

    Args:
        path: ``MANO_RIGHT.pkl`` / ``MANO_LEFT.pkl`` (real or project-generated), a ``.npz``
            written by :func:`convert_mano_to_npz`, or a folder holding ``MANO_<SIDE>.pkl``
            (then ``side`` is required).
        side: ``"right"``/``"left"``; inferred from metadata or the file name when omitted.
        tip_vertex_ids: override of the five fingertip vertices (thumb..pinky).

    Raises:
        AssetError: missing file, unreadable content, wrong shapes (message names the file).
        UnsafePickleError: the pickle references a global outside the allow-list.
    """
    p = os.fspath(path)
    if os.path.isdir(p):
        if side not in ("right", "left"):
            raise AssetError(p, "a folder was given: pass side='right' or 'left'")
        cands = [os.path.join(p, f"MANO_{side.upper()}.{ext}") for ext in ("pkl", "npz")]
        found = [c for c in cands if os.path.isfile(c)]
        if not found:
            raise AssetError(p, f"no MANO_{side.upper()}.pkl or .npz in this folder")
        p = found[0]
    if not os.path.isfile(p):
        raise AssetError(
            p,
            "MANO model file not found (MANO cannot be downloaded here: "
            "register at mano.is.tue.mpg.de, or run `hogsa assets` for the synthetic hand)",
        )
    data = _read_npz(p) if p.endswith(".npz") else _read_pickle(p)
    return model_from_dict(data, source=p, side=side, tip_vertex_ids=tip_vertex_ids)


# ----------------------------------------------------------------------------------------
# Release schema
# ----------------------------------------------------------------------------------------
def schema_dict(m: ManoModelData) -> dict[str, Any]:
    """``m`` as the MANO release's dictionary (``f``, ``J_regressor`` as CSC, ``kintree_table``
    with the uint32 root sentinel, ``J``, ``weights``, ``posedirs``, ``shapedirs``, ...), with
    the project's metadata (side, fingertips, contact sets, colours) under ``hogsa_meta``."""
    kintree = np.stack([m.parents, np.arange(m.num_joints)]).astype(np.int64)
    kintree[0, 0] = 4294967295  # the release's root sentinel (uint32 -1)
    meta = dict(m.meta)
    meta.update(
        side=m.side,
        tip_vertex_ids=[int(i) for i in m.tip_vertex_ids],
        contact_vertex_ids={k: [int(i) for i in v] for k, v in m.contact_vertex_ids.items()},
    )
    if m.vertex_colors is not None:
        meta["vertex_colors"] = np.round(m.vertex_colors, 6).tolist()
    out: dict[str, Any] = {
        "hands_components": m.hands_components,
        "f": m.faces.astype(np.uint32),
        "J_regressor": sp.csc_matrix(m.J_regressor),
        "kintree_table": kintree,
        "J": m.J_regressor @ m.v_template,
        "bs_style": "lbs",
        "hands_coeffs": m.hands_coeffs if m.hands_coeffs is not None else np.zeros((0, m.hands_mean.shape[0])),
        "weights": m.weights,
        "posedirs": m.posedirs,
        "hands_mean": m.hands_mean,
        "v_template": m.v_template,
        "shapedirs": m.shapedirs,
        "bs_type": "lrotmin",
        META_KEY: meta,
    }
    return out


def check_npz_destination(src: PathLike, dst: PathLike, overwrite: bool = False) -> None:
    """Refuse a destination :func:`convert_mano_to_npz` must not write.

    Raises:
        AssetError: ``dst`` does not end in ``.npz`` (:func:`load_mano` tells the formats
            apart by it), is a folder, is ``src`` itself, or exists and not ``overwrite``.
    """
    out = os.fspath(dst)
    if not out.endswith(".npz"):
        raise AssetError(out, "the converted model must be a .npz file (load_mano reads .npz by its suffix)")
    if os.path.isdir(out):
        raise AssetError(out, "is a folder; give the .npz file to write")
    if os.path.lexists(out):
        if os.path.exists(src) and os.path.exists(out) and os.path.samefile(src, out):
            raise AssetError(out, "is the source model itself")
        if not overwrite:
            raise AssetError(out, "already exists (overwrite=True, or hogsa convert-mano --overwrite, replaces it)")


def convert_mano_to_npz(
    src: PathLike, dst: PathLike, side: Optional[str] = None, overwrite: bool = False
) -> ManoModelData:
    """Convert a MANO pickle into a chumpy-free, pickle-free ``.npz`` (smplx-compatible keys).

    ``dst`` is checked before anything is read (:func:`check_npz_destination`) and written
    atomically: a temporary file next to it, removed when writing fails.

    Returns the loaded model. The npz holds dense arrays only; the metadata is a JSON string.
    """
    check_npz_destination(src, dst, overwrite)
    model = load_mano(src, side=side)
    d = schema_dict(model)
    d["J_regressor"] = model.J_regressor
    d[META_KEY] = json.dumps(d[META_KEY])
    d["bs_style"] = np.array("lbs")
    d["bs_type"] = np.array("lrotmin")
    d["f"] = model.faces.astype(np.int64)
    out = os.fspath(dst)
    os.makedirs(os.path.dirname(os.path.abspath(out)), exist_ok=True)
    with atomic_open(out) as fh:
        np.savez(fh, **d)
    return model
