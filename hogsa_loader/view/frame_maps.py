"""A picture of written frame maps: each cropped image beside its part mask and depth map."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from hogsa_loader.io.images import read_image
from hogsa_loader.view.pictures import sheet

__all__ = ["frame_maps_sheet"]

#: RGB of each part id (background, right hand, left hand, object top, object bottom).
_PART_RGB = np.array([[0, 0, 0], [230, 80, 60], [60, 120, 230], [240, 200, 40], [70, 190, 90]], np.uint8)


def _cell(img: np.ndarray, side: int) -> np.ndarray:
    return cv2.resize(img, (side, side), interpolation=cv2.INTER_NEAREST)


def frame_maps_sheet(folder: Path, images: list[Path], side: int = 192, limit: int = 4) -> np.ndarray:
    """(H, W, 3) uint8 RGB: one row per cropped image of ``images`` (at most ``limit``): the
    image, its ``<name>_mask.png`` in part colours over the image, its ``<name>_depth.png``
    (near = bright, none = black), from ``folder``."""
    rows = []
    for path in images[:limit]:
        rgb = read_image(path)[:, :, ::-1]
        mask = read_image(folder / f"{path.stem}_mask.png", cv2.IMREAD_UNCHANGED)
        depth = read_image(folder / f"{path.stem}_depth.png", cv2.IMREAD_UNCHANGED).astype(np.float32)
        rgb = cv2.resize(rgb, mask.shape[::-1], interpolation=cv2.INTER_AREA)
        over = np.where(mask[..., None] > 0, (0.4 * rgb + 0.6 * _PART_RGB[np.minimum(mask, 4)]), rgb)
        fg = depth > 0
        shade = np.zeros(depth.shape, np.uint8)
        if fg.any():
            lo, hi = depth[fg].min(), depth[fg].max()
            shade[fg] = (255 - 200 * (depth[fg] - lo) / max(hi - lo, 1e-6)).astype(np.uint8)
        depth_rgb = cv2.applyColorMap(shade, cv2.COLORMAP_VIRIDIS)[:, :, ::-1] * fg[..., None]
        cells = [_cell(np.ascontiguousarray(x.astype(np.uint8)), side) for x in (rgb, over, depth_rgb)]
        rows.append((path.stem, cells, ["image", "part mask", "depth"]))
    return sheet(rows, cols=3)
