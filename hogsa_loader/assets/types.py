"""Dataset-independent view of one annotated hand-object sequence.

Both readers (``datasets/arctic.py``, ``datasets/h2o.py``) expose their sequences as
:class:`SequenceData`, so HOGS training, POM and the sample builder never care which
dataset a frame came from.

Conventions (whatever the source dataset uses on disk):
* metres, axis-angle, OpenCV cameras ``p_cam = R p_world + T``;
* MANO finger pose is **relative to the MANO mean pose** (``flat_hand_mean=False``,
  ARCTIC's convention; H2O's ``flat_hand_mean=True`` poses are converted on reading);
* the object is the ARCTIC 7-D parameter split into ``arti`` (θ, rad), ``rot``
  (axis-angle) and ``trans`` (metres) in the world frame; rigid objects have θ = 0.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional

import numpy as np

__all__ = ["CameraTrack", "HandTrack", "ObjectTrack", "SequenceData"]


@dataclass
class HandTrack:
    """MANO parameters of one hand over F frames (world frame).

    Attributes:
        rot: (F, 3) global orientation, axis-angle.
        pose: (F, 45) finger pose relative to the MANO mean (flat_hand_mean=False).
        trans: (F, 3) MANO ``transl`` (m).
        betas: (10,) shape, one vector per sequence.
        valid: (F,) bool, False where the annotation is missing.
        fitting_err: (F,) per-frame MANO fitting error when the dataset has it (ARCTIC
            ``fitting_err``), else None.
    """

    rot: np.ndarray
    pose: np.ndarray
    trans: np.ndarray
    betas: np.ndarray
    valid: np.ndarray
    fitting_err: Optional[np.ndarray] = None


@dataclass
class ObjectTrack:
    """Object pose over F frames (world frame).

    Attributes:
        name: object name (ARCTIC ``OBJECTS`` name or H2O class name).
        arti: (F,) articulation angle θ (rad); zeros for rigid objects.
        rot: (F, 3) global rotation of the base part, axis-angle.
        trans: (F, 3) translation (m).
        valid: (F,) bool.
    """

    name: str
    arti: np.ndarray
    rot: np.ndarray
    trans: np.ndarray
    valid: np.ndarray


@dataclass
class CameraTrack:
    """One camera over F frames.

    Attributes:
        view: view index in its dataset (ARCTIC 0 = ego, 1..8 allocentric; H2O 0..4).
        world2cam: (F, 4, 4) extrinsics (static cameras repeat one matrix).
        K: (F, 3, 3) intrinsics of the full-resolution image.
        width, height: full-resolution image size (pixels).
        dist: (8,) or (F, 8) OpenCV rational distortion, or None for none.
        egocentric: True for head-mounted cameras.
    """

    view: int
    world2cam: np.ndarray
    K: np.ndarray
    width: int
    height: int
    dist: Optional[np.ndarray] = None
    egocentric: bool = False


@dataclass
class SequenceData:
    """Everything annotated about one sequence.

    Attributes:
        dataset: ``"arctic"`` or ``"h2o"``.
        subject: subject id (``"s01"``, ``"subject1"``...).
        name: sequence name (``"box_use_01"``, ``"h1/0"``...).
        right, left: hand tracks.
        object: object track.
        cameras: view index -> camera track.
        frame_ids: (F,) image file numbers of the GT frames (ARCTIC: GT index +
            ``ioi_offset``).
        image_paths: view -> list of F image paths (None where a frame has no image);
            for ARCTIC these are the ``cropped_images`` (what the baselines train on).
        mask_paths: view -> list of F foreground-mask paths, when the dataset has them
            (the generated world does).
        root: dataset root the sequence was read from.
        full_image_paths: view -> list of F full-resolution image paths when the dataset
            also has them separately (ARCTIC ``images/``), None where absent.
    """

    dataset: str
    subject: str
    name: str
    right: HandTrack
    left: HandTrack
    object: ObjectTrack
    cameras: dict[int, CameraTrack]
    frame_ids: np.ndarray
    image_paths: dict[int, list[Optional[Path]]] = field(default_factory=dict)
    mask_paths: dict[int, list[Optional[Path]]] = field(default_factory=dict)
    root: Optional[Path] = None
    full_image_paths: dict[int, list[Optional[Path]]] = field(default_factory=dict)

    @property
    def num_frames(self) -> int:
        return int(self.frame_ids.shape[0])
