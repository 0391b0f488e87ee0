"""Mesh decimation maps of a world: ``meta/mano_decimator_195.npy`` and ``meta/downsamplers.npy``."""

from __future__ import annotations

from pathlib import Path
from typing import Any, Mapping

import numpy as np
from scipy.sparse import csr_matrix
from scipy.spatial import cKDTree

from hogsa_loader.assets.objects.template import ObjectTemplate, farthest_point_sampling
from hogsa_loader.errors import PathLike

__all__ = [
    "MANO_DECIMATOR_FILE",
    "DOWNSAMPLERS_FILE",
    "NUM_HAND_SUB",
    "selection_matrix",
    "mano_decimator",
    "object_downsamplers",
    "write_decimation_files",
]

MANO_DECIMATOR_FILE = "mano_decimator_195.npy"
DOWNSAMPLERS_FILE = "downsamplers.npy"
#: Sub-sampled hand vertices (ARCTIC's InterField uses 195).
NUM_HAND_SUB = 195


def selection_matrix(ids: np.ndarray, num_verts: int) -> np.ndarray:
    """(len(ids), num_verts) float32 matrix with ``D[i, ids[i]] = 1``, zeros elsewhere."""
    D = np.zeros((len(ids), num_verts), dtype=np.float32)
    D[np.arange(len(ids)), ids] = 1.0
    return D


def mano_decimator(models: Mapping[str, Any], num: int = NUM_HAND_SUB) -> dict[str, np.ndarray]:
    """Decimation of both hands to ``num`` farthest-point vertices of their rest meshes.

    Args:
        models: ``{"right": ManoModelData, "left": ManoModelData}`` (``v_template`` (V, 3)).
        num: sub-sampled vertices.

    Returns:
        ``{"D_right", "D_left"}`` (num, V) float32 and ``{"vertex_ids_right",
        "vertex_ids_left"}`` (num,) int64.
    """
    out: dict[str, np.ndarray] = {}
    for side in ("right", "left"):
        verts = np.asarray(models[side].v_template, dtype=np.float64)
        ids = farthest_point_sampling(verts, num)
        out[f"D_{side}"] = selection_matrix(ids, verts.shape[0])
        out[f"vertex_ids_{side}"] = ids.astype(np.int64)
    return out


def object_downsamplers(templates: Mapping[str, ObjectTemplate]) -> dict[str, dict[str, Any]]:
    """Per object, the sparse map from its mesh vertices to its 600 sub-sampled points.

    Args:
        templates: ``{name: ObjectTemplate}`` (``sub_top``/``sub_bottom`` (300, 3)).

    Returns:
        ``{name: {"D": csr_matrix (600, V) float32, "vertex_ids": (600,) int64}}``.
    """
    out: dict[str, dict[str, Any]] = {}
    for name, t in templates.items():
        sub = np.concatenate([t.sub_top, t.sub_bottom]).astype(np.float64)
        ids = cKDTree(t.verts.astype(np.float64)).query(sub)[1].astype(np.int64)
        rows = np.arange(len(ids))
        D = csr_matrix((np.ones(len(ids), dtype=np.float32), (rows, ids)), shape=(len(ids), t.verts.shape[0]))
        out[name] = {"D": D, "vertex_ids": ids}
    return out


def _save(path: Path, obj: Any) -> None:
    with open(path, "wb") as fh:
        np.save(fh, np.array(obj, dtype=object), allow_pickle=True)


def write_decimation_files(
    meta_dir: PathLike, models: Mapping[str, Any], templates: Mapping[str, ObjectTemplate]
) -> tuple[Path, Path]:
    """Write ``mano_decimator_195.npy`` and ``downsamplers.npy`` into ``meta_dir``.

    Both are ``np.save``-d 0-d object arrays holding a dict (ARCTIC reads them with
    ``np.load(path, allow_pickle=True).item()``). Every map is a decimation matrix ``D`` of
    shape (sub-sampled vertices, mesh vertices) whose rows each select one mesh vertex
    (a single 1 per row), so ``D @ verts`` gives the sub-sampled points and every row sums to 1.

    ``mano_decimator_195.npy``
        ``{"D_right": (195, V) float32, "D_left": (195, V) float32, "vertex_ids_right": (195,)
        int64, "vertex_ids_left": (195,) int64}``, V = the hand model's vertex count; the 195
        vertices are farthest-point samples of each side's rest mesh. Dense, because ARCTIC's
        ``MANODecimator`` turns every value whose key contains ``"D"`` into a
        ``torch.FloatTensor`` and batch-multiplies it with the (B, V, 3) MANO vertices.
    ``downsamplers.npy``
        ``{obj: {"D": scipy.sparse.csr_matrix (600, V_obj) float32, "vertex_ids": (600,)
        int64}}`` for every object template: row i selects the ``mesh.obj`` vertex nearest to
        sub-sampled point i of ``top_keypoints_300.json`` (rows 0-299) then
        ``bottom_keypoints_300.json`` (rows 300-599), the order of ``ObjectTensors``' ``v_sub``.
        Sparse, as a dense (600, V_obj) matrix per object would take megabytes.

    Returns:
        (decimator path, downsamplers path).
    """
    meta_dir = Path(meta_dir)
    meta_dir.mkdir(parents=True, exist_ok=True)
    hand, objects = meta_dir / MANO_DECIMATOR_FILE, meta_dir / DOWNSAMPLERS_FILE
    _save(hand, mano_decimator(models))
    _save(objects, object_downsamplers(templates))
    return hand, objects
