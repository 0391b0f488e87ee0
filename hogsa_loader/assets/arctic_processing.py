"""ARCTIC's sequence processing and split building.

:func:`process_sequence` is ARCTIC's ``process_seq`` (src/arctic/processing.py) on a
dataset-independent :class:`~hogsa_loader.assets.types.SequenceData`, with ARCTIC's
float32 arithmetic bit for bit; :func:`build_split` is ``build_split``
(src/arctic/split.py); :func:`write_processed_splits` writes ``splits/<p>_<split>.npy``
for a whole root (the world generator calls it).
"""

from __future__ import annotations

import copy
import functools
from pathlib import Path
from typing import Any, Mapping, Optional, Sequence

import numpy as np
import torch
from tqdm import tqdm

from hogsa_loader.assets import arctic_float32 as a32
from hogsa_loader.assets.arctic import ArcticRoot, canonical_split, protocol_views
from hogsa_loader.assets.conventions import (
    ALLO_VIEWS,
    EGO_IMAGE_SIZE,
    EGO_VIEW,
    allocentric_bbox,
    ego_bbox,
    project,
    transform,
    validity_flags,
)
from hogsa_loader.assets.objects.template import MESH_FILE, PARAMS_FILE, _points, _read_obj
from hogsa_loader.assets.types import SequenceData
from hogsa_loader.errors import AssetError, PathLike, read_json
from hogsa_loader.io.atomic import atomic_open

__all__ = [
    "FRAME_MARGIN",
    "REQUEST_KEYS",
    "build_split",
    "crop_boxes",
    "image_name",
    "inner_frames",
    "process_sequence",
    "write_processed_splits",
]

#: Frames skipped at each end of a sequence in the split image lists (ARCTIC: 10).
FRAME_MARGIN = 10


def inner_frames(num_frames: int, margin: int = FRAME_MARGIN, stride: int = 1) -> np.ndarray:
    """The annotated frames of a sequence of ``num_frames`` that its split lists and poses use:
    all but ``margin`` at each end, every ``stride``-th; (K,) int64."""
    if margin < 0:
        raise ValueError(f"margin must be >= 0, got {margin}")
    return np.arange(margin, num_frames - margin, stride)


#: Keys of a processed sequence kept in the split files (``--request_keys``).
REQUEST_KEYS: tuple[str, ...] = ("cam_coord", "2d", "bbox", "params")
#: Frames posed per batch: ARCTIC's ``DataLoader`` batch (``construct_loader``,
#: batch_size=320). Equal values need equal batches (see :mod:`.arctic_float32`).
CHUNK_FRAMES = 320

_POINT_KEYS = ("joints.right", "joints.left", "kp3d", "bbox3d")
_VERT_KEYS = ("verts.right", "verts.left", "verts.object")


def _camera_stack(seq: SequenceData, ego_image_size: tuple[int, int]) -> tuple[np.ndarray, ...]:
    """(F,9,4,4) world2cam, (F,9,3,3) K, (F,8) dist, (9,2) image sizes of views 0..8."""
    F = seq.num_frames
    missing = [v for v in (EGO_VIEW,) + tuple(ALLO_VIEWS) if v not in seq.cameras]
    if missing:
        raise ValueError(f"{seq.subject}/{seq.name}: cameras {missing} are missing (ARCTIC needs views 0..8)")
    cams = [seq.cameras[v] for v in (EGO_VIEW,) + tuple(ALLO_VIEWS)]
    for c in cams:
        if c.world2cam.shape != (F, 4, 4) or c.K.shape != (F, 3, 3):
            raise ValueError(
                f"{seq.subject}/{seq.name}: camera {c.view} needs world2cam (F,4,4) and K (F,3,3) with F={F}, "
                f"got {c.world2cam.shape} and {c.K.shape}"
            )
    world2cam = np.stack([c.world2cam for c in cams], axis=1).astype(np.float64)
    K = np.stack([c.K for c in cams], axis=1).astype(np.float64)
    ego = cams[0]
    dist = np.zeros(8) if ego.dist is None else np.asarray(ego.dist, dtype=np.float64)
    dist = np.broadcast_to(dist, (F, 8)).copy()
    sizes = np.array([tuple(ego_image_size)] + [(c.width, c.height) for c in cams[1:]], dtype=np.float64)
    return world2cam, K, dist, sizes


