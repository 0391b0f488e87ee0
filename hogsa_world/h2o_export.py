"""Test data in the real H2O layout, converted from a generated ARCTIC-format world
(:func:`export_h2o_world`; there is no H2O world generator)."""

from __future__ import annotations

import json
import shutil
from pathlib import Path
from typing import Any, Optional, Sequence

import cv2
import numpy as np
import torch

from hogsa_loader.assets.arctic import ArcticRoot
from hogsa_loader.assets.conventions import EGO_VIEW, render_intrinsics
from hogsa_loader.assets.h2o import h2o_mano_from_tracks
from hogsa_loader.assets.h2o_io import H2OIntrinsics
from hogsa_loader.assets.h2o_meshes import H2O_MESH_NAMES, h2o_class_name
from hogsa_loader.assets.hands.mano_io import load_mano
from hogsa_loader.assets.objects.articulated import articulate
from hogsa_loader.assets.objects.rigid import H2O_OBJECT_NAMES
from hogsa_loader.assets.objects.template import TOP, ObjectTemplate
from hogsa_loader.assets.types import HandTrack, SequenceData
from hogsa_loader.errors import AssetError, PathLike
from hogsa_loader.geometry.rotations import axis_angle_to_matrix
from hogsa_loader.render.mesh_raster import render_meshes
from hogsa_world.h2o_writer import H2OCameraRecord, write_h2o_sequence
from hogsa_world.scene_render import HAND_BASE_SKIN, foreground, object_meshes, pose_sequence
from hogsa_world.stage import build_stage, light_for_camera
from hogsa_world.writer import _rng

__all__ = ["EXPORT_RECORD", "export_h2o_world", "write_obj_mesh"]

#: Record of an export, at the root of the H2O tree.
EXPORT_RECORD = "hogsa_h2o_export.json"
_F32 = torch.float32


def write_obj_mesh(
    folder: PathLike,
    stem: str,
    verts: np.ndarray,
    faces: np.ndarray,
    uv: Optional[np.ndarray] = None,
    texture: Optional[np.ndarray] = None,
) -> Path:
    """Write ``<folder>/<stem>.obj`` (vertices in the given unit; with ``uv`` + ``texture`` also
    ``<stem>.mtl`` and ``<stem>.png``; ``vt`` indices equal ``v`` indices).

    Returns:
        the OBJ path.
    """
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    lines = [f"mtllib {stem}.mtl\nusemtl material_0\n"] if uv is not None else []
    lines += [f"v {x:.9f} {y:.9f} {z:.9f}\n" for x, y, z in np.asarray(verts, np.float64).tolist()]
    f1 = np.asarray(faces, np.int64) + 1
    if uv is not None:
        lines += [f"vt {u:.9f} {v:.9f}\n" for u, v in np.asarray(uv, np.float64).tolist()]
        lines += [f"f {a}/{a} {b}/{b} {c}/{c}\n" for a, b, c in f1.tolist()]
        (folder / f"{stem}.mtl").write_text(
            f"newmtl material_0\nKa 1 1 1\nKd 1 1 1\nKs 0 0 0\nd 1\nillum 1\nmap_Kd {stem}.png\n"
        )
        cv2.imwrite(str(folder / f"{stem}.png"), np.ascontiguousarray(np.asarray(texture)[..., ::-1]))
    else:
        lines += [f"f {a} {b} {c}\n" for a, b, c in f1.tolist()]
    path = folder / f"{stem}.obj"
    path.write_text("".join(lines))
    return path


