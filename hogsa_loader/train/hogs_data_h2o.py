"""HOGS training data from H2O: full frames cropped around the annotated hands and object.

Start with :func:`load_h2o_hogs_data` (its docstring describes the crops, masks, views and
frames); :func:`select_h2o_sequences`, :func:`square_box` and :func:`crop_image` are its steps.
"""

from __future__ import annotations

from typing import Mapping, Optional, Sequence

import cv2
import numpy as np
import torch

from hogsa_loader.assets.conventions import (
    BBOX_PIXELS_PER_SCALE,
    CROP_ENLARGE,
    cropped_intrinsics,
    project,
    render_intrinsics,
    transform,
)
from hogsa_loader.assets.h2o import H2ORoot, read_h2o_rgb
from hogsa_loader.assets.h2o_io import H2O_CROP_SIZE, H2O_EGO_CAMERA
from hogsa_loader.assets.objects.rigid import H2O_OBJECT_NAMES
from hogsa_loader.assets.objects.template import ObjectTemplate
from hogsa_loader.assets.types import SequenceData
from hogsa_loader.render.part_masks import PosedMeshes, pose_meshes, render_camera_mask
from hogsa_loader.train.hogs_data import (
    FrameSelection,
    HogsData,
    ViewSample,
    check_subject,
    check_views,
    mask_supersample,
    pick_sequences,
    split_role,
    split_samples,
)

__all__ = [
    "H2O_VIEWS",
    "H2O_EVAL_VIEWS",
    "H2O_CROP_SIZE",
    "select_h2o_sequences",
    "square_box",
    "crop_image",
    "load_h2o_hogs_data",
]

#: Cameras trained on by default: the static ones (cam 4 is the moving egocentric camera).
H2O_VIEWS: tuple[int, ...] = (0, 1, 2, 3)
#: Held-out camera by default.
H2O_EVAL_VIEWS: tuple[int, ...] = (3,)
#: Box side / 2D extent of the projected meshes.
CROP_ENLARGE_H2O = 1.3
_MIN_SIDE_PX = 8.0


def select_h2o_sequences(
    root: H2ORoot, subject: str, object_name: str, sequences: Optional[Sequence[str]], label_cam: int = H2O_EGO_CAMERA
) -> list[tuple[str, str, int]]:
    """``(scene, seq, class id)`` of the sequences of ``subject`` showing ``object_name``.

    Args:
        sequences: ``"scene/seq"`` names to restrict to (e.g. ``["h1/0", "k2/3"]``).

    Raises:
        ValueError: unknown subject or object; see also :func:`pick_sequences`.
    """
    check_subject(subject, root.subjects())
    if object_name not in H2O_OBJECT_NAMES[1:]:
        raise ValueError(f"unknown object {object_name!r}; H2O objects are {list(H2O_OBJECT_NAMES[1:])}")
    cid = H2O_OBJECT_NAMES.index(object_name)
    shows: dict[str, list[str]] = {}
    for _, scene, seq in root.sequences(subject):
        cls, _ = root.read_obj_poses(subject, scene, seq, label_cam, root.frames(subject, scene, seq, label_cam))
        shows[f"{scene}/{seq}"] = [H2O_OBJECT_NAMES[c] for c in sorted(set(cls.tolist()) - {0})]
    return [(*name.split("/", 1), cid) for name in pick_sequences(subject, object_name, shows, sequences)]  # type: ignore[misc]


def square_box(points2d: np.ndarray, enlarge: float = CROP_ENLARGE_H2O) -> np.ndarray:
    """ARCTIC box ``(cx, cy, scale)`` of the square crop around 2D points.

    The crop (side ``CROP_ENLARGE · 200 · scale`` in ARCTIC's convention) is centred on the
    points' extent and ``enlarge`` times its larger side (at least 8 px).

    Args:
        points2d: (N, 2) full-image pixels.
    """
    lo, hi = points2d.min(0), points2d.max(0)
    side = max(float((hi - lo).max()) * enlarge, _MIN_SIDE_PX)
    return np.array([*(lo + hi) / 2.0, side / (CROP_ENLARGE * BBOX_PIXELS_PER_SCALE)])


