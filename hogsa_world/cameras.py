"""Cameras of a world: 8 static allocentric cameras per subject and the head-mounted one.

Conventions (ARCTIC's): OpenCV cameras, ``p_cam = R p_world + T``, K in
full-resolution pixels in OpenCV's convention (pixel i centred on coordinate i, as ARCTIC's
labels and cv2 crops; images are rendered with ``conventions.render_intrinsics``). View 0 is egocentric (per-frame
extrinsics, K for a 2800x2000 image, OpenCV rational distortion ``dist8``); views 1..8 are
allocentric with full-res sizes recorded per view as [w, h].
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from hogsa_loader.assets.conventions import EGO_IMAGE_SIZE
from hogsa_loader.geometry.cameras import look_at
from hogsa_world.stage import TABLE_Y, TABLE_Z, WORKSPACE

#: World up: the cameras' image-up direction.
_UP = np.array([0.0, 0.0, 1.0])

__all__ = ["AlloRig", "EgoCamera", "allocentric_rig", "ego_calibration", "ego_trajectory"]

#: Full-res sizes (w, h) of the allocentric views, alternating landscape / portrait.
ALLO_SIZES = ((2800, 2000), (2000, 2800))


@dataclass
class AlloRig:
    """Allocentric cameras of one subject (list index = view - 1).

    Attributes:
        world2cam: (8, 4, 4) float64.
        K: (8, 3, 3) float64 full-res intrinsics.
        sizes: 8 full-res (width, height).
    """

    world2cam: np.ndarray
    K: np.ndarray
    sizes: list[tuple[int, int]]


@dataclass
class EgoCamera:
    """Egocentric camera of one sequence.

    Attributes:
        R: (F, 3, 3) world->camera rotations; T: (F, 3, 1) translations (m).
        K: (3, 3) intrinsics of the full 2800x2000 image.
        dist8: (8,) k1, k2, p1, p2, k3, k4, k5, k6.
    """

    R: np.ndarray
    T: np.ndarray
    K: np.ndarray
    dist8: np.ndarray

    @property
    def world2cam(self) -> np.ndarray:
        """(F, 4, 4)."""
        out = np.zeros((self.R.shape[0], 4, 4))
        out[:, :3, :3] = self.R
        out[:, :3, 3] = self.T[..., 0]
        out[:, 3, 3] = 1.0
        return out


def _look_at(eye: np.ndarray, target: np.ndarray, roll: float) -> np.ndarray:
    """(4, 4) world->camera of a camera at ``eye`` looking at ``target``, image-up toward +z,
    rolled by ``roll`` radians (image x turning toward image -y)."""
    return look_at(eye, target, _UP, -roll)[0]


def allocentric_rig(base_rng: np.random.Generator, subject_rng: np.random.Generator) -> AlloRig:
    """A ring of 8 cameras around the table, re-calibrated (slightly moved) per subject.

    ``base_rng`` (shared by all subjects of a world) places the ring: azimuths every 45°
    with jitter, distances 1.15-1.45 m, heights alternating low/high (0.3-0.95 m above the
    table). ``subject_rng`` moves each camera by ~1 cm / 0.5° and jitters K, as a new
    calibration session would.
    """
    w2c, Ks, sizes = [], [], []
    az0 = base_rng.uniform(0, 2 * np.pi)
    for k in range(8):
        az = az0 + 2 * np.pi * k / 8 + base_rng.uniform(-0.12, 0.12)
        dist = base_rng.uniform(1.15, 1.45)
        height = base_rng.uniform(0.3, 0.55) if k % 2 == 0 else base_rng.uniform(0.65, 0.95)
        horiz = np.sqrt(max(dist**2 - height**2, 0.25))
        eye = WORKSPACE + np.array([horiz * np.cos(az), horiz * np.sin(az), height])
        eye = eye + subject_rng.normal(0, 0.01, 3)
        target = WORKSPACE + base_rng.normal(0, 0.03, 3) + subject_rng.normal(0, 0.005, 3)
        roll = base_rng.normal(0, 0.03) + subject_rng.normal(0, 0.005)
        w2c.append(_look_at(eye, target, roll))
        w, h = ALLO_SIZES[k % 2]
        d = np.linalg.norm(target - eye)
        f = 0.5 * min(w, h) * d / base_rng.uniform(0.34, 0.42) * subject_rng.uniform(0.99, 1.01)
        cx = w / 2 + subject_rng.normal(0, 15)
        cy = h / 2 + subject_rng.normal(0, 15)
        Ks.append(np.array([[f, 0.0, cx], [0.0, f, cy], [0.0, 0.0, 1.0]]))
        sizes.append((w, h))
    return AlloRig(world2cam=np.stack(w2c), K=np.stack(Ks), sizes=sizes)


def ego_calibration(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Head-camera K (2800x2000, ~76° horizontal field of view) and mild distortion.

    Returns:
        K (3, 3), dist8 (8,) in OpenCV rational order (k1, k2, p1, p2, k3, k4, k5, k6).
    """
    w, h = EGO_IMAGE_SIZE
    f = rng.uniform(1680, 1800)
    K = np.array(
        [
            [f * rng.uniform(0.998, 1.002), 0.0, w / 2 + rng.normal(0, 8)],
            [0.0, f, h / 2 + rng.normal(0, 8)],
            [0.0, 0.0, 1.0],
        ]
    )
    dist8 = np.array(
        [
            rng.uniform(-0.09, -0.05),  # k1 (barrel)
            rng.uniform(0.01, 0.03),  # k2
            rng.normal(0, 3e-4),  # p1
            rng.normal(0, 3e-4),  # p2
            rng.uniform(-0.004, 0.0),  # k3
            rng.uniform(0.0, 0.02),  # k4
            rng.uniform(0.0, 0.005),  # k5
            0.0,  # k6
        ]
    )
    return K, dist8


