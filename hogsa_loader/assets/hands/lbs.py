"""Linear blend skinning, one function per step.

Notation: B batch, V vertices, J joints, S shape coefficients, P = 9 (J - 1) pose features.
All functions are differentiable and device/dtype agnostic.
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor

from hogsa_loader.geometry.rotations import axis_angle_to_matrix

__all__ = [
    "blend_shapes",
    "regress_joints",
    "pose_features",
    "kinematic_chain",
    "vertex_transforms",
    "skin_vertices",
    "Skinning",
    "skin_template",
]


def blend_shapes(coeffs: Tensor, dirs: Tensor) -> Tensor:
    """Linear blend-shape offsets.

    Args:
        coeffs: (B, S) coefficients (betas).
        dirs: (V, 3, S) blend shapes.

    Returns:
        (B, V, 3) offsets ``sum_s coeffs[b, s] * dirs[v, :, s]``.
    """
    return torch.einsum("bs,vcs->bvc", coeffs, dirs)


def regress_joints(J_regressor: Tensor, vertices: Tensor) -> Tensor:
    """Joint locations as linear combinations of vertices.

    Args:
        J_regressor: (J, V).
        vertices: (B, V, 3).

    Returns:
        (B, J, 3).
    """
    return torch.einsum("jv,bvc->bjc", J_regressor, vertices)


def pose_features(rot_mats: Tensor) -> Tensor:
    """Pose-corrective features ``R_j - I`` of every non-root joint, row-major.

    Args:
        rot_mats: (B, J, 3, 3) local joint rotations.

    Returns:
        (B, 9 (J - 1)).
    """
    eye = torch.eye(3, dtype=rot_mats.dtype, device=rot_mats.device)
    return (rot_mats[:, 1:] - eye).flatten(1)


def kinematic_chain(rot_mats: Tensor, joints: Tensor, parents: Tensor) -> tuple[Tensor, Tensor]:
    """Compose local joint rotations along the kinematic tree.

    Args:
        rot_mats: (B, J, 3, 3) local rotations.
        joints: (B, J, 3) rest joint locations.
        parents: (J,) parent indices, -1 for the root, parents[j] < j.

    Returns:
        posed_joints: (B, J, 3) joint locations after posing.
        rel_transforms: (B, J, 4, 4) transforms mapping rest-pose points to posed points,
            ``G_j`` with the rest joint removed (``G_j = A_j * T(-j_rest)``).
    """
    B, J = joints.shape[:2]
    parent_list = parents.tolist()
    rel_joints = joints.clone()
    rel_joints[:, 1:] = joints[:, 1:] - joints[:, parent_list[1:]]
    local = torch.zeros(B, J, 4, 4, dtype=joints.dtype, device=joints.device)
    local[..., :3, :3] = rot_mats
    local[..., :3, 3] = rel_joints
    local[..., 3, 3] = 1.0
    world = [local[:, 0]]
    for j in range(1, J):
        world.append(world[parent_list[j]] @ local[:, j])
    A = torch.stack(world, dim=1)
    posed_joints = A[..., :3, 3]
    # Remove the rest joint: G = A - [0 | A_R j_rest]
    shift = torch.einsum("bjrc,bjc->bjr", A[..., :3, :3], joints)
    G = A.clone()
    G[..., :3, 3] = A[..., :3, 3] - shift
    return posed_joints, G


def vertex_transforms(weights: Tensor, transforms: Tensor) -> tuple[Tensor, Tensor]:
    """Blend per-joint rigid transforms into one affine transform per vertex.

    Args:
        weights: (V, J) skinning weights.
        transforms: (B, J, 4, 4) from :func:`kinematic_chain`.

    Returns:
        rot: (B, V, 3, 3) blended linear parts; trans: (B, V, 3) blended translations.
    """
    T = torch.einsum("vj,bjrc->bvrc", weights, transforms[..., :3, :])
    return T[..., :3], T[..., 3]


def skin_vertices(vertices: Tensor, weights: Tensor, transforms: Tensor) -> Tensor:
    """Blend per-joint rigid transforms with skinning weights and apply them.

    Args:
        vertices: (B, V, 3) rest-pose (shaped + pose-corrected) vertices.
        weights: (V, J) skinning weights.
        transforms: (B, J, 4, 4) from :func:`kinematic_chain`.

    Returns:
        (B, V, 3) posed vertices.
    """
    rot, trans = vertex_transforms(weights, transforms)
    return torch.einsum("bvrc,bvc->bvr", rot, vertices) + trans


class Skinning(NamedTuple):
    """Everything :func:`skin_template` computes.

    Attributes:
        vertices: (B, V, 3) posed vertices.
        joints: (B, J, 3) posed joints.
        rot_mats: (B, J, 3, 3) local joint rotations.
        v_posed: (B, V, 3) rest-pose vertices after shape and pose blend shapes.
        vertex_rot: (B, V, 3, 3) blended linear part of each vertex's transform.
        vertex_trans: (B, V, 3) blended translation of each vertex's transform.
    """

    vertices: Tensor
    joints: Tensor
    rot_mats: Tensor
    v_posed: Tensor
    vertex_rot: Tensor
    vertex_trans: Tensor


def skin_template(
    betas: Tensor,
    pose: Tensor,
    v_template: Tensor,
    shapedirs: Tensor,
    posedirs: Tensor,
    J_regressor: Tensor,
    parents: Tensor,
    weights: Tensor,
    pose_is_rotmat: bool = False,
) -> Skinning:
    """Shape, pose-correct, and skin a template (SMPL/MANO-style LBS, smplx's ``lbs``).

    Args:
        betas: (B, S) shape coefficients.
        pose: (B, J * 3) axis-angle per joint (root first), or (B, J, 3, 3) with
            ``pose_is_rotmat=True``.
        v_template: (V, 3) rest template.
        shapedirs: (V, 3, S) shape blend shapes.
        posedirs: (V, 3, 9 (J - 1)) pose-corrective blend shapes.
        J_regressor: (J, V) joint regressor.
        parents: (J,) kinematic tree.
        weights: (V, J) skinning weights.

    Returns:
        :class:`Skinning`: posed vertices and joints, local joint rotations and the
        intermediate per-vertex quantities (vertex transforms are what free-point
        Gaussians are skinned with).
    """
    B = betas.shape[0]
    J = parents.shape[0]
    v_shaped = v_template[None] + blend_shapes(betas, shapedirs)
    rest_joints = regress_joints(J_regressor, v_shaped)
    rot_mats = pose if pose_is_rotmat else axis_angle_to_matrix(pose.reshape(B, J, 3))
    v_posed = v_shaped + torch.einsum("bp,vcp->bvc", pose_features(rot_mats), posedirs)
    joints, transforms = kinematic_chain(rot_mats, rest_joints, parents)
    rot, trans = vertex_transforms(weights, transforms)
    vertices = torch.einsum("bvrc,bvc->bvr", rot, v_posed) + trans
    return Skinning(vertices, joints, rot_mats, v_posed, rot, trans)
