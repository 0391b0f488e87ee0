"""Physical sanity figures of generated motion (reported in ``hogsa_world.json``).

All computed from the posed geometry (hands from MANO forward of the stored parameters,
object posed from ``.object.npy``), with the analytic rounded-box SDF of
:mod:`hogsa_world.grasp` (exact for the procedural objects; the triangle mesh is
inscribed in it, so these depths are upper bounds of the depth inside the mesh).
"""

from __future__ import annotations

import numpy as np
import torch
from scipy.spatial.transform import Rotation

from hogsa_world.grasp import RoundedBox, object_sdf
from hogsa_world.grasp import rot_z_matrix as rot_z

__all__ = ["CONTACT_THRESHOLD", "hand_object_distances", "sequence_quality"]

#: ARCTIC's contact threshold: a hand vertex within 3 mm of the object is in contact.
CONTACT_THRESHOLD = 0.003


def hand_object_distances(hand_verts: np.ndarray, obj_params: np.ndarray, boxes: dict[int, RoundedBox]) -> np.ndarray:
    """Signed distance of every hand vertex to the object, per frame.

    Args:
        hand_verts: (F, V, 3) world vertices.
        obj_params: (F, 7) [θ, axis-angle, mm].
        boxes: the object's parts.

    Returns:
        (F, V) signed distances (m), negative inside.
    """
    out = np.zeros(hand_verts.shape[:2])
    R = Rotation.from_rotvec(obj_params[:, 1:4]).as_matrix()
    t = obj_params[:, 4:7] / 1000.0
    for i in range(hand_verts.shape[0]):
        p = (hand_verts[i] - t[i]) @ R[i]  # canonical frame
        out[i] = object_sdf(torch.as_tensor(p), boxes, torch.as_tensor(rot_z(-obj_params[i, 0]))).numpy()
    return out


def sequence_quality(joints: dict, verts: dict, obj_params: np.ndarray, boxes: dict[int, RoundedBox]) -> dict:
    """Penetration, contact and smoothness of one sequence.

    Args:
        joints: side -> (F, 21, 3); verts: side -> (F, V, 3) (world, metres).

    Returns:
        dict with ``max_penetration_mm``, ``contact_fraction`` (per hand: frames with a
        vertex within 3 mm of the object), ``max_joint_speed_m_per_frame`` and
        ``max_joint_accel_m_per_frame2``.
    """
    out = {
        "max_penetration_mm": 0.0,
        "contact_fraction": {},
        "max_joint_speed_m_per_frame": 0.0,
        "max_joint_accel_m_per_frame2": 0.0,
    }
    for side in ("right", "left"):
        d = hand_object_distances(np.asarray(verts[side], np.float64), obj_params, boxes)
        out["max_penetration_mm"] = max(out["max_penetration_mm"], float(max(0.0, -d.min()) * 1000))
        out["contact_fraction"][side] = round(float((d.min(1) <= CONTACT_THRESHOLD).mean()), 4)
        j = np.asarray(joints[side])
        out["max_joint_speed_m_per_frame"] = max(
            out["max_joint_speed_m_per_frame"], float(np.linalg.norm(np.diff(j, axis=0), axis=-1).max())
        )
        out["max_joint_accel_m_per_frame2"] = max(
            out["max_joint_accel_m_per_frame2"], float(np.linalg.norm(np.diff(j, 2, axis=0), axis=-1).max())
        )
    for k in ("max_penetration_mm", "max_joint_speed_m_per_frame", "max_joint_accel_m_per_frame2"):
        out[k] = round(out[k], 5)
    return out
