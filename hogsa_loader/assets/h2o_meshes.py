"""H2O object meshes as rigid :class:`~hogsa_loader.assets.objects.template.ObjectTemplate` objects.

H2O ships its 8 object meshes separately from the sequences, in metres, in the object
frame that ``obj_pose_rt`` poses. :func:`find_h2o_mesh` finds the file of a class,
:func:`load_h2o_object` reads it as a rigid template and :func:`h2o_mesh_provenance`
describes the file (path, sha256) for run manifests.
"""

from __future__ import annotations

import hashlib
from pathlib import Path
from typing import Any, Optional, Union

import numpy as np

from hogsa_loader.assets.objects.rigid import H2O_OBJECT_NAMES
from hogsa_loader.assets.objects.template import (
    BOTTOM,
    ObjectTemplate,
    bbox_corners,
    check_mesh_size,
    farthest_point_sampling,
    max_pairwise_distance,
    merge_uv_vertices,
)
from hogsa_loader.errors import AssetError, PathLike

__all__ = [
    "H2O_MESH_NAMES",
    "H2O_MESH_EXTENSIONS",
    "h2o_class_name",
    "h2o_mesh_candidates",
    "find_h2o_mesh",
    "load_h2o_object",
    "rigid_template",
    "h2o_mesh_provenance",
]

#: H2O class name (README) -> folder / file names used for its mesh (first: README name).
H2O_MESH_NAMES: dict[str, tuple[str, ...]] = {
    "book": ("book",),
    "espresso": ("espresso",),
    "lotion": ("lotion",),
    "spray": ("spray", "lotion_spray"),
    "milk": ("milk",),
    "cocoa": ("cocoa", "ovomaltine"),
    "chips": ("chips", "pringles"),
    "cappuccino": ("cappuccino", "starbucks"),
}
#: Mesh file extensions tried, in order.
H2O_MESH_EXTENSIONS: tuple[str, ...] = (".obj", ".ply")
#: Meshes larger than this (metres) are refused: H2O meshes are in metres, not mm.
MAX_DIAMETER_M = 1.5


def h2o_class_name(name: Union[str, int]) -> str:
    """The README class name of a class id (1..8), README name or mesh-name variant.

    Raises:
        ValueError: unknown name or id (lists the known names).
    """
    if isinstance(name, (int, np.integer)) or (isinstance(name, str) and name.isdigit()):
        cid = int(name)
        if 1 <= cid < len(H2O_OBJECT_NAMES):
            return H2O_OBJECT_NAMES[cid]
    else:
        for cls, variants in H2O_MESH_NAMES.items():
            if name in variants:
                return cls
    raise ValueError(
        f"unknown H2O object {name!r}; known: class ids 1..8 or {sorted(H2O_MESH_NAMES)} "
        f"(mesh names {sorted({v for vs in H2O_MESH_NAMES.values() for v in vs})})"
    )


def h2o_mesh_candidates(mesh_dir: PathLike, name: Union[str, int]) -> list[Path]:
    """Every path :func:`find_h2o_mesh` tries, in order (folder × file name × extension)."""
    variants = H2O_MESH_NAMES[h2o_class_name(name)]
    root = Path(mesh_dir)
    return [root / folder / f"{stem}{ext}" for folder in variants for stem in variants for ext in H2O_MESH_EXTENSIONS]


def find_h2o_mesh(mesh_dir: PathLike, name: Union[str, int]) -> Path:
    """The mesh file of an H2O class under ``mesh_dir`` (first existing candidate).

    The folder and file names differ between the public loaders, so this looks under
    ``<mesh_dir>/<folder>/<file>.{obj,ply}`` for every known name variant of a class
    (README name, h2oplayer name: e.g. cocoa = ``ovomaltine``, chips = ``pringles``,
    cappuccino = ``starbucks``, spray = ``lotion_spray``; HACO's
    ``spray/lotion_spray.obj`` is a folder/file mix, so every folder × file combination
    is tried).

    Raises:
        AssetError: ``mesh_dir`` is missing, or no candidate exists (lists the names tried).
    """
    root = Path(mesh_dir)
    if not root.is_dir():
        raise AssetError(root, "H2O object mesh folder not found")
    tried = h2o_mesh_candidates(root, name)
    for path in tried:
        if path.is_file():
            return path
    names = ", ".join(str(p.relative_to(root)) for p in tried)
    raise AssetError(root, f"no mesh for H2O object {h2o_class_name(name)!r}; tried {names}")


def _texture_image(mesh: Any) -> Optional[np.ndarray]:
    """(H, W, 3) uint8 RGB texture of a trimesh mesh, or None."""
    visual = getattr(mesh, "visual", None)
    if visual is None or getattr(visual, "kind", None) != "texture" or getattr(visual, "uv", None) is None:
        return None
    material = getattr(visual, "material", None)
    image = getattr(material, "image", None) or getattr(material, "baseColorTexture", None)
    if image is None:
        return None
    return np.array(image.convert("RGB"), dtype=np.uint8)  # a writable copy


def _spread(points: np.ndarray, k: int) -> np.ndarray:
    """(k, 3) farthest-point samples of ``points`` (cycled when there are fewer than k)."""
    n = points.shape[0]
    idx = farthest_point_sampling(points, min(k, n))
    return points[np.resize(idx, k)]


