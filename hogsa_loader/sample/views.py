"""Where a synthetic sample is seen from, and where its labels land: per-protocol view geometry.

:func:`allocentric_views` (ARCTIC protocol ``p1``) and :func:`egocentric_views` (``p2``,
with :class:`EgoCameras`) both return a :class:`ViewGeometry`, which says how the pipeline
renders the sample and checks its labels.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Mapping, Optional, Sequence

import numpy as np
import torch
from torch import Tensor

from hogsa_loader.assets.conventions import (
    BBOX_PIXELS_PER_SCALE,
    allocentric_bbox,
    cropped_bbox,
    cropped_intrinsics,
    distort_points,
    full_to_cropped,
    project,
    render_intrinsics,
    transform,
    undistort_map,
    validity_flags,
)
from hogsa_loader.sample.cameras import CameraSampler

__all__ = ["ViewGeometry", "EgoCameras", "allocentric_views", "egocentric_views"]


@dataclass
class ViewGeometry:
    """Cameras and label geometry of B samples.

    Attributes:
        world2cam: (B, 4, 4); K_full: (B, 3, 3) full-image intrinsics; image_size: (B, 2)
            full image (W, H); view: (B,) dataset view (0 = ego) or ``NOVEL_VIEW``.
        cam: key → (B, N, 3) camera-frame points of the geometry keys.
        label2d: key → (B, N, 2) 2D labels in pixels of the output image.
        pix2d: key → (B, N, 2) where the output pixels show those points (differs from
            ``label2d`` only under lens distortion).
        box_img: (B, 3) ARCTIC crop box in output-image pixels.
        box_full: (B, 3) the same box ``(cx, cy, scale)`` in full-image pixels (allocentric:
            the output image is the ``1.5 · 200 · scale`` square around its centre).
        flags: ``(is_valid, right_valid, left_valid)``, each (B,).
        K_render: (B, 3, 3) render intrinsics (render convention) at ``render_hw``.
        render_hw, out_hw: (H, W) of the render and of the output image.
        warp: optional (B, H_out, W_out, 2) ``grid_sample`` grid (align_corners=True) from
            the render into the output image.
        check_box: (x0, y0, x1, y1) region of the output image where labels are checked.
        egocentric: True for ``p2``; dist: (B, 8) lens distortion (ego) or None.

    The pipeline renders with ``K_render`` at ``render_hw``, applies ``warp`` when present, and
    checks labels against the pixels at ``pix2d`` inside ``check_box``.
    """

    world2cam: np.ndarray
    K_full: np.ndarray
    image_size: np.ndarray
    view: np.ndarray
    cam: dict[str, np.ndarray]
    label2d: dict[str, np.ndarray]
    pix2d: dict[str, np.ndarray]
    box_img: np.ndarray
    flags: tuple[np.ndarray, np.ndarray, np.ndarray]
    K_render: np.ndarray
    render_hw: tuple[int, int]
    out_hw: tuple[int, int]
    box_full: Optional[np.ndarray] = None
    warp: Optional[Tensor] = None
    check_box: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.0)
    egocentric: bool = False
    dist: Optional[np.ndarray] = None


def allocentric_views(
    sampler: CameraSampler, geo: Mapping[str, np.ndarray], rngs: Sequence[np.random.Generator], size: int
) -> ViewGeometry:
    """Allocentric cameras around the interaction centre and the ARCTIC crop of each (``p1``).

    Args:
        sampler: the subject's camera sampler.
        geo: world-frame points ``verts`` (B, V, 3), ``joints.right/left`` (B, 21, 3), ...
        rngs: one camera generator per sample.
        size: side S of the rendered crop.

    Cameras from the :class:`~hogsa_loader.sample.cameras.CameraSampler`; the crop box from
    the projected object vertices (:func:`~hogsa_loader.assets.conventions.allocentric_bbox`);
    an ``S × S`` render laid out like ARCTIC's cropped images (box enlarged 1.5×).
    """
    centres = np.stack([geo["verts"].mean(1), geo["joints.right"].mean(1), geo["joints.left"].mean(1)]).mean(0)
    cams = sampler.sample(centres, rngs)
    cam = {k: transform(cams.world2cam, v) for k, v in geo.items()}
    full2d = {k: project(v, cams.K) for k, v in cam.items()}
    box_full = allocentric_bbox(full2d["verts"])
    flags = validity_flags(full2d["verts"], full2d["joints.right"], full2d["joints.left"], box_full, cams.image_size)
    crop2d = {k: full_to_cropped(v, box_full, size) for k, v in full2d.items()}
    lo, hi = size / 6.0, size - size / 6.0  # the ARCTIC box inside the 1.5x crop
    return ViewGeometry(
        world2cam=cams.world2cam,
        K_full=cams.K,
        image_size=cams.image_size,
        view=cams.view,
        cam=cam,
        label2d=crop2d,
        pix2d=crop2d,
        box_img=cropped_bbox(box_full, size),
        box_full=box_full,
        flags=flags,
        K_render=render_intrinsics(cropped_intrinsics(cams.K, box_full, size)),
        render_hw=(size, size),
        out_hw=(size, size),
        check_box=(lo, lo, hi, hi),
    )


class EgoCameras:
    """The head-mounted camera of a subject's sequences (``p2``).

    Args:
        sequences: the subject's :class:`~hogsa_loader.assets.types.SequenceData` (their
            camera 0, egocentric).

    Raises:
        ValueError: no sequence has an egocentric camera.
    """

    def __init__(self, sequences: Sequence[Any]) -> None:
        self.tracks: dict[str, Any] = {}
        for seq in sequences:
            cam = seq.cameras.get(0)
            if cam is not None and cam.egocentric:
                self.tracks[f"{seq.subject}/{seq.name}"] = cam
        if not self.tracks:
            raise ValueError("no egocentric camera in the subject's sequences (protocol p2 needs view 0)")
        self.names = sorted(self.tracks)

    def pick(
        self, provenance: Mapping[str, Any], rng: np.random.Generator
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, tuple[int, int]]:
        """``(world2cam (4,4), K (3,3), dist (8,), (W, H))`` for one sample: the camera of the
        pose's source frame when known, else a random frame (drawn with ``rng``)."""
        name, frame = provenance.get("sequence"), provenance.get("frame")
        if name in self.tracks and frame is not None and 0 <= int(frame) < self.tracks[name].world2cam.shape[0]:
            track, f = self.tracks[name], int(frame)
        else:
            track = self.tracks[self.names[int(rng.integers(len(self.names)))]]
            f = int(rng.integers(track.world2cam.shape[0]))
        dist = np.zeros(8) if track.dist is None else np.asarray(track.dist, dtype=np.float64)
        dist = dist[f] if dist.ndim == 2 else dist
        return (
            np.asarray(track.world2cam[f], dtype=np.float64),
            np.asarray(track.K[f], dtype=np.float64),
            dist,
            (int(track.width), int(track.height)),
        )


