"""Background sources for compositing synthetic hand-object crops, and the loader's choice.

:func:`make_backgrounds` picks a source from the loader's arguments (its docstring describes
each source). Every source draws ``n`` backgrounds of a requested size from an explicit
:class:`torch.Generator`, so the same generator state gives the same images, whatever the
cache holds or which DataLoader worker asks. The base class, the crop settings and the
decoded-image cache live in :mod:`~hogsa_loader.compose.sources`; this module re-exports the
public names.
"""

from __future__ import annotations

import warnings
from typing import Optional, Sequence, Union

from hogsa_loader.compose.coco import COCO_PERSON, CocoBackgrounds, default_cache_dir
from hogsa_loader.compose.plate_backgrounds import PlateBackgrounds
from hogsa_loader.compose.procedural import ProceduralBackgrounds
from hogsa_loader.compose.sources import IMAGE_EXTENSIONS, BackgroundSource, CropSpec, FolderBackgrounds, ImageCache
from hogsa_loader.errors import PathLike

__all__ = [
    "BackgroundSource",
    "default_cache_dir",
    "CocoBackgrounds",
    "FolderBackgrounds",
    "ProceduralBackgrounds",
    "ImageCache",
    "CropSpec",
    "make_backgrounds",
    "IMAGE_EXTENSIONS",
    "COCO_PERSON",
]

_FALLBACK_WARNED = False


def make_backgrounds(
    coco_root: Optional[PathLike] = None,
    coco_ann: Optional[PathLike] = None,
    folder: Optional[PathLike] = None,
    categories: Optional[Sequence[str]] = None,
    exclude_person: bool = False,
    image_dir: Optional[PathLike] = None,
    crop: CropSpec = CropSpec(),
    cache_bytes: int = 512 * 2**20,
    index_cache: Union[bool, PathLike, None] = True,
    camera_plates: bool = False,
) -> BackgroundSource:
    """The background source the loader's arguments ask for.

    * ``coco_root`` and/or ``coco_ann`` → :class:`CocoBackgrounds` (``categories``,
      ``exclude_person``, ``image_dir`` and ``index_cache`` apply);
    * else ``folder`` → :class:`FolderBackgrounds`, or with ``camera_plates`` (a folder of
      ``hogsa plates``) :class:`~hogsa_loader.compose.plate_backgrounds.PlateBackgrounds`,
      which gives a sample seen through a dataset camera that camera's own plate;
    * else → :class:`ProceduralBackgrounds`, with a one-time warning (per process).

    Giving both a COCO source and a folder is an error.

    Raises:
        AssetError: missing or malformed files (see the classes).

    The sources:

    * :class:`~hogsa_loader.compose.coco.CocoBackgrounds` — a real COCO folder read through
      ``pycocotools``: random image (optionally only images showing given categories,
      optionally without people), random crop of random scale, optional horizontal flip;
    * :class:`~hogsa_loader.compose.sources.FolderBackgrounds` — any folder of ``.jpg``/``.png``
      images, same crops;
    * :class:`~hogsa_loader.compose.procedural.ProceduralBackgrounds` — the documented fallback
      when no image is given: gradients, multi-octave value noise, stripes/checkers, soft blobs
      and "table top" planes with lighting falloff and sensor grain.
    """
    global _FALLBACK_WARNED
    if (coco_root is not None or coco_ann is not None) and folder is not None:
        raise ValueError("give either a COCO source (coco_root/coco_ann) or a folder, not both")
    if camera_plates and folder is None:
        raise ValueError("camera_plates needs a folder of plates (hogsa plates)")
    if coco_root is not None or coco_ann is not None:
        return CocoBackgrounds(
            coco_root,
            coco_ann,
            image_dir=image_dir,
            categories=categories,
            exclude_person=exclude_person,
            crop=crop,
            cache_bytes=cache_bytes,
            index_cache=index_cache,
        )
    if categories is not None or exclude_person or image_dir is not None:
        raise ValueError("categories, exclude_person and image_dir apply to COCO images; give coco_root/coco_ann")
    if folder is not None:
        if camera_plates:
            return PlateBackgrounds(folder, crop=crop, cache_bytes=cache_bytes)
        return FolderBackgrounds(folder, crop=crop, cache_bytes=cache_bytes)
    if not _FALLBACK_WARNED:
        _FALLBACK_WARNED = True
        warnings.warn(
            "no background images given (coco_root / coco_ann / folder): using procedural "
            "backgrounds (gradients, noise, patterns); pass COCO for photoreal training data",
            UserWarning,
            stacklevel=2,
        )
    return ProceduralBackgrounds()
