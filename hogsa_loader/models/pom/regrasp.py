"""Re-grasp initialisation: put each perturbed hand back on the object with its own contacts."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping, Optional

import torch
from torch import Tensor

from hogsa_loader.assets.objects.articulated import articulation_matrix
from hogsa_loader.assets.objects.template import BOTTOM, TOP
from hogsa_loader.geometry.rotations import axis_angle_to_matrix, matrix_to_axis_angle
from hogsa_loader.models.pom.hands import SIDES, HandInfo
from hogsa_loader.models.pom.objects import ObjectSet, to_canonical
from hogsa_loader.models.pom.state import GraspState, HandParams, hand_forward

__all__ = ["SourceContacts", "source_contacts", "rigid_move_hand", "carry_with_part", "regrasp"]


@dataclass
class SourceContacts:
    """What each hand touched in its source frame.

    Attributes:
        sdf: side -> (B, V) signed distance of every hand vertex to the object (m, source
            pose and articulation).
        mask: side -> (B, V) bool, vertices within the contact distance (the contact set).
        on_top: side -> (B,) bool, most contact vertices lie on the top (articulated) part.
    """

    sdf: dict[str, Tensor]
    mask: dict[str, Tensor]
    on_top: dict[str, Tensor]

    def active(self, side: str) -> Tensor:
        """(B,) bool: the hand touched the object."""
        return self.mask[side].any(1)


def source_contacts(
    ref: GraspState, infos: Mapping[str, HandInfo], objects: ObjectSet, contact_distance: float = 0.005
) -> SourceContacts:
    """Contact sets of the source grasps ``ref`` (see :class:`SourceContacts`)."""
    sdf, mask, on_top = {}, {}, {}
    with torch.no_grad():
        for s in SIDES:
            v = to_canonical(hand_forward(infos[s], ref.hands[s]).vertices, ref.obj_rot, ref.obj_trans)
            parts = objects.part_sdf(v, ref.obj_names, ref.obj_arti)
            d = torch.minimum(parts[TOP], parts[BOTTOM])
            m = d < contact_distance
            top = (parts[TOP] <= d) & m
            sdf[s], mask[s] = d, m
            on_top[s] = top.sum(1) * 2 > m.sum(1)
    return SourceContacts(sdf, mask, on_top)


def rigid_move_hand(info: HandInfo, p: HandParams, M: Tensor, c: Tensor) -> HandParams:
    """Apply the world rigid motion ``x ↦ M x + c`` to posed hands.

    MANO poses vertices as ``R_g (x − J0) + J0 + t`` (rotation about the rest root joint
    ``J0``), so the new parameters are ``R_g' = M R_g`` and ``t' = M (J0 + t) + c − J0``.

    Args:
        info: the hand; p: (B,) parameters; M: (B, 3, 3) rotation; c: (B, 3) translation.

    Returns:
        new :class:`HandParams` (articulation and shape unchanged).
    """
    with torch.no_grad():
        wrist = hand_forward(info, p).joints[:, 0]  # J0 + t
    M = M.to(p.rot.dtype)
    rot = matrix_to_axis_angle(M @ axis_angle_to_matrix(p.rot))
    trans = torch.einsum("bij,bj->bi", M, wrist) + c.to(wrist.dtype) - (wrist - p.trans)
    return HandParams(rot, p.pose, trans, p.betas)


def _canonical_to_world(Mc: Tensor, tc: Tensor, obj_rot: Tensor, obj_trans: Tensor) -> tuple[Tensor, Tensor]:
    """A canonical-frame motion ``v ↦ Mc v + tc`` as the world motion ``x ↦ M x + c``."""
    R = axis_angle_to_matrix(obj_rot).to(Mc.dtype)
    M = R @ Mc @ R.transpose(-1, -2)
    c = torch.einsum("bij,bj->bi", R, tc) + obj_trans - torch.einsum("bij,bj->bi", M, obj_trans)
    return M, c


def carry_with_part(
    state: GraspState, source_arti: Tensor, contacts: SourceContacts, infos: Mapping[str, HandInfo]
) -> GraspState:
    """Hands holding the top part follow it from the source θ to the state's θ.

    Args:
        state: perturbed grasps (new θ in ``obj_arti``); source_arti: (B,) source θ;
        contacts: :func:`source_contacts` of the source grasps; infos: hands.

    Returns:
        a new state; hands not on the top part are unchanged.
    """
    A = articulation_matrix(state.obj_arti) @ articulation_matrix(source_arti.to(state.obj_arti)).transpose(-1, -2)
    zero = torch.zeros_like(state.obj_trans)
    M, c = _canonical_to_world(A.to(state.obj_trans.dtype), zero, state.obj_rot, state.obj_trans)
    hands = {}
    for s in SIDES:
        p = state.hands[s]
        moved = rigid_move_hand(infos[s], p, M, c)
        top = contacts.on_top[s].to(p.rot.device)[:, None]
        hands[s] = HandParams(
            torch.where(top, moved.rot, p.rot), p.pose, torch.where(top, moved.trans, p.trans), p.betas
        )
    return GraspState(hands, list(state.obj_names), state.obj_arti, state.obj_rot, state.obj_trans)


@dataclass
class _RigidFit:
    """Cost of moving one hand's canonical vertices ``base`` (B, V, 3) rigidly, for :func:`regrasp`."""

    base: Tensor
    C: Tensor  # (B, V) bool: source contacts
    target: Tensor  # (B, V) distances the contacts aim for
    objects: ObjectSet
    state: GraspState
    margin: float
    pen_weight: float
    rot_weight: float

    def __post_init__(self) -> None:
        self.wC = self.C.to(self.base.dtype)
        self.nC = self.wC.sum(1).clamp_min(1.0)

    def evaluate(self, M: Tensor, t: Tensor, grad: bool) -> tuple[Tensor, Tensor, Tensor, Optional[Tensor], Tensor]:
        """cost (B,), residuals r and weights w (B, V), SDF gradient (B, V, 3) or None, vertices."""
        state = self.state
        v = (self.base @ M.transpose(-1, -2) + t[:, None]).detach()
        g = None
        if grad:
            v.requires_grad_(True)
            d = self.objects.sdf(v, state.obj_names, state.obj_arti)
            (g,) = torch.autograd.grad(d.sum(), v)
            d, v = d.detach(), v.detach()
        else:
            with torch.no_grad():
                d = self.objects.sdf(v, state.obj_names, state.obj_arti)
        r = torch.where(self.C, d - self.target, d - self.margin)
        w = (self.wC + self.pen_weight * (d < self.margin).to(self.base.dtype)) / self.nC[:, None]
        cost = (w * r * r).sum(1) + self.rot_weight * matrix_to_axis_angle(M).pow(2).sum(-1)
        return cost, r, w, g, v

    def step(
        self, Mc: Tensor, tc: Tensor, pivot0: Tensor, lam: Tensor, max_step: float, max_rot_step: float
    ) -> tuple[Tensor, Tensor]:
        """The clamped LM step from ``(Mc, tc)``: the proposed rotation (B, 3, 3) and translation (B, 3)."""
        dt = self.base.dtype
        _, r, w, g, v = self.evaluate(Mc, tc, True)
        pivot = torch.einsum("bij,bj->bi", Mc, pivot0) + tc
        J = torch.cat([g, torch.cross(v - pivot[:, None], g, dim=-1)], -1)  # (B, V, 6)
        H = torch.einsum("bv,bvi,bvj->bij", w, J, J)
        rhs = -torch.einsum("bv,bvi,bv->bi", w, J, r)
        H[:, 3:, 3:] += self.rot_weight * torch.eye(3, dtype=dt, device=H.device)
        rhs[:, 3:] -= self.rot_weight * matrix_to_axis_angle(Mc)
        diag = torch.diagonal(H, dim1=-2, dim2=-1).clamp_min(1e-9)
        Hd = H + torch.diag_embed(lam[:, None] * diag) + 1e-12 * torch.eye(6, dtype=dt, device=H.device)
        x = torch.linalg.solve(Hd, rhs[..., None])[..., 0]
        dx, dw = x[:, :3], x[:, 3:]
        dx = dx * (max_step / dx.norm(dim=-1, keepdim=True).clamp_min(max_step))
        dw = dw * (max_rot_step / dw.norm(dim=-1, keepdim=True).clamp_min(max_rot_step))
        Rs = axis_angle_to_matrix(dw)
        return Rs @ Mc, torch.einsum("bij,bj->bi", Rs, tc - pivot) + pivot + dx


