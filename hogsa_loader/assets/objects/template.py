"""ARCTIC object templates: reading ``meta/object_vtemplates/<obj>/``.

Part labels follow the **code** convention of ARCTIC (its ``data_doc.md`` states the
opposite): in ``parts.json`` **0 = top (articulated) and 1 = bottom (base)**; the object
layer adds 1 (``parts_ids``), so ``parts_ids == 1`` is the top and ``parts_ids == 2`` the
bottom. In memory every length is in metres (the files are in mm and are divided by 1000
on load, as ARCTIC's ``ObjectTensors`` does), in the object's canonical frame whose z axis
is the articulation axis.
"""

from __future__ import annotations

import copy
import hashlib
import json
import math
import threading
from collections import OrderedDict
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterable, Mapping, Optional, Sequence

import cv2
import numpy as np

from hogsa_loader.errors import AssetError, PathLike, read_json

__all__ = [
    "OBJECT_NAMES",
    "TOP",
    "BOTTOM",
    "BBOX_CORNER_ORDER",
    "ObjectTemplate",
    "ObjectTemplates",
    "load_object_template",
    "load_object_templates",
    "read_object_meta",
    "sort_names",
    "bbox_corners",
    "farthest_point_sampling",
    "max_pairwise_distance",
]

#: ARCTIC's 11 objects; the position in this tuple is ARCTIC's object index
#: (``common/object_tensors.py`` ``OBJECTS``).
OBJECT_NAMES: tuple[str, ...] = (
    "capsulemachine",
    "box",
    "ketchup",
    "laptop",
    "microwave",
    "mixer",
    "notebook",
    "espressomachine",
    "waffleiron",
    "scissors",
    "phone",
)

#: ``parts.json`` value of the articulated (top) part (ARCTIC code convention).
TOP = 0
#: ``parts.json`` value of the base (bottom) part (ARCTIC code convention).
BOTTOM = 1

#: Order of the 8 corners written by :func:`bbox_corners`: corner ``k`` takes the max of
#: x if ``k & 4``, of y if ``k & 2`` and of z if ``k & 1`` (the min otherwise), i.e.
#: ``itertools.product((xmin, xmax), (ymin, ymax), (zmin, zmax))``.
BBOX_CORNER_ORDER = "itertools.product((xmin,xmax),(ymin,ymax),(zmin,zmax))"

MESH_FILE = "mesh.obj"
PARTS_FILE = "parts.json"
PARAMS_FILE = "object_params.json"
TOP300_FILE = "top_keypoints_300.json"
BOTTOM300_FILE = "bottom_keypoints_300.json"
TEX_MESH_FILE = "mesh_tex.obj"
TEX_IMAGE_FILE = "material.jpg"
TEX_MTL_FILE = "material.mtl"
OBJECT_META_FILE = "object_meta.json"
VTEMPLATES_DIR = "object_vtemplates"

MM_PER_M = 1000.0
NUM_KEYPOINTS = 16
NUM_SUB = 300


# --------------------------------------------------------------------------------------
# Data class
# --------------------------------------------------------------------------------------