_MAP_CACHE: dict[bytes, tuple[np.ndarray, np.ndarray]] = {}


def _distortion_map(K: np.ndarray, dist: np.ndarray, w: int, h: int) -> tuple[np.ndarray, np.ndarray]:
    key = np.concatenate([K.ravel(), dist.ravel(), [w, h]]).astype(np.float64).tobytes()
    if key not in _MAP_CACHE:
        if len(_MAP_CACHE) > 64:
            _MAP_CACHE.clear()
        _MAP_CACHE[key] = undistort_map(K, dist, w, h)
    return _MAP_CACHE[key]


def egocentric_views(
    ego: EgoCameras,
    geo: Mapping[str, np.ndarray],
    provenance: Sequence[Mapping[str, Any]],
    rngs: Sequence[np.random.Generator],
    size: int,
    distortion: bool = True,
) -> ViewGeometry:
    """The subject's egocentric camera and ARCTIC's whole-frame box (``p2``).

    Args:
        ego: the subject's :class:`EgoCameras`.
        geo: world-frame points (as :func:`allocentric_views`).
        provenance: per-sample pose provenance (``sequence``, ``frame`` pick the camera).
        rngs: one camera generator per sample.
        size: output width (the frame is scaled by ``size / W``).
        distortion: apply the lens distortion to the pixels (labels stay undistorted).

    The subject's head-mounted camera (:class:`EgoCameras`: the camera of the pose's source
    frame, else a random frame of the subject); the whole ``W × H`` frame scaled by
    ``e = S / W`` (ARCTIC's egocentric "cropped" image is the whole frame scaled by 0.3; the
    crop box is the whole frame, side ``W``). With ``distortion=True`` (default) the pixels
    go through the camera's lens distortion like ARCTIC's egocentric images (rendered
    undistorted with a margin, then resampled, see
    :func:`~hogsa_loader.assets.conventions.undistort_map`), while the 2D labels stay in the
    **undistorted** space as ARCTIC's view-0 targets do; validity flags use the distorted
    2D in the whole image, as ARCTIC's processing does. ``distortion=False`` renders a
    pinhole image whose pixels match the labels exactly.
    """
    picks = [ego.pick(p, r) for p, r in zip(provenance, rngs)]
    w2c = np.stack([p[0] for p in picks])
    K = np.stack([p[1] for p in picks])
    dist = np.stack([p[2] for p in picks])
    sizes = np.asarray([p[3] for p in picks], dtype=np.int64)
    W, H = int(sizes[0, 0]), int(sizes[0, 1])
    if not (sizes == sizes[0]).all():
        raise ValueError(f"egocentric image sizes differ within a batch: {np.unique(sizes, axis=0).tolist()}")
    e = size / W
    w_out, h_out = int(round(W * e)), int(round(H * e))
    K_img = np.diag([e, e, 1.0])[None] @ K
    cam = {k: transform(w2c, v) for k, v in geo.items()}
    und = {k: project(v, K) for k, v in cam.items()}
    dis = {k: project(distort_points(v, dist), K) for k, v in cam.items()} if distortion else und
    box_full = np.tile([W / 2.0, H / 2.0, W / BBOX_PIXELS_PER_SCALE], (len(picks), 1))
    flags = validity_flags(dis["verts"], dis["joints.right"], dis["joints.left"], box_full, sizes)
    label2d = {k: v * e for k, v in und.items()}
    pix2d = {k: v * e for k, v in dis.items()}
    warp = None
    K_render = render_intrinsics(K_img)
    render_hw = (h_out, w_out)
    if distortion:
        maps = [_distortion_map(K_img[b], dist[b], w_out, h_out) for b in range(len(picks))]
        pad_x = int(np.ceil(max(max(0.0, -mx.min(), mx.max() - (w_out - 1)) for mx, _ in maps))) + 2
        pad_y = int(np.ceil(max(max(0.0, -my.min(), my.max() - (h_out - 1)) for _, my in maps))) + 2
        render_hw = (h_out + 2 * pad_y, w_out + 2 * pad_x)
        K_pad = K_img.copy()
        K_pad[:, 0, 2] += pad_x
        K_pad[:, 1, 2] += pad_y
        K_render = render_intrinsics(K_pad)
        gx = np.stack([(mx + pad_x) * 2.0 / (render_hw[1] - 1) - 1.0 for mx, _ in maps])
        gy = np.stack([(my + pad_y) * 2.0 / (render_hw[0] - 1) - 1.0 for _, my in maps])
        warp = torch.as_tensor(np.stack([gx, gy], axis=-1), dtype=torch.float32)
    return ViewGeometry(
        world2cam=w2c,
        K_full=K,
        image_size=sizes,
        view=np.zeros(len(picks), dtype=np.int64),
        cam=cam,
        label2d=label2d,
        pix2d=pix2d,
        box_img=box_full * e,
        flags=flags,
        K_render=K_render,
        render_hw=render_hw,
        out_hw=(h_out, w_out),
        warp=warp,
        check_box=(0.0, 0.0, w_out - 1.0, h_out - 1.0),
        egocentric=True,
        dist=dist,
    )


def apply_warp(images: Tensor, warp: Tensor) -> Tensor:
    """Resample (B, H, W, C) renders through a (B, Ho, Wo, 2) ``grid_sample`` grid → (B, Ho, Wo, C)."""
    x = images.permute(0, 3, 1, 2)
    out = torch.nn.functional.grid_sample(
        x, warp.to(device=x.device, dtype=x.dtype), mode="bilinear", padding_mode="zeros", align_corners=True
    )
    return out.permute(0, 2, 3, 1)
