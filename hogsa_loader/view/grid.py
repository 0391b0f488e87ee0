"""Pictures of ArcticNet-SF samples: the network input with its 2D labels drawn on it.

Works on real and synthetic samples alike (both are ``(inputs, targets, meta_info)`` of
:func:`~hogsa_loader.sample.targets.make_arctic_sample`): the image is un-normalised
with the config's ImageNet mean/std, hand joints come from ``mano.j2d.norm.{r,l}`` (drawn
only where ``right_valid`` / ``left_valid``), object keypoints from ``object.kp2d.norm``.
"""

from __future__ import annotations

from typing import Any, Mapping, Optional, Sequence

import cv2
import numpy as np
import torch

from hogsa_loader.assets.conventions import HAND_BONES
from hogsa_loader.sample.augment import ArcticConfig, unnormalize_kp2d

__all__ = ["input_image", "draw_labels", "draw_skeletons", "sample_grid"]

#: RGB colours of the drawn labels.
COLORS = {"r": (235, 60, 40), "l": (40, 120, 245), "object": (250, 215, 0)}


def input_image(img: Any, config: ArcticConfig = ArcticConfig()) -> np.ndarray:
    """(3, S, S) normalised network input → (S, S, 3) uint8 RGB."""
    x = img.detach().cpu().numpy() if isinstance(img, torch.Tensor) else np.asarray(img)
    mean = np.asarray(config.img_norm_mean, dtype=np.float64)[:, None, None]
    std = np.asarray(config.img_norm_std, dtype=np.float64)[:, None, None]
    rgb = (x.astype(np.float64) * std + mean).transpose(1, 2, 0)
    return np.clip(rgb * 255.0 + 0.5, 0, 255).astype(np.uint8)


def _np(x: Any) -> np.ndarray:
    return x.detach().cpu().numpy() if isinstance(x, torch.Tensor) else np.asarray(x)


def _pt(p: np.ndarray) -> tuple[int, int]:
    return int(round(float(p[0]))), int(round(float(p[1])))


def draw_labels(
    image: np.ndarray, targets: Mapping[str, Any], img_res: Optional[int] = None, scale: float = 1.0
) -> np.ndarray:
    """Draw hand skeletons (right red, left blue; thin bones, joint dots) and object keypoints
    (small yellow dots), thin enough that the pixels underneath stay visible.

    Args:
        image: (H, W, 3) uint8 RGB, the patch (optionally resized by ``scale``).
        targets: the sample's targets (single sample, not a batch).
        img_res: patch side the normalised keypoints refer to (default ``image`` height / scale).
        scale: output pixels per patch pixel.

    Returns:
        a drawn copy of ``image``.
    """
    res = int(img_res if img_res is not None else round(image.shape[0] / scale))
    hands = {
        side: unnormalize_kp2d(_np(targets[f"mano.j2d.norm.{side}"]), res) * scale
        for side, flag in (("r", "right_valid"), ("l", "left_valid"))
        if float(_np(targets[flag])) > 0
    }
    obj = None
    if float(_np(targets["is_valid"])) > 0:
        obj = unnormalize_kp2d(_np(targets["object.kp2d.norm"]), res) * scale
    return draw_skeletons(image, hands, obj)


def draw_skeletons(
    image: np.ndarray, hands: Mapping[str, np.ndarray], object_kp: Optional[np.ndarray] = None
) -> np.ndarray:
    """Hand skeletons (thin bones, joint dots) and object keypoints (small dots) on a copy of ``image``.

    Args:
        image: (H, W, 3) uint8 RGB.
        hands: ``{"r" | "l": (21, 2)}`` pixel coordinates (right red, left blue).
        object_kp: (K, 2) object keypoints in pixels (yellow), drawn under the hands.

    Returns:
        a drawn copy of ``image``.
    """
    out = np.ascontiguousarray(image.copy())
    for q in () if object_kp is None else object_kp:
        cv2.circle(out, _pt(q), 1, COLORS["object"], -1, cv2.LINE_AA)
    for side, p in hands.items():
        for a, b in HAND_BONES:
            cv2.line(out, _pt(p[a]), _pt(p[b]), COLORS[side], 1, cv2.LINE_AA)
        for q in p:
            cv2.circle(out, _pt(q), 2, COLORS[side], -1, cv2.LINE_AA)
    return out


def sample_grid(
    rows: Sequence[tuple[str, Sequence[tuple[Mapping[str, Any], Mapping[str, Any], Mapping[str, Any]]]]],
    config: ArcticConfig = ArcticConfig(),
    cell: int = 224,
    labels: bool = True,
) -> np.ndarray:
    """A grid with one titled row per group of samples, labels drawn on every cell.

    Args:
        rows: ``(title, samples)`` pairs; each sample is ``(inputs, targets, meta_info)``.
        config: the samples' config (normalisation, ``img_res``).
        cell: side of one cell in pixels.
        labels: draw the 2D labels (else the bare inputs).

    Returns:
        (H, W, 3) uint8 RGB image.
    """
    cols = max((len(s) for _, s in rows), default=1)
    title_h, pad = 22, 4
    H = len(rows) * (cell + title_h + pad) + pad
    W = cols * (cell + pad) + pad
    grid = np.full((H, W, 3), 255, np.uint8)
    for r, (title, samples) in enumerate(rows):
        y0 = pad + r * (cell + title_h + pad)
        cv2.putText(grid, title, (pad, y0 + 15), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (0, 0, 0), 1, cv2.LINE_AA)
        for c, (inputs, targets, _) in enumerate(samples):
            img = input_image(inputs["img"], config)
            s = cell / img.shape[0]
            img = cv2.resize(img, (cell, cell), interpolation=cv2.INTER_LINEAR if s > 1 else cv2.INTER_AREA)
            if labels:
                img = draw_labels(img, targets, config.img_res, scale=s)
            x0 = pad + c * (cell + pad)
            grid[y0 + title_h : y0 + title_h + cell, x0 : x0 + cell] = img
    return grid