@dataclass
class ObjectTemplate:
    """One articulated object in its canonical frame (metres, numpy arrays).

    Attributes:
        name: object name (e.g. ``"box"``).
        verts: (V, 3) float32 ``mesh.obj`` vertices.
        faces: (F, 3) int64 triangles into ``verts``.
        parts: (V,) int64 ``parts.json`` labels, 0 = top (articulated), 1 = bottom.
        kp_top, kp_bottom: (16, 3) keypoints of each part.
        bbox_top, bbox_bottom: (8, 3) box corners of each part (order:
            :data:`BBOX_CORNER_ORDER` for the templates this project generates; read as
            stored for real ARCTIC files).
        mocap_top, mocap_bottom: (M, 3) MoCap marker positions (M may be 0).
        sub_top, sub_bottom: (300, 3) farthest-point samples of each part.
        diameter: metres, from ``object_meta.json`` when known, else the largest
            distance between two vertices.
        tex_verts: optional (Vt, 3) float32 vertices of the textured mesh.
        tex_faces: optional (Ft, 3) int64 triangles into ``tex_verts``.
        tex_uv: optional (Vt, 2) float32 texture coordinates, OBJ convention (origin at
            the bottom-left of the image, v pointing up).
        texture: optional (H, W, 3) uint8 RGB image.
        tex_parts: optional (Vt,) int64 part labels of the textured vertices (0/1 as
            ``parts``).
    """

    name: str
    verts: np.ndarray
    faces: np.ndarray
    parts: np.ndarray
    kp_top: np.ndarray
    kp_bottom: np.ndarray
    bbox_top: np.ndarray
    bbox_bottom: np.ndarray
    mocap_top: np.ndarray
    mocap_bottom: np.ndarray
    sub_top: np.ndarray
    sub_bottom: np.ndarray
    diameter: float
    tex_verts: Optional[np.ndarray] = None
    tex_faces: Optional[np.ndarray] = None
    tex_uv: Optional[np.ndarray] = None
    texture: Optional[np.ndarray] = None
    tex_parts: Optional[np.ndarray] = None

    def __post_init__(self) -> None:
        f32 = np.float32
        self.verts = np.ascontiguousarray(self.verts, dtype=f32).reshape(-1, 3)
        self.faces = np.ascontiguousarray(self.faces, dtype=np.int64).reshape(-1, 3)
        self.parts = np.ascontiguousarray(self.parts, dtype=np.int64).reshape(-1)
        for key in (
            "kp_top",
            "kp_bottom",
            "bbox_top",
            "bbox_bottom",
            "mocap_top",
            "mocap_bottom",
            "sub_top",
            "sub_bottom",
        ):
            setattr(self, key, np.ascontiguousarray(getattr(self, key), dtype=f32).reshape(-1, 3))
        self.diameter = float(self.diameter)
        if self.tex_verts is not None:
            self.tex_verts = np.ascontiguousarray(self.tex_verts, dtype=f32).reshape(-1, 3)
            self.tex_faces = np.ascontiguousarray(self.tex_faces, dtype=np.int64).reshape(-1, 3)
            self.tex_uv = np.ascontiguousarray(self.tex_uv, dtype=f32).reshape(-1, 2)
            self.texture = np.ascontiguousarray(self.texture, dtype=np.uint8)
            if self.tex_parts is not None:
                self.tex_parts = np.ascontiguousarray(self.tex_parts, dtype=np.int64).reshape(-1)
        if self.parts.shape[0] != self.verts.shape[0]:
            raise ValueError(
                f"object {self.name!r}: {self.parts.shape[0]} part labels for {self.verts.shape[0]} vertices"
            )

    @property
    def has_texture(self) -> bool:
        """True when a textured mesh and its image are attached."""
        return self.tex_verts is not None and self.texture is not None

    def part_mesh(self, part: int) -> tuple[np.ndarray, np.ndarray]:
        """Sub-mesh of one part (faces whose three vertices carry label ``part``).

        Args:
            part: :data:`TOP` (0) or :data:`BOTTOM` (1).

        Returns:
            (Vp, 3) float32 vertices and (Fp, 3) int64 faces re-indexed into them.
        """
        keep = self.parts == part
        face_keep = keep[self.faces].all(axis=1)
        new_index = np.cumsum(keep) - 1
        return self.verts[keep], new_index[self.faces[face_keep]]

    def part_points(self, part: int) -> np.ndarray:
        """(Vp, 3) vertices of one part (0 = top, 1 = bottom)."""
        return self.verts[self.parts == part]


# --------------------------------------------------------------------------------------
# Small geometric helpers shared with the procedural generator
# --------------------------------------------------------------------------------------


def bbox_corners(points: np.ndarray) -> np.ndarray:
    """The 8 corners of the axis-aligned box of ``points``.

    Args:
        points: (N, 3) points.

    Returns:
        (8, 3) corners; corner ``k`` takes the max of x if ``k & 4``, of y if ``k & 2``,
        of z if ``k & 1`` (see :data:`BBOX_CORNER_ORDER`).
    """
    lo, hi = points.min(axis=0), points.max(axis=0)
    bits = (np.arange(8)[:, None] >> np.array([2, 1, 0])[None, :]) & 1
    return np.where(bits == 1, hi[None, :], lo[None, :])


