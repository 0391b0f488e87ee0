"""Pose transfer: one grasp put on another subject's hands, and the grasps to show.

:func:`transfer_pose` keeps both hands' MANO articulation, the object pose and the
articulation exactly, gives the hands the target subject's own betas, puts each wrist
joint where the source wrist was (:func:`align_wrists`), then re-solves each hand's rigid
placement so that the vertices that touched the object in the source grasp touch it again
(POM's :func:`~hogsa_loader.models.pom.regrasp.regrasp`). :func:`transfer_report` gives GraspTTA's
contact / penetration figures of the source, the wrist-aligned and the transferred grasp.

Grasps to show (:class:`ViewPose`): an annotated frame (:func:`frame_pose`), a pose-bank
row (:func:`bank_pose`) or a default frame (:func:`default_pose`).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from torch import Tensor

from hogsa_loader.models.pom.bank import load_pose_bank
from hogsa_loader.models.pom.metrics import grasp_metrics
from hogsa_loader.models.pom.objects import to_canonical
from hogsa_loader.models.pom.regrasp import regrasp, source_contacts
from hogsa_loader.models.pom.state import GraspState, HandParams, hand_forward
from hogsa_loader.view.config import ViewError

__all__ = [
    "Transfer",
    "ViewPose",
    "align_wrists",
    "bank_pose",
    "default_pose",
    "frame_pose",
    "state_poses",
    "subject_betas",
    "transfer_pose",
    "transfer_report",
]

SIDES = ("right", "left")


@dataclass
class Transfer:
    """A grasp moved onto other hands.

    Attributes:
        source: the source grasps (B).
        aligned: target betas, each wrist joint where the source wrist was (rotation,
            articulation and object unchanged).
        state: ``aligned`` after the contact re-solve — what is rendered.
        contacts: :class:`~hogsa_loader.models.pom.regrasp.SourceContacts` of the source.
    """

    source: Any
    aligned: Any
    state: Any
    contacts: Any


def _betas_like(betas: Any, ref: Tensor) -> Tensor:
    b = torch.as_tensor(betas).to(ref.device, ref.dtype)
    if b.ndim == 1:
        b = b[None]
    return b.expand(ref.shape[0], -1).clone()


def align_wrists(state: Any, betas: Mapping[str, Any], infos: Mapping[str, Any]) -> Any:
    """The grasps of ``state`` with new betas, each wrist joint kept in place.

    MANO rotates about the rest wrist joint ``J0(β)``, so the posed wrist is ``J0(β) + t``;
    ``t' = t + J0(β_src) − J0(β)`` keeps it. Orientation, articulation and object are
    the source's tensors, unchanged.

    Args:
        state: :class:`~hogsa_loader.models.pom.state.GraspState` (B); betas: side → (10,) or
            (B, 10); infos: :func:`~hogsa_loader.models.pom.hands.hand_infos`.
    """
    hands = {}
    with torch.no_grad():
        for s in SIDES:
            p = state.hands[s]
            b = _betas_like(betas[s], p.betas)
            src = hand_forward(infos[s], p).joints[:, 0]
            new = hand_forward(infos[s], HandParams(p.rot, p.pose, p.trans, b)).joints[:, 0]
            hands[s] = HandParams(p.rot, p.pose, p.trans + (src - new), b)
    return GraspState(hands, list(state.obj_names), state.obj_arti, state.obj_rot, state.obj_trans)


def transfer_pose(
    source: Any,
    betas: Mapping[str, Any],
    infos: Mapping[str, Any],
    objects: Any,
    *,
    resolve: bool = True,
    steps: int = 20,
    contact_distance: float = 0.005,
) -> Transfer:
    """Put the grasps ``source`` on hands of shape ``betas``.

    1. :func:`align_wrists` (target betas, wrists kept);
    2. with ``resolve``: each hand's rigid placement re-solved so that its source
       contact vertices (within ``contact_distance`` of the object in ``source``) return to
       their source distances from the surface without penetrating
       (:func:`~hogsa_loader.models.pom.regrasp.regrasp`, ``steps`` Levenberg–Marquardt steps).
       Hands that touched nothing keep the aligned placement.

    Articulation (``pose``), object pose and articulation are the source's tensors and the
    betas are the target's, exactly; only each hand's global rotation and translation change.

    Args:
        source: :class:`~hogsa_loader.models.pom.state.GraspState` (B grasps, float32 as POM uses).
        betas: side → (10,) or (B, 10) target shape.
        infos: hands (:func:`~hogsa_loader.models.pom.hands.hand_infos` of the data root's layers).
        objects: :class:`~hogsa_loader.models.pom.objects.ObjectSet`.
    """
    contacts = source_contacts(source, infos, objects, contact_distance)
    aligned = align_wrists(source, betas, infos)
    state = regrasp(aligned, contacts, infos, objects, steps=steps) if resolve and steps > 0 else aligned
    return Transfer(source=source, aligned=aligned, state=state, contacts=contacts)


def _contact_error(state: Any, t: Transfer, infos: Mapping[str, Any], objects: Any) -> dict[str, np.ndarray]:
    """side → (B,) mean |d − d_src| (m) over the source contact vertices (NaN: no contact)."""
    out = {}
    with torch.no_grad():
        for s in SIDES:
            v = to_canonical(hand_forward(infos[s], state.hands[s]).vertices, state.obj_rot, state.obj_trans)
            d = objects.sdf(v, state.obj_names, state.obj_arti)
            m = t.contacts.mask[s].to(d.device)
            err = ((d - t.contacts.sdf[s].to(d)).abs() * m).sum(1) / m.sum(1).clamp_min(1)
            out[s] = torch.where(m.any(1), err, torch.full_like(err, float("nan"))).double().cpu().numpy()
    return out


def transfer_report(t: Transfer, infos: Mapping[str, Any], objects: Any) -> list[dict[str, Any]]:
    """Contact and penetration figures of a :class:`Transfer`, per grasp.

    For each of ``source``, ``aligned`` (betas changed, wrists kept) and ``transferred``
    (after the re-solve): GraspTTA's :func:`~hogsa_loader.models.pom.metrics.grasp_metrics`
    (penetration depth mm, intersection volume cm³, contact ratio, per-hand contact,
    acceptance with the source's touching hands required) and, per hand, the mean change
    of the source contact vertices' distance to the surface (``contact_error_mm``: 0 means
    every source contact is kept exactly).

    Returns:
        B records ``{"source": {...}, "aligned": {...}, "transferred": {...}}``.
    """
    active = {s: t.contacts.active(s) for s in SIDES}
    stages = {"source": t.source, "aligned": t.aligned, "transferred": t.state}
    recs: list[dict[str, Any]] = [{} for _ in range(t.source.batch)]
    for name, st in stages.items():
        m = grasp_metrics(st, infos, objects, active=active)
        err = _contact_error(st, t, infos, objects)
        for b, rec in enumerate(recs):
            rec[name] = {
                "penetration_depth_mm": round(float(m["penetration_depth"][b]) * 1e3, 3),
                "intersection_cm3": round(float(m["intersection"][b]) * 1e6, 3),
                "contact_ratio": round(float(m["contact_ratio"][b]), 4),
                "contact_right": bool(m["contact_right"][b]),
                "contact_left": bool(m["contact_left"][b]),
                "accept": bool(m["accept"][b]),
                "contact_error_mm": {
                    s: (None if np.isnan(err[s][b]) else round(float(err[s][b]) * 1e3, 3)) for s in SIDES
                },
            }
    return recs


@dataclass
class ViewPose:
    """One grasp to show.

    Attributes:
        label: short name (``"s01 box_use_01:20"``, ``"bank pose_bank:3"``).
        subject: the subject whose hands (betas) the grasp was made with.
        object: object name.
        state: :class:`~hogsa_loader.models.pom.state.GraspState` of batch 1 (float32).
        origin: where it comes from (JSON-able).
    """

    label: str
    subject: str
    object: str
    state: Any
    origin: dict[str, Any]


def _state(poses: Mapping[str, np.ndarray], obj: str) -> Any:
    def t(x: Any) -> Tensor:
        return torch.as_tensor(np.asarray(x, dtype=np.float32)).reshape(1, -1)

    hands = {
        s: HandParams(
            t(poses[f"{s}_rot"]),
            t(poses[f"{s}_pose"]),
            t(poses[f"{s}_trans"]),
            t(np.asarray(poses[f"{s}_betas"]).reshape(-1)[:10]),
        )
        for s in SIDES
    }
    return GraspState(hands, [obj], t(poses["obj_arti"]).reshape(1), t(poses["obj_rot"]), t(poses["obj_trans"]))


def state_poses(state: Any) -> dict[str, Tensor]:
    """POSE_KEYS tensors of a :class:`~hogsa_loader.models.pom.state.GraspState` (``obj_arti`` (B, 1))."""
    out = {f"{s}_{k}": getattr(state.hands[s], k) for s in SIDES for k in ("rot", "pose", "betas", "trans")}
    out.update(obj_arti=state.obj_arti.reshape(-1, 1), obj_rot=state.obj_rot, obj_trans=state.obj_trans)
    return out


def subject_betas(root: Any, subject: str) -> dict[str, np.ndarray]:
    """side → (10,) betas of ``subject`` (from its first sequence; ARCTIC's are per subject)."""
    seqs = root.sequences(subject)
    if not seqs:
        raise ViewError(f"subject {subject} has no sequence in {root.root if hasattr(root, 'root') else root}")
    sd = root.sequence(subject, seqs[0].split("/", 1)[1])
    return {s: np.asarray(getattr(sd, s).betas, dtype=np.float32).reshape(-1)[:10] for s in SIDES}


def frame_pose(root: Any, subject: str, sequence: str, index: int) -> ViewPose:
    """Annotated frame ``index`` (GT frame index) of ``subject``'s ``sequence``."""
    have = [s.split("/", 1)[1] for s in root.sequences(subject)]
    if sequence not in have:
        raise ViewError(f"--frame: subject {subject} has no sequence {sequence!r} (has {', '.join(have)})")
    sd = root.sequence(subject, sequence)
    n = len(sd.object.arti)
    if not 0 <= index < n:
        raise ViewError(f"--frame: {sequence} has frames 0..{n - 1}, got {index}")
    if not (sd.right.valid[index] and sd.left.valid[index] and sd.object.valid[index]):
        raise ViewError(f"--frame: frame {index} of {sequence} is not annotated for both hands and the object")
    poses = {f"{s}_{k}": getattr(getattr(sd, s), k)[index] for s in SIDES for k in ("rot", "pose", "trans")}
    poses.update({f"{s}_betas": getattr(sd, s).betas for s in SIDES})
    poses.update(obj_arti=sd.object.arti[index], obj_rot=sd.object.rot[index], obj_trans=sd.object.trans[index])
    return ViewPose(
        f"{subject} {sequence}:{index}",
        subject,
        sd.object.name,
        _state(poses, sd.object.name),
        {"kind": "frame", "subject": subject, "sequence": sequence, "frame": int(index)},
    )


def default_pose(root: Any, subject: str, obj: str) -> ViewPose:
    """The middle annotated frame of ``subject``'s first sequence of ``obj``."""
    seqs = [s.split("/", 1)[1] for s in root.sequences(subject) if s.split("/", 1)[1].split("_", 1)[0] == obj]
    if not seqs:
        raise ViewError(f"subject {subject} has no sequence of {obj}; give --pose-bank NAME:I")
    sd = root.sequence(subject, seqs[0])
    ok = np.flatnonzero(sd.right.valid & sd.left.valid & sd.object.valid)
    if not len(ok):
        raise ViewError(f"{subject}/{seqs[0]} has no frame annotated for both hands and the object")
    return frame_pose(root, subject, seqs[0], int(ok[len(ok) // 2]))


def bank_pose(bundle: Any, name: str, row: int) -> ViewPose:
    """Row ``row`` of the bundle's pose bank ``name``."""
    if name not in bundle.pose_banks:
        raise ViewError(
            f"--pose-bank: the bundle has no pose bank {name!r} (has {', '.join(sorted(bundle.pose_banks)) or 'none'})"
        )
    bank = load_pose_bank(bundle.pose_banks[name].path)
    if not 0 <= row < len(bank):
        raise ViewError(f"--pose-bank: {name} has rows 0..{len(bank) - 1}, got {row}")
    sid, seq, frame = bank.sources[row]
    st = bank.state.select([row])
    return ViewPose(
        f"bank {name}:{row}",
        sid,
        st.obj_names[0],
        st.map(lambda x: x.float()),
        {
            "kind": "pose_bank",
            "bank": name,
            "row": int(row),
            "subject": sid,
            "sequence": seq,
            "frame": int(frame),
            "accept": bool(float(bank.metrics["accept"][row]) > 0.5),
        },
    )
