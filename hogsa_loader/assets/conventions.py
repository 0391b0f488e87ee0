"""ARCTIC camera, crop and validity conventions.

Small numpy functions shared by the ARCTIC processing code, the world generator and the
sample builder, so that every producer and consumer of ARCTIC-format data uses one
definition of: projection, ego-lens distortion, the object-centred crop box, the
full-image → cropped-image map and the validity flags.

Conventions: OpenCV pinhole cameras, ``p_cam = R p_world + T``; 2D points in pixels of the
image they belong to; crop boxes as ``(cx, cy, scale)`` with side ``200 * scale`` px.
"""

from __future__ import annotations

import numpy as np

__all__ = [
    "MASK_IDS",
    "ALLO_VIEWS",
    "HAND_BONES",
    "BBOX_PIXELS_PER_SCALE",
    "CROP_ENLARGE",
    "CROPPED_SIZE",
    "EGO_IMAGE_SCALE",
    "EGO_IMAGE_SIZE",
    "EGO_VIEW",
    "EGO_DISTORTED_VIEW",
    "MIN_ALLO_SCALE",
    "allocentric_bbox",
    "cropped_bbox",
    "cropped_intrinsics",
    "distort_points",
    "undistort_map",
    "ego_bbox",
    "full_to_cropped",
    "project",
    "render_intrinsics",
    "transform",
    "validity_flags",
]

#: Part ids of ARCTIC-format segmentation masks (and of the mesh rasteriser's part buffer).
MASK_IDS = {"background": 0, "right": 1, "left": 2, "object_top": 3, "object_bottom": 4}

#: (parent, child) pairs of the 21 ARCTIC/MANO joints (ARCTIC's joint order: wrist, then
#: index, middle, pinky, ring, thumb chains of three, then the five tips 16..20).
HAND_BONES: tuple[tuple[int, int], ...] = (
    (0, 1),
    (1, 2),
    (2, 3),
    (3, 17),
    (0, 4),
    (4, 5),
    (5, 6),
    (6, 18),
    (0, 7),
    (7, 8),
    (8, 9),
    (9, 20),
    (0, 10),
    (10, 11),
    (11, 12),
    (12, 19),
    (0, 13),
    (13, 14),
    (14, 15),
    (15, 16),
)

#: View 0 is the egocentric camera, 1..8 the allocentric ones.
EGO_VIEW: int = 0
ALLO_VIEWS: tuple[int, ...] = tuple(range(1, 9))
#: Index of the distorted-ego copy in processed ``cam_coord``/``2d``, which hold 10 views
#: (the 9 cameras, then the egocentric view with its lens distortion applied).
EGO_DISTORTED_VIEW: int = 9
#: Egocentric image size assumed by the ARCTIC code, (width, height).
EGO_IMAGE_SIZE: tuple[int, int] = (2800, 2000)
#: Egocentric cropped images are the whole frame resized by this factor.
EGO_IMAGE_SCALE: float = 0.3
#: Allocentric cropped images are square crops of this side.
CROPPED_SIZE: int = 1000
#: The cropped image covers the box enlarged by this factor.
CROP_ENLARGE: float = 1.5
#: Box side in pixels per unit of ``scale``.
BBOX_PIXELS_PER_SCALE: float = 200.0
#: Allocentric boxes are at least this scale (600 px).
MIN_ALLO_SCALE: float = 3.0


