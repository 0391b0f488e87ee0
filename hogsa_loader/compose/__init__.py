"""Backgrounds and alpha compositing of synthetic hand-object renders.

* :mod:`~hogsa_loader.compose.backgrounds` — :func:`make_backgrounds` and the sources
  (:class:`CocoBackgrounds` via pycocotools in :mod:`~hogsa_loader.compose.coco`,
  :class:`FolderBackgrounds` and the base class in :mod:`~hogsa_loader.compose.sources`,
  the :class:`ProceduralBackgrounds` fallback in :mod:`~hogsa_loader.compose.procedural`),
  all ``sample(n, H, W, generator)`` → ``(n, H, W, 3)`` float32 in [0, 1], deterministic
  given the generator.
* :mod:`~hogsa_loader.compose.alpha` — :func:`composite` (premultiplied "over"),
  :class:`AlphaComposite`, optional :func:`harmonize` / :class:`Harmonize`.

Example::

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
    "ProceduralBackgrounds",
    "composite",
    "harmonize",
    "make_backgrounds",
]