def crop_image(image: np.ndarray, box: np.ndarray, size: int, max_supersample: int = 8) -> np.ndarray:
    """(size, size, C) crop of a full image: pixel i shows label coordinate ``origin + i / k``.

    ``k = size / side``; pixels outside the image are 0 (black). When the crop shrinks the
    image (k < 1) it is warped at s = ceil(1/k) samples per pixel side and box-filtered, the
    warp origin shifted by −(s − 1) / (2 s k) so block centres land on the same coordinates.

    Args:
        image: (H, W, C) uint8 or float32 (the dtype is kept; integers are rounded).
        box: ``(cx, cy, scale)`` (see :func:`square_box`).
    """
    side = CROP_ENLARGE * BBOX_PIXELS_PER_SCALE * float(box[2])
    k = size / side
    ox, oy = box[0] - side / 2.0, box[1] - side / 2.0
    s = int(min(max_supersample, max(1, np.ceil(1.0 / k - 1e-9))))
    shift = (s - 1) / (2.0 * s * k)
    M = np.array([[1.0 / (s * k), 0.0, ox - shift], [0.0, 1.0 / (s * k), oy - shift]])
    big = cv2.warpAffine(
        image,
        M,
        (s * size, s * size),
        flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
        borderMode=cv2.BORDER_CONSTANT,
        borderValue=(0, 0, 0),
    )
    if s == 1:
        return big
    small = big.reshape(size, s, size, s, -1).astype(np.float64).mean((1, 3)).reshape((size, size) + image.shape[2:])
    return (small.round() if np.issubdtype(image.dtype, np.integer) else small).astype(image.dtype)


def load_h2o_hogs_data(
    root: H2ORoot,
    subject: str,
    object_name: str,
    *,
    mano_layers: Mapping[str, torch.nn.Module],
    template: ObjectTemplate,
    selection: Optional[FrameSelection] = None,
    crop_enlarge: float = CROP_ENLARGE_H2O,
) -> HogsData:
    """Load every training and held-out (frame, view) of an H2O ``subject`` + ``object_name``.

    H2O has full 1280×720 frames (no ARCTIC crops) and no masks. For every selected sequence
    of the subject showing the object, every used camera and frame becomes a
    :class:`~hogsa_loader.train.hogs_data.ViewSample`:

    * **Crop.** The annotated meshes (both MANO hands, the object mesh posed by
      ``obj_pose_rt``) are projected; the square box centred on their 2D extent, of side
      ``crop_enlarge`` × the larger extent, is expressed as an ARCTIC box ``(cx, cy, scale)``,
      so the crop intrinsics are ARCTIC's
      ``render_intrinsics(cropped_intrinsics(K, box, image_size))``
      (:mod:`hogsa_loader.assets.conventions`). The image is warped into that crop
      (crop pixel i shows label coordinate ``origin + i · side / size``, black outside the
      frame, like ARCTIC's padding), supersampled and box-filtered when the crop shrinks.
    * **Mask.** Always rendered from the annotated meshes at the training resolution
      (:mod:`hogsa_loader.render.part_masks`); the object is rigid, so it is all part id 4.
      The image keeps its real background (see :func:`~hogsa_loader.train.hogs_data.load_hogs_data`).
    * **Views.** ``views`` default the static cameras 0–3; the egocentric camera 4 (moving,
      head-mounted) is used only when listed. ``eval_views`` default camera 3, held out.
    * **Frames.** Every ``frame_stride``-th frame of the label camera's files; a frame is used
      only where both hands and the object are annotated (``valid``), its image exists and
      every mesh vertex is in front of the camera. The held-out frames follow
      :func:`~hogsa_loader.train.hogs_data.split_role`.

    ``HogsData.crop_size`` (the resolution the trainer's ``margin`` is given at) is
    :data:`H2O_CROP_SIZE`.

    Args:
        root: the H2O root.
        subject: e.g. ``"subject1"``; object_name: H2O class name (``"book"``...).
        mano_layers: ``{"right", "left"}`` MANO layers, ``flat_hand_mean=False``.
        template: the object's rigid template (:func:`~hogsa_loader.assets.h2o_meshes.load_h2o_object`).
        selection: frames, views and resolution (default views: the static cameras 0–3,
            camera 3 held out; default size: :data:`H2O_CROP_SIZE`).
        crop_enlarge: crop side / extent of the projected meshes.
    """
    sel = selection or FrameSelection()
    chosen = select_h2o_sequences(root, subject, object_name, sel.sequences)
    views = tuple(int(v) for v in (H2O_VIEWS if sel.views is None else sel.views))
    train_views, eval_views = check_views(views, H2O_EVAL_VIEWS if sel.eval_views is None else sel.eval_views)
    size = int(sel.image_size or H2O_CROP_SIZE)
    seqs, train, held = [], [], []
    for si, (scene, seq_id, cid) in enumerate(chosen):
        seq = _open_sequence(root, subject, scene, seq_id, cid, mano_layers, views)
        seqs.append(seq)
        jobs = _sequence_jobs(seq, views, sel.frame_stride, train_views, eval_views, sel.eval_every_frame)
        if not jobs:
            continue
        posed = pose_meshes(seq, sorted({f for _, f, _ in jobs}), mano_layers, template)
        for v, f, role in jobs:
            s = _crop_sample(seq, posed, si, v, f, size, crop_enlarge)
            if s is not None:
                (held if role == "eval" else train).append(s)
    train, held = split_samples(train, held, sel.max_eval, f"H2O {subject}/{object_name} (views {views})")
    return HogsData(
        subject,
        object_name,
        seqs,
        train,
        held,
        train_views,
        eval_views,
        size,
        crop_size=H2O_CROP_SIZE,
        mask_source="render",
    )