def _f32(a: np.ndarray) -> torch.Tensor:
    return torch.as_tensor(np.ascontiguousarray(a), dtype=torch.float32)


def _pose_chunk(
    seq: SequenceData, sl: slice, mano_layers: Mapping[str, Any], obj: a32.ObjectTensors32
) -> dict[str, torch.Tensor]:
    """World-frame points of frames ``sl``, float32: joints (n,21,3), kp3d, bbox3d, verts.

    Posed with ARCTIC's float32 arithmetic (:mod:`.arctic_float32`) on float32 inputs, as
    ARCTIC's loader gives them (``obj_trans`` in mm).
    """
    out: dict[str, torch.Tensor] = {}
    for side, hand in (("right", seq.right), ("left", seq.left)):
        layer = mano_layers[side]
        n = hand.rot[sl].shape[0]
        betas = np.broadcast_to(np.asarray(hand.betas, dtype=np.float32).reshape(1, -1), (n, hand.betas.size))
        verts, joints = a32.mano_forward(
            layer, _f32(hand.rot[sl]), _f32(hand.pose[sl]), _f32(betas), _f32(hand.trans[sl])
        )
        out[f"joints.{side}"] = joints
        out[f"verts.{side}"] = verts
    o = seq.object
    res = a32.object_forward(obj, _f32(o.arti[sl]), _f32(o.rot[sl]), _f32(o.trans[sl] * 1000.0))
    out["kp3d"] = res["kp3d"]
    out["bbox3d"] = res["bbox3d"]
    out["verts.object"] = res["v"]
    return out


