"""Training data of one HOGS model: the (frame, view) images of one subject + object.

Start with :func:`load_hogs_data`, which returns a :class:`HogsData` (its docstring describes the
``masks`` and ``window`` options) of :class:`ViewSample` training and held-out samples (how a
sample is made: :class:`ViewSample`; the split: :func:`split_role`). H2O has its own loader with
the same split rules (:mod:`hogsa_loader.train.hogs_data_h2o`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Mapping, Optional, Sequence

import cv2
import numpy as np
import torch
from torch import Tensor

from hogsa_loader.assets.arctic import ArcticRoot
from hogsa_loader.assets.arctic_processing import crop_boxes
from hogsa_loader.assets.conventions import ALLO_VIEWS, cropped_intrinsics, project, render_intrinsics, transform
from hogsa_loader.assets.types import SequenceData
from hogsa_loader.render.part_masks import pose_meshes, render_camera_mask

__all__ = [
    "MASK_MODES",
    "WINDOWS",
    "ViewSample",
    "foreground_window",
    "FrameSelection",
    "HogsData",
    "select_sequences",
    "check_subject",
    "pick_sequences",
    "load_hogs_data",
    "dilate_mask",
    "split_role",
    "check_views",
    "split_samples",
    "mask_supersample",
    "crop_boxes",
]

#: Where the part masks come from (``load_hogs_data(masks=...)``).
MASK_MODES = ("auto", "files", "render")
#: Which part of each cropped image is trained on (``load_hogs_data(window=...)``).
WINDOWS = ("crop", "fg")


@dataclass(frozen=True)
class FrameSelection:
    """Which (frame, view) images a HOGS loader uses, and at what resolution.

    Attributes:
        sequences: sequence names (None: every sequence of the subject with the object;
            H2O names them ``"scene/seq"``).
        views: camera views used (None: the dataset's default).
        eval_views: views held out from training, among ``views`` (None: the dataset's default).
        eval_every_frame: of the used frames (after ``frame_stride``), those at positions
            ``i % eval_every_frame == eval_every_frame // 2`` are held out (0: none).
        frame_stride: use every n-th frame only.
        image_size: training resolution (None: the dataset's crop size).
        max_eval: at most this many held-out samples (evenly spaced).
    """

    sequences: Optional[Sequence[str]] = None
    views: Optional[Sequence[int]] = None
    eval_views: Optional[Sequence[int]] = None
    eval_every_frame: int = 8
    frame_stride: int = 1
    image_size: Optional[int] = None
    max_eval: int = 8


@dataclass
class ViewSample:
    """One (sequence, frame, view) image.

    Attributes:
        seq_index: index into :attr:`HogsData.sequences`; frame: frame index; view: view.
        image: (H, W, 3) uint8 RGB; mask: (H, W) uint8 part mask (0 = background).
        world2cam: (4, 4) float64; K: (3, 3) float64 render intrinsics at (H, W).

    For every selected sequence of the subject that shows the object, every allocentric view
    and frame becomes a :class:`ViewSample`: the cropped image and its part mask (resized to
    the training resolution), the camera (world→camera and *render* intrinsics of the crop)
    and the annotated poses of that frame. Crop boxes are recomputed exactly as ARCTIC's
    processing does (object-template vertices posed by the object layer, projected, then
    :func:`~hogsa_loader.assets.conventions.allocentric_bbox`), and the intrinsics are
    ``render_intrinsics(cropped_intrinsics(K, bbox, cropped_size))`` scaled to the training
    resolution, so rendered pixels line up with the labels.
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
    """Training and held-out samples of one subject + object.

    Masks (``masks``): ``"files"`` reads the generated world's ``masks/`` images; ``"render"``
    rasterises the part masks from the annotated meshes (:mod:`hogsa_loader.render.part_masks`),
    for real ARCTIC, which ships none; ``"auto"`` (default) uses the files of a sequence when
    every used image has one, else renders. With mask files the background is removed at the
    native resolution before resizing (:func:`_read_foreground`). With rendered masks the
    image is kept as it is, real background included (the mask is an estimate from the
    annotations, not a segmentation of the picture): the trainer and the evaluation multiply
    the image by the mask at the training resolution, so no pixel outside the mask is ever a
    colour target (see :meth:`~hogsa_loader.train.hogs_trainer.HogsTrainer.targets`).

    Window (``window``): ``"crop"`` (default) trains on the whole cropped image (1.5× the
    ARCTIC box); ``"fg"`` on a square window around the posed hands and object of each frame
    (their projected vertices' extent plus ``window_margin`` each side, rounded up to a whole
    multiple of the training resolution, kept inside the cropped image), so the same training
    resolution spends more of its pixels on the hands and the object: on the small world's
    s01/box and s02/notebook at 128 px the window is on average 1.33–1.38× smaller than the
    crop (1.0–1.95×; the hands often reach far out). The intrinsics of each sample follow its
    window exactly (translation then scale of the render intrinsics).
    """

    subject: str
    object_name: str
    sequences: list[SequenceData]
    train: list[ViewSample]
    eval: list[ViewSample]
    train_views: tuple[int, ...]
    eval_views: tuple[int, ...]
    image_size: int
    crop_size: int = 0  # resolution the ``margin`` setting is given at (ARCTIC: the cropped size)
    mask_source: str = "files"  # "files", "render" or "files+render" (per sequence)

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
    check_subject(subject, root.subjects())
    objects = sorted(root.object_templates(load_texture=False))
    if object_name not in objects:
        raise ValueError(f"unknown object {object_name!r}; the data root has templates for {objects}")
    have = [s.split("/", 1)[1] for s in root.sequences(subject)]
    return pick_sequences(subject, object_name, {s: [s.split("_", 1)[0]] for s in have}, sequences)


def check_subject(subject: str, subjects: Sequence[str]) -> None:
    """Raise ValueError naming the root's subjects when ``subject`` is not one of them."""
    if subject not in subjects:
        raise ValueError(f"unknown subject {subject!r}; the data root has {list(subjects)}")


def pick_sequences(
    subject: str, object_name: str, shows: Mapping[str, Sequence[str]], sequences: Optional[Sequence[str]]
) -> list[str]:
    """Names of the sequences showing ``object_name``, optionally restricted to ``sequences``.

    Args:
        shows: every sequence name of the subject -> the objects it shows.

    Raises:
        ValueError: unknown or mismatching names in ``sequences``, or no sequence left.
    """
    mine = [s for s in shows if object_name in shows[s]]
    if sequences:
        bad = [s for s in sequences if s not in shows]
        if bad:
            raise ValueError(f"sequences {bad} do not exist for subject {subject} (has {list(shows)})")
        wrong = [s for s in sequences if s not in mine]
        if wrong:
            raise ValueError(f"sequences {wrong} do not show object {object_name!r}")
        mine = [s for s in mine if s in sequences]
    if not mine:
        raise ValueError(
            f"subject {subject} has no sequence with object {object_name!r} (objects per sequence: {dict(shows)})"
        )
    return mine


def dilate_mask(mask: Tensor, margin: int) -> Tensor:
    """(B, H, W) bool foreground dilated by ``margin`` pixels (square structuring element)."""
    m = mask.float()[:, None]
    if margin > 0:
        m = torch.nn.functional.max_pool2d(m, 2 * margin + 1, stride=1, padding=margin)
    return m[:, 0] > 0.5


def _cut(img: np.ndarray, window: Optional[tuple[int, int, int]]) -> np.ndarray:
    """``img[y0:y0+side, x0:x0+side]`` for ``window = (x0, y0, side)`` (None: whole image)."""
    if window is None:
        return img
    x0, y0, side = window
    return img[y0 : y0 + side, x0 : x0 + side]


def _read_foreground(
    image_path, mask_path, size: int, window: Optional[tuple[int, int, int]] = None
) -> tuple[np.ndarray, np.ndarray]:
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
    img, parts = _cut(img, window), _cut(parts, window)
    fg = cv2.cvtColor(img, cv2.COLOR_BGR2RGB) * (parts > 0)[..., None].astype(np.uint8)
    if fg.shape[0] == size and fg.shape[1] == size:
        return fg, parts
    fg = cv2.resize(fg, (size, size), interpolation=cv2.INTER_AREA)
    cover = cv2.resize((parts > 0).astype(np.float32), (size, size), interpolation=cv2.INTER_AREA)
    small = cv2.resize(parts, (size, size), interpolation=cv2.INTER_NEAREST)
    grown = cv2.dilate(small, np.ones((3, 3), np.uint8))
    small = np.where((small == 0) & (cover > 0), grown, small)
    return fg, small


def _read_image(image_path, size: int, window: Optional[tuple[int, int, int]] = None) -> np.ndarray:
    """(size, size, 3) uint8 RGB image (of the window), background kept (area-resized)."""
    img = cv2.imread(str(image_path), cv2.IMREAD_COLOR)
    if img is None:
        raise FileNotFoundError(f"cannot read image {image_path}")
    img = cv2.cvtColor(_cut(img, window), cv2.COLOR_BGR2RGB)
    if img.shape[:2] != (size, size):
        img = cv2.resize(img, (size, size), interpolation=cv2.INTER_AREA)
    return img


def foreground_window(
    posed, frame: int, world2cam: np.ndarray, K_crop: np.ndarray, crop: int, size: int, margin: float = 0.15
) -> tuple[int, int, int]:
    """Square window ``(x0, y0, side)`` (cropped-image pixels) around the posed meshes.

    Args:
        posed: :class:`~hogsa_loader.render.part_masks.PosedMeshes` holding ``frame``.
        world2cam: (4, 4); K_crop: (3, 3) render intrinsics of the whole cropped image.
        crop: cropped-image side; size: training resolution.
        margin: added on each side, as a fraction of the meshes' larger extent.

    The side is rounded up to a whole multiple of ``size`` (at most ``crop``), so resizing
    the window to ``size`` is an exact k×k box filter and masks rendered at ``size`` match
    the resized mask files pixel for pixel.
    """
    i = posed.index(frame)
    pts = np.concatenate([m[1][i].numpy().astype(np.float64) for m in posed.meshes])
    cam = transform(world2cam, pts)
    cam = cam[cam[:, 2] > 1e-6]
    if len(cam) == 0:
        return 0, 0, crop
    uv = project(cam, K_crop)
    lo, hi = np.clip(uv.min(0), 0, crop), np.clip(uv.max(0), 0, crop)
    side = float(max(hi - lo)) * (1 + 2 * margin)
    side = int(min(crop, size * max(1, int(np.ceil(side / size - 1e-9)))))  # a whole multiple of size
    c = (lo + hi) / 2
    x0, y0 = (int(np.clip(round(float(c[k]) - side / 2), 0, crop - side)) for k in range(2))
    return x0, y0, side


def mask_supersample(native: float, size: int) -> int:
    """Samples per pixel side for a mask rendered at ``size`` of an image ``native`` px wide."""
    return int(min(4, max(1, np.ceil(native / size - 1e-6))))


def split_role(
    i: int, view: int, train_views: Sequence[int], eval_views: Sequence[int], eval_every_frame: int
) -> Optional[str]:
    """``"train"``, ``"eval"`` or None for the ``i``-th used frame seen from ``view``.

    Frames at positions ``i % eval_every_frame == eval_every_frame // 2`` are held out
    (``eval_every_frame`` 0: none); held-out frames of the eval views are evaluated, the
    other frames of the training views are trained on.

    Split: ``eval_views`` (camera views never used in training) and every ``eval_every_frame``-th
    frame are held out; evaluation uses held-out views × held-out frames.
    """
    is_eval_frame = eval_every_frame > 0 and i % eval_every_frame == eval_every_frame // 2
    if view in eval_views and is_eval_frame:
        return "eval"
    if view in train_views and not is_eval_frame:
        return "train"
    return None


def check_views(views: Sequence[int], eval_views: Sequence[int]) -> tuple[tuple[int, ...], tuple[int, ...]]:
    """``(train_views, eval_views)``: ``views`` minus the held-out ones, and the held-out ones.

    Raises:
        ValueError: a held-out view that is not among ``views``, or no training view left.
    """
    eval_views = tuple(int(v) for v in eval_views)
    bad = [v for v in eval_views if v not in views]
    if bad:
        raise ValueError(f"eval views must be among the camera views {tuple(views)}, got {bad}")
    train_views = tuple(v for v in views if v not in eval_views)
    if not train_views:
        raise ValueError("every view is held out; nothing left to train on")
    return train_views, eval_views


def split_samples(
    train: list[ViewSample], held: list[ViewSample], max_eval: int, what: str
) -> tuple[list[ViewSample], list[ViewSample]]:
    """``(train, held)`` with at most ``max_eval`` held-out samples, evenly spaced.

    Raises:
        ValueError: no training or no held-out sample (``what`` names the subject/object).
    """
    if not train:
        raise ValueError(f"no usable training images for {what}")
    if not held:
        raise ValueError(f"no usable held-out images for {what} (none in the eval views' held-out frames)")
    if len(held) > max_eval:
        idx = np.linspace(0, len(held) - 1, max_eval).round().astype(int)
        held = [held[i] for i in idx]
    return train, held


def load_hogs_data(
    root: ArcticRoot,
    subject: str,
    object_name: str,
    selection: Optional[FrameSelection] = None,
    *,
    masks: str = "auto",
    window: str = "crop",
    window_margin: float = 0.15,
) -> HogsData:
    """Load every training and held-out (frame, view) of ``subject`` + ``object_name``.

    Args:
        root: the ARCTIC(-format) root.
        selection: frames, views and resolution (default views: allocentric 1..8, view 8
            held out; default size: the cropped size).
        masks: ``"auto"``, ``"files"`` or ``"render"`` (see :class:`HogsData`).
        window: ``"crop"`` or ``"fg"`` (see :class:`HogsData`); window_margin: its margin.
    """
    if masks not in MASK_MODES:
        raise ValueError(f"masks must be one of {MASK_MODES}, got {masks!r}")
    if window not in WINDOWS:
        raise ValueError(f"window must be one of {WINDOWS}, got {window!r}")
    sel = selection or FrameSelection()
    names = select_sequences(root, subject, object_name, sel.sequences)
    views = tuple(int(v) for v in (ALLO_VIEWS if sel.views is None else sel.views))
    bad = [v for v in views if v not in ALLO_VIEWS]
    if bad:
        raise ValueError(f"views must be allocentric views {ALLO_VIEWS}, got {bad}")
    try:
        train_views, eval_views = check_views(views, (8,) if sel.eval_views is None else sel.eval_views)
    except ValueError as exc:
        raise ValueError(f"{exc} (ARCTIC: allocentric views only)") from None
    crop = root.world_meta().cropped_size
    size = int(sel.image_size or crop)
    seqs, train, held, sources = [], [], [], set()
    for si, name in enumerate(names):
        seq = root.sequence(subject, name)
        seqs.append(seq)
        split = (train_views, eval_views)
        jobs = _sequence_jobs(seq, f"{subject}/{name}", views, sel.frame_stride, split, sel.eval_every_frame)
        render = _renders_masks(seq, jobs, masks, f"{subject}/{name}")
        sources.add("render" if render else "files")
        posed = None
        if render or window == "fg":
            template = root.object_templates()[seq.object.name]
            posed = pose_meshes(seq, sorted({f for _, f, _ in jobs}), root.mano_layers(), template)
        boxes = crop_boxes(root, seq, views)
        for v, f, role in jobs:
            s = _view_sample(seq, si, v, f, boxes[v][f], posed, render, crop, size, window, window_margin)
            (held if role == "eval" else train).append(s)
    return HogsData(
        subject,
        object_name,
        seqs,
        *split_samples(train, held, sel.max_eval, f"{subject}/{object_name}"),
        train_views,
        eval_views,
        size,
        crop_size=crop,
        mask_source="+".join(sorted(sources)),
    )


def _sequence_jobs(
    seq: Any,
    where: str,
    views: Sequence[int],
    frame_stride: int,
    split_views: tuple[Sequence[int], Sequence[int]],
    eval_every_frame: int,
) -> list[tuple[int, int, str]]:
    """``(view, frame, "train" | "eval")`` of every used image of ``seq`` that exists.

    Raises:
        ValueError: a used view has no cropped images.
    """
    train_views, eval_views = split_views
    frames = list(range(0, seq.num_frames, max(1, frame_stride)))
    jobs = [
        (v, f, role)
        for v in views
        for i, f in enumerate(frames)
        if (role := split_role(i, v, train_views, eval_views, eval_every_frame)) is not None
    ]
    missing = sorted({v for v, _, _ in jobs if v not in seq.image_paths})
    if missing:
        raise ValueError(f"{where}: views {missing} have no cropped images")
    return [(v, f, role) for v, f, role in jobs if seq.image_paths[v][f] is not None]


def _renders_masks(seq: Any, jobs: Sequence[tuple[int, int, str]], masks: str, where: str) -> bool:
    """Whether the part masks of ``jobs`` are rendered (``masks="render"``, or no mask file
    for some image with ``"auto"``) rather than read.

    Raises:
        ValueError: ``masks="files"`` and some used image has no mask file.
    """
    have_masks = all(v in seq.mask_paths and seq.mask_paths[v][f] is not None for v, f, _ in jobs)
    if masks == "files" and not have_masks:
        raise ValueError(
            f"{where}: some used images have no mask file (masks='files'; "
            "use masks='render' or 'auto' to render them from the annotations)"
        )
    return masks == "render" or not have_masks


def _view_sample(
    seq: Any,
    si: int,
    v: int,
    f: int,
    box: np.ndarray,
    posed: Any,
    render: bool,
    crop: int,
    size: int,
    window: str,
    window_margin: float,
) -> ViewSample:
    """One (frame ``f``, view ``v``) sample of sequence number ``si`` at ``size`` px: the
    cropped image (or the ``fg`` window of it around the posed meshes), its part mask (read,
    or with ``render`` rendered from the posed meshes) and the camera (``Ks``: intrinsics of
    the training image; ``box``: the view's crop box of the frame)."""
    cam = seq.cameras[v]
    K_crop = render_intrinsics(cropped_intrinsics(cam.K[f], box, crop))
    win = None
    Ks = np.diag([size / crop, size / crop, 1.0]) @ K_crop
    if window == "fg":
        win = foreground_window(posed, f, cam.world2cam[f], K_crop, crop, size, window_margin)
        x0, y0, side = win
        Ks = np.diag([size / side, size / side, 1.0]) @ np.array([[1.0, 0, -x0], [0, 1, -y0], [0, 0, 1]]) @ K_crop
    ip = seq.image_paths[v][f]
    if not render:
        image, mask = _read_foreground(ip, seq.mask_paths[v][f], size, win)
    else:
        image = _read_image(ip, size, win)
        native = crop if win is None else win[2]
        mask = render_camera_mask(posed, cam, f, Ks, size, supersample=mask_supersample(native, size))
    return ViewSample(si, f, v, image, mask, cam.world2cam[f].astype(np.float64), Ks)
