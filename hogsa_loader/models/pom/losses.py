"""POM losses (GraspTTA's terms, made topology-free), per sample.

All inputs are in the object's canonical frame (metres). Every loss returns a (B,) tensor
(one value per sample, summed over the two hands by the caller). Scales follow GraspTTA's
code, normalised to its point counts (3000 object points, 778 hand vertices) so that they
do not depend on how many points a model or a cloud has.
"""

from __future__ import annotations

from typing import Optional, Sequence

import torch
from torch import Tensor

from hogsa_loader.geometry.meshes import vertex_normals
from hogsa_loader.models.pom.contactnet import contact_map
from hogsa_loader.models.pom.geometry import nearest
from hogsa_loader.models.pom.objects import ObjectSet

__all__ = [
    "hand_contact",
    "contact_consistency",
    "hand_centric",
    "penetration",
    "hand_in_object",
    "object_in_hand",
    "pose_prior",
    "NEAR_DISTANCE",
]

#: GraspTTA's "near" set for the hand-centric loss (2 cm).
NEAR_DISTANCE = 0.02
REF_OBJ_POINTS = 3000
REF_HAND_VERTS = 778
#: Penetration depths are measured in centimetres (1 cm = 1).
CM = 0.01


def hand_contact(obj_points: Tensor, hand_verts: Tensor, idx: Optional[Tensor] = None) -> tuple[Tensor, Tensor, Tensor]:
    """Hand-derived contact map and nearest hand vertex of every object point.

    Args:
        obj_points: (B, N, 3); hand_verts: (B, V, 3) (differentiable).
        idx: (B, N) nearest-vertex ids to reuse (None: searched now).

    Returns:
        C (B, N) GraspTTA map, dist (B, N) metres, idx (B, N) nearest vertex ids; C and
        dist carry gradients to ``hand_verts`` (the index is chosen without gradient).
    """
    if idx is None:
        _, idx = nearest(obj_points, hand_verts)
    nn = torch.gather(hand_verts, 1, idx[..., None].expand(-1, -1, 3))
    dist = ((nn - obj_points).pow(2).sum(-1) + 1e-12).sqrt()
    return contact_map(dist), dist, idx


def contact_consistency(c_hand: Tensor, c_target: Tensor) -> Tensor:
    """``L_C`` (B,): 0.3 · mean squared difference between the two maps (target detached);
    GraspTTA's ``1e-4 · Σ`` over its 3000 points."""
    return 0.3 * (c_hand - c_target.detach()).pow(2).mean(-1)


def hand_centric(
    obj_points: Tensor,
    hand_verts: Tensor,
    prior_ids: Tensor,
    dist: Tensor,
    near: float = NEAR_DISTANCE,
    idx: Optional[Tensor] = None,
) -> tuple[Tensor, Tensor]:
    """``L_H`` (B,): pull object points near the hand onto the prior contact vertices.

    ``L_H = 7500 · mean_{i∈M} min_{k∈P} ||o_i − h_k||²`` with M the object points within
    ``near`` (2 cm) of the hand and P the prior finger-pad/palm vertices (GraspTTA's
    ``2.5 · 3000 · mean``).

    Args:
        obj_points: (B, N, 3); hand_verts: (B, V, 3); prior_ids: (P,) vertex ids;
        dist: (B, N) object point -> nearest hand vertex distance (defines M).
        idx: (B, N) nearest prior-vertex positions (into ``prior_ids``) to reuse.

    Returns:
        loss (B,) (zero for samples with no object point within ``near``) and the
        nearest prior-vertex positions (B, N).
    """
    prior = hand_verts[:, prior_ids]
    if idx is None:
        _, idx = nearest(obj_points, prior)
    nn = torch.gather(prior, 1, idx[..., None].expand(-1, -1, 3))
    d2 = (nn - obj_points).pow(2).sum(-1)
    m = (dist.detach() < near).to(d2.dtype)
    return 7500.0 * (d2 * m).sum(-1) / m.sum(-1).clamp_min(1.0), idx


def hand_in_object(
    hand_verts_c: Tensor, objects: ObjectSet, names: Sequence[str], arti: Tensor
) -> tuple[Tensor, Tensor]:
    """Penetration of hand vertices into the object (SDF grid, sign by ray parity).

    Returns:
        loss (B,) ``(778/V) · Σ_v (relu(−sdf) / 1 cm)²`` and the signed distances (B, V).
    """
    sdf = objects.sdf(hand_verts_c, names, arti)
    V = hand_verts_c.shape[1]
    return (REF_HAND_VERTS / V) * (torch.relu(-sdf) / CM).pow(2).sum(-1), sdf


def object_in_hand(
    obj_points: Tensor, hand_verts: Tensor, faces: Tensor, idx: Tensor, dist: Tensor, near: float = 0.01
) -> Tensor:
    """GraspTTA's interior term: object points inside the hand by the nearest-vertex normal test.

    A point o with nearest hand vertex h (outward normal n) is inside when ``(h − o)·n > 0``;
    only points within ``near`` of the hand are considered.

    Returns:
        (B,) ``0.1 · (3000/N) · Σ_{inside} (d / 1 cm)²``.
    """
    normals = vertex_normals(hand_verts, faces).detach()
    nn = torch.gather(hand_verts, 1, idx[..., None].expand(-1, -1, 3))
    n = torch.gather(normals, 1, idx[..., None].expand(-1, -1, 3))
    inside = (((nn - obj_points) * n).sum(-1) > 0) & (dist.detach() < near)
    N = obj_points.shape[1]
    return 0.1 * (REF_OBJ_POINTS / N) * ((dist / CM).pow(2) * inside.to(dist.dtype)).sum(-1)


def penetration(
    hand_verts_c: Tensor,
    obj_points: Tensor,
    faces: Tensor,
    idx: Tensor,
    dist: Tensor,
    objects: ObjectSet,
    names: Sequence[str],
    arti: Tensor,
) -> tuple[Tensor, Tensor]:
    """``L_P`` (B,) = :func:`hand_in_object` + :func:`object_in_hand`; also returns the SDF (B, V).

    ``L_P = (778/V) Σ_v (relu(−sdf(h_v))/cm)² + 0.1 (3000/N) Σ_{i inside} (d_i/cm)²``. Depths
    are in centimetres, not GraspTTA's ``120 · Σ d²`` in metres: with that scale a few
    millimetres of penetration weigh less than the hand-centric pull, and the optimisation
    was measured to push hands ~4 mm into the objects.
    """
    l_hand, sdf = hand_in_object(hand_verts_c, objects, names, arti)
    return l_hand + object_in_hand(obj_points, hand_verts_c, faces, idx, dist), sdf


def pose_prior(
    pose: Tensor, pose_ref: Tensor, betas: Tensor, betas_ref: Tensor, w_pose: float = 1.0, w_shape: float = 1.0
) -> Tensor:
    """Mild prior (B,): mean squared articulation change (rad²) + shape change to the source."""
    return w_pose * (pose - pose_ref.detach()).pow(2).mean(-1) + w_shape * (betas - betas_ref.detach()).pow(2).mean(-1)
