"""Pictures of orbits and transfer grids: backgrounds, keypoints, titled sheets, animations."""

from __future__ import annotations

import shutil
from collections.abc import Mapping, Sequence
from pathlib import Path

import cv2
import imageio.v3 as iio
import numpy as np
import torch
from torch import Tensor

from hogsa_loader.compose import composite
from hogsa_loader.errors import PathLike
from hogsa_loader.extras import require
from hogsa_loader.render.mesh_raster import save_png
from hogsa_loader.view.grid import draw_skeletons

__all__ = [
    "DEMO_PHOTOS",
    "caption",
    "demo_photographs",
    "draw_keypoints",
    "neutral_background",
    "sheet",
    "to_uint8",
    "write_png",
    "write_video",
]

DEMO_PHOTOS = (
    "astronaut.png",
    "chelsea.png",
    "coffee.png",
    "rocket.jpg",
    "motorcycle_left.png",
    "motorcycle_right.png",
)
"""The colour photographs shipped with scikit-image that serve as default photo backgrounds."""


def neutral_background(size: int) -> Tensor:
    """(S, S, 3) a soft vertical grey gradient."""
    g = torch.linspace(0.88, 0.72, size)[:, None, None]
    return g.expand(size, size, 3).clone()


def to_uint8(rgb: Tensor, alpha: Tensor, background: Tensor) -> np.ndarray:
    """Premultiplied (N, S, S, 3) over (S, S, 3) or (N, S, S, 3) → (N, S, S, 3) uint8."""
    img = composite(rgb, alpha, background.expand_as(rgb), clamp=True)
    return (img * 255.0).round().to(torch.uint8).numpy()


def draw_keypoints(image: np.ndarray, kp: Mapping[str, np.ndarray]) -> np.ndarray:
    """Hand skeletons (right red, left blue) and object keypoints (yellow) on a copy of ``image``.

    Args:
        image: (H, W, 3) uint8 RGB; kp: ``joints.right`` / ``joints.left`` (21, 2),
            ``kp3d`` (K, 2) pixel coordinates.
    """
    hands = {s[0]: kp[f"joints.{s}"] for s in ("right", "left") if kp.get(f"joints.{s}") is not None}
    return draw_skeletons(image, hands, kp.get("kp3d"))


def sheet(rows: Sequence[tuple[str, Sequence[np.ndarray], Sequence[str]]], cols: int, pad: int = 4) -> np.ndarray:
    """A white sheet of titled rows of equal-size cells, each row wrapped at ``cols`` cells.

    Args:
        rows: ``(title, images (H, W, 3) uint8, captions)``.
        cols: cells per line.

    Returns:
        (H, W, 3) uint8 RGB.
    """
    cell_h, cell_w = next(im.shape[:2] for _, ims, _ in rows for im in ims)
    title_h, cap_h = 22, 16
    lines = [(r, i0) for r, (_, ims, _) in enumerate(rows) for i0 in range(0, max(1, len(ims)), cols)]
    H = pad + sum((title_h if i0 == 0 else 0) + cell_h + cap_h + pad for _, i0 in lines)
    W = pad + min(cols, max(len(ims) for _, ims, _ in rows)) * (cell_w + pad)
    out = np.full((H, W, 3), 255, np.uint8)
    y = pad
    for r, i0 in lines:
        title, ims, caps = rows[r]
        if i0 == 0:
            cv2.putText(out, title, (pad, y + 15), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (0, 0, 0), 1, cv2.LINE_AA)
            y += title_h
        for j, im in enumerate(ims[i0 : i0 + cols]):
            x = pad + j * (cell_w + pad)
            out[y : y + cell_h, x : x + cell_w] = im
            if i0 + j < len(caps):
                cv2.putText(
                    out,
                    caps[i0 + j],
                    (x + 2, y + cell_h + 12),
                    cv2.FONT_HERSHEY_SIMPLEX,
                    0.4,
                    (60, 60, 60),
                    1,
                    cv2.LINE_AA,
                )
        y += cell_h + cap_h + pad
    return out


def caption(img: np.ndarray, text: str) -> np.ndarray:
    """A copy of the (H, W, 3) uint8 ``img`` with ``text`` (white, outlined) in its top-left corner."""
    out = np.ascontiguousarray(img.copy())
    cv2.putText(out, text, (4, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.42, (0, 0, 0), 2, cv2.LINE_AA)
    cv2.putText(out, text, (4, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.42, (255, 255, 255), 1, cv2.LINE_AA)
    return out


def write_png(path: Path, img: np.ndarray) -> None:
    """Write an (H, W, 3) uint8 RGB image (OSError when it cannot be written)."""
    save_png(path, torch.from_numpy(np.ascontiguousarray(img)))


def write_video(path: Path, frames: Sequence[np.ndarray], fps: float) -> None:
    """Write (H, W, 3) uint8 RGB frames as a looping GIF (``.gif``, Pillow through imageio) or
    an H.264 MP4 (``.mp4``, needs the imageio-ffmpeg package)."""
    if path.suffix == ".gif":
        iio.imwrite(path, np.stack(frames), duration=1000.0 / fps, loop=0)
    else:
        iio.imwrite(path, np.stack(frames), fps=fps, codec="libx264", plugin="FFMPEG")


def demo_photographs(out: PathLike) -> Path:
    """Copy scikit-image's bundled colour photographs (:data:`DEMO_PHOTOS`) into ``out``; returns ``out``."""
    src = Path(require("skimage.data", "demo", "the demo's photographs").__file__).parent
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    for name in DEMO_PHOTOS:
        if (src / name).is_file() and not (out / name).is_file():
            shutil.copy2(src / name, out / name)
    return out
