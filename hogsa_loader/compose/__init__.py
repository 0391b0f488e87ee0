"""Backgrounds and alpha compositing of synthetic hand-object renders.

:func:`make_backgrounds` (:mod:`~hogsa_loader.compose.backgrounds`) picks a source, all ``sample(n, H, W, generator)`` →
``(n, H, W, 3)`` float32 in [0, 1], deterministic given the generator: :class:`CocoBackgrounds` (pycocotools,
:mod:`~hogsa_loader.compose.coco`), :class:`FolderBackgrounds` (base class in :mod:`~hogsa_loader.compose.sources`),
:class:`PlateBackgrounds` (a dataset's clean plates, each sample on its own camera's,
:mod:`~hogsa_loader.compose.plate_backgrounds`), :class:`ProceduralBackgrounds` (fallback,
:mod:`~hogsa_loader.compose.procedural`). :mod:`~hogsa_loader.compose.alpha`
has :func:`composite` (premultiplied "over"), :class:`AlphaComposite`, optional :func:`harmonize` / :class:`Harmonize`::

    from hogsa_loader.compose import AlphaComposite, make_backgrounds
    bgs = make_backgrounds(coco_root="/data/coco", categories=["dining table"], exclude_person=True)
    gen = torch.Generator().manual_seed(0)
    out = AlphaComposite()(rgb, alpha, bgs.sample(rgb.shape[0], H, W, gen).to(rgb.device))
"""

from hogsa_loader.compose.alpha import AlphaComposite, Harmonize, composite, harmonize
from hogsa_loader.compose.backgrounds import (
    COCO_PERSON,
    IMAGE_EXTENSIONS,
    BackgroundSource,
    CocoBackgrounds,
    CropSpec,
    FolderBackgrounds,
    ImageCache,
    ProceduralBackgrounds,
    make_backgrounds,
)
from hogsa_loader.compose.plate_backgrounds import PlateBackgrounds

__all__ = [
    "AlphaComposite",
    "BackgroundSource",
    "COCO_PERSON",
    "CocoBackgrounds",
    "CropSpec",
    "FolderBackgrounds",
    "Harmonize",
    "IMAGE_EXTENSIONS",
    "ImageCache",
    "PlateBackgrounds",
    "ProceduralBackgrounds",
    "composite",
    "harmonize",
    "make_backgrounds",
]
