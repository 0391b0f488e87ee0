"""Clean background plates as a background source that knows which camera each plate is.

:class:`PlateBackgrounds` reads a folder written by :func:`~hogsa_loader.compose.plates.build_plates`;
:func:`crop_to_plate` maps a dataset crop's pixels into its plate.
"""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import cv2
import numpy as np

from hogsa_loader.assets.conventions import BBOX_PIXELS_PER_SCALE, CROP_ENLARGE, cropped_intrinsics
from hogsa_loader.compose.sources import CropSpec, FolderBackgrounds
from hogsa_loader.errors import AssetError, PathLike, read_json

__all__ = ["PLATES_MANIFEST", "PlateBackgrounds", "crop_to_plate"]

#: File name of a plate folder's manifest.
PLATES_MANIFEST = "plates.json"


def crop_to_plate(bbox: np.ndarray, cropped_size: int, resized: int, gain: float) -> np.ndarray:
    """(2, 3) affine from a resized cropped image's pixels to plate pixels (OpenCV coordinates).

    The cropped image is the dataset's crop of the full image
    (:func:`~hogsa_loader.assets.conventions.cropped_intrinsics`), resized to ``resized``
    pixels; the plate is the full image scaled by ``gain``. Resizing scales coordinates
    whose pixel centres sit at ``j + 0.5``, so the scales are applied in those.

    Args:
        bbox: (3,) ``(cx, cy, scale)`` of the frame in the full image.
        cropped_size: side of the dataset's cropped images.
        resized: side of the resized crop.
        gain: plate width / full image width.
    """
    half = np.array([[1.0, 0.0, 0.5], [0.0, 1.0, 0.5], [0.0, 0.0, 1.0]])  # OpenCV -> centres at j + 0.5
    full_to_crop = cropped_intrinsics(np.eye(3), np.asarray(bbox, np.float64), cropped_size)
    M = (
        np.linalg.inv(half)
        @ np.diag([gain, gain, 1.0])
        @ half
        @ np.linalg.inv(full_to_crop)
        @ np.linalg.inv(half)
        @ np.diag([cropped_size / resized, cropped_size / resized, 1.0])
        @ half
    )
    return M[:2]


class PlateBackgrounds(FolderBackgrounds):
    """Background plates, each the backdrop of one dataset camera.

    :meth:`sample` draws random crops of random plates exactly as :class:`FolderBackgrounds`
    over the same (flat) folder does. :meth:`camera_plate` gives a sample rendered through a
    dataset camera that camera's own backdrop instead: its plate cut by the sample's crop box as
    the dataset cuts its cropped images (the square of side ``1.5 · 200 · scale`` around the box
    centre), so table, floor and walls stand where the real frames of that view have them;
    pixels beyond the full frame are black, as in the dataset's crops, and pixels inside the
    frame but beyond the region the plate covers repeat the plate's edge.

    Args:
        folder: a plate folder (PNGs and ``plates.json``: per plate its subject, view, full
            frame size and the box of the scaled frame it keeps).
        crop: random crop settings of :meth:`sample`.
        cache_bytes: LRU capacity of decoded images (per process).

    Raises:
        AssetError: no manifest, or a manifest that names a missing plate.
    """

    kind = "plates"

    def __init__(self, folder: PathLike, crop: CropSpec = CropSpec(), cache_bytes: int = 512 * 2**20) -> None:
        folder = Path(folder)
        manifest = folder / PLATES_MANIFEST
        if not manifest.is_file():
            raise AssetError(manifest, "is missing: camera plates need the manifest written by `hogsa plates`")
        super().__init__(folder, recursive=False, crop=crop, cache_bytes=cache_bytes)
        rec = read_json(manifest)
        index = {p.name: i for i, p in enumerate(self.paths)}
        self._plates: dict[tuple[str, int], tuple[int, float, tuple[int, int], tuple[float, float]]] = {}
        try:
            width = float(rec["settings"]["width"])
            for p in rec["plates"]:
                if p["file"] not in index:
                    raise AssetError(folder / p["file"], f"is named by {PLATES_MANIFEST} but missing")
                full_w, full_h = (int(v) for v in p["full_size"])
                where = (float(p["box"][0]), float(p["box"][1]))
                self._plates[(str(p["subject"]), int(p["view"]))] = (
                    index[p["file"]],
                    width / full_w,
                    (full_w, full_h),
                    where,
                )
        except (KeyError, IndexError, TypeError, ValueError) as e:
            raise AssetError(manifest, f"is not a plate manifest ({e!r})") from e

    def has_plate(self, subject: str, view: int) -> bool:
        """Whether the folder has the plate of (``subject``, ``view``)."""
        return (str(subject), int(view)) in self._plates

    def camera_plate(self, subject: str, view: int, box_full: np.ndarray, size: int) -> Optional[np.ndarray]:
        """The backdrop of dataset camera (``subject``, ``view``) in a crop of that camera.

        Args:
            subject, view: the dataset camera.
            box_full: (3,) ``(cx, cy, scale)`` crop box in its full-image pixels.
            size: side of the square output crop.

        Returns:
            (size, size, 3) uint8 RGB, or None when the folder has no plate of that camera.
            Output pixel ``j`` (OpenCV convention: integer coordinates are pixel centres) shows
            full-image pixel ``j · 1.5 · 200 · scale / size + (cx − 0.75 · 200 · scale)``, the
            dataset's crop mapping, so labels made with it land on the plate where they should.

        Raises:
            AssetError: the plate image cannot be read.
        """
        entry = self._plates.get((str(subject), int(view)))
        if entry is None:
            return None
        idx, gain, (full_w, full_h), (x0, y0) = entry
        img = self._decode(idx, 1)
        if img is None:
            raise AssetError(self.paths[idx], "cannot be read as an image")
        box = np.asarray(box_full, np.float64)
        side = CROP_ENLARGE * BBOX_PIXELS_PER_SCALE * float(box[2])
        # sample at the plate's own pixel density, then area-average down to the output
        inter = max(int(size), int(np.ceil(side * gain)))
        M = crop_to_plate(box, int(size), inter, gain)
        M[:, 2] -= (x0, y0)
        out = cv2.warpAffine(
            img, M, (inter, inter), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP, borderMode=cv2.BORDER_REPLICATE
        )
        if inter != size:
            out = cv2.resize(out, (int(size), int(size)), interpolation=cv2.INTER_AREA)
        # the full frame's extent in output pixels: black beyond it
        k = size / side
        cols = np.arange(size) / k + box[0] - side / 2.0  # output pixel j shows full-image x = j / k + origin
        rows = np.arange(size) / k + box[1] - side / 2.0
        out[:, (cols < -0.5) | (cols > full_w - 0.5)] = 0
        out[(rows < -0.5) | (rows > full_h - 0.5)] = 0
        return np.ascontiguousarray(out)
