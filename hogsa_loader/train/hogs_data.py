"""Training data of one HOGS model: the (frame, view) images of one subject + object.

For every selected sequence of the subject that shows the object, every allocentric view
and frame becomes a :class:`ViewSample`: the cropped image and its part mask (resized to
the training resolution), the camera (world→camera and *render* intrinsics of the crop)
and the annotated poses of that frame. Crop boxes are recomputed exactly as ARCTIC's
processing does (object-template vertices posed by the object layer, projected, then
:func:`~hogsa_loader.datasets.conventions.allocentric_bbox`), and the intrinsics are
``render_intrinsics(cropped_intrinsics(K, bbox, cropped_size))`` scaled to the training
resolution, so rendered pixels line up with the labels.

Split: ``eval_views`` (camera views never used in training) and every ``eval_every_frame``-th
frame are held out; evaluation uses held-out views × held-out frames.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional, Sequence

import cv2
import numpy as np
import torch
from torch import Tensor

from hogsa_loader.datasets.arctic import ArcticRoot
from hogsa_loader.datasets.conventions import (
    ALLO_VIEWS,
    allocentric_bbox,
    cropped_intrinsics,
    project,
    render_intrinsics,
    transform,
)
from hogsa_loader.datasets.types import SequenceData

__all__ = ["ViewSample", "HogsData", "select_sequences", "load_hogs_data", "dilate_mask"]


@dataclass
class ViewSample:
    """One (sequence, frame, view) image.

    Attributes:
        seq_index: index into :attr:`HogsData.sequences`; frame: frame index; view: view.
        image: (H, W, 3) uint8 RGB; mask: (H, W) uint8 part mask (0 = background).
        world2cam: (4, 4) float64; K: (3, 3) float64 render intrinsics at (H, W).
    """

    seq_index: int
    frame: int
    view: int
    image: np.ndarray
    mask: np.ndarray
    world2cam: np.ndarray
    K: np.ndarray


@dataclass
class HogsData:
    """Training and held-out samples of one subject + object."""

    subject: str
    object_name: str
    sequences: list[SequenceData]
    train: list[ViewSample]
    eval: list[ViewSample]
    train_views: tuple[int, ...]
    eval_views: tuple[int, ...]
    image_size: int

    def poses(self, samples: Sequence[ViewSample], dtype: torch.dtype = torch.float32) -> dict[str, Tensor]:
        """Batched annotated poses of the samples' frames (keys ``{side}_rot/pose/betas/trans``,
        ``obj_arti`` (B, 1), ``obj_rot``, ``obj_trans``)."""
        out: dict[str, list[np.ndarray]] = {}

        def push(k: str, v: np.ndarray) -> None:
            out.setdefault(k, []).append(np.asarray(v, dtype=np.float64))

        for s in samples:
            seq = self.sequences[s.seq_index]
            f = s.frame
            for side in ("right", "left"):
                h = getattr(seq, side)
                push(f"{side}_rot", h.rot[f])
                push(f"{side}_pose", h.pose[f])
                push(f"{side}_betas", h.betas)
                push(f"{side}_trans", h.trans[f])
            push("obj_arti", seq.object.arti[f : f + 1])
            push("obj_rot", seq.object.rot[f])
            push("obj_trans", seq.object.trans[f])
        return {k: torch.as_tensor(np.stack(v), dtype=dtype) for k, v in out.items()}


def select_sequences(root: ArcticRoot, subject: str, object_name: str, sequences: Optional[Sequence[str]]) -> list[str]:
    """Sequence names of ``subject`` showing ``object_name`` (optionally restricted).

    Raises:
        ValueError: unknown subject / object, unknown or mismatching sequence names, or no
            sequence left.
    """
    subjects = root.subjects()
    if subject not in subjects:
        raise ValueError(f"unknown subject {subject!r}; the data root has {subjects}")
    objects = sorted(root.object_templates(load_texture=False))
    if object_name not in objects:
        raise ValueError(f"unknown object {object_name!r}; the data root has templates for {objects}")
    have = [s.split("/", 1)[1] for s in root.sequences(subject)]
    mine = [s for s in have if s.split("_", 1)[0] == object_name]
    if sequences:
        bad = [s for s in sequences if s not in have]
        if bad:
            raise ValueError(f"sequences {bad} do not exist for subject {subject} (has {have})")
        wrong = [s for s in sequences if s not in mine]
        if wrong:
            raise ValueError(f"sequences {wrong} do not show object {object_name!r}")
        mine = [s for s in mine if s in sequences]
    if not mine:
        raise ValueError(f"subject {subject} has no sequence with object {object_name!r} (has {have})")
    return mine


def dilate_mask(mask: Tensor, margin: int) -> Tensor:
    """(B, H, W) bool foreground dilated by ``margin`` pixels (square structuring element)."""
    m = mask.float()[:, None]
    if margin > 0:
        m = torch.nn.functional.max_pool2d(m, 2 * margin + 1, stride=1, padding=margin)
    return m[:, 0] > 0.5


def _crop_boxes(root: ArcticRoot, seq: SequenceData, views: Sequence[int]) -> dict[int, np.ndarray]:
    """view → (F, 3) allocentric crop boxes from the posed object template (as processing does)."""
    layer = root.object_layer()
    obj = seq.object
    n = obj.rot.shape[0]
    f64 = torch.float64
    with torch.no_grad():
        res = layer(
            angles=torch.as_tensor(obj.arti, dtype=f64).reshape(n, 1),
            global_orient=torch.as_tensor(obj.rot, dtype=f64),
            transl=torch.as_tensor(obj.trans, dtype=f64),
            names=[obj.name] * n,
        )
    verts = res["v"].numpy()  # (F, V, 3)
    out = {}
    for v in views:
        cam = seq.cameras[v]
        out[v] = allocentric_bbox(project(transform(cam.world2cam[:, None], verts[:, None])[:, 0], cam.K))
    return out


def _read_foreground(image_path, mask_path, size: int) -> tuple[np.ndarray, np.ndarray]:
    """Foreground image and part mask at ``size``.

    The background is removed at the native resolution (image × (mask > 0)) *before*
    resizing, so the area-averaged result is the premultiplied foreground over black —
    what a render on black must match. Resizing first would mix the table into every
    silhouette pixel. The part mask is resized by nearest neighbour, then every pixel with
    partial foreground coverage gets a neighbouring part id (3×3 dilation), so no
    foreground colour ends up outside the mask.
    """
    img = cv2.imread(str(image_path), cv2.IMREAD_COLOR)
    if img is None:
        raise FileNotFoundError(f"cannot read image {image_path}")
    parts = cv2.imread(str(mask_path), cv2.IMREAD_UNCHANGED)
    if parts is None:
        raise FileNotFoundError(f"cannot read mask {mask_path}")
    if parts.shape[:2] != img.shape[:2]:
        parts = cv2.resize(parts, (img.shape[1], img.shape[0]), interpolation=cv2.INTER_NEAREST)
    fg = cv2.cvtColor(img, cv2.COLOR_BGR2RGB) * (parts > 0)[..., None].astype(np.uint8)
    if fg.shape[0] == size and fg.shape[1] == size:
        return fg, parts
    fg = cv2.resize(fg, (size, size), interpolation=cv2.INTER_AREA)
    cover = cv2.resize((parts > 0).astype(np.float32), (size, size), interpolation=cv2.INTER_AREA)
    small = cv2.resize(parts, (size, size), interpolation=cv2.INTER_NEAREST)
    grown = cv2.dilate(small, np.ones((3, 3), np.uint8))
    small = np.where((small == 0) & (cover > 0), grown, small)
    return fg, small


def load_hogs_data(
    root: ArcticRoot,
    subject: str,
    object_name: str,
    *,
    sequences: Optional[Sequence[str]] = None,
    eval_views: Sequence[int] = (8,),
    eval_every_frame: int = 8,
    frame_stride: int = 1,
    image_size: Optional[int] = None,
    max_eval: int = 8,
) -> HogsData:
    """Load every training and held-out (frame, view) of ``subject`` + ``object_name``.

    Args:
        root: the ARCTIC(-format) root.
        sequences: sequence names to use (default every sequence of the subject with the object).
        eval_views: allocentric views held out from training.
        eval_every_frame: of the used frames (after ``frame_stride``), those at positions
            ``i % eval_every_frame == eval_every_frame // 2`` are held out (0: none).
        frame_stride: use every n-th frame only.
        image_size: training resolution (default the cropped size).
        max_eval: at most this many held-out samples (evenly spaced).
    """
    names = select_sequences(root, subject, object_name, sequences)
    eval_views = tuple(int(v) for v in eval_views)
    bad = [v for v in eval_views if v not in ALLO_VIEWS]
    if bad:
        raise ValueError(f"eval views must be allocentric views {ALLO_VIEWS}, got {bad}")
    train_views = tuple(v for v in ALLO_VIEWS if v not in eval_views)
    if not train_views:
        raise ValueError("every view is held out; nothing left to train on")
    crop = root.world_meta().cropped_size
    size = int(image_size or crop)
    scale = np.diag([size / crop, size / crop, 1.0])
    seqs, train, held = [], [], []
    for si, name in enumerate(names):
        seq = root.sequence(subject, name)
        seqs.append(seq)
        boxes = _crop_boxes(root, seq, ALLO_VIEWS)
        for v in ALLO_VIEWS:
            if v not in seq.image_paths or v not in seq.mask_paths:
                raise ValueError(f"{subject}/{name}: view {v} has no cropped images or masks")
            cam = seq.cameras[v]
            Ks = scale @ render_intrinsics(cropped_intrinsics(cam.K, boxes[v], crop))
            for i, f in enumerate(range(0, seq.num_frames, max(1, frame_stride))):
                is_eval_frame = eval_every_frame > 0 and i % eval_every_frame == eval_every_frame // 2
                is_eval = v in eval_views and is_eval_frame
                is_train = v in train_views and not is_eval_frame
                if not (is_eval or is_train):
                    continue
                ip, mp = seq.image_paths[v][f], seq.mask_paths[v][f]
                if ip is None or mp is None:
                    continue
                image, mask = _read_foreground(ip, mp, size)
                s = ViewSample(si, f, v, image, mask, cam.world2cam[f].astype(np.float64), Ks[f])
                (held if is_eval else train).append(s)
    if not train:
        raise ValueError(f"no training images for {subject}/{object_name}")
    if not held:
        raise ValueError(f"no held-out images for {subject}/{object_name} (eval views {eval_views})")
    if len(held) > max_eval:
        idx = np.linspace(0, len(held) - 1, max_eval).round().astype(int)
        held = [held[i] for i in idx]
    return HogsData(subject, object_name, seqs, train, held, train_views, eval_views, size)