def ego_trajectory(num_frames: int, rng: np.random.Generator, focus: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-frame world->camera of the head camera.

    The head sits just behind the table edge ~0.4 m above the table and looks down at a
    point halfway between the workspace and ``focus`` (e.g. the object centre); small
    smooth sinusoidal head motion (~1 cm, ~2°) is added.

    Args:
        num_frames: F.
        rng: sequence random stream.
        focus: (F, 3) world points the subject attends to.

    Returns:
        R (F, 3, 3), T (F, 3, 1).
    """
    t = np.arange(num_frames, dtype=np.float64)
    head = np.array([rng.normal(0, 0.02), TABLE_Y[0] - rng.uniform(0.03, 0.07), TABLE_Z + rng.uniform(0.38, 0.44)])
    R, T = [], []
    motion = np.zeros((num_frames, 3))
    look = np.zeros((num_frames, 3))
    roll = np.zeros(num_frames)
    for axis in range(3):
        for amp, period in ((0.008, rng.uniform(40, 70)), (0.004, rng.uniform(15, 25))):
            motion[:, axis] += amp * np.sin(2 * np.pi * t / period + rng.uniform(0, 2 * np.pi))
            look[:, axis] += 2.5 * amp * np.sin(2 * np.pi * t / period + rng.uniform(0, 2 * np.pi))
    roll += 0.02 * np.sin(2 * np.pi * t / rng.uniform(30, 60) + rng.uniform(0, 2 * np.pi))
    base_target = np.array([WORKSPACE[0], WORKSPACE[1] + 0.02, TABLE_Z])
    for i in range(num_frames):
        target = 0.5 * base_target + 0.5 * focus[i] + look[i]
        M = _look_at(head + motion[i], target, roll[i])
        R.append(M[:3, :3])
        T.append(M[:3, 3:4])
    return np.stack(R), np.stack(T)
