"""Preview sheets of the assets: both hands in named poses, objects at several openings.

Rendered with the classical mesh rasteriser (:mod:`hogsa_loader.render.mesh_raster`).
"""

from __future__ import annotations

from typing import Sequence

import cv2
import numpy as np
import torch

from hogsa_loader.assets.hands.anatomy import named_articulation
from hogsa_loader.assets.hands.mano import MANOLayer
from hogsa_loader.assets.hands.mano_io import ManoModelData
from hogsa_loader.assets.objects.articulated import articulate
from hogsa_loader.errors import PathLike
from hogsa_loader.render.mesh_raster import (
    Light,
    MeshPart,
    camera_look_at,
    intrinsics_from_fov,
    render_meshes,
    save_png,
)

__all__ = ["hand_preview", "object_preview", "save_sheet"]

_BG = (0.93, 0.93, 0.95)


def _label(img: np.ndarray, text: str) -> np.ndarray:
    out = np.ascontiguousarray((img * 255).astype(np.uint8))
    cv2.putText(out, text, (6, 18), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (30, 30, 30), 1, cv2.LINE_AA)
    return out.astype(np.float32) / 255.0


def _view(
    parts: Sequence[MeshPart], center: np.ndarray, direction: np.ndarray, up: np.ndarray, dist: float, size: int
) -> np.ndarray:
    eye = center + dist * direction / np.linalg.norm(direction)
    w2c = camera_look_at(torch.tensor(eye), torch.tensor(center), torch.tensor(up)).float()
    K = intrinsics_from_fov(35.0, size, size)
    out = render_meshes(
        parts, w2c, K, size, size, light=Light(direction=(0.3, 0.5, 1.0)), background=_BG, supersample=2
    )
    return out.rgb.numpy()


def hand_preview(
    right: ManoModelData,
    left: ManoModelData,
    poses: Sequence[str] = ("flat", "relaxed", "fist", "pinch", "spread", "point"),
    size: int = 224,
) -> np.ndarray:
    """(2 * size, len(poses) * size, 3) sheet: right hand (top row), left hand (bottom row).

    Views look at the back of the hand from above the thumb side, fingers pointing up.
    """
    rows = []
    for model in (right, left):
        layer = MANOLayer(model, flat_hand_mean=True, dtype=torch.float32)
        colors = torch.tensor(
            model.vertex_colors if model.vertex_colors is not None else np.full((model.num_verts, 3), 0.75),
            dtype=torch.float32,
        )
        faces = torch.as_tensor(model.faces)
        cells = []
        for name in poses:
            art = torch.tensor(named_articulation(model, name), dtype=torch.float32)[None]
            v = layer(hand_pose=art).vertices[0]
            center = v.mean(0).numpy()
            side = 1.0 if model.side == "right" else -1.0
            img = _view(
                [MeshPart(v, faces, 1, vertex_colors=colors)],
                center,
                np.array([0.35 * side, 1.0, 0.55]),
                np.array([-side, 0.0, 0.0]),
                0.42,
                size,
            )
            cells.append(_label(img, f"{model.side} {name}"))
        rows.append(np.concatenate(cells, axis=1))
    return np.concatenate(rows, axis=0)


def object_preview(templates: Sequence, angles: Sequence[float] = (0.0, 0.3, 0.9), size: int = 224) -> np.ndarray:
    """(len(templates) * size, len(angles) * size, 3) sheet of textured objects opening."""
    rows = []
    for t in templates:
        if t.tex_verts is None:
            raise ValueError(f"object {t.name!r} has no textured mesh to preview")
        verts = torch.tensor(t.tex_verts, dtype=torch.float32)
        is_top = torch.tensor(t.tex_parts == 0)
        tex = torch.tensor(t.texture, dtype=torch.float32) / 255.0
        uv = torch.tensor(t.tex_uv, dtype=torch.float32)
        faces = torch.as_tensor(t.tex_faces)
        extent = float(np.linalg.norm(t.verts.max(0) - t.verts.min(0)))
        cells = []
        for a in angles:
            v = articulate(verts[None], is_top, torch.tensor([a]), torch.zeros(1, 3), torch.zeros(1, 3))[0]
            center = t.verts.mean(0)
            img = _view(
                [MeshPart(v, faces, 1, uv=uv, texture=tex)],
                center,
                np.array([-0.6, 0.7, 0.9]),
                np.array([0.0, 1.0, 0.0]),
                2.2 * extent,
                size,
            )
            cells.append(_label(img, f"{t.name} theta={a:.2f}"))
        rows.append(np.concatenate(cells, axis=1))
    return np.concatenate(rows, axis=0)


def save_sheet(path: PathLike, sheet: np.ndarray) -> None:
    """Write a float (H, W, 3) sheet in [0, 1] as PNG."""
    save_png(path, torch.from_numpy(np.ascontiguousarray(sheet)))
