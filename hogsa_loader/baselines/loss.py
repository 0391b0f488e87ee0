"""ArcticNet-SF training loss, term by term as ARCTIC defines it.

Every term is a mean squared error over the frames (or joints) that its validity mask keeps,
multiplied by ARCTIC's weight; a term whose frame mask is all zero is 0. The contact-deviation
term measures, for hand vertices within 3 mm of the object in the ground truth, how far the
predicted hand vertex lies from its predicted corresponding object vertex.

Only ARCTIC's prediction and processed-target keys are read, so the same function scores real
and synthetic samples.
"""

from __future__ import annotations

from collections.abc import Mapping

import torch
from torch import Tensor

from hogsa_loader.geometry.rotations import axis_angle_to_matrix

__all__ = [
    "ARCTIC_SF_LOSS_WEIGHTS",
    "CONTACT_THRESHOLD_M",
    "arcticnet_sf_loss",
    "contact_deviation",
    "masked_mse",
    "joint_masked_mse",
]

#: ARCTIC's weight of every ArcticNet-SF loss term.
ARCTIC_SF_LOSS_WEIGHTS: Mapping[str, float] = {
    "loss/mano/cam_t/r": 1.0,
    "loss/mano/cam_t/l": 1.0,
    "loss/object/cam_t": 1.0,
    "loss/mano/kp2d/r": 5.0,
    "loss/mano/kp3d/r": 5.0,
    "loss/mano/pose/r": 10.0,
    "loss/mano/beta/r": 0.001,
    "loss/mano/kp2d/l": 5.0,
    "loss/mano/kp3d/l": 5.0,
    "loss/mano/pose/l": 10.0,
    "loss/cd": 1.0,
    "loss/mano/transl/l": 1.0,
    "loss/mano/beta/l": 0.001,
    "loss/object/kp2d": 1.0,
    "loss/object/kp3d": 5.0,
    "loss/object/radian": 1.0,
    "loss/object/rot": 1.0,
    "loss/object/transl": 1.0,
}

#: A hand vertex is in contact when its ground-truth distance to the object is at most this (m).
CONTACT_THRESHOLD_M = 3e-3


def _frame_mask(valid: Tensor) -> Tensor:
    """Boolean frame mask from a 0/1 (float, int or bool) tensor; (B,) -> (B,)."""
    return valid.reshape(-1).long() != 0


def masked_mse(pred: Tensor, gt: Tensor, valid: Tensor) -> Tensor:
    """Mean squared error over the elements of the valid frames only.

    Args:
        pred: (B, ...) prediction.
        gt: (B, ...) target, same shape.
        valid: (B,) frame validity (0/1).

    Returns:
        () mean of ``(pred - gt)^2`` over all elements of the valid frames; 0 when no frame
        is valid (still attached to ``pred``'s graph).
    """
    sq = (pred - gt).square().reshape(pred.shape[0], -1)
    keep = _frame_mask(valid).to(pred.device)[:, None]
    total = torch.where(keep, sq, torch.zeros_like(sq)).sum()
    count = keep.sum() * sq.shape[1]
    return total / count.clamp_min(1).to(sq.dtype)


def joint_masked_mse(pred: Tensor, gt: Tensor, joints_valid: Tensor) -> Tensor:
    """Squared error with invalid joints zeroed, averaged over *all* entries (ARCTIC's rule).

    Args:
        pred: (B, J, D) predicted keypoints.
        gt: (B, J, D) target keypoints.
        joints_valid: (B, J) per-joint validity (0/1).

    Returns:
        () ``mean((pred - gt)^2 * joints_valid)`` over B*J*D entries.
    """
    sq = (pred - gt).square()
    return (sq * joints_valid.to(sq.dtype)[..., None]).mean()


def _root_relative(points: Tensor, root: int) -> Tensor:
    """Subtract one point from all; (B, N, 3) -> (B, N, 3)."""
    return points - points[:, root : root + 1]


