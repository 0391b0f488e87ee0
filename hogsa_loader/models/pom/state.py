"""Batched bimanual grasp state (both hands' MANO parameters + object pose) and frame loading.

Parameters are stored exactly as :class:`~hogsa_loader.assets.types.SequenceData` holds
them: ARCTIC world frame, axis-angle, metres, finger pose relative to the MANO mean
(``flat_hand_mean=False``), object ``arti`` (θ, rad) / ``rot`` (axis-angle) / ``trans`` (m).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Iterable, Mapping, Sequence

import numpy as np
import torch
from torch import Tensor

from hogsa_loader.assets.arctic_processing import inner_frames
from hogsa_loader.assets.hands.mano import ManoOutput
from hogsa_loader.models.pom.hands import SIDES, HandInfo
from hogsa_loader.models.pom.objects import ObjectSet, to_canonical

__all__ = ["HandParams", "GraspState", "load_frames", "hand_forward", "contact_flags", "canonical_hands"]

HAND_KEYS = ("rot", "pose", "trans", "betas")


@dataclass
class HandParams:
    """MANO parameters of B hands (world frame).

    Attributes:
        rot: (B, 3) global orientation; pose: (B, 45) relative to the MANO mean;
        trans: (B, 3) ``transl`` (m); betas: (B, 10) shape.
    """

    rot: Tensor
    pose: Tensor
    trans: Tensor
    betas: Tensor

    def map(self, fn) -> "HandParams":
        return HandParams(*(fn(getattr(self, k)) for k in HAND_KEYS))

    def as_dict(self) -> dict[str, Tensor]:
        return {k: getattr(self, k) for k in HAND_KEYS}


@dataclass
class GraspState:
    """B bimanual grasps.

    Attributes:
        hands: ``{"right": HandParams, "left": HandParams}``.
        obj_names: B object names.
        obj_arti: (B,) θ; obj_rot: (B, 3) axis-angle; obj_trans: (B, 3) metres.
    """

    hands: dict[str, HandParams]
    obj_names: list[str]
    obj_arti: Tensor
    obj_rot: Tensor
    obj_trans: Tensor

    @property
    def batch(self) -> int:
        return len(self.obj_names)

    def map(self, fn) -> "GraspState":
        """Apply ``fn`` to every tensor (e.g. ``.detach().clone()``, ``.to(device)``)."""
        return GraspState(
            {s: h.map(fn) for s, h in self.hands.items()},
            list(self.obj_names),
            fn(self.obj_arti),
            fn(self.obj_rot),
            fn(self.obj_trans),
        )

    def select(self, idx: Tensor | Sequence[int]) -> "GraspState":
        """Sub-batch (index or bool mask)."""
        idx_t = torch.as_tensor(idx)
        if idx_t.dtype == torch.bool:
            idx_t = idx_t.nonzero().squeeze(-1)
        names = [self.obj_names[int(i)] for i in idx_t]
        out = self.map(lambda t: t[idx_t.to(t.device)])
        out.obj_names = names
        return out

    @staticmethod
    def cat(states: Iterable["GraspState"]) -> "GraspState":
        states = list(states)
        hands = {
            s: HandParams(*(torch.cat([getattr(st.hands[s], k) for st in states]) for k in HAND_KEYS)) for s in SIDES
        }
        return GraspState(
            hands,
            [n for st in states for n in st.obj_names],
            torch.cat([st.obj_arti for st in states]),
            torch.cat([st.obj_rot for st in states]),
            torch.cat([st.obj_trans for st in states]),
        )


def load_frames(
    root, seq_ids: Sequence[str], stride: int = 1, dtype: torch.dtype = torch.float32, margin: int = 0
) -> tuple[GraspState, list[tuple[str, str, int]]]:
    """Annotated frames of ARCTIC sequences as one :class:`GraspState`.

    Args:
        root: an :class:`~hogsa_loader.assets.arctic.ArcticRoot` (or anything with
            ``.sequence(sid, seq)`` returning SequenceData).
        seq_ids: ``"sid/seq"`` ids.
        stride: keep every ``stride``-th frame.
        margin: annotated frames left out at each end of a sequence (>= 0).

    Returns:
        the state (B = all kept frames) and the source ``(subject, sequence, frame index)``.
    """
    parts: dict[str, list] = {f"{s}_{k}": [] for s in SIDES for k in HAND_KEYS}
    names, arti, rot, trans, src = [], [], [], [], []
    for sid_seq in seq_ids:
        sid, seq = sid_seq.split("/")
        sd = root.sequence(sid, seq)
        keep = inner_frames(sd.num_frames, margin, stride)
        keep = keep[sd.right.valid[keep] & sd.left.valid[keep] & sd.object.valid[keep]]
        for side in SIDES:
            h = getattr(sd, side)
            parts[f"{side}_rot"].append(h.rot[keep])
            parts[f"{side}_pose"].append(h.pose[keep])
            parts[f"{side}_trans"].append(h.trans[keep])
            parts[f"{side}_betas"].append(np.repeat(np.asarray(h.betas).reshape(1, -1)[:, :10], len(keep), 0))
        names += [sd.object.name] * len(keep)
        arti.append(sd.object.arti[keep])
        rot.append(sd.object.rot[keep])
        trans.append(sd.object.trans[keep])
        src += [(sid, seq, int(i)) for i in keep]

    def t(x: list) -> Tensor:
        return torch.as_tensor(np.concatenate(x), dtype=dtype)

    hands = {s: HandParams(*(t(parts[f"{s}_{k}"]) for k in HAND_KEYS)) for s in SIDES}
    return GraspState(hands, names, t(arti), t(rot), t(trans)), src


def hand_forward(info: HandInfo, params: HandParams) -> ManoOutput:
    """MANO forward of one side: (B, V, 3) world vertices and (B, 21, 3) joints, on the
    parameters' device (:meth:`HandInfo.layer_on`)."""
    return info.layer_on(params.rot.device)(params.rot, params.pose, params.betas, params.trans)


def canonical_hands(state: GraspState, infos: Mapping[str, HandInfo]) -> dict[str, ManoOutput]:
    """Both hands posed and moved into the object canonical frame (vertices and joints)."""
    out = {}
    for side in SIDES:
        o = hand_forward(infos[side], state.hands[side])
        o.vertices = to_canonical(o.vertices, state.obj_rot, state.obj_trans)
        o.joints = to_canonical(o.joints, state.obj_rot, state.obj_trans)
        out[side] = o
    return out


def contact_flags(
    state: GraspState, infos: Mapping[str, HandInfo], objects: ObjectSet, threshold: float = 0.005
) -> dict[str, Tensor]:
    """Which hands touch the object (some vertex within ``threshold`` or inside; SDF grid).

    Returns:
        ``{side: (B,) bool}``.
    """
    with torch.no_grad():
        hands = canonical_hands(state, infos)
        return {
            s: objects.sdf(hands[s].vertices, state.obj_names, state.obj_arti).min(1).values <= threshold for s in SIDES
        }
