"""Depth maps, part masks and exact intrinsics of a dataset's own cropped images.

ARCTIC ships RGB crops and annotations, no depth and no masks. :func:`cropped_cameras` gives
the camera of every allocentric cropped image (the crop box recomputed as ARCTIC's processing
does, :func:`~hogsa_loader.assets.arctic_processing.crop_boxes`); :func:`render_frame_maps`
rasterises the annotated hands and object into it: metric depth and part ids
(:data:`~hogsa_loader.assets.conventions.MASK_IDS`) pixel-aligned with the cropped image.
"""

from __future__ import annotations

import io
import time
import zipfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Optional, Sequence

import numpy as np
import torch

from hogsa_loader.assets.arctic import ArcticRoot
from hogsa_loader.assets.arctic_processing import crop_boxes
from hogsa_loader.assets.conventions import MASK_IDS, cropped_intrinsics, render_intrinsics
from hogsa_loader.assets.types import SequenceData
from hogsa_loader.errors import AssetError, UsageError
from hogsa_loader.io.atomic import atomic_write, atomic_write_json
from hogsa_loader.io.images import write_image
from hogsa_loader.io.locks import writer_lock
from hogsa_loader.render.mesh_raster import render_meshes
from hogsa_loader.render.part_masks import PosedMeshes, inside_image, pose_meshes

__all__ = [
    "DEPTH_PNG_METRES",
    "FrameMaps",
    "FrameMapsConfig",
    "cropped_cameras",
    "render_frame_maps",
    "write_frame_maps",
]


@dataclass(frozen=True)
class FrameMaps:
    """What one cropped image shows, rendered from the annotations.

    Attributes:
        view, frame: the camera and the annotation frame (``image`` is the file showing it).
        image: path of the cropped image.
        K: (3, 3) float64 intrinsics of the cropped image in the labels' (OpenCV) pixel
            convention: ``K @ X_cam`` divided by z gives ARCTIC's 2-D keypoints of the crop.
        world2cam: (4, 4) float64 extrinsics.
        depth: (S, S) float32 camera-space depth (z, metres) of the nearest hand or object
            surface; 0 where neither is.
        mask: (S, S) uint8 part id (1 right hand, 2 left hand, 3 object top, 4 object bottom,
            0 background), 0 also where the crop reaches past the original image.
    """

    view: int
    frame: int
    image: Optional[Path]
    K: np.ndarray
    world2cam: np.ndarray
    depth: np.ndarray
    mask: np.ndarray


def _check_view(seq: SequenceData, view: int) -> None:
    if view not in seq.cameras:
        raise ValueError(f"{seq.subject}/{seq.name}: no view {view} (views {sorted(seq.cameras)})")
    if seq.cameras[view].egocentric or view == 0:
        raise ValueError(
            f"{seq.subject}/{seq.name}: view {view} is the egocentric camera, whose images are lens-distorted; "
            "depth and masks are rendered for the allocentric views 1-8"
        )


def cropped_cameras(root: ArcticRoot, seq: SequenceData, view: int) -> tuple[np.ndarray, np.ndarray, int]:
    """The cameras of every allocentric cropped image of ``seq`` seen from ``view``.

    Args:
        root: the dataset root (object layer, cropped-image size).
        seq: the sequence.
        view: allocentric view (1-8).

    Returns:
        ``(K (F, 3, 3), world2cam (F, 4, 4), size)``: label-convention intrinsics of the
        ``size × size`` cropped image of every frame (its box projects the posed object
        template, as ARCTIC's processing does) and the extrinsics.

    Raises:
        ValueError: ``view`` is not one of the sequence's allocentric views.
    """
    _check_view(seq, view)
    size = int(root.world_meta().cropped_size)
    cam = seq.cameras[view]
    boxes = crop_boxes(root, seq, [view])[view]
    return cropped_intrinsics(cam.K, boxes, size), np.asarray(cam.world2cam, np.float64), size


