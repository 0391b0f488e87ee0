"""H2O per-frame text formats: strict parsers, readers and line formatters.

Every H2O label file is one line of space-separated numbers (counts in
:data:`H2O_COUNTS`; each parser's docstring gives its layout). Tokens must be plain
decimal numbers (``1``, ``-0.5``, ``1e-3``); anything else (``nan``, ``inf``, ``1_000``,
``0x1f``, commas) raises :class:`~hogsa_loader.errors.AssetError` naming the file, as do
wrong counts, non-finite values, flags other than 0/1, class ids out of range and 4x4
matrices whose last row is not ``[0, 0, 0, 1]`` or whose rotation block is not a rotation.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Optional, Sequence, Union

import numpy as np

from hogsa_loader.assets.objects.rigid import H2O_OBJECT_NAMES, parse_h2o_obj_pose_rt
from hogsa_loader.errors import AssetError, PathLike

__all__ = [
    "H2O_ACTION_MAX",
    "H2O_CAM_INTRINSICS_FILE",
    "H2O_COUNTS",
    "H2O_CROP_SIZE",
    "H2O_EGO_CAMERA",
    "H2O_IMAGE_SIZE",
    "H2O_MANO_HAND_SLICES",
    "H2O_SIDES",
    "H2O_VERB_MAX",
    "H2OHandJoints",
    "H2OIntrinsics",
    "H2OManoHand",
    "H2OManoLabels",
    "format_h2o_line",
    "intrinsics_matrix",
    "parse_h2o_action_label",
    "parse_h2o_cam_intrinsics",
    "parse_h2o_cam_pose",
    "parse_h2o_hand_pose",
    "parse_h2o_hand_pose_mano",
    "parse_h2o_numbers",
    "parse_h2o_obj_pose",
    "parse_h2o_obj_pose_rt_strict",
    "parse_h2o_verb_label",
    "read_h2o_text",
]

#: Numbers per line of each per-frame label folder (and of ``cam_intrinsics.txt``).
H2O_COUNTS: dict[str, int] = {
    "cam_pose": 16,
    "hand_pose_mano": 124,
    "obj_pose_rt": 17,
    "hand_pose": 128,
    "obj_pose": 64,
    "action_label": 1,
    "verb_label": 1,
    "cam_intrinsics": 6,
}

#: Hands in file order: the left hand comes first in every H2O hand file.
H2O_SIDES: tuple[str, str] = ("left", "right")

#: Slices of one 124-number ``hand_pose_mano`` line (62 per hand, not the README's 59).
H2O_MANO_HAND_SLICES: dict[str, dict[str, slice]] = {
    side: {
        "valid": slice(o, o + 1),
        "trans": slice(o + 1, o + 4),
        "pose": slice(o + 4, o + 52),
        "betas": slice(o + 52, o + 62),
    }
    for side, o in (("left", 0), ("right", 62))
}

#: Index of the head-mounted camera (``cam4``); ``cam0``..``cam3`` are static.
H2O_EGO_CAMERA: int = 4
#: Side (px) of the square crops this library makes of H2O's full frames: the default
#: resolution of HOGS runs on H2O, and the crop side an H2O bundle records.
H2O_CROP_SIZE = 256
#: Full-resolution ``rgb/`` image size, (width, height).
H2O_IMAGE_SIZE: tuple[int, int] = (1280, 720)
#: Name of the per-camera intrinsics file.
H2O_CAM_INTRINSICS_FILE = "cam_intrinsics.txt"
#: Largest action / verb label (README tables).
H2O_ACTION_MAX: int = 36
H2O_VERB_MAX: int = 11

# A plain decimal number: optional sign, digits with optional fraction (or a leading-dot
# fraction), optional exponent. Rejects nan/inf, underscores, hex, commas.
_NUMBER = re.compile(r"[+-]?(?:\d+(?:\.\d*)?|\.\d+)(?:[eE][+-]?\d+)?")
_NON_FINITE = re.compile(r"[+-]?(?:nan|inf|infinity)", re.IGNORECASE)
_NumbersLike = Union[str, bytes, Sequence[float], np.ndarray]


# ----------------------------------------------------------------------------------------
# Generic number lines
# ----------------------------------------------------------------------------------------
def parse_h2o_numbers(values: _NumbersLike, count: int, what: str, path: Optional[PathLike] = None) -> np.ndarray:
    """Parse one H2O line into exactly ``count`` finite float64 numbers.

    Args:
        values: the file text (whitespace-separated tokens; a trailing newline is fine),
            or the numbers themselves.
        count: required number of values.
        what: format name used in messages (``"cam_pose"``...).
        path: file the line came from (for messages).

    Returns:
        (count,) float64 array.

    Raises:
        AssetError: non-numeric token, wrong count, NaN or infinite value.
    """
    where = f"<h2o {what}>" if path is None else path
    if isinstance(values, (bytes, bytearray)):
        try:
            values = bytes(values).decode("utf-8")
        except UnicodeDecodeError as exc:
            raise AssetError(where, f"{what} file is not UTF-8 text ({exc.reason})") from None
    if isinstance(values, str):
        tokens = values.split()
        for i, tok in enumerate(tokens):
            if _NUMBER.fullmatch(tok) is None:
                if _NON_FINITE.fullmatch(tok):
                    raise AssetError(where, f"{what} value {i} is {tok!r}: NaN or infinite values are not allowed")
                shown = tok if len(tok) <= 40 else tok[:37] + "..."
                raise AssetError(where, f"{what} token {i} ({shown!r}) is not a plain decimal number")
        arr = np.array([float(t) for t in tokens], dtype=np.float64)
    else:
        try:
            arr = np.asarray(values, dtype=np.float64).reshape(-1)
        except (TypeError, ValueError, OverflowError) as exc:
            raise AssetError(where, f"{what} values are not numbers ({exc})") from None
    if arr.shape[0] != count:
        raise AssetError(where, f"{what} needs exactly {count} numbers, got {arr.shape[0]}")
    if not np.isfinite(arr).all():
        bad = int(np.flatnonzero(~np.isfinite(arr))[0])
        raise AssetError(where, f"{what} value {bad} is {arr[bad]}: NaN or infinite values are not allowed")
    return arr


def read_h2o_text(path: PathLike) -> str:
    """Read a label file as UTF-8 text.

    Raises:
        AssetError: the file is missing, unreadable or not UTF-8.
    """
    p = Path(path)
    if not p.is_file():
        raise AssetError(p, "file is missing")
    try:
        return p.read_bytes().decode("utf-8")
    except OSError as exc:
        raise AssetError(p, f"cannot read file ({exc})") from None
    except UnicodeDecodeError as exc:
        raise AssetError(p, f"file is not UTF-8 text ({exc.reason})") from None


def _flag(x: float, what: str, where: PathLike) -> bool:
    if x not in (0.0, 1.0):
        raise AssetError(where, f"{what} must be 0 or 1, got {x}")
    return x == 1.0


def _class_id(x: float, where: PathLike, what: str) -> int:
    if x != math.floor(x) or not 0 <= x < len(H2O_OBJECT_NAMES):
        raise AssetError(where, f"{what} class id must be an integer in 0..{len(H2O_OBJECT_NAMES) - 1}, got {x}")
    return int(x)


def _check_rigid(mat: np.ndarray, what: str, where: PathLike, atol: float) -> None:
    """Last row [0, 0, 0, 1] and a proper rotation block (within ``atol``)."""
    with np.errstate(all="ignore"):
        if np.abs(mat[3] - np.array([0.0, 0.0, 0.0, 1.0])).max() > atol:
            raise AssetError(where, f"{what}: last row of the 4x4 must be [0, 0, 0, 1], got {mat[3].tolist()}")
        rot = mat[:3, :3]
        err = float(np.abs(rot @ rot.T - np.eye(3)).max())
        if not err <= atol:
            raise AssetError(where, f"{what}: rotation block is not orthonormal (max |R Rᵀ - I| = {err:.3g})")
        det = float(np.linalg.det(rot))
        if not abs(det - 1.0) <= atol:
            raise AssetError(where, f"{what}: rotation block has determinant {det:.4f}, expected +1")


# ----------------------------------------------------------------------------------------
# Individual formats
# ----------------------------------------------------------------------------------------
def parse_h2o_cam_pose(values: _NumbersLike, path: Optional[PathLike] = None, atol: float = 1e-3) -> np.ndarray:
    """Parse ``cam_pose/XXXXXX.txt``: a row-major 4x4 camera-to-world transform.

    Args:
        values: file text or 16 numbers.
        path: source file (for messages).
        atol: tolerance of the rigid-transform checks (text files keep few decimals).

    Returns:
        (4, 4) float64 camera-to-world matrix (``p_world = R p_cam + t``).
    """
    where = "<h2o cam_pose>" if path is None else path
    mat = parse_h2o_numbers(values, 16, "cam_pose", where).reshape(4, 4)
    _check_rigid(mat, "cam_pose", where, atol)
    return mat


def parse_h2o_obj_pose_rt_strict(
    values: _NumbersLike, path: Optional[PathLike] = None, atol: float = 1e-3
) -> tuple[int, np.ndarray]:
    """Parse ``obj_pose_rt/XXXXXX.txt``: class id + row-major 4x4 object-to-camera transform.

    Tokenizes like every other H2O parser here, then delegates the class-id and rigidity
    checks to :func:`hogsa_loader.assets.objects.rigid.parse_h2o_obj_pose_rt`.

    Returns:
        ``(class_id, T)``: class id 0..8 (0 = no object) and the (4, 4) float64
        object-to-camera transform (zeros when class 0 comes with a zero matrix).
    """
    where = "<h2o obj_pose_rt>" if path is None else path
    arr = parse_h2o_numbers(values, 17, "obj_pose_rt", where)
    with np.errstate(all="ignore"):
        class_id, mat = parse_h2o_obj_pose_rt(arr, path=where, atol=atol)
    if mat.any():
        # Defensive: repeat the rigidity checks with NaN-safe comparisons (``not err <= atol``),
        # so overflowing entries can never slip through as NaN.
        _check_rigid(mat, "obj_pose_rt", where, atol)
    return class_id, mat


@dataclass(frozen=True)
class H2OIntrinsics:
    """Contents of ``cam_intrinsics.txt``.

    Attributes:
        fx, fy, cx, cy: pinhole parameters (pixels).
        width, height: image size (pixels).
    """

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int

    @property
    def K(self) -> np.ndarray:
        """(3, 3) float64 intrinsic matrix."""
        return intrinsics_matrix(self.fx, self.fy, self.cx, self.cy)

    def to_array(self) -> np.ndarray:
        """(6,) ``fx fy cx cy width height`` (the file order)."""
        return np.array([self.fx, self.fy, self.cx, self.cy, self.width, self.height], dtype=np.float64)


def intrinsics_matrix(fx: float, fy: float, cx: float, cy: float) -> np.ndarray:
    """(3, 3) float64 pinhole matrix ``[[fx, 0, cx], [0, fy, cy], [0, 0, 1]]``."""
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]], dtype=np.float64)


def parse_h2o_cam_intrinsics(values: _NumbersLike, path: Optional[PathLike] = None) -> H2OIntrinsics:
    """Parse ``cam_intrinsics.txt`` (``fx fy cx cy width height``).

    Raises:
        AssetError: wrong count, non-finite values, fx/fy not positive, width/height not
            positive integers.
    """
    where = "<h2o cam_intrinsics>" if path is None else path
    fx, fy, cx, cy, w, h = parse_h2o_numbers(values, 6, "cam_intrinsics", where).tolist()
    if not (fx > 0 and fy > 0):
        raise AssetError(where, f"cam_intrinsics focal lengths must be positive, got fx={fx}, fy={fy}")
    for name, v in (("width", w), ("height", h)):
        if v != math.floor(v) or not 0 < v < 1e6:
            raise AssetError(where, f"cam_intrinsics {name} must be a positive integer, got {v}")
    return H2OIntrinsics(fx, fy, cx, cy, int(w), int(h))


@dataclass
class H2OManoHand:
    """MANO labels of one hand over F frames, exactly as stored (``flat_hand_mean=True``,
    frame of the camera folder they were read from).

    Attributes:
        valid: (F,) bool.
        trans: (F, 3) translation (m).
        pose: (F, 48) axis-angle, 3 global + 45 finger values relative to the flat hand.
        betas: (F, 10) per-frame shape.
    """

    valid: np.ndarray
    trans: np.ndarray
    pose: np.ndarray
    betas: np.ndarray

    @property
    def num_frames(self) -> int:
        return int(self.valid.shape[0])


@dataclass
class H2OManoLabels:
    """Both hands of ``hand_pose_mano`` over F frames.

    Attributes:
        left, right: :class:`H2OManoHand` of each side.
    """

    left: H2OManoHand
    right: H2OManoHand

    def hand(self, side: str) -> H2OManoHand:
        """The hand of ``side`` (``"left"`` / ``"right"``)."""
        if side not in H2O_SIDES:
            raise KeyError(f"side must be 'left' or 'right', got {side!r}")
        return self.left if side == "left" else self.right

    def to_array(self) -> np.ndarray:
        """(F, 124) file layout (left first, 62 numbers per hand)."""
        F = self.left.num_frames
        out = np.zeros((F, 124), dtype=np.float64)
        for side in H2O_SIDES:
            h, sl = self.hand(side), H2O_MANO_HAND_SLICES[side]
            out[:, sl["valid"]] = np.asarray(h.valid, dtype=np.float64).reshape(F, 1)
            out[:, sl["trans"]] = h.trans
            out[:, sl["pose"]] = h.pose
            out[:, sl["betas"]] = h.betas
        return out

    @classmethod
    def from_array(cls, arr: np.ndarray, path: Optional[PathLike] = None) -> "H2OManoLabels":
        """Split validated (F, 124) lines (see :func:`parse_h2o_hand_pose_mano`)."""
        arr = np.asarray(arr, dtype=np.float64).reshape(-1, 124)
        hands = {}
        for side in H2O_SIDES:
            sl = H2O_MANO_HAND_SLICES[side]
            v = arr[:, sl["valid"]][:, 0]
            bad = ~np.isin(v, (0.0, 1.0))
            if bad.any():
                where = "<h2o hand_pose_mano>" if path is None else path
                raise AssetError(where, f"{side} valid flag must be 0 or 1, got {v[bad][0]}")
            hands[side] = H2OManoHand(
                valid=v == 1.0,
                trans=arr[:, sl["trans"]].copy(),
                pose=arr[:, sl["pose"]].copy(),
                betas=arr[:, sl["betas"]].copy(),
            )
        return cls(left=hands["left"], right=hands["right"])


def parse_h2o_hand_pose_mano(values: _NumbersLike, path: Optional[PathLike] = None) -> H2OManoLabels:
    """Parse ``hand_pose_mano/XXXXXX.txt`` (124 numbers, left hand first, 62 per hand).

    Each hand is ``[valid, trans 3, pose 48, betas 10]`` with ``flat_hand_mean=True``, in
    the frame of the camera folder. The README's "first 59 numbers belong to the left hand"
    is wrong (1 + 3 + 48 + 10 = 62); every loader slices 62 per hand, and so does this one
    (:data:`H2O_MANO_HAND_SLICES`).

    Returns:
        :class:`H2OManoLabels` with F = 1.
    """
    where = "<h2o hand_pose_mano>" if path is None else path
    arr = parse_h2o_numbers(values, 124, "hand_pose_mano", where)
    return H2OManoLabels.from_array(arr[None], path=where)


@dataclass
class H2OHandJoints:
    """Contents of ``hand_pose/XXXXXX.txt``.

    Attributes:
        valid: (2,) bool, left then right.
        joints: (2, 21, 3) camera-frame joints (m), left then right; wrist first, then
            four joints per finger (OpenPose-like).
    """

    valid: np.ndarray
    joints: np.ndarray


def parse_h2o_hand_pose(values: _NumbersLike, path: Optional[PathLike] = None) -> H2OHandJoints:
    """Parse ``hand_pose/XXXXXX.txt``: ``[valid_L, 21x3 L, valid_R, 21x3 R]`` (128 numbers)."""
    where = "<h2o hand_pose>" if path is None else path
    arr = parse_h2o_numbers(values, 128, "hand_pose", where).reshape(2, 64)
    valid = np.array([_flag(arr[i, 0], f"{side} valid flag", where) for i, side in enumerate(H2O_SIDES)])
    return H2OHandJoints(valid=valid, joints=arr[:, 1:].reshape(2, 21, 3).copy())


def parse_h2o_obj_pose(values: _NumbersLike, path: Optional[PathLike] = None) -> tuple[int, np.ndarray]:
    """Parse ``obj_pose/XXXXXX.txt``: class id + 21 box points (64 numbers).

    Returns:
        ``(class_id, points)`` with points (21, 3): centre, 8 corners, 12 edge midpoints,
        camera frame (m).
    """
    where = "<h2o obj_pose>" if path is None else path
    arr = parse_h2o_numbers(values, 64, "obj_pose", where)
    return _class_id(arr[0], where, "obj_pose"), arr[1:].reshape(21, 3).copy()


def _parse_label(values: _NumbersLike, path: Optional[PathLike], what: str, hi: int) -> int:
    where = f"<h2o {what}>" if path is None else path
    x = float(parse_h2o_numbers(values, 1, what, where)[0])
    if x != math.floor(x) or not 0 <= x <= hi:
        raise AssetError(where, f"{what} must be an integer in 0..{hi}, got {x}")
    return int(x)


def parse_h2o_action_label(values: _NumbersLike, path: Optional[PathLike] = None) -> int:
    """Parse ``action_label/XXXXXX.txt`` (cam4 only): one integer 0..36, 0 = background."""
    return _parse_label(values, path, "action_label", H2O_ACTION_MAX)


def parse_h2o_verb_label(values: _NumbersLike, path: Optional[PathLike] = None) -> int:
    """Parse ``verb_label/XXXXXX.txt``: one integer 0..11, 0 = background."""
    return _parse_label(values, path, "verb_label", H2O_VERB_MAX)


# ----------------------------------------------------------------------------------------
# Writing
# ----------------------------------------------------------------------------------------
def format_h2o_line(values: Union[Sequence[float], np.ndarray], precision: Optional[int] = None) -> str:
    """One H2O line (no newline).

    Args:
        values: the numbers.
        precision: decimals of ``%.Nf`` formatting (the real files keep a few); ``None``
            writes the shortest exact ``repr`` of each float, so reading gives the same
            float64 values back. Integral values are written as integers either way when
            ``precision`` is None (``1`` rather than ``1.0``).

    Raises:
        ValueError: a value is NaN or infinite.
    """
    arr = np.asarray(values, dtype=np.float64).reshape(-1)
    if not np.isfinite(arr).all():
        raise ValueError("H2O lines cannot hold NaN or infinite values")
    if precision is not None:
        return " ".join(f"{x:.{int(precision)}f}" for x in arr.tolist())
    return " ".join(str(int(x)) if x.is_integer() and abs(x) < 2**53 else repr(x) for x in arr.tolist())
