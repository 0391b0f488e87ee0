"""Camera placement: OpenCV world→camera matrices of cameras looking at a point.

Conventions: OpenCV cameras (``p_cam = R p + t``, x right, y down, z forward).
"""

from __future__ import annotations

import numpy as np

__all__ = ["LOOK_AT_PARALLEL", "look_at"]

#: A unit ``up`` whose part across the viewing direction is shorter than this counts as
#: parallel to it (:func:`look_at` then uses another axis).
LOOK_AT_PARALLEL = 1e-6


def look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray, roll_rad: np.ndarray | float = 0.0) -> np.ndarray:
    """OpenCV world→camera matrices of cameras at ``eye`` looking at ``target``.

    The image "up" (−y) is the projection of ``up`` (a fallback axis is used when the view
    direction is parallel to it); the camera is then rolled by ``roll_rad`` about its z axis.

    Args:
        eye: (B, 3) camera centres.
        target: (B, 3) look-at points.
        up: (3,) world up vector (unit length).
        roll_rad: (B,) or scalar roll angles.

    Returns:
        (B, 4, 4) float64.
    """
    eye = np.asarray(eye, dtype=np.float64).reshape(-1, 3)
    target = np.asarray(target, dtype=np.float64).reshape(-1, 3)
    B = eye.shape[0]
    z = target - eye
    z /= np.linalg.norm(z, axis=1, keepdims=True)
    up = np.broadcast_to(np.asarray(up, dtype=np.float64), (B, 3)).copy()
    y = -(up - np.sum(up * z, axis=1, keepdims=True) * z)
    n = np.linalg.norm(y, axis=1, keepdims=True)
    bad = n[:, 0] < LOOK_AT_PARALLEL
    if bad.any():  # looking straight along up: any perpendicular axis
        alt = np.where(np.abs(z[bad, :1]) < 0.9, np.array([[1.0, 0, 0]]), np.array([[0, 1.0, 0]]))
        y[bad] = -(alt - np.sum(alt * z[bad], axis=1, keepdims=True) * z[bad])
        n[bad] = np.linalg.norm(y[bad], axis=1, keepdims=True)
    y /= n
    x = np.cross(y, z)
    roll = np.broadcast_to(np.asarray(roll_rad, dtype=np.float64), (B,))
    c, s = np.cos(roll)[:, None], np.sin(roll)[:, None]
    x, y = c * x + s * y, -s * x + c * y
    R = np.stack([x, y, z], axis=1)
    out = np.zeros((B, 4, 4))
    out[:, :3, :3] = R
    out[:, :3, 3] = -np.einsum("bij,bj->bi", R, eye)
    out[:, 3, 3] = 1.0
    return out