def farthest_point_sampling(points: np.ndarray, k: int, start: Optional[int] = None) -> np.ndarray:
    """Deterministic farthest-point sampling.

    Args:
        points: (N, 3) candidate points.
        k: number of samples (``k <= N``).
        start: index of the first sample; default: the point farthest from the centroid.

    Returns:
        (k,) int64 indices into ``points``.
    """
    pts = np.asarray(points, dtype=np.float64)
    if k > pts.shape[0]:
        raise ValueError(f"cannot pick {k} samples out of {pts.shape[0]} points")
    if start is None:
        start = int(np.argmax(((pts - pts.mean(axis=0)) ** 2).sum(axis=1)))
    chosen = np.empty(k, dtype=np.int64)
    chosen[0] = start
    x, y, z = (np.ascontiguousarray(pts[:, j]) for j in range(3))

    def sq_dist(i: int) -> np.ndarray:  # summed x, y, z in order: equal to ((pts - p) ** 2).sum(1)
        return (x - x[i]) ** 2 + (y - y[i]) ** 2 + (z - z[i]) ** 2

    dist = sq_dist(start)
    for i in range(1, k):
        nxt = int(np.argmax(dist))
        chosen[i] = nxt
        np.minimum(dist, sq_dist(nxt), out=dist)
    return chosen


def max_pairwise_distance(points: np.ndarray) -> float:
    """Largest distance between two of ``points`` (via the convex hull).

    Args:
        points: (N, 3) points.

    Returns:
        the diameter of the point set, in the unit of ``points``.
    """
    from scipy.spatial import ConvexHull  # deferred: scipy.spatial adds ~1 s to every process importing templates
    from scipy.spatial.distance import pdist  # deferred: as above

    pts = np.asarray(points, dtype=np.float64)
    try:
        pts = pts[ConvexHull(pts).vertices]
    except Exception:  # degenerate (flat) sets: fall back to all points
        pass
    if pts.shape[0] < 2:
        return 0.0
    return float(pdist(pts).max())


# --------------------------------------------------------------------------------------
# Validation helpers (every failure is an AssetError naming the file)
# --------------------------------------------------------------------------------------


def _points(value: Any, path: Path, key: str, count: Optional[int]) -> np.ndarray:
    """Convert a JSON value to (count, 3) finite float64 points (mm)."""
    if isinstance(value, Mapping):  # marker dicts {name: xyz} keep their stored order
        value = list(value.values())
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise AssetError(path, f"{key!r} is not a list of numeric 3-vectors") from exc
    if arr.size == 0 and count is None:
        return np.zeros((0, 3))
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise AssetError(path, f"{key!r} has shape {arr.shape}, expected (N, 3)")
    if count is not None and arr.shape[0] != count:
        raise AssetError(path, f"{key!r} has {arr.shape[0]} points, expected {count}")
    if not np.isfinite(arr).all():
        raise AssetError(path, f"{key!r} contains NaN or infinite values")
    return arr


#: Largest mesh file read (an object template of a few hundred thousand faces is tens of MB;
#: a file past this would take gigabytes to parse).
MAX_MESH_BYTES = 128 * 2**20


def check_mesh_size(path: Path) -> None:
    """Refuse a mesh file larger than :data:`MAX_MESH_BYTES` before it is parsed.

    Raises:
        AssetError: the file is missing or too large (naming its size and the cap).
    """
    if not path.is_file():
        raise AssetError(path, "file is missing")
    size = path.stat().st_size
    if size > MAX_MESH_BYTES:
        raise AssetError(
            path, f"mesh file of {size} bytes, more than the {MAX_MESH_BYTES} read (simplify the mesh first)"
        )


