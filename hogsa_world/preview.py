"""``world_preview.png``: cropped images with the annotations drawn on top.

The joints and object keypoints are recomputed from the files alone (``raw_seqs`` +
``misc.json`` + ``body_models/mano`` + ``object_vtemplates``): MANO forward, object
articulation, camera projection, then ARCTIC's crop map for views 1..8 (object-centred
box, :func:`~hogsa_loader.assets.conventions.full_to_cropped`) or distortion + ego scale
for view 0. A misaligned annotation is therefore visible at a glance.
"""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import torch

from hogsa_loader.assets.arctic import read_npy
from hogsa_loader.assets.conventions import (
    HAND_BONES,
    allocentric_bbox,
    distort_points,
    full_to_cropped,
    project,
    transform,
)
from hogsa_loader.assets.hands.mano import MANOLayer
from hogsa_loader.assets.hands.mano_io import load_mano
from hogsa_loader.assets.objects.articulated import articulate
from hogsa_loader.assets.objects.template import load_object_template
from hogsa_loader.errors import PathLike

__all__ = ["HAND_BONES", "project_annotations", "write_world_preview"]

_COLORS = {"right": (230, 60, 40), "left": (40, 110, 240), "kp_top": (250, 220, 0), "kp_bottom": (0, 230, 200)}


class _World:
    """Files of a generated world, loaded once."""

    def __init__(self, root: Path) -> None:
        self.root = root
        self.data = root / "arctic_data" / "data"
        self.meta = json.loads((self.data / "meta" / "hogsa_world.json").read_text())
        self.misc = json.loads((self.data / "meta" / "misc.json").read_text())
        mano_dir = root / "body_models" / "mano"
        self.layers = {
            s: MANOLayer(load_mano(mano_dir, side=s), flat_hand_mean=False, dtype=torch.float64)
            for s in ("right", "left")
        }
        self._templates: dict = {}
        self._load_template = load_object_template

    def template(self, name: str):
        if name not in self._templates:
            self._templates[name] = self._load_template(
                self.data / "meta" / "object_vtemplates" / name, load_texture=False
            )
        return self._templates[name]

    def raw(self, sid: str, seq: str) -> tuple[dict, np.ndarray, dict]:
        base = self.data / "raw_seqs" / sid
        return (
            read_npy(base / f"{seq}.mano.npy"),
            np.asarray(read_npy(base / f"{seq}.object.npy")),
            read_npy(base / f"{seq}.egocam.dist.npy"),
        )


def project_annotations(world: "_World", sid: str, seq: str, frames: list[int], view: int) -> dict:
    """2D joints (21 per hand) and object keypoints (16 top, 16 bottom) in cropped-image pixels.

    Returns:
        dict ``right``/``left`` (n, 21, 2), ``kp_top``/``kp_bottom`` (n, 16, 2).
    """
    mano, obj, ego = world.raw(sid, seq)
    idx = np.asarray(frames)
    pts = {}
    for side, layer in world.layers.items():
        p = mano[side]
        out = layer(
            global_orient=torch.as_tensor(p["rot"][idx], dtype=torch.float64),
            hand_pose=torch.as_tensor(p["pose"][idx], dtype=torch.float64),
            betas=torch.as_tensor(np.repeat(p["shape"][None], len(idx), 0), dtype=torch.float64),
            transl=torch.as_tensor(p["trans"][idx], dtype=torch.float64),
        )
        pts[side] = out.joints.numpy()
    t = world.template(seq.split("_")[0])
    op = torch.as_tensor(obj[idx].astype(np.float64))

    def pose(points: np.ndarray, top: bool) -> np.ndarray:
        x = torch.as_tensor(points, dtype=torch.float64)[None].expand(len(idx), -1, -1)
        return articulate(x, torch.full((points.shape[0],), top), op[:, 0], op[:, 1:4], op[:, 4:7] / 1000).numpy()

    pts["kp_top"] = pose(t.kp_top, True)
    pts["kp_bottom"] = pose(t.kp_bottom, False)
    mesh = articulate(
        torch.as_tensor(t.verts, dtype=torch.float64)[None].expand(len(idx), -1, -1),
        torch.as_tensor(t.parts == 0),
        op[:, 0],
        op[:, 1:4],
        op[:, 4:7] / 1000,
    ).numpy()
    m = world.misc[sid]
    out2d = {}
    if view == 0:
        w2c = np.zeros((len(idx), 4, 4))
        w2c[:, :3, :3] = ego["R_k_cam_np"][idx]
        w2c[:, :3, 3] = ego["T_k_cam_np"][idx, :, 0]
        w2c[:, 3, 3] = 1
        K = ego["intrinsics"].astype(np.float64)
        s = world.meta["ego_image_scale"]
        for k, p in pts.items():
            out2d[k] = project(distort_points(transform(w2c, p), ego["dist8"].astype(np.float64)), K) * s
        return out2d
    K = np.asarray(m["intris_mat"][view - 1])
    w2c = np.asarray(m["world2cam"][view - 1])
    bbox = allocentric_bbox(project(transform(w2c, mesh), K))
    for k, p in pts.items():
        out2d[k] = full_to_cropped(project(transform(w2c, p), K), bbox, world.meta["cropped_size"])
    return out2d


