"""Anatomy read off any MANO-schema model: fingers, joint axes, named poses, contact prior.

Everything here is derived from the model's own joints, skinning weights and normals, so it
works the same on the official MANO files, on MANO-HD and on the project's synthetic hand.

MANO joint layout (16): 0 wrist; 1-3 index; 4-6 middle; 7-9 pinky; 10-12 ring; 13-15 thumb.
"""

from __future__ import annotations

from typing import Mapping

import numpy as np

from hogsa_loader.assets.hands.mano_io import ManoModelData
from hogsa_loader.geometry.meshes import vertex_normals_np

__all__ = [
    "FINGER_JOINTS",
    "FINGERS",
    "JointAxes",
    "derive_joint_axes",
    "named_articulation",
    "NAMED_POSES",
    "derive_contact_prior",
    "unit_rows",
]

#: MANO joint ids per finger (base -> distal), in MANO's finger order.
FINGER_JOINTS: Mapping[str, tuple[int, int, int]] = {
    "index": (1, 2, 3),
    "middle": (4, 5, 6),
    "pinky": (7, 8, 9),
    "ring": (10, 11, 12),
    "thumb": (13, 14, 15),
}
#: Finger names in the ARCTIC fingertip order (joints 16..20).
FINGERS = ("thumb", "index", "middle", "ring", "pinky")

NAMED_POSES = ("flat", "relaxed", "fist", "pinch", "spread", "point", "grasp")


class JointAxes:
    """Per-joint rotation axes (rest frame, unit vectors), rows = joints 1..15.

    Attributes:
        flex: (15, 3) axis whose positive rotation curls the segment toward the palm.
        abduct: (15, 3) axis whose positive rotation moves the segment toward the thumb side.
        twist: (15, 3) the bone direction.
        palm_normal: (3,) unit normal pointing out of the palm (palmar side).
    """

    def __init__(self, flex: np.ndarray, abduct: np.ndarray, twist: np.ndarray, palm_normal: np.ndarray) -> None:
        self.flex, self.abduct, self.twist, self.palm_normal = flex, abduct, twist, palm_normal


def unit_rows(v: np.ndarray) -> np.ndarray:
    """Normalise vectors along the last axis."""
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def rest_joints(model: ManoModelData) -> np.ndarray:
    """(16, 3) rest joints regressed from the template."""
    return model.J_regressor @ model.v_template


def derive_joint_axes(model: ManoModelData) -> JointAxes:
    """Flexion / abduction / twist axes of every non-root joint from the rest skeleton.

    The palm normal is the normal of the (wrist, index MCP, pinky MCP) plane, oriented
    to the palmar side using the hand side (the plane's winding flips under mirroring).
    """
    J = rest_joints(model)
    sign = 1.0 if model.side == "right" else -1.0
    n_palm = unit_rows(sign * np.cross(J[1] - J[0], J[7] - J[0]))
    across = unit_rows(J[7] - J[1])  # index -> pinky
    flex = np.zeros((15, 3))
    abduct = np.zeros((15, 3))
    twist = np.zeros((15, 3))
    for name, joints in FINGER_JOINTS.items():
        chain = list(joints) + [None]
        for a, j in enumerate(joints):
            nxt = chain[a + 1]
            if nxt is None:  # distal joint: direction of the previous bone
                d = J[j] - J[joints[a - 1]]
            else:
                d = J[nxt] - J[j]
            d = unit_rows(d)
            if name == "thumb":
                # the thumb curls across the palm toward the little finger
                n = unit_rows(0.55 * n_palm + 0.85 * across)
            else:
                n = n_palm
            f = unit_rows(np.cross(d, n))
            # orient flex so that +angle moves the bone toward n
            if np.dot(np.cross(f, d), n) < 0:
                f = -f
            ab = unit_rows(np.cross(f, d))
            # +abduction moves toward the thumb side (away from the pinky)
            if np.dot(np.cross(ab, d), across) > 0:
                ab = -ab
            flex[j - 1], abduct[j - 1], twist[j - 1] = f, ab, d
    return JointAxes(flex, abduct, twist, n_palm)


def articulation_from_angles(axes: JointAxes, flex: np.ndarray, abduct: np.ndarray) -> np.ndarray:
    """45-D axis-angle articulation from per-joint flexion/abduction angles (radians).

    Args:
        axes: from :func:`derive_joint_axes`.
        flex: (..., 15) flexion angles of joints 1..15.
        abduct: (..., 15) abduction angles.

    Returns:
        (..., 45) articulation (rotation vectors are combined as a sum, exact for one axis).
    """
    rv = flex[..., None] * axes.flex + abduct[..., None] * axes.abduct
    return rv.reshape(rv.shape[:-2] + (45,))