def _read_obj(path: Path, keep_order: bool = True) -> Any:
    """Load an OBJ with trimesh (``process=False``).

    Args:
        keep_order: keep the file's vertex order (``mesh.obj``, whose ``parts.json`` labels
            follow it). A textured mesh is read with False: a vertex whose faces use
            several texture coordinates (``f a/b`` with different ``b`` at a UV seam, as
            scan meshes are written) is then split into one vertex per coordinate, where
            keeping the order would keep one coordinate per vertex and smear every face
            along the seam across the texture atlas.
    """
    import trimesh  # deferred: trimesh adds ~1-3 s to every process importing templates

    check_mesh_size(path)
    try:
        mesh = trimesh.load(str(path), process=False, force="mesh", maintain_order=keep_order, skip_materials=True)
    except Exception as exc:  # trimesh raises many kinds of errors on bad files
        raise AssetError(path, f"cannot parse mesh ({exc})") from exc
    verts = np.asarray(getattr(mesh, "vertices", np.zeros((0, 3))), dtype=np.float64)
    faces = np.asarray(getattr(mesh, "faces", np.zeros((0, 3))), dtype=np.int64)
    if verts.ndim != 2 or verts.shape[0] == 0 or faces.ndim != 2 or faces.shape[0] == 0:
        raise AssetError(path, "mesh has no vertices or no triangles")
    if faces.shape[1] != 3:
        raise AssetError(path, f"faces have {faces.shape[1]} corners, expected triangles")
    if not np.isfinite(verts).all():
        raise AssetError(path, "vertices contain NaN or infinite values")
    if faces.min() < 0 or faces.max() >= verts.shape[0]:
        raise AssetError(path, "a face refers to a vertex that does not exist")
    return mesh