def _open_sequence(
    root: H2ORoot,
    subject: str,
    scene: str,
    seq_id: str,
    cid: int,
    mano_layers: Mapping[str, torch.nn.Module],
    views: tuple[int, ...],
) -> SequenceData:
    """Open one H2O sequence with the cameras ``views``.

    Raises:
        ValueError: a camera of ``views`` has no folder.
    """
    seq = root.sequence(subject, scene, seq_id, mano_layers, cameras=views, object_class=cid)
    missing = [v for v in views if v not in seq.cameras]
    if missing:
        raise ValueError(f"{subject}/{seq.name}: no camera folder for views {missing} (has {sorted(seq.cameras)})")
    return seq


def _sequence_jobs(
    seq: SequenceData,
    views: tuple[int, ...],
    frame_stride: int,
    train_views: tuple[int, ...],
    eval_views: tuple[int, ...],
    eval_every_frame: int,
) -> list[tuple[int, int, str]]:
    """``(view, frame, role)`` of every usable (frame, view): all three annotated, image present."""
    frames = list(range(0, seq.num_frames, max(1, frame_stride)))
    ok = seq.right.valid & seq.left.valid & seq.object.valid
    return [
        (v, f, role)
        for v in views
        for i, f in enumerate(frames)
        if ok[f]
        and seq.image_paths[v][f] is not None
        and (role := split_role(i, v, train_views, eval_views, eval_every_frame)) is not None
    ]


def _crop_sample(
    seq: SequenceData, posed: PosedMeshes, si: int, v: int, f: int, size: int, crop_enlarge: float
) -> Optional[ViewSample]:
    """The (size, size) crop of frame ``f`` of camera ``v`` with its rendered mask.

    Returns None when a mesh vertex is not in front of the camera.
    """
    cam = seq.cameras[v]
    cam_pts = transform(cam.world2cam[f], posed.points(posed.index(f)))
    if (cam_pts[:, 2] <= 1e-3).any():
        return None
    box = square_box(project(cam_pts, cam.K[f]), crop_enlarge)
    Ks = render_intrinsics(cropped_intrinsics(cam.K[f], box, size))
    full = read_h2o_rgb(seq.image_paths[v][f], expected_size=(cam.width, cam.height))
    side = CROP_ENLARGE * BBOX_PIXELS_PER_SCALE * box[2]
    mask = render_camera_mask(posed, cam, f, Ks, size, supersample=mask_supersample(side, size))
    return ViewSample(si, f, v, crop_image(full, box, size), mask, cam.world2cam[f].astype(np.float64), Ks)
