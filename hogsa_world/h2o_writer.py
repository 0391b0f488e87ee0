"""A writer of small H2O-format trees (the layout the H2O reader accepts), for test data."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Mapping, Optional, Sequence

import cv2
import numpy as np

from hogsa_loader.assets import h2o_io
from hogsa_loader.assets.h2o import MODALITY_FOLDERS, SeqId
from hogsa_loader.assets.h2o_io import H2OIntrinsics, H2OManoLabels
from hogsa_loader.errors import AssetError, PathLike

__all__ = ["H2OCameraRecord", "write_h2o_sequence"]


@dataclass
class H2OCameraRecord:
    """Everything to write into one ``camK`` folder for F frames.

    Attributes:
        cam_pose: (F, 4, 4) or (4, 4) camera-to-world (static cameras may pass one).
        intrinsics: contents of ``cam_intrinsics.txt``.
        mano: MANO labels in this camera's frame, ``flat_hand_mean=True`` (or None).
        obj_class: (F,) class ids 0..8 for ``obj_pose_rt`` (or None).
        obj_transform: (F, 4, 4) object-to-camera (with ``obj_class``).
        hand_pose: (F, 128) ``hand_pose`` lines (or None).
        obj_pose: (F, 64) ``obj_pose`` lines (or None).
        action_label, verb_label: (F,) integers (or None).
        rgb: F images (H, W, 3) uint8 RGB written as ``rgb/NNNNNN.png`` (or None).
    """

    cam_pose: np.ndarray
    intrinsics: H2OIntrinsics
    mano: Optional[H2OManoLabels] = None
    obj_class: Optional[np.ndarray] = None
    obj_transform: Optional[np.ndarray] = None
    hand_pose: Optional[np.ndarray] = None
    obj_pose: Optional[np.ndarray] = None
    action_label: Optional[np.ndarray] = None
    verb_label: Optional[np.ndarray] = None
    rgb: Optional[Sequence[np.ndarray]] = None


def _write_line(path: Path, values: np.ndarray, precision: Optional[int], check: Callable[[str, Path], object]) -> None:
    line = h2o_io.format_h2o_line(values, precision)
    check(line, path)  # what is written must read back (AssetError names the file otherwise)
    path.write_text(line + "\n", encoding="utf-8")


@dataclass
class _Frames:
    """The frames of one sequence and how its text files are written."""

    frame_ids: list[int]
    precision: Optional[int]
    upper_case: bool

    def folder(self, cdir: Path, modality: str) -> Path:
        """The (created) folder of ``modality`` in camera folder ``cdir``."""
        name = MODALITY_FOLDERS[modality][-1] if self.upper_case else modality
        d = cdir / name
        d.mkdir(parents=True, exist_ok=True)
        return d

    def rows(self, arr: np.ndarray, shape: tuple[int, ...], what: str) -> np.ndarray:
        """``arr`` as float64 (F, *shape); ValueError for another shape."""
        F = len(self.frame_ids)
        a = np.asarray(arr, dtype=np.float64)
        if a.shape != (F, *shape):
            raise ValueError(f"{what} must have shape {(F, *shape)}, got {a.shape}")
        return a

    def write(self, d: Path, rows: Sequence[np.ndarray], check: Callable[[str, Path], object]) -> None:
        """One ``NNNNNN.txt`` line file per frame in ``d``."""
        for f, r in zip(self.frame_ids, rows):
            _write_line(d / f"{f:06d}.txt", r, self.precision, check)


def _write_labels(fr: _Frames, cdir: Path, rec: H2OCameraRecord) -> None:
    """The text modalities of one camera: ``cam_pose``, MANO, object pose, and the optional ones."""
    F = len(fr.frame_ids)
    pose = np.asarray(rec.cam_pose, dtype=np.float64)
    pose = np.broadcast_to(pose, (F, 4, 4)) if pose.shape == (4, 4) else fr.rows(pose, (4, 4), "cam_pose")
    fr.write(fr.folder(cdir, "cam_pose"), [m.reshape(16) for m in pose], h2o_io.parse_h2o_cam_pose)
    if rec.mano is not None:
        rows = fr.rows(rec.mano.to_array(), (124,), "mano")
        fr.write(fr.folder(cdir, "hand_pose_mano"), rows, h2o_io.parse_h2o_hand_pose_mano)
    if rec.obj_class is not None or rec.obj_transform is not None:
        if rec.obj_class is None or rec.obj_transform is None:
            raise ValueError("obj_class and obj_transform go together")
        cls = fr.rows(rec.obj_class, (), "obj_class")
        mats = fr.rows(rec.obj_transform, (4, 4), "obj_transform")
        d = fr.folder(cdir, "obj_pose_rt")
        fr.write(
            d, [np.concatenate([[c], m.reshape(16)]) for c, m in zip(cls, mats)], h2o_io.parse_h2o_obj_pose_rt_strict
        )
    simple = (
        ("hand_pose", rec.hand_pose, (128,), h2o_io.parse_h2o_hand_pose),
        ("obj_pose", rec.obj_pose, (64,), h2o_io.parse_h2o_obj_pose),
        ("action_label", rec.action_label, (), h2o_io.parse_h2o_action_label),
        ("verb_label", rec.verb_label, (), h2o_io.parse_h2o_verb_label),
    )
    for modality, arr, shape, parser in simple:
        if arr is None:
            continue
        rows = fr.rows(arr, shape, modality)
        fr.write(fr.folder(cdir, modality), [np.atleast_1d(r) for r in rows], parser)


def _write_rgb(fr: _Frames, cdir: Path, rec: H2OCameraRecord) -> None:
    """``rgb/NNNNNN.png`` of one camera: its images, or flat grey placeholders of the intrinsics' size."""
    F = len(fr.frame_ids)
    if rec.rgb is not None and len(rec.rgb) != F:
        raise ValueError(f"rgb must hold {F} images, got {len(rec.rgb)}")
    d = fr.folder(cdir, "rgb")
    for i, f in enumerate(fr.frame_ids):
        if rec.rgb is not None:
            img = np.asarray(rec.rgb[i])
            if img.dtype != np.uint8 or img.ndim != 3 or img.shape[2] != 3:
                raise ValueError(f"rgb images must be (H, W, 3) uint8, got {img.shape} {img.dtype}")
        else:
            img = np.full((rec.intrinsics.height, rec.intrinsics.width, 3), 128, dtype=np.uint8)
        if not cv2.imwrite(str(d / f"{f:06d}.png"), np.ascontiguousarray(img[:, :, ::-1])):
            raise AssetError(d / f"{f:06d}.png", "cannot write image")