def contact_deviation(v_obj: Tensor, v_hand: Tensor, dist: Tensor, idx: Tensor, frame_valid: Tensor) -> Tensor:
    """Per-frame contact deviation between predicted hand vertices and object vertices.

    For every hand vertex whose ground-truth distance ``dist`` to the object is at most
    3 mm, take the distance between the predicted hand vertex and the predicted object
    vertex ``idx`` (its ground-truth nearest neighbour) and average over those vertices.

    Args:
        v_obj: (B, Vo, 3) predicted object vertices (may be zero-padded).
        v_hand: (B, Vh, 3) predicted hand vertices.
        dist: (B, Vh) ground-truth hand-to-object distances (m).
        idx: (B, Vh) index of the nearest object vertex (long).
        frame_valid: (B,) frames to evaluate (0/1).

    Returns:
        (B,) mean deviation in metres; nan for an invalid frame or one without contact.
    """
    corr = torch.gather(v_obj, 1, idx.long()[..., None].expand(-1, -1, 3))
    sq = (corr - v_hand).square().sum(-1)
    contact = (dist <= CONTACT_THRESHOLD_M) & _frame_mask(frame_valid).to(dist.device)[:, None]
    positive = contact & (sq > 0)
    # sqrt with a finite gradient at exactly-coincident vertices
    norm = torch.where(positive, torch.where(positive, sq, torch.ones_like(sq)).sqrt(), torch.zeros_like(sq))
    count = contact.sum(1).to(sq.dtype)
    per_frame = norm.sum(1) / count.clamp_min(1)
    return torch.where(count > 0, per_frame, torch.full_like(per_frame, float("nan")))


def _nanmean_or_zero(x: Tensor) -> Tensor:
    """Mean of the non-nan entries; 0 when all are nan. (B,) -> ()."""
    ok = ~torch.isnan(x)
    total = torch.where(ok, x, torch.zeros_like(x)).sum()
    return total / ok.sum().clamp_min(1).to(x.dtype)


def _contact_loss(pred: Mapping[str, Tensor], gt: Mapping[str, Tensor]) -> Tensor:
    """Right plus left contact deviation, each averaged over the frames that have contact."""
    total = pred["object.v.cam"].new_zeros(())
    for side, hand_valid in (("r", "right_valid"), ("l", "left_valid")):
        valid = gt["is_valid"].reshape(-1) * gt[hand_valid].reshape(-1)
        cd = contact_deviation(
            pred["object.v.cam"], pred[f"mano.v3d.cam.{side}"], gt[f"dist.{side}o"], gt[f"idx.{side}o"], valid
        )
        total = total + _nanmean_or_zero(cd)
    return total


def _hand_terms(pred: Mapping[str, Tensor], gt: Mapping[str, Tensor], side: str) -> dict[str, Tensor]:
    """Unweighted MANO terms of one hand (``side`` is "r" or "l")."""
    valid = gt["right_valid" if side == "r" else "left_valid"]
    jv = gt[f"joints_valid_{side}"]
    gt_rot = axis_angle_to_matrix(gt[f"mano.pose.{side}"].reshape(-1, 16, 3))
    beta, j2d, j3d = f"mano.beta.{side}", f"mano.j2d.norm.{side}", f"mano.j3d.cam.{side}"
    cam, cam_init = f"mano.cam_t.wp.{side}", f"mano.cam_t.wp.init.{side}"
    return {
        f"loss/mano/pose/{side}": masked_mse(pred[f"mano.pose.{side}"], gt_rot, valid),
        f"loss/mano/beta/{side}": masked_mse(pred[beta], gt[beta], valid),
        f"loss/mano/kp2d/{side}": joint_masked_mse(pred[j2d], gt[j2d], jv),
        f"loss/mano/kp3d/{side}": joint_masked_mse(_root_relative(pred[j3d], 0), _root_relative(gt[j3d], 0), jv),
        # the refined and the initial weak-perspective camera are both supervised
        f"loss/mano/cam_t/{side}": masked_mse(pred[cam], gt[cam], valid) + masked_mse(pred[cam_init], gt[cam], valid),
    }