def _draw(img: np.ndarray, ann: dict, j: int, scale: float) -> np.ndarray:
    img = np.ascontiguousarray(img)
    lw = 1
    for side in ("right", "left"):
        p = ann[side][j] * scale
        for a, b in HAND_BONES:
            cv2.line(
                img,
                tuple(int(round(x)) for x in p[a]),
                tuple(int(round(x)) for x in p[b]),
                _COLORS[side],
                lw,
                cv2.LINE_AA,
            )
        for q in p:
            cv2.circle(img, (int(round(q[0])), int(round(q[1]))), 2, _COLORS[side], -1, cv2.LINE_AA)
    for k in ("kp_top", "kp_bottom"):
        for q in ann[k][j] * scale:
            cv2.drawMarker(img, (int(round(q[0])), int(round(q[1]))), _COLORS[k], cv2.MARKER_CROSS, 5, 1)
    return img


def _cell(world: "_World", sid: str, seq: str, view: int, frame: int, ann: dict, j: int, h: int) -> np.ndarray:
    m = world.misc[sid]
    path = world.data / "cropped_images" / sid / seq / str(view) / f"{frame + m['ioi_offset']:05d}.jpg"
    img = cv2.cvtColor(cv2.imread(str(path)), cv2.COLOR_BGR2RGB)
    scale = h / img.shape[0]
    img = cv2.resize(img, (int(round(img.shape[1] * scale)), h), interpolation=cv2.INTER_AREA)
    img = _draw(img, ann, j, scale)
    w = int(round(1.4 * h))
    cell = np.full((h, w, 3), 255, np.uint8)
    x0 = (w - img.shape[1]) // 2
    cell[:, x0 : x0 + img.shape[1]] = img[:, :w]
    cv2.putText(
        cell, f"{sid}/{seq} v{view} f{frame}", (4, 12), cv2.FONT_HERSHEY_SIMPLEX, 0.35, (0, 0, 0), 1, cv2.LINE_AA
    )
    return cell


def write_world_preview(
    root: PathLike, path: PathLike, frames: int = 5, views: tuple[int, ...] = (0, 2, 5), cell_height: int = 200
) -> Path:
    """Write the preview grid.

    Layout: one row with all 9 views of the first sequence at its middle frame, then per
    sequence ``len(views)`` rows x ``frames`` columns (frames spread over the sequence).
    Right-hand joints red, left blue, object top keypoints yellow, bottom cyan.
    """
    world = _World(Path(root))
    rows = []
    seqs = [(s["sid"], s["seq"], s["num_frames"]) for s in world.meta["sequences"]]
    sid, seq, F = seqs[0]
    mid = int(0.55 * (F - 1))
    rows.append(
        np.concatenate(
            [
                _cell(world, sid, seq, v, mid, project_annotations(world, sid, seq, [mid], v), 0, cell_height)
                for v in range(9)
            ],
            axis=1,
        )
    )
    width = rows[0].shape[1]
    for sid, seq, F in seqs:
        picks = [int(round(f * (F - 1))) for f in np.linspace(0.1, 0.9, frames)]
        for v in views:
            ann = project_annotations(world, sid, seq, picks, v)
            row = np.concatenate([_cell(world, sid, seq, v, f, ann, j, cell_height) for j, f in enumerate(picks)], 1)
            pad = np.full((row.shape[0], max(0, width - row.shape[1]), 3), 255, np.uint8)
            rows.append(np.concatenate([row, pad], axis=1)[:, :width])
    sheet = np.concatenate(rows, axis=0)
    path = Path(path)
    cv2.imwrite(str(path), cv2.cvtColor(sheet, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_PNG_COMPRESSION, 6])
    return path