def _fit_rigid(fit: _RigidFit, act: Tensor, steps: int, max_step: float, max_rot_step: float) -> tuple[Tensor, Tensor]:
    """``steps`` LM iterations from the identity; canonical rotation (B, 3, 3) and translation (B, 3).
    A step is kept only for active samples whose cost went down (else the damping grows)."""
    base, dt = fit.base, fit.base.dtype
    B = base.shape[0]
    pivot0 = (base * fit.wC[..., None]).sum(1) / fit.nC[:, None]
    Mc = torch.eye(3, dtype=dt, device=base.device).expand(B, 3, 3).clone()
    tc = torch.zeros(B, 3, dtype=dt, device=base.device)
    lam = torch.full((B,), 1e-3, dtype=dt, device=base.device)
    cost = fit.evaluate(Mc, tc, False)[0]
    for _ in range(steps):
        M_new, t_new = fit.step(Mc, tc, pivot0, lam, max_step, max_rot_step)
        cost_new = fit.evaluate(M_new, t_new, False)[0]
        ok = (cost_new < cost) & act
        Mc = torch.where(ok[:, None, None], M_new, Mc)
        tc = torch.where(ok[:, None], t_new, tc)
        cost = torch.where(ok, cost_new, cost)
        lam = torch.where(ok, lam / 3.0, lam * 10.0).clamp(1e-6, 1e6)
    return Mc, tc