def write_h2o_sequence(
    root: PathLike,
    subject: str,
    scene: str,
    seq: SeqId,
    frame_ids: Sequence[int],
    cameras: Mapping[int, H2OCameraRecord],
    precision: Optional[int] = None,
    placeholder_rgb: bool = False,
    upper_case: bool = False,
) -> Path:
    """Write a small H2O-format sequence tree.

    Args:
        root: dataset root (created if needed).
        subject, scene, seq: e.g. ``"subject1", "h1", 0``.
        frame_ids: (F,) frame numbers (file names ``{frame:06d}``).
        cameras: camera index K -> what to write into ``camK``.
        precision: decimals of the text files (``None``: exact float ``repr``).
        placeholder_rgb: write a flat grey ``rgb/`` PNG of the intrinsics' size for every
            frame of cameras whose record has no ``rgb``.
        upper_case: use the README spellings ``hand_pose_MANO`` / ``obj_pose_RT``.

    Returns:
        The sequence folder.

    Raises:
        ValueError: array shapes inconsistent with F.
        AssetError: a value that would not read back (named after the file it was for).
    """
    frame_ids = [int(f) for f in frame_ids]
    F = len(frame_ids)
    if F == 0 or len(set(frame_ids)) != F or min(frame_ids) < 0:
        raise ValueError("frame_ids must be distinct non-negative integers (at least one)")
    seq_dir = Path(root) / subject / scene / str(seq)
    fr = _Frames(frame_ids, precision, upper_case)
    for cam, rec in cameras.items():
        cdir = seq_dir / f"cam{int(cam)}"
        cdir.mkdir(parents=True, exist_ok=True)
        _write_line(
            cdir / h2o_io.H2O_CAM_INTRINSICS_FILE, rec.intrinsics.to_array(), precision, h2o_io.parse_h2o_cam_intrinsics
        )
        _write_labels(fr, cdir, rec)
        if rec.rgb is not None or placeholder_rgb:
            _write_rgb(fr, cdir, rec)
    return seq_dir