def merge_uv_vertices(
    verts: np.ndarray, faces: np.ndarray, uv: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Merge vertices with the same position and texture coordinate (files that give every
    face corner its own ``vt``, read with seams split, would otherwise be triangle soups).
    Vertices keep the order of their first occurrence, so a mesh without such duplicates
    is returned unchanged.

    Args:
        verts: (V, 3); faces: (F, 3) int; uv: (V, 2).

    Returns:
        (V', 3) vertices, (F, 3) faces, (V', 2) UVs.
    """
    _, first, inv = np.unique(np.concatenate([verts, uv], 1), axis=0, return_index=True, return_inverse=True)
    if len(first) == len(verts):
        return verts, faces, uv
    order = np.argsort(first)  # unique rows by first occurrence
    rank = np.empty(len(first), dtype=np.int64)
    rank[order] = np.arange(len(first))
    keep = first[order]
    return verts[keep], rank[inv.reshape(-1)][faces], uv[keep]


def _read_parts(path: Path, num_verts: int) -> np.ndarray:
    """Read and check ``parts.json`` against the vertex count of ``mesh.obj``."""
    raw = read_json(path)
    if not isinstance(raw, list):
        raise AssetError(path, f"expected a JSON list of part labels, got {type(raw).__name__}")
    try:
        arr = np.asarray(raw, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError) as exc:
        raise AssetError(path, "part labels must be numbers") from exc
    if arr.shape[0] != num_verts:
        raise AssetError(path, f"has {arr.shape[0]} labels but {MESH_FILE} has {num_verts} vertices")
    if not np.isin(arr, (TOP, BOTTOM)).all():
        bad = np.unique(arr[~np.isin(arr, (TOP, BOTTOM))])[:5]
        raise AssetError(path, f"labels must be 0 (top) or 1 (bottom), found {bad.tolist()}")
    parts = arr.astype(np.int64)
    for label, word in ((TOP, "top"), (BOTTOM, "bottom")):
        if not (parts == label).any():
            raise AssetError(path, f"the {word} part (label {label}) has no vertex")
    return parts


def _read_sub(path: Path) -> np.ndarray:
    """Read ``{"keypoints": 300x3}`` (mm)."""
    raw = read_json(path)
    if not isinstance(raw, Mapping) or "keypoints" not in raw:
        raise AssetError(path, 'expected a JSON object with key "keypoints"')
    return _points(raw["keypoints"], path, "keypoints", NUM_SUB)


def _read_texture(folder: Path, verts_mm: np.ndarray, parts: np.ndarray) -> dict[str, Any]:
    """Read ``mesh_tex.obj`` + ``material.jpg``; label textured vertices by nearest vertex."""
    from scipy.spatial import cKDTree  # deferred: scipy.spatial adds ~1 s to every process importing templates

    obj_path = folder / TEX_MESH_FILE
    img_path = folder / TEX_IMAGE_FILE
    mesh = _read_obj(obj_path, keep_order=False)  # (seam vertices split: one UV per vertex)
    uv = getattr(mesh.visual, "uv", None)
    tex_verts = np.asarray(mesh.vertices, dtype=np.float64)
    if uv is None or np.asarray(uv).shape != (tex_verts.shape[0], 2):
        raise AssetError(obj_path, "textured mesh has no per-vertex texture coordinates (vt)")
    uv = np.asarray(uv, dtype=np.float64)
    if not np.isfinite(uv).all():
        raise AssetError(obj_path, "texture coordinates contain NaN or infinite values")
    tex_verts, tex_faces, uv = merge_uv_vertices(tex_verts, np.asarray(mesh.faces, dtype=np.int64), uv)
    if not img_path.is_file():
        raise AssetError(img_path, f"file is missing (needed by {TEX_MESH_FILE})")
    bgr = cv2.imread(str(img_path), cv2.IMREAD_COLOR)
    if bgr is None or bgr.ndim != 3:
        raise AssetError(img_path, "cannot decode image")
    _, nearest = cKDTree(verts_mm).query(tex_verts)
    return {
        "tex_verts": tex_verts / MM_PER_M,
        "tex_faces": tex_faces,
        "tex_uv": uv,
        "texture": np.ascontiguousarray(bgr[..., ::-1]),
        "tex_parts": parts[nearest],
    }


# --------------------------------------------------------------------------------------
# Loading
# --------------------------------------------------------------------------------------


def read_object_meta(path: PathLike) -> dict[str, dict[str, float]]:
    """Read ``meta/object_meta.json`` (``{obj: {"diameter": metres}}``).

    Args:
        path: the JSON file.

    Returns:
        ``{name: {"diameter": float}}``.
    """
    path = Path(path)
    raw = read_json(path)
    if not isinstance(raw, Mapping):
        raise AssetError(path, 'expected a JSON object {name: {"diameter": ...}}')
    out: dict[str, dict[str, float]] = {}
    for name, entry in raw.items():
        if not isinstance(entry, Mapping) or "diameter" not in entry:
            raise AssetError(path, f"entry {name!r} has no 'diameter'")
        try:
            diameter = float(entry["diameter"])
        except (TypeError, ValueError) as exc:
            raise AssetError(path, f"diameter of {name!r} is not a number") from exc
        if not math.isfinite(diameter) or diameter <= 0:
            raise AssetError(path, f"diameter of {name!r} must be finite and > 0, got {diameter}")
        out[str(name)] = dict(entry, diameter=diameter)
    return out


#: Templates kept in memory by :func:`load_object_template`, keyed by the folder, the
#: arguments and every file's name and content hash: a changed file is read again.
TEMPLATE_CACHE_SIZE = 64
_TEMPLATE_CACHE: "OrderedDict[tuple, ObjectTemplate]" = OrderedDict()
_TEMPLATE_CACHE_LOCK = threading.Lock()


def _folder_fingerprint(folder: Path) -> tuple[tuple[str, str], ...]:
    """``(name, BLAKE2b of the content)`` of every file directly in ``folder``, sorted by name
    (hashing a template's files costs milliseconds; parsing them, seconds)."""
    out = []
    try:
        for p in sorted(folder.iterdir()):
            if p.is_file():
                out.append((p.name, hashlib.blake2b(p.read_bytes(), digest_size=16).hexdigest()))
    except OSError as exc:
        raise AssetError(folder, f"cannot list the object template folder ({exc})") from None
    return tuple(out)


def load_object_template(
    folder: PathLike,
    name: Optional[str] = None,
    object_meta: Optional[Mapping[str, Mapping[str, Any]]] = None,
    load_texture: bool = True,
) -> ObjectTemplate:
    """Read one ARCTIC ``meta/object_vtemplates/<obj>/`` folder.

    The folder holds:

    ============================  ===========================================================
    file                          content (units as stored on disk)
    ============================  ===========================================================
    ``mesh.obj``                  the mesh all numbers refer to (mm), read with trimesh
                                  ``process=False``
    ``parts.json``                one int per ``mesh.obj`` vertex, values in {0, 1}
    ``object_params.json``        ``mocap_top``/``mocap_bottom`` (M,3), ``bbox_top``/
                                  ``bbox_bottom`` (8,3), ``keypoints_top``/
                                  ``keypoints_bottom`` (16,3), mm
    ``top_keypoints_300.json``    ``{"keypoints": 300x3}`` farthest-point samples of the top
    ``bottom_keypoints_300.json`` same for the bottom part
    ``top.obj``/``bottom.obj``    the two parts as separate meshes (mm, optional)
    ``mesh_tex.obj`` + ``material.mtl`` + ``material.jpg``  textured mesh (mm, optional)
    ============================  ===========================================================

    Args:
        folder: the object's folder.
        name: object name; default: the folder name.
        object_meta: parsed ``object_meta.json`` (see :func:`read_object_meta`); when it
            has an entry for ``name`` its diameter (metres) is used, otherwise the
            diameter is the largest vertex-to-vertex distance.
        load_texture: read ``mesh_tex.obj`` + ``material.jpg`` when ``mesh_tex.obj`` exists.

    A template read before is returned as a copy while none of the folder's files changed
    (names and contents).

    Returns:
        the template in metres (files are mm and divided by 1000).

    Raises:
        AssetError: a file is missing, malformed or inconsistent (the message names it).
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise AssetError(folder, "object template folder is missing")
    name = folder.name if name is None else name
    entry = None if object_meta is None else object_meta.get(name)
    key = (
        str(folder.resolve()),
        name,
        bool(load_texture),
        json.dumps(entry, sort_keys=True, default=str),
        _folder_fingerprint(folder),
    )
    with _TEMPLATE_CACHE_LOCK:
        cached = _TEMPLATE_CACHE.get(key)
        if cached is not None:
            _TEMPLATE_CACHE.move_to_end(key)
    if cached is not None:
        return copy.deepcopy(cached)
    template = _load_object_template(folder, name, object_meta, load_texture)
    with _TEMPLATE_CACHE_LOCK:
        _TEMPLATE_CACHE[key] = template
        while len(_TEMPLATE_CACHE) > TEMPLATE_CACHE_SIZE:
            _TEMPLATE_CACHE.popitem(last=False)
    return copy.deepcopy(template)


def _load_object_template(
    folder: Path, name: str, object_meta: Optional[Mapping[str, Mapping[str, Any]]], load_texture: bool
) -> ObjectTemplate:
    mesh = _read_obj(folder / MESH_FILE)
    verts_mm = np.asarray(mesh.vertices, dtype=np.float64)
    faces = np.asarray(mesh.faces, dtype=np.int64)
    parts = _read_parts(folder / PARTS_FILE, verts_mm.shape[0])

    params_path = folder / PARAMS_FILE
    params = read_json(params_path)
    if not isinstance(params, Mapping):
        raise AssetError(params_path, "expected a JSON object")
    expected = {
        "keypoints_top": NUM_KEYPOINTS,
        "keypoints_bottom": NUM_KEYPOINTS,
        "bbox_top": 8,
        "bbox_bottom": 8,
        "mocap_top": None,
        "mocap_bottom": None,
    }
    arrays: dict[str, np.ndarray] = {}
    for key, count in expected.items():
        if key not in params:
            raise AssetError(params_path, f"key {key!r} is missing")
        arrays[key] = _points(params[key], params_path, key, count)

    sub_top = _read_sub(folder / TOP300_FILE)
    sub_bottom = _read_sub(folder / BOTTOM300_FILE)

    if object_meta is not None and name in object_meta:
        diameter = float(object_meta[name]["diameter"])
    else:
        diameter = max_pairwise_distance(verts_mm) / MM_PER_M

    tex: dict[str, Any] = {}
    if load_texture and (folder / TEX_MESH_FILE).is_file():
        tex = _read_texture(folder, verts_mm, parts)

    m = 1.0 / MM_PER_M
    return ObjectTemplate(
        name=name,
        verts=verts_mm * m,
        faces=faces,
        parts=parts,
        kp_top=arrays["keypoints_top"] * m,
        kp_bottom=arrays["keypoints_bottom"] * m,
        bbox_top=arrays["bbox_top"] * m,
        bbox_bottom=arrays["bbox_bottom"] * m,
        mocap_top=arrays["mocap_top"] * m,
        mocap_bottom=arrays["mocap_bottom"] * m,
        sub_top=sub_top * m,
        sub_bottom=sub_bottom * m,
        diameter=diameter,
        **tex,
    )


def sort_names(names: Iterable[str]) -> list[str]:
    """ARCTIC objects first in ARCTIC index order, then any others alphabetically."""
    names = list(names)
    known = [n for n in OBJECT_NAMES if n in names]
    return known + sorted(n for n in names if n not in OBJECT_NAMES)


def load_object_templates(
    meta_dir: PathLike, names: Optional[Sequence[str]] = None, load_texture: bool = True
) -> dict[str, ObjectTemplate]:
    """Read every (or the named) object under ``meta_dir/object_vtemplates``.

    Args:
        meta_dir: ARCTIC's ``meta`` folder; ``meta_dir/object_meta.json`` is optional.
        names: objects to read; default: every sub-folder.
        load_texture: also read the textured meshes when present.

    Returns:
        ``{name: template}`` ordered as ARCTIC's object index (unknown names after,
        alphabetically) unless ``names`` gives an order.
    """
    meta_dir = Path(meta_dir)
    root = meta_dir / VTEMPLATES_DIR
    if not root.is_dir():
        raise AssetError(root, "object template folder is missing")
    meta_path = meta_dir / OBJECT_META_FILE
    meta = read_object_meta(meta_path) if meta_path.is_file() else None
    if names is None:
        names = sort_names(p.name for p in root.iterdir() if p.is_dir())
    out: dict[str, ObjectTemplate] = {}
    for name in names:
        out[name] = load_object_template(root / name, name=name, object_meta=meta, load_texture=load_texture)
    return out


class ObjectTemplates(Mapping[str, ObjectTemplate]):
    """``{name: ObjectTemplate}`` of ``meta_dir/object_vtemplates``, each object read when it is
    first asked for and then kept (a loader that models one object of ARCTIC's 11 reads that one).

    The names (the sub-folders, in ARCTIC's object order) and ``object_meta.json`` are read when
    the mapping is made; iterating over ``items()`` or ``values()`` reads every object.

    Args:
        meta_dir: ARCTIC's ``meta`` folder.
        load_texture: also read the textured meshes when present.
        textured: another mapping of the same folder made with ``load_texture=True``; an object
            it has read is taken from it (a textured template carries everything an untextured
            one does).

    Raises:
        AssetError: the folder or ``object_meta.json`` is unreadable (on creation); an
            object's files are missing or malformed (when that object is read; names the file).
    """

    def __init__(
        self, meta_dir: PathLike, load_texture: bool = True, textured: Optional["ObjectTemplates"] = None
    ) -> None:
        meta_dir = Path(meta_dir)
        self.folder = meta_dir / VTEMPLATES_DIR
        if not self.folder.is_dir():
            raise AssetError(self.folder, "object template folder is missing")
        meta_path = meta_dir / OBJECT_META_FILE
        self._meta = read_object_meta(meta_path) if meta_path.is_file() else None
        self._names = sort_names(p.name for p in self.folder.iterdir() if p.is_dir())
        self.load_texture = bool(load_texture)
        self._textured = textured
        self._read: dict[str, ObjectTemplate] = {}
        self._lock = threading.Lock()

    def __getstate__(self) -> dict[str, Any]:  # a copy (or a spawned worker's) gets its own lock
        state = dict(self.__dict__)
        del state["_lock"]
        return state

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.__dict__.update(state)
        self._lock = threading.Lock()

    def __getitem__(self, name: str) -> ObjectTemplate:
        with self._lock:
            if name not in self._read:
                if name not in self._names:
                    raise KeyError(name)
                if self._textured is not None and name in self._textured._read:
                    self._read[name] = self._textured._read[name]
                else:
                    self._read[name] = load_object_template(
                        self.folder / name, name=name, object_meta=self._meta, load_texture=self.load_texture
                    )
            return self._read[name]

    def __iter__(self):
        return iter(self._names)

    def __len__(self) -> int:
        return len(self._names)

    def __contains__(self, name: object) -> bool:
        return name in self._names

    def __repr__(self) -> str:
        return f"ObjectTemplates({str(self.folder)!r}, {len(self)} objects, {len(self._read)} read)"