def _object_terms(pred: Mapping[str, Tensor], gt: Mapping[str, Tensor]) -> dict[str, Tensor]:
    """Unweighted object terms (keypoints, pose, articulation, cameras, relative translations)."""
    valid = gt["is_valid"].reshape(-1)
    right, left = gt["right_valid"].reshape(-1), gt["left_valid"].reshape(-1)
    gt_kp2d = torch.cat((gt["object.kp2d.norm.t"], gt["object.kp2d.norm.b"]), dim=1)
    kp3d = "object.kp3d.cam"
    root = pred[kp3d].shape[1] // 2  # first keypoint of the bottom part
    r_wp, l_wp, o_wp = "mano.cam_t.wp.r", "mano.cam_t.wp.l", "object.cam_t.wp"
    rad_p, rad_g = pred["object.radian"].reshape(-1), gt["object.radian"].reshape(-1)
    return {
        "loss/object/kp2d": masked_mse(pred["object.kp2d.norm"], gt_kp2d, valid),
        "loss/object/kp3d": masked_mse(_root_relative(pred[kp3d], root), _root_relative(gt[kp3d], root), valid),
        "loss/object/radian": masked_mse(rad_p, rad_g, valid),
        "loss/object/rot": masked_mse(pred["object.rot"].reshape(-1, 3), gt["object.rot"].reshape(-1, 3), valid),
        "loss/object/cam_t": masked_mse(pred[o_wp], gt[o_wp], valid)
        + masked_mse(pred["object.cam_t.wp.init"], gt[o_wp], valid),
        "loss/mano/transl/l": masked_mse(pred[l_wp] - pred[r_wp], gt[l_wp] - gt[r_wp], right * left),
        "loss/object/transl": masked_mse(pred[o_wp] - pred[r_wp], gt[o_wp] - gt[r_wp], right * valid),
    }


def arcticnet_sf_loss(pred: Mapping[str, Tensor], targets: Mapping[str, Tensor]) -> dict[str, Tensor]:
    """All ArcticNet-SF loss terms, weighted, and their sum.

    Args:
        pred: ARCTIC prediction keys: ``mano.beta.{r,l}`` (B, 10), ``mano.pose.{r,l}``
            (B, 16, 3, 3), ``mano.j3d.cam.{r,l}`` (B, 21, 3), ``mano.v3d.cam.{r,l}`` (B, Vh, 3),
            ``mano.j2d.norm.{r,l}`` (B, 21, 2), ``mano.cam_t.wp[.init].{r,l}`` (B, 3),
            ``object.kp2d.norm`` (B, 32, 2), ``object.kp3d.cam`` (B, 32, 3), ``object.rot``
            (B, 3), ``object.radian`` (B, 1), ``object.cam_t.wp[.init]`` (B, 3),
            ``object.v.cam`` (B, Vo, 3).
        targets: processed ARCTIC targets: ``mano.pose.{r,l}`` (B, 48) axis-angle,
            ``mano.beta.{r,l}``, ``mano.j3d.cam.{r,l}``, ``mano.j2d.norm.{r,l}``,
            ``object.kp2d.norm.{t,b}`` (B, 16, 2), ``object.kp3d.cam``, ``object.rot``,
            ``object.radian``, ``mano.cam_t.wp.{r,l}``, ``object.cam_t.wp``, ``is_valid``,
            ``right_valid``, ``left_valid`` (B,), ``joints_valid_{r,l}`` (B, 21),
            ``dist.{ro,lo}`` (B, Vh), ``idx.{ro,lo}`` (B, Vh) long.

    Returns:
        ``{name: () tensor}`` for every key of :data:`ARCTIC_SF_LOSS_WEIGHTS`, already
        multiplied by its weight, plus ``"loss"``: their sum.
    """
    raw: dict[str, Tensor] = {}
    raw.update(_hand_terms(pred, targets, "r"))
    raw.update(_hand_terms(pred, targets, "l"))
    raw.update(_object_terms(pred, targets))
    raw["loss/cd"] = _contact_loss(pred, targets)
    out = {key: raw[key] * weight for key, weight in ARCTIC_SF_LOSS_WEIGHTS.items()}
    out["loss"] = sum(out.values())
    return out
