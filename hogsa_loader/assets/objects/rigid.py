"""H2O rigid objects: ``obj_pose_rt`` parsing and rigid posing.

H2O stores one line of 17 numbers per frame in ``obj_pose_rt/XXXXXX.txt``:
``[class_id, 16 numbers]`` where the 16 numbers are a **row-major 4x4 object-to-camera**
transform (object mesh vertices in metres, object frame -> camera frame:
``p_cam = R p_obj + t``). Class 0 means "no object" (0 background, 1 book, 2 espresso,
3 lotion, 4 spray, 5 milk, 6 cocoa, 7 chips, 8 cappuccino).
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Optional, Sequence, Union

import numpy as np
from torch import Tensor

from hogsa_loader.errors import AssetError, PathLike

__all__ = ["H2O_OBJECT_NAMES", "parse_h2o_obj_pose_rt", "read_h2o_obj_pose_rt", "pose_rigid"]

#: H2O class ids (README names); index = class id, 0 = no object.
H2O_OBJECT_NAMES: tuple[str, ...] = (
    "background",
    "book",
    "espresso",
    "lotion",
    "spray",
    "milk",
    "cocoa",
    "chips",
    "cappuccino",
)

_DEFAULT_SOURCE = "<h2o obj_pose_rt>"


def _numbers(values: Union[str, Sequence[float], np.ndarray], where: PathLike) -> np.ndarray:
    """Text line or sequence -> float64 vector."""
    if isinstance(values, (bytes, str)):
        text = values.decode() if isinstance(values, bytes) else values
        try:
            return np.array([float(tok) for tok in text.split()], dtype=np.float64)
        except ValueError as exc:
            raise AssetError(where, f"obj_pose_rt line has a non-numeric token ({exc})") from exc
    try:
        return np.asarray(values, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError) as exc:
        raise AssetError(where, "obj_pose_rt values are not numbers") from exc


def parse_h2o_obj_pose_rt(
    values: Union[str, Sequence[float], np.ndarray], path: Optional[PathLike] = None, atol: float = 1e-3
) -> tuple[int, np.ndarray]:
    """Parse one H2O ``obj_pose_rt`` record.

    Args:
        values: the line as text, or its 17 numbers.
        path: file the line came from (for error messages).
        atol: tolerance for the last row ``[0, 0, 0, 1]``, for ``R Rᵀ = I`` and for
            ``det R = 1`` (text files keep few decimals).

    Returns:
        ``(class_id, T)`` with ``T`` the (4, 4) float64 object-to-camera transform. For
        class 0 ("no object") with an all-zero matrix, ``T`` is returned as zeros
        without further checks.

    Raises:
        AssetError: wrong count, non-finite values, a class id that is not an integer in
            0..8, a last row that is not ``[0, 0, 0, 1]`` or a non-orthonormal rotation.
    """
    where = _DEFAULT_SOURCE if path is None else path
    arr = _numbers(values, where)
    if arr.shape[0] != 17:
        raise AssetError(where, f"obj_pose_rt needs 17 numbers (class id + 4x4), got {arr.shape[0]}")
    if not np.isfinite(arr).all():
        raise AssetError(where, "obj_pose_rt contains NaN or infinite values")
    cls = arr[0]
    if cls != math.floor(cls) or not 0 <= cls < len(H2O_OBJECT_NAMES):
        raise AssetError(where, f"class id must be an integer in 0..{len(H2O_OBJECT_NAMES) - 1}, got {cls}")
    class_id = int(cls)
    mat = arr[1:].reshape(4, 4)
    if class_id == 0 and not mat.any():
        return 0, mat
    if np.abs(mat[3] - np.array([0.0, 0.0, 0.0, 1.0])).max() > atol:
        raise AssetError(where, f"last row of the 4x4 must be [0, 0, 0, 1], got {mat[3].tolist()}")
    rot = mat[:3, :3]
    ortho_err = np.abs(rot @ rot.T - np.eye(3)).max()
    if ortho_err > atol:
        raise AssetError(where, f"rotation block is not orthonormal (max |R Rᵀ - I| = {ortho_err:.3g})")
    det = float(np.linalg.det(rot))
    if abs(det - 1.0) > atol:
        raise AssetError(where, f"rotation block has determinant {det:.4f}, expected +1")
    return class_id, mat


def read_h2o_obj_pose_rt(path: PathLike, atol: float = 1e-3) -> tuple[int, np.ndarray]:
    """Read and parse one ``obj_pose_rt/XXXXXX.txt`` file.

    Args:
        path: the text file.
        atol: see :func:`parse_h2o_obj_pose_rt`.

    Returns:
        ``(class_id, T (4, 4))``.
    """
    path = Path(path)
    if not path.is_file():
        raise AssetError(path, "file is missing")
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise AssetError(path, f"cannot read file ({exc})") from exc
    return parse_h2o_obj_pose_rt(text, path=path, atol=atol)


def pose_rigid(points: Tensor, transform: Tensor) -> Tensor:
    """Apply rigid 4x4 transforms: ``p' = R p + t``.

    Args:
        points: (B, N, 3) points (object frame).
        transform: (B, 4, 4) transforms (e.g. H2O object-to-camera). Leading dims
            broadcast, so (N, 3) with (4, 4) also works.

    Returns:
        (B, N, 3) transformed points (dtype of ``points``).
    """
    transform = transform.to(points.dtype)
    rot = transform[..., :3, :3]
    trans = transform[..., :3, 3]
    return points @ rot.transpose(-1, -2) + trans[..., None, :]