@functools.lru_cache(maxsize=32)
def _template_mm(folder: str, stamp: tuple[int, ...]) -> Optional[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """``mesh.obj`` vertices, keypoints and box corners of a template folder, mm (cached per mtime)."""
    path = Path(folder)
    try:
        verts = np.asarray(_read_obj(path / MESH_FILE).vertices, dtype=np.float64)
        params = read_json(path / PARAMS_FILE)
        kp = np.concatenate([_points(params[k], path, k, None) for k in ("keypoints_top", "keypoints_bottom")])
        bbox = np.concatenate([_points(params[k], path, k, None) for k in ("bbox_top", "bbox_bottom")])
    except (AssetError, KeyError, TypeError, ValueError):
        return None
    return verts, kp, bbox


def _object_tensors(seq: SequenceData, object_layer: Any) -> a32.ObjectTensors32:
    """The sequence's object as ARCTIC's ``ObjectTensors`` holds it.

    From the template files' millimetres when the sequence was read from a root whose
    template is the layer's (bit-equal to ARCTIC); otherwise the layer's float32 metres.
    """
    name = seq.object.name
    if name not in object_layer.name_to_index:
        where: PathLike = name
        if seq.root is not None:
            where = ArcticRoot(seq.root).meta_dir / "object_vtemplates" / name
        raise AssetError(
            where, f"no template for object '{name}' (sequence {seq.subject}/{seq.name}; known: {object_layer.names})"
        )
    if seq.root is not None:
        folder = ArcticRoot(seq.root).meta_dir / "object_vtemplates" / name
        files = [folder / MESH_FILE, folder / PARAMS_FILE]
        if all(f.is_file() for f in files):
            mm = _template_mm(str(folder), tuple(f.stat().st_mtime_ns for f in files))
            obj = a32.ObjectTensors32.from_mm(object_layer, name, *mm) if mm is not None else None
            if obj is not None:
                return obj
    return a32.ObjectTensors32.from_layer(object_layer, name)


def _to_camera(world2cam: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
    """ARCTIC's rigid move: ``world2cam @ [p, 1]`` batched, then ``xyz / w``.

    Args:
        world2cam: (n, 4, 4) float32; points: (n, N, 3) float32.

    Returns:
        (n, N, 3) float32 camera-frame points.
    """
    homo = torch.ones(points.shape[0], points.shape[1], 4, dtype=points.dtype)
    homo[:, :, :3] = points
    out = torch.bmm(world2cam, homo.permute(0, 2, 1)).permute(0, 2, 1)
    return out[:, :, :3] / out[:, :, 3:4]


def _project(K: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
    """ARCTIC's pinhole projection: ``K @ p`` batched, then ``xy / z``.

    Args:
        K: (n, 3, 3) float32; points: (n, N, 3) float32.

    Returns:
        (n, N, 2) float32 pixels.
    """
    uvw = torch.bmm(K, points.permute(0, 2, 1)).permute(0, 2, 1)
    return uvw[:, :, :2] / uvw[:, :, 2:3]


def _distort(points: torch.Tensor, dist: torch.Tensor) -> torch.Tensor:
    """ARCTIC's ego distortion (OpenCV rational + tangential): float64 on float32 points.

    Args:
        points: (n, N, 3) float32 camera-frame points; dist: (8,) float32 k1 k2 p1 p2 k3 k4 k5 k6.

    Returns:
        (n, N, 3) float32 distorted points (same z).
    """
    p = points.double()
    z = p[:, :, 2]
    z_inv = 1 / z
    x, y = p[:, :, 0] * z_inv, p[:, :, 1] * z_inv
    xx, yy, xy = x * x, y * y, x * y
    r2 = xx + yy
    r4 = r2 * r2
    r6 = r4 * r2
    radial = (1 + dist[0] * r2 + dist[1] * r4 + dist[4] * r6) / (1 + dist[5] * r2 + dist[6] * r4 + dist[7] * r6)
    xd = x * radial + 2 * dist[2] * xy + dist[3] * (r2 + 2 * xx)
    yd = y * radial + 2 * dist[3] * xy + dist[2] * (r2 + 2 * yy)
    return torch.stack([xd * z, yd * z, z], dim=2).float()


def _allo_bbox(v2d: np.ndarray) -> np.ndarray:
    """ARCTIC's allocentric box in float32: side 1.1·D + 0.6·D around the 2D extent.

    Args:
        v2d: (..., V, 2) float32 projected object vertices.

    Returns:
        (..., 3) float32 ``(cx, cy, scale)``, scale ≥ 3.
    """
    lo, hi = v2d.min(axis=-2), v2d.max(axis=-2)
    w, h = hi[..., 0] - lo[..., 0], hi[..., 1] - lo[..., 1]
    pad = np.maximum(w, h) * np.float32(0.6)
    cx, cy = lo[..., 0] + w / np.float32(2), lo[..., 1] + h / np.float32(2)
    side = np.where(w / h > 1, w, h) * np.float32(1.1)
    scale = np.maximum((side + pad) / np.float32(200), np.float32(3))
    return np.stack([cx, cy, scale], axis=-1)


def _centroid(v2d: np.ndarray) -> np.ndarray:
    """(..., V, 2) → (..., 1, 2) float32 mean, reduced as ARCTIC (torch, float32)."""
    return torch.from_numpy(np.ascontiguousarray(v2d)).mean(dim=-2, keepdim=True).numpy()


def _rot_cam(world2cam: np.ndarray, rotvec: np.ndarray) -> np.ndarray:
    """Axis-angle of ``R_world2cam · R(rotvec)``: (n,9,4,4) float32, (n,3) → (n,9,3) float32.

    ARCTIC's ``transform_mano_rot_cam`` per view, in float32 quaternions.
    """
    rv = _f32(rotvec)
    views = [a32.rot_to_camera(rv, _f32(world2cam[:, v])) for v in range(world2cam.shape[1])]
    return torch.stack(views, dim=1).numpy()


def _float32_layers(mano_layers: Mapping[str, Any]) -> dict[str, Any]:
    """The MANO layers with float32 buffers, as ARCTIC's (a float32 layer is used as is, others copied)."""
    return {
        side: layer if layer.v_template.dtype == torch.float32 else copy.deepcopy(layer).float()
        for side, layer in mano_layers.items()
    }


def _concat_chunks(acc: dict[str, dict[str, list[np.ndarray]]]) -> dict[str, Any]:
    """Join the per-chunk arrays over frames: ``world_coord``/``cam_coord``/``2d`` dicts and the (F,9,3) ``bbox``."""
    out: dict[str, Any] = {
        g: {k: np.concatenate(v, axis=0) for k, v in acc[g].items()} for g in ("world_coord", "cam_coord", "2d")
    }
    out["bbox"] = np.concatenate(acc["bbox"]["bbox"], axis=0)
    return out


def process_sequence(
    seq: SequenceData,
    mano_layers: Mapping[str, Any],
    object_layer: Any,
    *,
    export_verts: bool = False,
    ego_image_size: tuple[int, int] = EGO_IMAGE_SIZE,
    chunk_frames: int = CHUNK_FRAMES,
) -> dict[str, dict[str, np.ndarray] | np.ndarray]:
    """ARCTIC ``process_seq`` of one sequence.

    Output (F frames; views in ``cam_coord``/``2d`` are the 10 of
    ARCTIC: ``[ego undistorted, allo 1..8, ego distorted]``; flags/rotations/bbox use views 0..8):

    ``world_coord`` (metres, world frame)
        ``joints.right``/``joints.left`` (F,21,3), ``kp3d`` (F,32,3), ``bbox3d`` (F,16,3),
        ``rot_r``/``rot_l``/``obj_rot`` (F,3) (+ ``verts.right``/``verts.left`` (F,V,3),
        ``verts.object`` (F,Vo,3) with ``export_verts``).
    ``cam_coord`` (metres, camera frame of each view)
        ``joints.right``/``joints.left`` (F,10,21,3), ``kp3d`` (F,10,32,3), ``bbox3d``
        (F,10,16,3), ``rot_r_cam``/``rot_l_cam``/``obj_rot_cam`` (F,9,3) axis-angle of
        ``R_world2cam · R_global`` (angle in [0, π]), ``is_valid``/``left_valid``/``right_valid``
        (F,9) int64 in {0,1} (+ ``verts.*`` (F,10,V,3) with ``export_verts``).
    ``2d`` (full-resolution pixels)
        pinhole projection of every ``cam_coord`` point key, (F,10,N,2); view 9 projects the
        distorted ego points with ``K_ego``.
    ``bbox`` (F,9,3)
        ``(cx, cy, scale)``: allocentric = (1.1 + 0.6) × 2D extent of the projected object
        vertices, scale ≥ 3 (:func:`~hogsa_loader.assets.conventions.allocentric_bbox`);
        ego = the whole image (:func:`~hogsa_loader.assets.conventions.ego_bbox`).
    ``params`` (per frame)
        ``rot_r, pose_r, trans_r, shape_r (F,10), fitting_err_r`` and the same with ``_l``,
        ``obj_arti`` (F,), ``obj_rot`` (F,3), ``obj_trans`` (F,3) **mm** (as stored in the raw
        file), ``world2ego`` (F,4,4), ``dist`` (F,8), ``K_ego`` (F,3,3).

    Differences from ARCTIC, on purpose:

    * no SMPL-X: the project's worlds have no body, so ``joints.smplx``/``verts.smplx`` and
      the ``smplx_*`` params are omitted (the training dataset does not read them);
    * floats are stored as float32 (ARCTIC's tensors are float32 too), flags as int64 (ARCTIC's
      ``long`` flags); ``fitting_err`` is zeros when the sequence has none;
    * computation is batched over chunks of frames (no Python loop over single frames);
    * ``ego_image_size`` is an argument (ARCTIC hard-codes 2800×2000, the default).

    Args:
        seq: the sequence (world frame, metres); cameras 0 (ego, per frame, with ``dist``)
            and 1..8 are required.
        mano_layers: ``{"right": MANOLayer, "left": MANOLayer}`` with ``flat_hand_mean=False``
            (outputs are taken as float32, as ARCTIC's layers give).
        object_layer: an :class:`~hogsa_loader.assets.objects.articulated.ArticulatedObjectLayer`
            holding ``seq.object.name``.
        export_verts: also store ``verts.right/left/object`` in every coordinate frame.
        ego_image_size: (width, height) of the full ego image, used for the ego box and the
            ego validity region (generated worlds declare theirs in ``meta/hogsa_world.json``).
        chunk_frames: frames posed per batch (values equal ARCTIC's bit for bit only at
            the default, ARCTIC's batch of 320 frames).

    Returns:
        ``{"world_coord", "cam_coord", "2d", "bbox", "params"}`` as listed above.
    """
    F = seq.num_frames
    world2cam, K, dist, sizes = _camera_stack(seq, ego_image_size)
    world2cam, K, dist = (a.astype(np.float32) for a in (world2cam, K, dist))  # ARCTIC's FloatTensors
    keep = _POINT_KEYS + (_VERT_KEYS if export_verts else ())
    ego_box = ego_bbox(tuple(ego_image_size)).astype(np.float32)
    obj = _object_tensors(seq, object_layer)
    mano_layers = _float32_layers(mano_layers)
    acc: dict[str, dict[str, list[np.ndarray]]] = {"world_coord": {}, "cam_coord": {}, "2d": {}, "bbox": {}}
    with torch.no_grad():
        for start in range(0, F, max(1, chunk_frames)):
            sl = slice(start, min(F, start + max(1, chunk_frames)))
            for group, key, value in _process_chunk(
                seq, sl, world2cam, K, dist, mano_layers, obj, keep, ego_box, sizes
            ):
                acc[group].setdefault(key, []).append(value)
    out = _concat_chunks(acc)
    out["params"] = _params(seq, world2cam[:, EGO_VIEW], K[:, EGO_VIEW], dist)
    return out


def _process_chunk(
    seq: SequenceData,
    sl: slice,
    world2cam: np.ndarray,
    K: np.ndarray,
    dist: np.ndarray,
    mano_layers: Mapping[str, Any],
    obj: a32.ObjectTensors32,
    keep: Sequence[str],
    ego_box: np.ndarray,
    sizes: np.ndarray,
) -> list[tuple[str, str, np.ndarray]]:
    """The outputs of frames ``sl`` as ``(group, key, value)`` in ARCTIC's key order.

    Precision is ARCTIC's, bit for bit: the world-frame points and the camera-frame rotations
    are computed in float32 in the same order as ARCTIC's processing so that values match it
    bit for bit (:mod:`hogsa_loader.assets.arctic_float32`: smplx's MANO ``lbs``,
    ``ObjectTensors``' quaternions on ``float32(mm) / 1000`` templates, ``transform_mano_rot_cam``),
    in batches of ARCTIC's 320 frames; cameras are rounded to float32, points are moved and
    projected in float32 (batched homogeneous 4×4 and 3×3 products, then a division), the ego
    distortion runs in float64 on the float32 points, and the allocentric box and the validity
    regions are float32 with ARCTIC's order of operations. The training dataset truncates 2D
    labels to integer pixels, so a label that float64 geometry would put at 52.999997 px
    instead of ARCTIC's 53.000005 px lands one pixel off. The shared MANO and object layers
    (float32 or float64 ``MANOLayer`` / ``ArticulatedObjectLayer``) are only read here (their
    buffers, the part masks); a sequence that was not read from a root with the layer's
    template files is posed from the layer's float32 metres.

    Args:
        seq: the sequence; sl: its frames in this chunk.
        world2cam: (F, 9, 4, 4), K: (F, 9, 3, 3), dist: (F, 8) float32 cameras.
        mano_layers: float32 MANO layers; obj: the object's float32 tensors.
        keep: point keys stored; ego_box: (3,) float32; sizes: per-view image sizes.
    """
    out: list[tuple[str, str, np.ndarray]] = []
    w2c = world2cam[sl]
    world = _pose_chunk(seq, sl, mano_layers, obj)
    cam, p2d = {}, {}
    for key, pts in world.items():
        if key in keep or key == "verts.object":  # object verts: needed for bbox/flags
            cam[key], p2d[key] = _views(pts, _f32(w2c), _f32(K[sl]), _f32(dist[0]))
    bbox, flags = _boxes_and_flags(p2d, ego_box, sizes)
    for key in keep:
        out.append(("world_coord", key, world[key].numpy()))
        out.append(("cam_coord", key, cam[key]))
        out.append(("2d", key, p2d[key]))
    rots = {"rot_r": seq.right.rot[sl], "rot_l": seq.left.rot[sl], "obj_rot": seq.object.rot[sl]}
    for key, rot in rots.items():
        out.append(("world_coord", key, rot.astype(np.float32)))
    for key, rot in rots.items():
        out.append(("cam_coord", f"{key}_cam", _rot_cam(w2c, rot)))
    is_valid, right_valid, left_valid = flags
    out.append(("cam_coord", "is_valid", is_valid.astype(np.int64)))
    out.append(("cam_coord", "left_valid", left_valid.astype(np.int64)))
    out.append(("cam_coord", "right_valid", right_valid.astype(np.int64)))
    out.append(("bbox", "bbox", bbox))
    return out


def _views(
    points: torch.Tensor, world2cam: torch.Tensor, K: torch.Tensor, dist: torch.Tensor
) -> tuple[np.ndarray, np.ndarray]:
    """Points in ARCTIC's 10 views ``[ego, allo 1..8, ego distorted]``, float32.

    Args:
        points: (n, N, 3) world points; world2cam: (n, 9, 4, 4); K: (n, 9, 3, 3); dist: (8,).

    Returns:
        camera-frame points (n, 10, N, 3) and pixels (n, 10, N, 2).
    """
    cams = [_to_camera(world2cam[:, v].contiguous(), points) for v in range(9)]
    cams.append(_distort(cams[EGO_VIEW], dist))
    Ks = [K[:, v].contiguous() for v in range(9)] + [K[:, EGO_VIEW].contiguous()]
    pixels = [_project(k, c) for k, c in zip(Ks, cams)]
    return torch.stack(cams, dim=1).numpy(), torch.stack(pixels, dim=1).numpy()


def _boxes_and_flags(
    p2d: Mapping[str, np.ndarray], ego_box: np.ndarray, sizes: np.ndarray
) -> tuple[np.ndarray, tuple[np.ndarray, ...]]:
    """Crop boxes (n, 9, 3) float32 and (is_valid, right_valid, left_valid), each (n, 9).

    Allocentric boxes come from the object vertices; validity on views 0..8 judges view 0
    on the distorted ego projection (view 9).
    """
    v2d = p2d["verts.object"]
    bbox = np.empty((v2d.shape[0], 9, 3), dtype=np.float32)
    bbox[:, EGO_VIEW] = ego_box
    bbox[:, 1:] = _allo_bbox(v2d[:, 1:9])
    order = [9] + list(ALLO_VIEWS)
    flags = validity_flags(
        _centroid(v2d[:, order]), p2d["joints.right"][:, order], p2d["joints.left"][:, order], bbox, sizes
    )
    return bbox, flags


def _params(seq: SequenceData, world2ego: np.ndarray, K_ego: np.ndarray, dist: np.ndarray) -> dict[str, np.ndarray]:
    """ARCTIC ``params``, float32, without the SMPL-X keys."""
    F = seq.num_frames
    f32 = np.float32
    p: dict[str, np.ndarray] = {}
    for sfx, hand in (("r", seq.right), ("l", seq.left)):
        p[f"rot_{sfx}"] = hand.rot.astype(f32)
        p[f"pose_{sfx}"] = hand.pose.astype(f32)
        p[f"trans_{sfx}"] = hand.trans.astype(f32)
        p[f"shape_{sfx}"] = np.repeat(np.asarray(hand.betas, dtype=f32).reshape(1, -1), F, axis=0)
        err = hand.fitting_err if hand.fitting_err is not None else np.zeros(F)
        p[f"fitting_err_{sfx}"] = np.asarray(err, dtype=f32)
    p["obj_arti"] = seq.object.arti.astype(f32)
    p["obj_rot"] = seq.object.rot.astype(f32)
    p["obj_trans"] = (seq.object.trans * 1000.0).astype(f32)
    p["world2ego"] = world2ego.astype(f32)
    p["dist"] = dist.astype(f32)
    p["K_ego"] = K_ego.astype(f32)
    return p


# ----------------------------------------------------------------------------------------
# Splits
# ----------------------------------------------------------------------------------------
def crop_boxes(root: ArcticRoot, seq: SequenceData, views: Sequence[int]) -> dict[int, np.ndarray]:
    """view → (F, 3) allocentric crop boxes ``(cx, cy, scale)`` of every frame of ``seq``.

    The object template is posed by ``root.object_layer()`` in float64 and its projected
    vertices give the box (:func:`~hogsa_loader.assets.conventions.allocentric_bbox`),
    as processing does.
    """
    layer = root.object_layer()
    obj = seq.object
    n = obj.rot.shape[0]
    f64 = torch.float64
    with torch.no_grad():
        res = layer(
            angles=torch.as_tensor(obj.arti, dtype=f64).reshape(n, 1),
            global_orient=torch.as_tensor(obj.rot, dtype=f64),
            transl=torch.as_tensor(obj.trans, dtype=f64),
            names=[obj.name] * n,
        )
    verts = res["v"].numpy()  # (F, V, 3)
    out = {}
    for v in views:
        cam = seq.cameras[v]
        out[v] = allocentric_bbox(project(transform(cam.world2cam[:, None], verts[:, None])[:, 0], cam.K))
    return out


def image_name(sid: str, seq: str, view: int, frame_id: int) -> str:
    """``./data/arctic_data/data/images/<sid>/<seq>/<view>/<frame_id:05d>.jpg`` (ARCTIC imgname)."""
    return f"./data/arctic_data/data/images/{sid}/{seq}/{view}/{frame_id:05d}.jpg"


def _check_offset(root: ArcticRoot, sid: str, frame_margin: int) -> None:
    """File numbers ``margin .. F − margin − 1`` minus the offset must be GT indices."""
    offset = root.subject_misc(sid).ioi_offset
    if abs(offset) > frame_margin:
        raise AssetError(
            root.misc_path,
            f"subject {sid}: ioi_offset {offset} exceeds the split's frame margin "
            f"{frame_margin}, so its first or last listed images have no GT frame",
        )


def build_split(
    root: ArcticRoot,
    protocol: str,
    split: str,
    processed: Optional[Mapping[str, Mapping[str, Any]]] = None,
    frame_margin: int = FRAME_MARGIN,
) -> dict[str, Any]:
    """ARCTIC ``build_split``.

    Split image names are numbered as ARCTIC's ``build_split`` numbers them: file numbers
    ``margin .. F − margin − 1``, whatever the subject's ``ioi_offset``. The dataset reads the
    label of file ``n`` at GT index ``n − ioi_offset`` (the file shows that frame), so with
    offset k a split holds GT frames ``margin − k .. F − margin − 1 − k``, the images and
    labels of ARCTIC's released split files (whose first image is ``…/00010.jpg``).

    Args:
        root: the data root (protocol files, misc.json for ``ioi_offset``).
        protocol: ``"p1"`` (views 1..8) or ``"p2"`` (view 0) (also ``p1a``/``p2a``).
        split: ``train``/``val``/``test`` (mini/tiny/small prefixes are stripped).
        processed: ``{"sid/seq": process_sequence(...)}``; sequences missing here are read
            from ``root`` and processed (ego image size from ``root.world_meta()``).
        frame_margin: frames skipped at each end (ARCTIC: 10).

    Returns:
        ``{"data_dict": {"sid/seq": {"cam_coord", "2d", "bbox", "params"}}, "imgnames": [...]}``.
        Image names have the file numbers ``margin .. F − margin − 1`` (frame-major, then
        views), as ARCTIC's; the dataset pairs file ``n`` with GT index ``n − ioi_offset``.

    Raises:
        AssetError: a subject's ``|ioi_offset|`` exceeds ``frame_margin`` (listed images
            would have no GT frame).
    """
    split = canonical_split(split)
    views = protocol_views(protocol)
    seqs = root.protocol(protocol)[split]
    data_dict: dict[str, dict[str, Any]] = {}
    imgnames: list[str] = []
    for key in seqs:
        sid, name = key.split("/")
        data = processed.get(key) if processed is not None else None
        if data is None:
            layers = root.mano_layers()
            data = process_sequence(
                root.sequence(sid, name), layers, root.object_layer(), ego_image_size=root.world_meta().ego_image_size
            )
        data_dict[key] = {k: data[k] for k in REQUEST_KEYS}
        F = int(data["params"]["rot_r"].shape[0])
        _check_offset(root, sid, frame_margin)
        for frame in inner_frames(F, frame_margin).tolist():
            for view in views:
                imgnames.append(image_name(sid, name, view, frame))
    if len(set(imgnames)) != len(imgnames):
        raise AssetError(root.protocol_path(protocol), f"split {split} lists an image twice")
    return {"data_dict": data_dict, "imgnames": imgnames}


def _save_npy_atomic(path: Path, obj: Any) -> None:
    """``np.save`` of a Python object to ``path`` via a temporary file."""
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_open(path) as fh:
        np.save(fh, np.asarray(obj, dtype=object) if not isinstance(obj, np.ndarray) else obj, allow_pickle=True)


def write_processed_splits(
    data_root: PathLike,
    protocols: Sequence[str] = ("p1", "p2"),
    splits: Sequence[str] = ("train", "val"),
    progress: bool = True,
) -> dict[str, Path]:
    """Process every sequence the protocols need and write ``splits/<p>_<split>.npy``.

    Each sequence is processed once (shared by all protocols/splits). The ego image size
    comes from ``meta/hogsa_world.json`` (ARCTIC default 2800×2000). Files are written
    with ``np.save`` (a pickled dict, as ARCTIC's), deterministically and atomically.

    Args:
        data_root: ARCTIC ``./data`` folder.
        protocols: protocol names with a ``splits_json/protocol_<p>.json``.
        splits: split names.
        progress: show a tqdm bar over the sequences being processed.

    Returns:
        ``{"p1_train": path, ...}``.
    """
    root = ArcticRoot(data_root)
    ego_size = root.world_meta().ego_image_size
    plan = {(p, canonical_split(s)): root.protocol(p)[canonical_split(s)] for p in protocols for s in splits}
    for p in protocols:
        protocol_views(p)
    needed: list[str] = []
    for seqs in plan.values():
        needed.extend(s for s in seqs if s not in needed)
    processed: dict[str, dict[str, Any]] = {}
    if needed:
        layers = root.mano_layers()
        obj_layer = root.object_layer()
    with tqdm(needed, desc="ARCTIC process_seq", unit="seq", disable=not progress) as bar:
        for key in bar:
            bar.set_postfix_str(key)
            sid, name = key.split("/")
            processed[key] = process_sequence(root.sequence(sid, name), layers, obj_layer, ego_image_size=ego_size)
    out: dict[str, Path] = {}
    for p, s in plan:
        data = build_split(root, p, s, processed)
        path = root.split_path(p, s)
        _save_npy_atomic(path, data)
        out[f"{p}_{s}"] = path
    return out
