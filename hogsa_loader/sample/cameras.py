"""Cameras of synthetic samples: novel viewpoints around the hands and object, or the
dataset's own cameras.

:class:`CameraSampler` draws the cameras of one subject (its docstring describes the two
kinds and how defaults are derived), configured by :class:`CameraConfig`; :func:`~hogsa_loader.geometry.cameras.look_at`
builds world→camera matrices.

Conventions: OpenCV cameras (``p_cam = R p + t``, x right, y down, z forward), metres.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional, Sequence

import numpy as np

from hogsa_loader.geometry.cameras import look_at

__all__ = ["NOVEL_VIEW", "CameraConfig", "CameraBatch", "CameraSampler", "look_at"]

#: View id recorded for novel (non-dataset) cameras.
NOVEL_VIEW: int = 100


@dataclass(frozen=True)
class CameraConfig:
    """How synthetic cameras are drawn (None = derived from the dataset's cameras).

    Attributes:
        azimuth_deg: azimuth range about the world up axis (default the full circle).
        elevation_deg: elevation range above the horizontal plane through the centre;
            None = the dataset cameras' elevations widened by ``elevation_margin_deg``.
        elevation_margin_deg: widening of the derived elevation range (each side).
        distance_m: camera-to-centre distance range; None = the dataset cameras'
            distances times ``(0.9, 1.1)``.
        roll_deg: roll about the optical axis, uniform in ``±roll_deg``.
        target_jitter_m: std of a Gaussian offset of the look-at target (m).
        dataset_prob: probability of using one of the dataset's camera poses instead.
        focal_px: virtual focal length (fx = fy); None = median of the dataset's fx.
        image_size: virtual full image (W, H); None = the most common dataset size.
        up: world up vector; None = the mean "up" (−y axis) of the dataset cameras.
    """

    azimuth_deg: tuple[float, float] = (0.0, 360.0)
    elevation_deg: Optional[tuple[float, float]] = None
    elevation_margin_deg: float = 10.0
    distance_m: Optional[tuple[float, float]] = None
    roll_deg: float = 15.0
    target_jitter_m: float = 0.02
    dataset_prob: float = 0.25
    focal_px: Optional[float] = None
    image_size: Optional[tuple[int, int]] = None
    up: Optional[tuple[float, float, float]] = None


@dataclass
class CameraBatch:
    """Cameras of B samples.

    Attributes:
        world2cam: (B, 4, 4) float64 extrinsics.
        K: (B, 3, 3) float64 full-image intrinsics (label convention).
        image_size: (B, 2) int64 full image (W, H).
        view: (B,) int64 dataset view, or :data:`NOVEL_VIEW`.
    """

    world2cam: np.ndarray
    K: np.ndarray
    image_size: np.ndarray
    view: np.ndarray


class CameraSampler:
    """Draws cameras for samples of one subject.

    It draws, per sample, either

    * a **novel** camera on a sphere around the interaction centre: azimuth over the full
      360°, elevation and distance in configurable ranges, looking at the centre (plus a small
      target jitter) with a random roll; its full-image intrinsics are a *virtual* camera like
      the dataset's (same focal length, principal point at the image centre, the dataset's
      most common image size); or
    * one of the subject's **dataset** camera poses (world→camera, K and image size as
      recorded in ``misc.json``), with probability ``dataset_prob``.

    Defaults are derived from the dataset's cameras of the subject (see :class:`CameraConfig`)
    so that objects appear at the same pixel scale as in the real images (the ARCTIC crop box
    depends on it: 1.7 × the projected object extent, at least 600 px).

    Args:
        world2cam: (V, 4, 4) the subject's dataset cameras (the protocol's views).
        K: (V, 3, 3) their full-image intrinsics.
        image_size: (V, 2) their (W, H).
        views: (V,) their view ids.
        reference_centre: (3,) a typical interaction centre (e.g. the mean object
            position of the subject's sequences), used to derive default elevations and
            distances from the dataset cameras.
        config: :class:`CameraConfig`.
    """

    def __init__(
        self,
        world2cam: np.ndarray,
        K: np.ndarray,
        image_size: np.ndarray,
        views: Sequence[int],
        reference_centre: np.ndarray,
        config: CameraConfig = CameraConfig(),
    ) -> None:
        self.world2cam = np.asarray(world2cam, dtype=np.float64).reshape(-1, 4, 4)
        self.K = np.asarray(K, dtype=np.float64).reshape(-1, 3, 3)
        self.sizes = np.asarray(image_size, dtype=np.int64).reshape(-1, 2)
        self.views = np.asarray(list(views), dtype=np.int64)
        self.config = config
        R = self.world2cam[:, :3, :3]
        centres = -np.einsum("vji,vj->vi", R, self.world2cam[:, :3, 3])
        if config.up is not None:
            up = np.asarray(config.up, dtype=np.float64)
        else:
            up = (-R[:, 1, :]).sum(axis=0)
        if np.linalg.norm(up) < 1e-9:
            raise ValueError("cannot derive the world up vector from the dataset cameras; set CameraConfig.up")
        self.up = up / np.linalg.norm(up)
        # an orthonormal frame (e1, e2, up) for azimuth
        helper = np.array([1.0, 0.0, 0.0]) if abs(self.up[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
        self.e1 = np.cross(self.up, helper)
        self.e1 /= np.linalg.norm(self.e1)
        self.e2 = np.cross(self.up, self.e1)
        rel = centres - np.asarray(reference_centre, dtype=np.float64).reshape(1, 3)
        dist = np.linalg.norm(rel, axis=1)
        elev = np.degrees(np.arcsin(np.clip(rel @ self.up / np.maximum(dist, 1e-9), -1, 1)))
        m = config.elevation_margin_deg
        self.elevation = (
            tuple(config.elevation_deg)
            if config.elevation_deg is not None
            else (float(max(-89.0, elev.min() - m)), float(min(89.0, elev.max() + m)))
        )
        self.distance = (
            tuple(config.distance_m)
            if config.distance_m is not None
            else (float(dist.min() * 0.9), float(dist.max() * 1.1))
        )
        self.focal = (
            float(config.focal_px)
            if config.focal_px is not None
            else float(np.median(np.concatenate([self.K[:, 0, 0], self.K[:, 1, 1]])))
        )
        if config.image_size is not None:
            self.image_wh = (int(config.image_size[0]), int(config.image_size[1]))
        else:
            sizes, counts = np.unique(self.sizes, axis=0, return_counts=True)
            best = sizes[np.argmax(counts)]
            self.image_wh = (int(best[0]), int(best[1]))
        if not (self.distance[0] > 0 and self.distance[1] >= self.distance[0]):
            raise ValueError(f"bad camera distance range {self.distance}")

    def virtual_K(self) -> np.ndarray:
        """(3, 3) the virtual full-image intrinsics of novel cameras."""
        W, H = self.image_wh
        return np.array([[self.focal, 0.0, (W - 1) / 2.0], [0.0, self.focal, (H - 1) / 2.0], [0.0, 0.0, 1.0]])

    def sample(self, centres: np.ndarray, rngs: Sequence[np.random.Generator]) -> CameraBatch:
        """Draw one camera per sample.

        Args:
            centres: (B, 3) interaction centres (world frame).
            rngs: B generators (one per sample; each draws the same number of values
                whichever camera kind it picks, so streams stay aligned).

        Returns:
            :class:`CameraBatch`.
        """
        centres = np.asarray(centres, dtype=np.float64).reshape(-1, 3)
        B = centres.shape[0]
        cfg = self.config
        u = np.array([r.random(8) for r in rngs]).reshape(B, 8)
        jitter = np.array([r.standard_normal(3) for r in rngs]).reshape(B, 3) * cfg.target_jitter_m
        az = np.radians(cfg.azimuth_deg[0] + u[:, 0] * (cfg.azimuth_deg[1] - cfg.azimuth_deg[0]))
        # uniform on the sphere band between the two elevations
        s0, s1 = np.sin(np.radians(self.elevation[0])), np.sin(np.radians(self.elevation[1]))
        el = np.arcsin(s0 + u[:, 1] * (s1 - s0))
        d = self.distance[0] + u[:, 2] * (self.distance[1] - self.distance[0])
        roll = np.radians((2 * u[:, 3] - 1) * cfg.roll_deg)
        dirs = (
            np.cos(el)[:, None] * (np.cos(az)[:, None] * self.e1 + np.sin(az)[:, None] * self.e2)
            + np.sin(el)[:, None] * self.up
        )
        target = centres + jitter
        w2c = look_at(target + d[:, None] * dirs, target, self.up, roll)
        K = np.broadcast_to(self.virtual_K(), (B, 3, 3)).copy()
        size = np.broadcast_to(np.array(self.image_wh, dtype=np.int64), (B, 2)).copy()
        view = np.full(B, NOVEL_VIEW, dtype=np.int64)
        use_ds = u[:, 4] < cfg.dataset_prob
        if use_ds.any() and len(self.views):
            pick = np.minimum((u[:, 5] * len(self.views)).astype(np.int64), len(self.views) - 1)
            w2c[use_ds] = self.world2cam[pick[use_ds]]
            K[use_ds] = self.K[pick[use_ds]]
            size[use_ds] = self.sizes[pick[use_ds]]
            view[use_ds] = self.views[pick[use_ds]]
        return CameraBatch(world2cam=w2c, K=K, image_size=size, view=view)