def regrasp(
    state: GraspState,
    contacts: SourceContacts,
    infos: Mapping[str, HandInfo],
    objects: ObjectSet,
    steps: int = 20,
    margin: float = 0.001,
    pen_weight: float = 10.0,
    rot_weight: float = 2e-4,
    max_step: float = 0.02,
    max_rot_step: float = 0.2,
) -> GraspState:
    """Batched Levenberg–Marquardt fit of each hand's rigid motion to its source contacts.

    Our addition before the paper's 200 Adam steps (``POMConfig.snap``). The paper's learning
    rates (translation 3e-5, rotation/pose 5e-4 over 200 steps) move a hand by at most ~6 mm
    and ~6°, so a hand the perturbation moved 6 cm off (or into) the object would stay there
    and end up a "hand next to an object", not a grasp. Two closed-form steps fix that while
    keeping the perturbation's new relative pose as far as the contacts allow:

    1. :func:`carry_with_part`: a hand whose source contacts lie on the object's top part
       follows the part when the perturbation changes the articulation angle θ (rigid
       rotation about the hinge: canonical ``A = R(θ_new) R(θ_src)^T``);
    2. :func:`regrasp`: a batched 6-DoF Levenberg–Marquardt fit of each hand's rigid motion
       (about its contact centroid) so that the hand vertices that touched the object in the
       source frame (SDF < ``contact_distance``) return to their source distances from the
       surface, no vertex penetrates, and the rotation the perturbation drew is kept unless the
       contacts need otherwise (a quadratic rotation prior ``rot_weight``).

    All quantities are in the object's canonical frame; the result is converted back to the
    hands' MANO global orientation and translation by :func:`rigid_move_hand`.

    Per hand, with canonical vertices ``v`` (moved by the current ``(Mc, tc)``), SDF ``d(v)``
    and source distances ``d_src``, the cost is (C = source contact set, |C| its size)

    ``E = (1/|C|) [Σ_{v∈C} (d(v) − max(d_src, margin))² + pen_weight Σ_{v: d(v)<margin} (d(v) − margin)²]
    + rot_weight ‖ω_tot‖²``

    where ω_tot is the axis-angle of the accumulated rotation (a 0.35 rad change costs as
    much as a 5 mm mean contact error with the default ``rot_weight``). Each step solves the
    damped normal equations of the linearised residuals in (δ, ω) (translation, rotation
    about the contact centroid), clamps the step, and keeps it only for samples whose cost
    went down (else the damping grows). Hands without source contacts are left unchanged.

    Args:
        state: grasps to move (world frame); contacts: from the source grasps.
        steps: LM iterations; margin: clearance the vertices aim for (m).
        pen_weight: weight of the penetration residuals; rot_weight: rotation prior (m²/rad²).
        max_step / max_rot_step: largest translation (m) / rotation (rad) per iteration.

    Returns:
        a new state with moved hands.
    """
    hands = dict(state.hands)
    for s in SIDES:
        p = state.hands[s]
        C = contacts.mask[s].to(p.trans.device)
        act = C.any(1)
        if not bool(act.any()):
            continue
        with torch.no_grad():
            base = to_canonical(hand_forward(infos[s], p).vertices, state.obj_rot, state.obj_trans)
        target = contacts.sdf[s].to(base).clamp_min(margin)
        fit = _RigidFit(base, C, target, objects, state, margin, pen_weight, rot_weight)
        Mc, tc = _fit_rigid(fit, act, steps, max_step, max_rot_step)
        M, c = _canonical_to_world(Mc, tc, state.obj_rot, state.obj_trans)
        moved = rigid_move_hand(infos[s], p, M, c)
        a = act[:, None]
        hands[s] = HandParams(torch.where(a, moved.rot, p.rot), p.pose, torch.where(a, moved.trans, p.trans), p.betas)
    return GraspState(hands, list(state.obj_names), state.obj_arti, state.obj_rot, state.obj_trans)