def render_frame_maps(
    root: ArcticRoot,
    seq: SequenceData,
    view: int,
    frames: Sequence[int],
    *,
    size: Optional[int] = None,
    supersample: int = 1,
    posed: Optional[PosedMeshes] = None,
) -> list[FrameMaps]:
    """Depth and part masks of the cropped images of ``frames`` seen from ``view``.

    The MANO hands and the articulated object template are posed with each frame's
    annotations (:func:`~hogsa_loader.render.part_masks.pose_meshes`) and rasterised with
    :func:`~hogsa_loader.render.mesh_raster.render_meshes` (z-buffer) in the cropped image's
    camera: each pixel takes the depth and part of the nearest of its ``supersample²``
    samples.

    Args:
        root: the dataset root.
        seq: the sequence.
        view: allocentric view (1-8).
        frames: annotation frame indices.
        size: side of the maps (default the cropped images' own, ARCTIC: 1000); the
            intrinsics returned are those of the cropped image scaled to it.
        supersample: samples per pixel side.
        posed: meshes posed beforehand for these frames (else posed here).

    Returns:
        one :class:`FrameMaps` per frame, in order.

    Raises:
        ValueError: an egocentric or unknown view, or a frame outside the sequence.
    """
    K_all, w2c, crop = cropped_cameras(root, seq, view)
    frames = [int(f) for f in frames]
    bad = [f for f in frames if not 0 <= f < seq.num_frames]
    if bad:
        raise ValueError(f"{seq.subject}/{seq.name}: frames {bad} outside 0..{seq.num_frames - 1}")
    side = int(size or crop)
    if posed is None:
        template = root.object_templates()[seq.object.name]
        posed = pose_meshes(seq, frames, root.mano_layers(), template)
    cam = seq.cameras[view]
    paths = list(seq.image_paths.get(view) or [])
    paths += [None] * (seq.num_frames - len(paths))
    out = []
    for f in frames:
        # resized as cv2.resize resizes (pixel edges scale, x' = (x + 0.5)·s − 0.5): scale the
        # edge-convention (render) intrinsics, then back to the labels' centre convention
        K_render = np.diag([side / crop, side / crop, 1.0]) @ render_intrinsics(K_all[f])
        K = K_all[f].copy() if side == crop else K_render - np.array([[0, 0, 0.5], [0, 0, 0.5], [0, 0, 0]])
        rend = render_meshes(
            posed.parts(posed.index(f)),
            torch.as_tensor(w2c[f], dtype=torch.float32),
            torch.as_tensor(K_render, dtype=torch.float32),
            side,
            side,
            supersample=supersample,
        )
        inside = inside_image(K_render, cam.K[f], cam.width, cam.height, side)
        part = rend.part_id.numpy().astype(np.uint8) * inside
        depth = torch.nan_to_num(rend.depth, posinf=0.0).numpy().astype(np.float32) * inside
        depth[part == 0] = 0.0
        out.append(FrameMaps(view, f, paths[f], K, w2c[f].copy(), depth, part))
    return out


#: Depth PNG unit: one count is this many metres (16-bit PNG, 0 = no surface; up to 65.5 m).
DEPTH_PNG_METRES = 1e-3


@dataclass
class FrameMapsConfig:
    """Settings of :func:`write_frame_maps` (``hogsa frame-maps`` derives one flag per field)."""

    data: Optional[str] = field(default=None, metadata={"help": "ARCTIC(-format) data root", "required": True})
    out: Optional[str] = field(default=None, metadata={"help": "output folder of the maps", "required": True})
    subjects: tuple[str, ...] = field(default=(), metadata={"help": "subjects (default: every subject of the root)"})
    sequences: tuple[str, ...] = field(default=(), metadata={"help": "sequence names (default: every one)"})
    views: tuple[int, ...] = field(default=(1, 2, 3, 4, 5, 6, 7, 8), metadata={"help": "allocentric views"})
    size: int = field(default=0, metadata={"help": "side of the maps in pixels (0: the cropped images' own)"})
    frame_stride: int = field(default=1, metadata={"help": "every N-th frame"})
    quiet: bool = field(default=False, metadata={"help": "no progress messages"})

    def check(self) -> None:
        """Raise :class:`~hogsa_loader.errors.UsageError` for settings that cannot work."""
        if self.size < 0 or self.frame_stride < 1:
            raise UsageError(f"--size must be >= 0 and --frame-stride >= 1, got {self.size}, {self.frame_stride}")
        bad = [v for v in self.views if not 1 <= v <= 8]
        if bad or not self.views:
            raise UsageError(f"--views must be allocentric views 1..8, got {list(self.views)}")


def _view_folder(out: Path, seq: SequenceData, view: int) -> Path:
    return out / seq.subject / seq.name / str(view)


#: Frames rendered and written at a time (their maps held in memory together).
_CHUNK = 32


def _write_view(
    root: ArcticRoot, seq: SequenceData, view: int, frames: list[int], folder: Path, size: int, stride: int
) -> None:
    """The maps of ``frames`` as PNGs under ``folder``, a few frames at a time, then
    ``cameras.npz`` (written last: a view with one is complete; it records ``size`` and
    ``stride``)."""
    folder.mkdir(parents=True, exist_ok=True)
    template = root.object_templates()[seq.object.name]
    names, Ks, w2cs = [], [], []
    for i in range(0, len(frames), _CHUNK):
        chunk = frames[i : i + _CHUNK]
        posed = pose_meshes(seq, chunk, root.mano_layers(), template)
        for m in render_frame_maps(root, seq, view, chunk, size=size or None, posed=posed):
            stem = m.image.stem if m.image is not None else f"frame{m.frame:05d}"
            depth = np.round(m.depth / DEPTH_PNG_METRES).clip(0, 65535).astype(np.uint16)
            write_image(folder / f"{stem}_depth.png", depth, durable=False)
            write_image(folder / f"{stem}_mask.png", m.mask, durable=False)
            names.append(stem)
            Ks.append(m.K)
            w2cs.append(m.world2cam)
    buf = io.BytesIO()
    np.savez(
        buf,
        frames=np.asarray(frames, np.int64),
        names=np.asarray(names),
        K=np.stack(Ks),
        world2cam=np.stack(w2cs),
        settings=np.asarray([size, stride], np.int64),
    )
    atomic_write(folder / "cameras.npz", buf.getvalue())