def transform(world2cam: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Rigidly move points: ``p_cam = R p + T``.

    Args:
        world2cam: (..., 4, 4) extrinsics (leading dims broadcast against ``points``).
        points: (..., N, 3) points.

    Returns:
        (..., N, 3) camera-frame points.
    """
    R = world2cam[..., :3, :3]
    T = world2cam[..., :3, 3]
    return np.einsum("...ij,...nj->...ni", R, points) + T[..., None, :]


def project(points_cam: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Pinhole projection ``u = K p / z`` (no distortion).

    Args:
        points_cam: (..., N, 3) camera-frame points (z > 0 in front).
        K: (..., 3, 3) intrinsics.

    Returns:
        (..., N, 2) pixel coordinates.
    """
    p = np.einsum("...ij,...nj->...ni", K, points_cam)
    return p[..., :2] / p[..., 2:3]


def distort_points(points_cam: np.ndarray, dist8: np.ndarray) -> np.ndarray:
    """Apply ARCTIC's egocentric lens distortion in 3D (``distort_pts3d_all``).

    A point (X, Y, Z) becomes x = X/Z, y = Y/Z, r² = x² + y², radial factor
    ``(1 + k1 r² + k2 r⁴ + k3 r⁶) / (1 + k4 r² + k5 r⁴ + k6 r⁶)`` plus OpenCV tangential
    terms, scaled back by Z; projecting the result with K gives OpenCV's distorted pixel.

    Args:
        points_cam: (..., N, 3) camera-frame points.
        dist8: (..., 8) coefficients in OpenCV rational order k1, k2, p1, p2, k3, k4, k5, k6.

    Returns:
        (..., N, 3) distorted camera-frame points (same z).
    """
    k1, k2, p1, p2, k3, k4, k5, k6 = (dist8[..., i, None] for i in range(8))
    z = points_cam[..., 2]
    x = points_cam[..., 0] / z
    y = points_cam[..., 1] / z
    r2 = x * x + y * y
    radial = (1 + k1 * r2 + k2 * r2**2 + k3 * r2**3) / (1 + k4 * r2 + k5 * r2**2 + k6 * r2**3)
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return np.stack([xd * z, yd * z, z], axis=-1)


def allocentric_bbox(points2d: np.ndarray) -> np.ndarray:
    """Object-centred square box of an allocentric view (``get_bbox_from_kp2d``).

    D = max(x-extent, y-extent) of the projected object vertices; side = 1.7·D centred on
    the extent centre; scale = side / 200, clamped to ≥ 3 (600 px).

    Args:
        points2d: (..., N, 2) projections of the object vertices (full-image pixels).

    Returns:
        (..., 3) ``(cx, cy, scale)``.
    """
    lo = points2d.min(axis=-2)
    hi = points2d.max(axis=-2)
    centre = (lo + hi) / 2.0
    extent = (hi - lo).max(axis=-1)
    scale = np.maximum(1.7 * extent / BBOX_PIXELS_PER_SCALE, MIN_ALLO_SCALE)
    return np.concatenate([centre, scale[..., None]], axis=-1)


def ego_bbox(image_size: tuple[int, int] = EGO_IMAGE_SIZE) -> np.ndarray:
    """The egocentric box: the whole 2800-px-wide frame, (cx, cy, scale) = (1400, 1000, 14)."""
    w, h = image_size
    return np.array([w / 2.0, h / 2.0, max(w, h) / BBOX_PIXELS_PER_SCALE])


def full_to_cropped(points2d: np.ndarray, bbox: np.ndarray, size: int = CROPPED_SIZE) -> np.ndarray:
    """Map full-image pixels into the allocentric cropped image (``transform_kp2d``).

    The cropped image shows the square of side ``1.5 · 200 · scale`` around the box
    centre, resized to ``size × size``: ``x' = (x − (cx − 0.75·s)) · size / (1.5·s)``.

    Args:
        points2d: (..., N, 2) full-image pixels.
        bbox: (..., 3) ``(cx, cy, scale)`` of the same image.
        size: side of the cropped image (ARCTIC: 1000).

    Returns:
        (..., N, 2) cropped-image pixels.
    """
    s = bbox[..., 2] * BBOX_PIXELS_PER_SCALE
    side = CROP_ENLARGE * s
    origin = bbox[..., :2] - side[..., None] / 2.0
    return (points2d - origin[..., None, :]) * (size / side)[..., None, None]


def cropped_bbox(bbox: np.ndarray, size: int = CROPPED_SIZE) -> np.ndarray:
    """The box expressed in cropped-image pixels: centre (size/2, size/2), scale size/300."""
    out = np.empty_like(bbox, dtype=np.float64)
    out[..., 0] = size / 2.0
    out[..., 1] = size / 2.0
    out[..., 2] = size / (CROP_ENLARGE * BBOX_PIXELS_PER_SCALE)
    return out


def cropped_intrinsics(K: np.ndarray, bbox: np.ndarray, size: int = CROPPED_SIZE) -> np.ndarray:
    """Intrinsics of the cropped image, so it can be rendered directly.

    The crop is the affine map of :func:`full_to_cropped`, so ``K' = A K`` with A =
    scale then shift (label coordinates; give a renderer :func:`render_intrinsics` of it).

    Args:
        K: (..., 3, 3) full-image intrinsics.
        bbox: (..., 3) full-image box.
        size: cropped image side.

    Returns:
        (..., 3, 3) intrinsics whose projection equals ``full_to_cropped(project(p, K))``.
    """
    s = bbox[..., 2] * BBOX_PIXELS_PER_SCALE
    side = CROP_ENLARGE * s
    k = size / side
    origin = bbox[..., :2] - side[..., None] / 2.0
    A = np.zeros(bbox.shape[:-1] + (3, 3))
    A[..., 0, 0] = k
    A[..., 1, 1] = k
    A[..., 0, 2] = -origin[..., 0] * k
    A[..., 1, 2] = -origin[..., 1] * k
    A[..., 2, 2] = 1.0
    return A @ K


def render_intrinsics(K: np.ndarray) -> np.ndarray:
    """Intrinsics to give a renderer so its pixels line up with ARCTIC/OpenCV labels.

    ARCTIC's labels use OpenCV's convention: pixel ``(i, j)`` is centred on coordinate
    ``(i, j)`` (cv2 crops and warps work in it too). Our renderers (mesh rasteriser,
    Gaussian rasterisers, like gsplat) sample pixel ``(i, j)`` at ``(i + 0.5, j + 0.5)``.
    Shifting the principal point by +0.5 px makes pixel ``(i, j)`` show the ray of label
    coordinate ``(i, j)``.

    Args:
        K: (..., 3, 3) label (OpenCV-convention) intrinsics.

    Returns:
        (..., 3, 3) intrinsics for rendering.
    """
    out = np.array(K, dtype=np.float64, copy=True)
    out[..., 0, 2] += 0.5 * out[..., 2, 2]
    out[..., 1, 2] += 0.5 * out[..., 2, 2]
    return out


def _in_region(points2d: np.ndarray, region: np.ndarray) -> np.ndarray:
    """(..., N) bool: inside ``region`` (..., 4) = [x0, x1, y0, y1] (inclusive)."""
    x, y = points2d[..., 0], points2d[..., 1]
    r = region[..., None, :]
    return (x >= r[..., 0]) & (x <= r[..., 1]) & (y >= r[..., 2]) & (y <= r[..., 3])


def validity_flags(
    obj_points2d: np.ndarray,
    joints2d_r: np.ndarray,
    joints2d_l: np.ndarray,
    bbox: np.ndarray,
    image_size: np.ndarray,
    min_joints: int = 3,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """ARCTIC validity flags of one view (``forward_valid``).

    The region is the crop box clipped to the image: x ∈ [max(cx − side/2, 1),
    min(cx + side/2, W)], same for y. ``is_valid`` = the 2D centroid of the object vertices
    is inside; a hand is valid iff its wrist (joint 0) and at least ``min_joints`` of its
    21 joints are inside. For the egocentric view pass the *distorted* 2D points and the
    ego box (whole image).

    Args:
        obj_points2d: (..., V, 2) projected object vertices.
        joints2d_r, joints2d_l: (..., 21, 2) projected hand joints.
        bbox: (..., 3) crop box.
        image_size: (..., 2) or (2,) image (width, height).

    Returns:
        ``(is_valid, right_valid, left_valid)``, each (...) float32 in {0, 1}.
    """
    image_size = np.asarray(image_size, dtype=np.float64)
    half = bbox[..., 2] * BBOX_PIXELS_PER_SCALE / 2.0
    region = np.stack(
        [
            np.maximum(bbox[..., 0] - half, 1.0),
            np.minimum(bbox[..., 0] + half, image_size[..., 0]),
            np.maximum(bbox[..., 1] - half, 1.0),
            np.minimum(bbox[..., 1] + half, image_size[..., 1]),
        ],
        axis=-1,
    )
    centroid = obj_points2d.mean(axis=-2, keepdims=True)
    is_valid = _in_region(centroid, region)[..., 0]

    def hand(j2d: np.ndarray) -> np.ndarray:
        inside = _in_region(j2d, region)
        return inside[..., 0] & (inside.sum(axis=-1) >= min_joints)

    f32 = np.float32
    return is_valid.astype(f32), hand(joints2d_r).astype(f32), hand(joints2d_l).astype(f32)


def undistort_map(
    K: np.ndarray, dist8: np.ndarray, width: int, height: int, iters: int = 30
) -> tuple[np.ndarray, np.ndarray]:
    """``cv2.remap`` maps that turn an undistorted rendering into the distorted image.

    For every distorted output pixel (OpenCV/ARCTIC convention: pixel (i, j) centred on
    label coordinate (j, i)) the undistorted normalised point is found by fixed-point
    inversion of the distortion model of
    :func:`distort_points`; the maps hold its label
    coordinate in the undistorted image, which is its pixel index there when that image
    was rendered with :func:`render_intrinsics`.

    Args:
        K: (3, 3) intrinsics of the (width, height) image.
        dist8: (8,) distortion.

    Returns:
        map_x, map_y: (height, width) float32.
    """
    k1, k2, p1, p2, k3, k4, k5, k6 = dist8
    jj, ii = np.meshgrid(np.arange(width, dtype=np.float64), np.arange(height, dtype=np.float64))
    xd = (jj - K[0, 2]) / K[0, 0]
    yd = (ii - K[1, 2]) / K[1, 1]
    x, y = xd.copy(), yd.copy()
    for _ in range(iters):
        r2 = x * x + y * y
        radial = (1 + k1 * r2 + k2 * r2**2 + k3 * r2**3) / (1 + k4 * r2 + k5 * r2**2 + k6 * r2**3)
        dx = 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
        dy = p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
        x = (xd - dx) / radial
        y = (yd - dy) / radial
    check = distort_points(np.stack([x, y, np.ones_like(x)], -1).reshape(-1, 3), np.asarray(dist8, dtype=np.float64))
    err = np.abs(check[:, 0] - xd.reshape(-1)).max() + np.abs(check[:, 1] - yd.reshape(-1)).max()
    if not err < 1e-7:
        raise RuntimeError(f"distortion inversion did not converge (residual {err:.2e})")
    map_x = x * K[0, 0] + K[0, 2]
    map_y = y * K[1, 1] + K[1, 2]
    return map_x.astype(np.float32), map_y.astype(np.float32)
