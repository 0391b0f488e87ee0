"""A synthetic frame before ARCTIC's augmentation: the interface between rendering and samples.

The synthetic pipeline renders and composites a crop, then describes it exactly as a real
ARCTIC cropped image is described, so the same sample builder
(:func:`hogsa_loader.sample.targets.make_arctic_sample`) turns either into
``(inputs, targets, meta_info)``. Offline export stores :class:`SynthFrame` records (image
+ labels), so augmentation stays random when the shards are read back.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Optional

import numpy as np

from hogsa_loader.sample.targets import HandLabels, ObjectLabels

__all__ = ["SynthFrame"]


@dataclass
class SynthFrame:
    """One composited synthetic crop and its labels.

    Attributes:
        image: (S, S, 3) uint8 RGB — the composited crop; every 2D label is in its pixels
            (OpenCV convention: integer coordinates are pixel centres).
        alpha: (S, S) float32 rendered opacity of hands + object in [0, 1].
        part_alpha: (S, S, 3) float32 per-part opacity (right hand, left hand, object).
        bbox: (3,) ``(cx, cy, scale)`` ARCTIC crop box in ``image`` pixels (side ``200·scale``).
        K_full: (3, 3) intrinsics of the virtual full-resolution camera image.
        image_size: ``(W, H)`` of that full image.
        right, left: hand labels (2D in ``image`` pixels, 3D in the full camera frame).
        obj: object labels.
        imgname: ``meta_info["imgname"]`` (unique, names the synthetic source).
        meta: JSON-able provenance (seed, sample index, subject, object, pose source,
            camera source) — enough to reproduce the frame.
        egocentric: an egocentric (``p2``) frame: ``image`` is the whole frame scaled, its
            labels undistorted (ARCTIC's view-0 convention); dist: (8,) its lens distortion.
        extra_targets: targets added after ARCTIC's (e.g. the interaction field of
            :mod:`~hogsa_loader.sample.interfield`); the offline export stores them
            (``labels.npz`` members ``extra.<key>``).
    """

    image: np.ndarray
    alpha: np.ndarray
    part_alpha: np.ndarray
    bbox: np.ndarray
    K_full: np.ndarray
    image_size: tuple[int, int]
    right: HandLabels
    left: HandLabels
    obj: ObjectLabels
    imgname: str
    meta: dict[str, Any] = field(default_factory=dict)
    extra_targets: dict[str, Any] = field(default_factory=dict)
    egocentric: bool = False
    dist: Optional[np.ndarray] = None