def _written_settings(folder: Path) -> tuple[int, int]:
    """``(size, frame stride)`` a complete view was written with."""
    try:
        with np.load(folder / "cameras.npz", allow_pickle=False) as cams:
            size, stride = (int(v) for v in cams["settings"])
    except (OSError, ValueError, KeyError, zipfile.BadZipFile) as exc:
        raise AssetError(
            folder / "cameras.npz", f"unreadable ({type(exc).__name__}: {exc}); remove the view to redo it"
        ) from None
    return size, stride


def write_frame_maps(cfg: FrameMapsConfig, log: Optional[Callable[[str], None]] = print) -> dict[str, Any]:
    """Depth maps, part masks and cameras of every selected cropped image, resumable per view.

    Writes ``OUT/<subject>/<sequence>/<view>/``: ``<image>_depth.png`` (16-bit, millimetres,
    0 = no hand or object), ``<image>_mask.png`` (8-bit part ids) for each cropped image
    ``<image>.jpg``, and ``cameras.npz`` (``frames`` annotation indices, ``names`` image
    names, ``K`` (F, 3, 3) label-convention intrinsics of the cropped images at the maps'
    size, ``world2cam`` (F, 4, 4)); ``OUT/maps.json`` lists what was written. A view whose
    ``cameras.npz`` exists is complete and is not written again.

    Returns:
        the manifest (``maps.json``'s content).
    """
    say = log or (lambda s: None)
    root = ArcticRoot(cfg.data)
    out = Path(cfg.out)  # type: ignore[arg-type]
    out.mkdir(parents=True, exist_ok=True)
    with writer_lock(out, ".frame-maps.lock", what="hogsa frame-maps"):
        return _write_all(cfg, root, out, say)


def _write_all(cfg: FrameMapsConfig, root: ArcticRoot, out: Path, say: Callable[[str], None]) -> dict[str, Any]:
    subjects = list(cfg.subjects) or root.subjects()
    every = {sid: [n.split("/", 1)[1] for n in root.sequences(sid)] for sid in subjects}
    unknown = sorted(set(cfg.sequences) - {n for names in every.values() for n in names})
    if unknown:
        raise UsageError(f"--sequences {','.join(unknown)}: not sequences of {', '.join(subjects)}")
    done, written = [], 0
    for sid, names in every.items():
        for name in [n for n in names if not cfg.sequences or n in cfg.sequences]:
            seq = root.sequence(sid, name)
            frames = list(range(0, seq.num_frames, cfg.frame_stride))
            for view in cfg.views:
                folder = _view_folder(out, seq, view)
                if view not in seq.cameras:
                    continue
                if (folder / "cameras.npz").is_file():
                    had = _written_settings(folder)
                    if had != (cfg.size, cfg.frame_stride):
                        raise UsageError(
                            f"{folder} was written with --size {had[0]} --frame-stride {had[1]}; give those, "
                            "or another --out"
                        )
                else:
                    t0 = time.perf_counter()
                    _write_view(root, seq, view, frames, folder, cfg.size, cfg.frame_stride)
                    written += len(frames)
                    secs = time.perf_counter() - t0
                    say(f"[frame-maps] {sid}/{name} view {view}: {len(frames)} frames in {secs:.1f} s")
                done.append(f"{sid}/{name}/{view}")
    manifest = {
        "kind": "frame_maps",
        "views": done,
        "depth_png_metres": DEPTH_PNG_METRES,
        "mask_ids": {"background": 0, **MASK_IDS},
        "settings": {"size": cfg.size, "frame_stride": cfg.frame_stride},
    }
    atomic_write_json(out / "maps.json", manifest)
    say(f"[frame-maps] {len(done)} views in {out} ({written} frames written now)")
    return manifest


def view_images(cfg: FrameMapsConfig, view_id: str) -> tuple[Path, list[Path]]:
    """The folder of a written view (``"sid/seq/view"`` of the manifest) and the cropped
    images its maps were written for, in frame order."""
    sid, name, view = view_id.split("/")
    folder = Path(cfg.out) / sid / name / view  # type: ignore[arg-type]
    seq = ArcticRoot(cfg.data).sequence(sid, name)
    with np.load(folder / "cameras.npz", allow_pickle=False) as cams:
        frames = [int(f) for f in cams["frames"]]
    paths = seq.image_paths.get(int(view)) or []
    return folder, [p for p in (paths[f] for f in frames if f < len(paths)) if p is not None]