def rigid_template(
    name: str,
    verts: np.ndarray,
    faces: np.ndarray,
    *,
    tex_verts: Optional[np.ndarray] = None,
    tex_faces: Optional[np.ndarray] = None,
    tex_uv: Optional[np.ndarray] = None,
    texture: Optional[np.ndarray] = None,
) -> ObjectTemplate:
    """A rigid :class:`ObjectTemplate` (all bottom part; see :func:`load_h2o_object`).

    Args:
        name: object name.
        verts: (V, 3) metres; faces: (F, 3).
        tex_verts, tex_faces, tex_uv, texture: optional textured mesh (OBJ uv convention)
            and its (H, W, 3) uint8 RGB image.
    """
    verts = np.asarray(verts, dtype=np.float64)
    kp = _spread(verts, 16)
    sub = _spread(verts, 300)
    box = bbox_corners(verts)
    tex: dict[str, Any] = {}
    if tex_verts is not None and texture is not None:
        tex = dict(
            tex_verts=tex_verts,
            tex_faces=tex_faces,
            tex_uv=tex_uv,
            texture=texture,
            tex_parts=np.full(len(tex_verts), BOTTOM, dtype=np.int64),
        )
    return ObjectTemplate(
        name=name,
        verts=verts,
        faces=faces,
        parts=np.full(len(verts), BOTTOM, dtype=np.int64),
        kp_top=kp,
        kp_bottom=kp,
        bbox_top=box,
        bbox_bottom=box,
        mocap_top=np.zeros((0, 3)),
        mocap_bottom=np.zeros((0, 3)),
        sub_top=sub,
        sub_bottom=sub,
        diameter=max_pairwise_distance(verts),
        **tex,
    )


def load_h2o_object(mesh_dir: PathLike, name: Union[str, int], *, load_texture: bool = True) -> ObjectTemplate:
    """Find and read the mesh of an H2O class as a rigid template named by its class.

    Returns the mesh as a *rigid* template that the articulated
    machinery (``ObjectGaussians``, ``HogsModel``, checkpoints) takes unchanged:

    * every vertex and face is in the **bottom** part (``parts == BOTTOM``; the top part is
      empty), so the articulation ``R_z(-θ)`` never moves anything (H2O's θ is always 0);
      rendered part masks show the object as "object bottom" (id 4);
    * ``verts``/``faces``: the mesh with coincident vertices welded (UV seams split them in
      an OBJ); with a UV texture (an OBJ's ``map_Kd`` image, a PLY's texture file) the unwelded
      mesh is kept as the textured mesh (``tex_verts``/``tex_faces``/``tex_uv``/``texture``,
      all bottom) that ``ObjectGaussians`` binds to and takes its initial colours from;
      a mesh without a texture (e.g. vertex colours only) starts from a constant grey;
    * the ARCTIC-shaped point sets keep their shapes (16 + 16 keypoints, 8 + 8 box corners,
      300 + 300 samples): a rigid object's "top" and "bottom" sets are the same points
      (farthest-point samples of the vertices, box corners of the vertices);
    * ``diameter``: the largest vertex distance.

    Args:
        mesh_dir: the folder holding the per-object mesh folders.
        name: class id (1..8), README name or mesh-name variant.
        load_texture: keep the UV texture when the mesh has one.

    Raises:
        AssetError: no mesh (names tried), unreadable mesh, no triangles, non-finite
            values, or a size that is not in metres.
    """
    import trimesh  # deferred: trimesh adds ~1-3 s to every process importing objects

    cls = h2o_class_name(name)
    path = find_h2o_mesh(mesh_dir, cls)
    check_mesh_size(path)
    try:
        # (maintain_order=False: an OBJ vertex with several texture coordinates at a UV
        # seam is split, one per coordinate; the geometry is welded below anyway)
        mesh = trimesh.load(str(path), process=False, force="mesh", maintain_order=False)
    except Exception as exc:  # trimesh raises many kinds of errors on bad files
        raise AssetError(path, f"cannot parse mesh ({exc})") from exc
    verts = np.asarray(getattr(mesh, "vertices", np.zeros((0, 3))), dtype=np.float64)
    faces = np.asarray(getattr(mesh, "faces", np.zeros((0, 3))), dtype=np.int64)
    if verts.ndim != 2 or len(verts) == 0 or faces.ndim != 2 or len(faces) == 0 or faces.shape[1] != 3:
        raise AssetError(path, "mesh has no vertices or no triangles")
    if not np.isfinite(verts).all():
        raise AssetError(path, "vertices contain NaN or infinite values")
    welded = trimesh.Trimesh(verts, faces, process=True)
    w_verts = np.asarray(welded.vertices, dtype=np.float64)
    size = float(np.ptp(w_verts, axis=0).max())
    if size > MAX_DIAMETER_M:
        raise AssetError(path, f"mesh is {size:.1f} units across; H2O meshes are in metres (millimetres given?)")
    tex: dict[str, Any] = {}
    image = _texture_image(mesh) if load_texture else None
    if image is not None:
        tv, tf, tuv = merge_uv_vertices(verts, faces, np.asarray(mesh.visual.uv, dtype=np.float64))
        tex = dict(tex_verts=tv, tex_faces=tf, tex_uv=tuv, texture=image)
    return rigid_template(cls, w_verts, np.asarray(welded.faces, dtype=np.int64), **tex)


def h2o_mesh_provenance(mesh_dir: PathLike, name: Union[str, int]) -> dict[str, str]:
    """``{"mesh", "sha256", "h2o_class"}`` of the mesh file :func:`find_h2o_mesh` picks."""
    path = find_h2o_mesh(mesh_dir, name)
    digest = hashlib.sha256(path.read_bytes()).hexdigest()
    return {"mesh": str(path.resolve()), "sha256": digest, "h2o_class": h2o_class_name(name)}