def _finger_angles(curl: Mapping[str, float], spread: Mapping[str, float]) -> tuple[np.ndarray, np.ndarray]:
    flex = np.zeros(15)
    abd = np.zeros(15)
    for name, (j1, j2, j3) in FINGER_JOINTS.items():
        c = curl.get(name, 0.0)
        if name == "thumb":
            flex[[j1 - 1, j2 - 1, j3 - 1]] = [0.55 * c, 0.6 * c, 0.8 * c]
        else:
            flex[[j1 - 1, j2 - 1, j3 - 1]] = [1.35 * c, 1.55 * c, 0.95 * c]
        abd[j1 - 1] = spread.get(name, 0.0)
    return flex, abd


def named_articulation(model: ManoModelData, name: str) -> np.ndarray:
    """A recognisable hand pose as an absolute 45-D articulation (``flat_hand_mean=True``).

    Args:
        model: any MANO-schema model.
        name: one of :data:`NAMED_POSES`; ``relaxed`` is the model's ``hands_mean``.

    Returns:
        (45,) axis-angle articulation of joints 1..15.
    """
    if name == "relaxed":
        return model.hands_mean.copy()
    axes = derive_joint_axes(model)
    if name == "flat":
        curl, spread = {}, {}
    elif name == "fist":
        curl = {f: 1.0 for f in FINGERS}
        curl["thumb"] = 1.0
        spread = {"thumb": 0.35}
    elif name == "pinch":
        curl = {"thumb": 0.75, "index": 0.55, "middle": 0.35, "ring": 0.45, "pinky": 0.55}
        spread = {"thumb": 0.55, "index": -0.05}
    elif name == "spread":
        curl = {f: 0.05 for f in FINGERS}
        spread = {"index": 0.22, "middle": 0.04, "ring": -0.12, "pinky": -0.3, "thumb": -0.25}
    elif name == "point":
        curl = {"thumb": 0.7, "index": 0.0, "middle": 1.0, "ring": 1.0, "pinky": 1.0}
        spread = {"thumb": 0.4}
    elif name == "grasp":
        curl = {"thumb": 0.45, "index": 0.45, "middle": 0.5, "ring": 0.55, "pinky": 0.6}
        spread = {"thumb": 0.6, "index": 0.05, "pinky": -0.1}
    else:
        raise ValueError(f"unknown pose {name!r}; choose from {NAMED_POSES}")
    flex, abd = _finger_angles(curl, spread)
    return articulation_from_angles(axes, flex, abd)


def derive_contact_prior(model: ManoModelData, pad_cos: float = 0.35) -> dict[str, np.ndarray]:
    """Prior contact vertices: finger pads (palmar side of the two distal segments) and palm.

    A vertex belongs to a finger's pad when its dominant skinning joint is that finger's
    middle or distal joint and its rest normal faces the palmar side (thumb: faces the
    fingers). Palm: dominant joint is the wrist and the normal faces the palmar side, in the
    distal two thirds of the wrist-to-knuckle span.

    Returns:
        dict ``{thumb, index, middle, ring, pinky, palm}`` of sorted vertex id arrays.
    """
    axes = derive_joint_axes(model)
    J = rest_joints(model)
    n = vertex_normals_np(model.v_template, model.faces)
    dom = model.weights.argmax(1)
    out: dict[str, np.ndarray] = {}
    across = unit_rows(J[7] - J[1])
    for name, (_j1, j2, j3) in FINGER_JOINTS.items():
        if name == "thumb":
            facing = unit_rows(0.6 * axes.palm_normal + 0.8 * across)
        else:
            facing = axes.palm_normal
        sel = np.isin(dom, [j2, j3]) & (n @ facing > pad_cos)
        out[name] = np.flatnonzero(sel)
    knuckles = J[[1, 4, 7, 10]].mean(0)
    axis = knuckles - J[0]
    t = (model.v_template - J[0]) @ axis / (axis @ axis)
    palm = (dom == 0) & (n @ axes.palm_normal > 0.6) & (t > 0.3) & (t < 1.0)
    out["palm"] = np.flatnonzero(palm)
    return out
