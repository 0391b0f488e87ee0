"""ARCTIC's object files, written: an :class:`~hogsa_loader.assets.objects.template.ObjectTemplate`
as an ``object_vtemplates/<obj>/`` folder (mm) and ``meta/object_meta.json``, the layout the
template reader takes, for the generated world's objects."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Iterable, Optional

import cv2
import numpy as np

from hogsa_loader.assets.objects.template import (
    BOTTOM,
    BOTTOM300_FILE,
    MESH_FILE,
    MM_PER_M,
    OBJECT_META_FILE,
    PARAMS_FILE,
    PARTS_FILE,
    TEX_IMAGE_FILE,
    TEX_MESH_FILE,
    TEX_MTL_FILE,
    TOP,
    TOP300_FILE,
    ObjectTemplate,
    read_object_meta,
    sort_names,
)
from hogsa_loader.errors import AssetError, PathLike

__all__ = ["write_object_meta", "write_object_template"]

#: JPEG quality of a written texture (byte-reproducible for the same image).
JPEG_QUALITY = 95


def _fmt_rows(rows: np.ndarray, prefix: str) -> str:
    """Lines ``prefix a b c`` with 6 decimals (mm -> nanometre resolution)."""
    cols = rows.shape[1]
    fmt = prefix + " " + " ".join(["%.6f"] * cols) + "\n"
    return (fmt * rows.shape[0]) % tuple(rows.ravel().tolist())  # one formatting call


def _obj_text(
    verts_mm: np.ndarray, faces: np.ndarray, uv: Optional[np.ndarray] = None, mtl: Optional[str] = None
) -> str:
    """Wavefront OBJ text; with ``uv`` the ``vt`` indices equal the ``v`` indices."""
    lines = []
    if mtl is not None:
        lines.append(f"mtllib {mtl}\nusemtl material_0\n")
    lines.append(_fmt_rows(verts_mm.astype(np.float64), "v"))
    f1 = faces.astype(np.int64) + 1
    if uv is not None:
        lines.append(_fmt_rows(uv.astype(np.float64), "vt"))
        lines.append(("f %d/%d %d/%d %d/%d\n" * len(f1)) % tuple(np.repeat(f1, 2, axis=1).ravel().tolist()))
    else:
        lines.append(("f %d %d %d\n" * len(f1)) % tuple(f1.ravel().tolist()))
    return "".join(lines)


def _json_points(points_m: np.ndarray) -> list[list[float]]:
    """Metres -> mm lists rounded to 6 decimals (stable, byte-reproducible JSON)."""
    mm = np.asarray(points_m, dtype=np.float64).reshape(-1, 3) * MM_PER_M
    return [[round(float(x), 6) for x in row] for row in mm]


def _write_text(path: Path, text: str) -> None:
    with open(path, "w", encoding="utf-8", newline="\n") as fh:
        fh.write(text)


def write_object_template(template: ObjectTemplate, folder: PathLike) -> Path:
    """Write ``template`` in the ARCTIC ``object_vtemplates/<obj>/`` layout (mm).

    Writes ``mesh.obj``, ``parts.json``, ``object_params.json``,
    ``top_keypoints_300.json``, ``bottom_keypoints_300.json``, ``top.obj``,
    ``bottom.obj`` and, when a textured mesh is attached, ``mesh_tex.obj``,
    ``material.mtl`` and ``material.jpg`` (JPEG quality 95, byte-reproducible).

    Args:
        template: the object (metres).
        folder: destination folder (created).

    Returns:
        the folder.
    """
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    verts_mm = template.verts.astype(np.float64) * MM_PER_M

    _write_text(folder / MESH_FILE, _obj_text(verts_mm, template.faces))
    _write_text(folder / PARTS_FILE, json.dumps([int(p) for p in template.parts]))
    params = {
        "mocap_top": _json_points(template.mocap_top),
        "mocap_bottom": _json_points(template.mocap_bottom),
        "bbox_top": _json_points(template.bbox_top),
        "bbox_bottom": _json_points(template.bbox_bottom),
        "keypoints_top": _json_points(template.kp_top),
        "keypoints_bottom": _json_points(template.kp_bottom),
    }
    _write_text(folder / PARAMS_FILE, json.dumps(params))
    _write_text(folder / TOP300_FILE, json.dumps({"keypoints": _json_points(template.sub_top)}))
    _write_text(folder / BOTTOM300_FILE, json.dumps({"keypoints": _json_points(template.sub_bottom)}))
    for part, fname in ((TOP, "top.obj"), (BOTTOM, "bottom.obj")):
        pv, pf = template.part_mesh(part)
        _write_text(folder / fname, _obj_text(pv.astype(np.float64) * MM_PER_M, pf))

    if template.has_texture:
        assert template.tex_verts is not None and template.tex_faces is not None
        assert template.tex_uv is not None and template.texture is not None
        _write_text(
            folder / TEX_MESH_FILE,
            _obj_text(
                template.tex_verts.astype(np.float64) * MM_PER_M,
                template.tex_faces,
                uv=template.tex_uv,
                mtl=TEX_MTL_FILE,
            ),
        )
        _write_text(
            folder / TEX_MTL_FILE,
            "newmtl material_0\nKa 1.000000 1.000000 1.000000\nKd 1.000000 1.000000 1.000000\n"
            f"Ks 0.000000 0.000000 0.000000\nd 1.000000\nillum 1\nmap_Kd {TEX_IMAGE_FILE}\n",
        )
        ok = cv2.imwrite(
            str(folder / TEX_IMAGE_FILE),
            np.ascontiguousarray(template.texture[..., ::-1]),
            [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY],
        )
        if not ok:
            raise AssetError(folder / TEX_IMAGE_FILE, "cv2 could not write the texture")
    return folder


def write_object_meta(meta_dir: PathLike, templates: Iterable[ObjectTemplate]) -> Path:
    """Write ``meta_dir/object_meta.json`` = ``{name: {"diameter": metres}}``.

    Entries already in the file for other objects are kept.

    Args:
        meta_dir: ARCTIC's ``meta`` folder.
        templates: objects whose diameter to record.

    Returns:
        the JSON path.
    """
    meta_dir = Path(meta_dir)
    meta_dir.mkdir(parents=True, exist_ok=True)
    path = meta_dir / OBJECT_META_FILE
    meta: dict[str, Any] = {}
    if path.is_file():
        meta = {k: dict(v) for k, v in read_object_meta(path).items()}
    for t in templates:
        meta[t.name] = {"diameter": round(float(t.diameter), 9)}
    ordered = {k: meta[k] for k in sort_names(meta.keys())}
    _write_text(path, json.dumps(ordered, indent=1) + "\n")
    return path