def _baked_mesh(template: ObjectTemplate, angle: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The textured mesh posed at articulation ``angle`` in the object frame: verts, faces, uv."""
    pts = torch.as_tensor(template.tex_verts, dtype=torch.float64)[None]
    top = torch.as_tensor(template.tex_parts == TOP)
    zero = torch.zeros(1, 3, dtype=torch.float64)
    verts = articulate(pts, top, torch.tensor([angle], dtype=torch.float64), zero, zero)[0].numpy()
    return verts, np.asarray(template.tex_faces), np.asarray(template.tex_uv)


def _small_intrinsics(K: np.ndarray, width: int, height: int, size: tuple[int, int]) -> np.ndarray:
    """Label intrinsics of a ``size`` image showing the original's full width, centred vertically."""
    s = size[0] / width
    out = np.diag([s, s, 1.0]) @ np.asarray(K, np.float64)
    out[1, 2] -= (height * s - size[1]) / 2.0
    return out


def _frames_track(h: HandTrack, idx: np.ndarray) -> HandTrack:
    return HandTrack(rot=h.rot[idx], pose=h.pose[idx], trans=h.trans[idx], betas=h.betas, valid=h.valid[idx])


def _hand_colors(root: ArcticRoot, subject: str, models: dict) -> dict[str, torch.Tensor]:
    """Per-vertex albedo of the subject's hands, as the world renders them."""
    subj = [s for s in root.world_meta().extra.get("subjects", []) if s.get("sid") == subject]
    skin = np.asarray(subj[0]["skin_rgb"], np.float64) if subj else HAND_BASE_SKIN
    tone = np.clip(skin / HAND_BASE_SKIN, 0.2, 1.3)
    return {side: torch.as_tensor(np.clip(models[side].vertex_colors * tone, 0, 1), dtype=_F32) for side in models}


def _check_export(
    object_class: str, mesh_name: Optional[str], allo_views: Sequence[int], frame_stride: int
) -> tuple[str, str]:
    """The H2O class name and mesh name of an export; ValueError for bad arguments."""
    cls = h2o_class_name(object_class)
    mesh_name = mesh_name or H2O_MESH_NAMES[cls][-1]
    if mesh_name not in H2O_MESH_NAMES[cls]:
        raise ValueError(f"mesh name {mesh_name!r} is not a known name of H2O class {cls!r} ({H2O_MESH_NAMES[cls]})")
    if len(allo_views) != 4:
        raise ValueError(f"H2O has 4 static cameras; give 4 allocentric views, got {list(allo_views)}")
    if int(frame_stride) < 1:
        raise ValueError(f"frame stride must be >= 1, got {frame_stride}")
    return cls, mesh_name


def _check_replace(seq_dir: Path, overwrite: bool) -> bool:
    """Whether ``seq_dir`` holds files to replace; AssetError when it does and ``overwrite`` is off
    (frames of two exports would mix)."""
    replace_old = seq_dir.is_dir() and any(seq_dir.iterdir())
    if replace_old and not overwrite:
        raise AssetError(
            seq_dir,
            "already holds an H2O sequence; its frames would mix with this export's "
            "(pass overwrite=True, or --overwrite, to replace it)",
        )
    return replace_old


def _constant_articulation(seq: SequenceData, name: str) -> float:
    """The sequence's articulation angle (rad); ValueError when it varies (H2O objects are rigid)."""
    arti = seq.object.arti
    if float(np.ptp(arti)) > 1e-6:
        raise ValueError(
            f"{name}: articulation varies ({arti.min():.4f}..{arti.max():.4f} rad); "
            "H2O objects are rigid, export a grab sequence"
        )
    return float(arti[0])


def _object_to_world(seq: SequenceData, idx: np.ndarray) -> np.ndarray:
    """(F, 4, 4) object-to-world transforms of frames ``idx``."""
    obj2world = np.repeat(np.eye(4)[None], len(idx), 0)
    obj2world[:, :3, :3] = axis_angle_to_matrix(torch.as_tensor(seq.object.rot[idx])).numpy()
    obj2world[:, :3, 3] = seq.object.trans[idx]
    return obj2world


def _render_frames(scene: dict[str, Any], w2c: np.ndarray, K: np.ndarray, size: tuple[int, int]) -> list[np.ndarray]:
    """(H, W, 3) uint8 frames of one camera: world stage and foreground seen from (F, 4, 4) ``w2c``.

    Args:
        scene: ``posed``, ``hand_faces``, ``colors``, ``meshes``, ``stage`` (see
            :mod:`hogsa_world.scene_render`).
        K: (3, 3) label intrinsics of the ``size`` = (W, H) image.
    """
    W, H = size
    Kr = torch.as_tensor(render_intrinsics(K), dtype=_F32)
    rgb = []
    for i in range(len(w2c)):
        fg = foreground(scene["posed"], i, scene["hand_faces"], scene["colors"], scene["meshes"])
        m = w2c[i]
        r = render_meshes(
            scene["stage"] + fg,
            torch.as_tensor(m, dtype=_F32),
            Kr,
            H,
            W,
            light=light_for_camera(m),
            background=(0.1, 0.1, 0.1),
        )
        rgb.append(np.clip(np.rint(r.rgb.numpy() * 255.0), 0, 255).astype(np.uint8))
    return rgb


def _export_scene(
    root: ArcticRoot, subject: str, sequence: str, idx: np.ndarray, template: ObjectTemplate, models: dict, seed: int
) -> dict[str, Any]:
    """What the world's scene renderer needs for frames ``idx``: posed meshes, hand faces and
    colours, object meshes, and the stage of world seed ``seed``."""
    raw = root.raw_sequence(subject, sequence)
    layers = root.mano_layers(dtype=torch.float64)
    mano = {side: {k: np.asarray(v)[idx] if k != "shape" else v for k, v in raw.mano[side].items()} for side in layers}
    return {
        "posed": pose_sequence(layers, mano, raw.object[idx], template),
        "hand_faces": {side: torch.as_tensor(models[side].faces) for side in models},
        "colors": _hand_colors(root, subject, models),
        "meshes": object_meshes(template),
        "stage": build_stage(_rng(seed, "stage")),
    }


def _camera_records(
    root: ArcticRoot,
    seq: SequenceData,
    subject: str,
    sequence: str,
    cams: dict[int, tuple[int, Any]],
    idx: np.ndarray,
    template: ObjectTemplate,
    cls: str,
    seed: int,
    size: tuple[int, int],
) -> dict[int, H2OCameraRecord]:
    """The H2O record (images, camera pose, intrinsics, MANO and object labels in its frame) of every camera."""
    W, H = size
    F = len(idx)
    w2c = {k: cam.world2cam[idx] for k, (_, cam) in cams.items()}
    obj2world = _object_to_world(seq, idx)
    models = {side: load_mano(root.mano_dir, side=side) for side in ("right", "left")}
    left, right = _frames_track(seq.left, idx), _frames_track(seq.right, idx)
    scene = _export_scene(root, subject, sequence, idx, template, models, seed)
    records: dict[int, H2OCameraRecord] = {}
    for k, (_, cam) in cams.items():
        K = _small_intrinsics(cam.K[0], cam.width, cam.height, (W, H))
        rgb = _render_frames(scene, w2c[k], K, (W, H))
        records[k] = H2OCameraRecord(
            cam_pose=np.linalg.inv(w2c[k]),
            intrinsics=H2OIntrinsics(fx=K[0, 0], fy=K[1, 1], cx=K[0, 2], cy=K[1, 2], width=W, height=H),
            mano=h2o_mano_from_tracks(left, right, w2c[k], models),
            obj_class=np.full(F, H2O_OBJECT_NAMES.index(cls)),
            obj_transform=w2c[k] @ obj2world,
            rgb=rgb,
        )
    return records


def _export_record(
    root: ArcticRoot,
    subject: str,
    sequence: str,
    seq: SequenceData,
    angle: float,
    seed: int,
    where: tuple[str, str, int],
    cls: str,
    mesh_path: Path,
    out: Path,
) -> dict[str, Any]:
    """The ``source`` and ``h2o`` parts of the export record.

    Args:
        where: (h2o_subject, scene, seq_id) the sequence was written to.
        mesh_path: the written object mesh, under ``out``.
    """
    h2o_subject, scene, seq_id = where
    return {
        "source": {
            "arctic_root": str(root.data_root),
            "subject": subject,
            "sequence": sequence,
            "object": seq.object.name,
            "articulation": angle,
            "stage_seed": int(seed),
        },
        "h2o": {
            "subject": h2o_subject,
            "scene": scene,
            "seq": int(seq_id),
            "object_class": cls,
            "class_id": H2O_OBJECT_NAMES.index(cls),
            "mesh": str(mesh_path.relative_to(out)),
        },
    }


def export_h2o_world(
    arctic_root: PathLike,
    out: PathLike,
    *,
    subject: str = "s05",
    sequence: str = "box_grab_01",
    object_class: str = "book",
    mesh_name: Optional[str] = None,
    h2o_subject: str = "subject1",
    scene: str = "h1",
    seq_id: int = 0,
    allo_views: Sequence[int] = (1, 2, 3, 4),
    image_size: tuple[int, int] = (320, 180),
    frame_stride: int = 4,
    seed: Optional[int] = None,
    overwrite: bool = False,
) -> dict[str, Any]:
    """Convert one grab sequence of a generated world into an H2O tree that
    :class:`~hogsa_loader.assets.h2o.H2ORoot` reads like the real dataset::

        <out>/subject1/h1/0/cam{0..4}/{rgb,cam_pose,hand_pose_mano,obj_pose_rt}/NNNNNN.{png,txt}
        <out>/subject1/h1/0/cam{0..4}/cam_intrinsics.txt
        <out>/object/<mesh name>/<mesh name>.obj (+ .mtl, .png)    the rigid object mesh (metres)
        <out>/hogsa_h2o_export.json                                 what was converted from where

    The object is the template posed at the sequence's constant articulation, in the object
    frame. ``cam0``..``cam3`` are the world's views ``allo_views``, ``cam4`` its egocentric view
    (rendered undistorted, as H2O's images are); ``cam_pose`` is camera-to-world (ARCTIC's world
    frame is H2O's). Intrinsics are scaled by ``width / original width`` with the image centred
    vertically. ``hand_pose_mano`` (flat_hand_mean=True) and ``obj_pose_rt`` are in every
    camera's frame (:func:`~hogsa_loader.assets.h2o.h2o_mano_from_tracks`). Images come from
    the world's scene renderer; file numbers are ARCTIC frame indices. Deterministic.

    Args:
        arctic_root: the world (ARCTIC ``./data``).
        out: H2O root to write (created).
        subject, sequence: the world sequence (its articulation must be constant).
        object_class: H2O class the object plays (README name, e.g. ``"book"``).
        mesh_name: a known mesh variant of the class (default the last, e.g. ``ovomaltine``).
        h2o_subject, scene, seq_id: where the sequence goes.
        allo_views: the 4 allocentric views written as ``cam0``..``cam3``.
        image_size: (width, height) of the rendered frames; frame_stride: every n-th frame.
        seed: the world's seed (gives its stage); default: the one ``hogsa_world.json`` records.
        overwrite: replace an existing ``<out>/<h2o_subject>/<scene>/<seq_id>`` folder.

    Returns: the record written to ``<out>/hogsa_h2o_export.json``.

    Raises:
        ValueError: varying articulation, unknown class or mesh name, not 4 allocentric views,
            frame stride < 1.
        AssetError: the sequence folder already holds files and ``overwrite`` is False.
    """
    cls, mesh_name = _check_export(object_class, mesh_name, allo_views, frame_stride)
    seq_dir = Path(out) / h2o_subject / scene / str(int(seq_id))
    replace_old = _check_replace(seq_dir, overwrite)
    root = ArcticRoot(arctic_root)
    seed = int(root.world_meta().extra.get("seed", 0)) if seed is None else seed
    seq: SequenceData = root.sequence(subject, sequence)
    angle = _constant_articulation(seq, f"{subject}/{sequence}")
    template = root.object_templates()[seq.object.name]
    out = Path(out)
    verts, faces, uv = _baked_mesh(template, angle)
    mesh_path = write_obj_mesh(out / "object" / mesh_name, mesh_name, verts, faces, uv, template.texture)
    idx = np.arange(0, seq.num_frames, int(frame_stride))
    cams = {k: (v, seq.cameras[v]) for k, v in enumerate(allo_views)} | {4: (EGO_VIEW, seq.cameras[EGO_VIEW])}
    W, H = int(image_size[0]), int(image_size[1])
    records = _camera_records(root, seq, subject, sequence, cams, idx, template, cls, seed, (W, H))
    if replace_old:  # (only now: a failed export leaves the old one in place)
        shutil.rmtree(seq_dir)
    write_h2o_sequence(out, h2o_subject, scene, seq_id, idx.tolist(), records)
    record = _export_record(
        root, subject, sequence, seq, angle, seed, (h2o_subject, scene, seq_id), cls, mesh_path, out
    )
    record |= {
        "cameras": {f"cam{k}": {"world_view": int(v)} for k, (v, _) in cams.items()},
        "frames": idx.tolist(),
        "image_size": [W, H],
    }
    (out / EXPORT_RECORD).write_text(json.dumps(record, indent=1, sort_keys=True) + "\n")
    return record
