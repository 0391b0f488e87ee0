"""ARCTIC-like sequence motion: rest, reach, grasp, manipulate, release, rest."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from scipy.ndimage import gaussian_filter1d, maximum_filter1d
from scipy.spatial.transform import Rotation

from hogsa_loader.assets.objects.template import TOP, ObjectTemplate
from hogsa_world.grasp import (
    Grasp,
    HandKit,
    RoundedBox,
    fit_part_boxes,
    grasp_specs,
    object_sdf,
    optimise_grasp,
    placement_rotation,
    rot_z_matrix,
    styled_spec,
)
from hogsa_world.stage import TABLE_Z, WORKSPACE

__all__ = ["SequenceMotion", "min_jerk", "rot_z", "build_motion", "hands_to_params"]

SIDES = ("right", "left")
PRE_GRASP_OFFSET = 0.05  # m, pre-grasp distance from the surface along the palm normal
REST_CLEARANCE = 0.004  # m, resting hands hover this much above the table


def min_jerk(s: np.ndarray) -> np.ndarray:
    """Minimum-jerk profile of s clipped to [0, 1]."""
    s = np.clip(s, 0.0, 1.0)
    return s**3 * (10 - 15 * s + 6 * s * s)


rot_z = rot_z_matrix


def _slerp(Ra: np.ndarray, Rb: np.ndarray, s: float) -> np.ndarray:
    rel = Rotation.from_matrix(Ra.T @ Rb).as_rotvec()
    return Ra @ Rotation.from_rotvec(s * rel).as_matrix()


def _phase(t: float, t0: float, t1: float) -> float:
    return float(min_jerk(np.array((t - t0) / max(t1 - t0, 1e-9))))


@dataclass
class SequenceMotion:
    """Motion of one sequence.

    Attributes:
        object_params: (F, 7) float64 [θ, axis-angle (3), translation mm (3)].
        hands: side -> dict ``rot`` (F,3), ``pose`` (F,45), ``trans`` (F,3), ``shape`` (10,).
        attached: side -> (F,) bool, frames where the hand is rigidly attached to its part.
        grasps: side -> the grasp used.
        focus: (F, 3) object centre (world) per frame, for the head camera.
    """

    object_params: np.ndarray
    hands: dict
    attached: dict
    grasps: dict
    focus: np.ndarray


# --------------------------------------------------------------------------------------
# Timeline (fractions of the sequence)
# --------------------------------------------------------------------------------------
#: per hand: (reach start, reach end = close start, close end, open start, open end, rest);
#: object: manipulation keyframe times (rest, k1, k2, back at rest).
_TIMELINES = {
    "grab": {
        "right": (0.02, 0.22, 0.34, 0.68, 0.80, 0.98),
        "left": (0.04, 0.24, 0.36, 0.66, 0.78, 0.96),
        "object": (0.38, 0.48, 0.56, 0.65),
    },
    "use": {  # left holds the base, right opens and closes the top part
        "left": (0.01, 0.14, 0.24, 0.76, 0.87, 0.995),
        "right": (0.12, 0.29, 0.38, 0.72, 0.80, 0.97),
        "object": (0.40, 0.50, 0.57, 0.70),
    },
}


def _object_keyframes(action: str, rng: np.random.Generator) -> list[tuple[float, float, np.ndarray, np.ndarray]]:
    """Keyframes relative to the rest pose: (θ, ΔR about the object centre, Δt world)."""
    sgn = rng.choice([-1.0, 1.0])
    if action == "grab":
        lift = rng.uniform(0.09, 0.13)
        k1 = (
            0.0,
            Rotation.from_rotvec(
                [rng.uniform(-0.15, 0.15), sgn * rng.uniform(0.1, 0.2), sgn * rng.uniform(0.3, 0.45)]
            ).as_matrix(),
            np.array([rng.uniform(-0.03, 0.03), -rng.uniform(0.03, 0.07), lift]),
        )
        k2 = (
            0.0,
            Rotation.from_rotvec(
                [rng.uniform(0.15, 0.3), -sgn * rng.uniform(0.05, 0.15), -sgn * rng.uniform(0.1, 0.25)]
            ).as_matrix(),
            np.array([sgn * rng.uniform(0.02, 0.04), -rng.uniform(0.0, 0.03), lift + rng.uniform(0.0, 0.02)]),
        )
        k3 = (0.0, rot_z(rng.uniform(-0.1, 0.1)), np.array([rng.uniform(-0.02, 0.02), rng.uniform(-0.02, 0.02), 0.0]))
        return [k1, k2, k3]
    theta_max = rng.uniform(0.22, 0.4) * np.pi
    lift = rng.uniform(0.03, 0.06)
    tilt = Rotation.from_rotvec([-rng.uniform(0.1, 0.25), 0.0, sgn * rng.uniform(0.05, 0.2)]).as_matrix()
    k1 = (0.6 * theta_max, tilt, np.array([0.0, -rng.uniform(0.0, 0.03), lift]))
    k2 = (theta_max, tilt @ rot_z(sgn * rng.uniform(0.05, 0.15)), np.array([0.0, -0.02, lift]))
    k3 = (0.0, rot_z(rng.uniform(-0.08, 0.08)), np.array([rng.uniform(-0.015, 0.015), rng.uniform(-0.015, 0.015), 0.0]))
    return [k1, k2, k3]


def _object_rest(template: ObjectTemplate, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Rest pose: canonical +y up, +x away from the subject, small yaw; bottom on the table."""
    R0 = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])  # x->+y, y->+z, z->+x
    R = rot_z(rng.uniform(-0.15, 0.15)) @ R0
    v = template.verts.astype(np.float64) @ R.T
    centre = (v.min(0) + v.max(0)) / 2
    t = np.array(
        [
            WORKSPACE[0] + rng.uniform(-0.02, 0.02) - centre[0],
            WORKSPACE[1] + rng.uniform(-0.02, 0.02) - centre[1],
            TABLE_Z + 0.0005 - v[:, 2].min(),
        ]
    )
    return R, t


def _object_track(F: int, action: str, template: ObjectTemplate, rng: np.random.Generator):
    """Per-frame θ (F,), R (F,3,3), t (F,3) (metres) and the rest / final poses."""
    R_rest, t_rest = _object_rest(template, rng)
    centre_c = (template.verts.min(0) + template.verts.max(0)).astype(np.float64) / 2
    c_w = R_rest @ centre_c + t_rest
    keys = [(0.0, np.eye(3), np.zeros(3))] + _object_keyframes(action, rng)
    times = [f * (F - 1) for f in _TIMELINES[action]["object"]]
    theta = np.zeros(F)
    Rs = np.zeros((F, 3, 3))
    ts = np.zeros((F, 3))
    for i in range(F):
        k = int(np.searchsorted(times, i, side="right")) - 1
        if k < 0:
            th, dR, dt = keys[0]
        elif k >= len(times) - 1:
            th, dR, dt = keys[-1]
        else:
            s = _phase(i, times[k], times[k + 1])
            a, b = keys[k], keys[k + 1]
            th = (1 - s) * a[0] + s * b[0]
            dR = _slerp(a[1], b[1], s)
            dt = (1 - s) * a[2] + s * b[2]
        theta[i] = th
        Rs[i] = dR @ R_rest
        ts[i] = dR @ (t_rest - c_w) + c_w + dt
    return theta, Rs, ts, (R_rest, t_rest)


# --------------------------------------------------------------------------------------
# Hands
# --------------------------------------------------------------------------------------
def _part_pose(part: int, theta: float, R: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """World pose of a part frame: top = R R_z(-θ), bottom = R."""
    return (R @ rot_z(-theta), t) if part == TOP else (R, t)


def _rest_pose(kit: HandKit, betas: np.ndarray, side: str, rng: np.random.Generator, half_width: float) -> tuple:
    """Hand resting palm-down on the table beside the object (world R, wrist, articulation).

    Args:
        half_width: the object's half extent along world x at rest, from the workspace
            centre; the hand rests beyond it.
    """
    sgn = 1.0 if side == "right" else -1.0
    art = kit.mean * rng.uniform(0.7, 0.9)
    art_t = torch.as_tensor(art[None])
    b = torch.as_tensor(np.asarray(betas, np.float64)[None])
    v, j = kit.local(art_t, b)
    v, j = v[0].numpy(), j[0].numpy()
    yaw = -sgn * rng.uniform(0.15, 0.35)  # fingers turned slightly toward the midline
    fingers = np.array([np.sin(yaw), np.cos(yaw), 0.0])
    R = placement_rotation(j[4] - j[0], kit.axes.palm_normal, fingers, np.array([0.0, 0.0, -1.0]))
    tilt = Rotation.from_rotvec([0.0, sgn * rng.uniform(0.1, 0.3), 0.0]).as_matrix()  # roll onto the pinky side
    R = tilt @ R
    w = (v - j[0]) @ R.T
    xy = np.array(
        [WORKSPACE[0] + sgn * (max(0.17, half_width + 0.08) + rng.uniform(0.0, 0.04)), rng.uniform(-0.29, -0.24)]
    )
    wrist = np.array([xy[0], xy[1], TABLE_Z + REST_CLEARANCE - w[:, 2].min()])
    return R, wrist, art


def _hand_track(F: int, times: tuple, grasp: Grasp, rest0: tuple, rest1: tuple, part_pose) -> tuple:
    """World (R (F,3,3), wrist (F,3), art (F,45)) and attached mask of one hand."""
    a0, a1, c1, h1, o1, e1 = [x * (F - 1) for x in times]
    g = grasp
    pre_wrist = g.wrist - PRE_GRASP_OFFSET * g.normal
    Rs, Ws, As = np.zeros((F, 3, 3)), np.zeros((F, 3)), np.zeros((F, 45))
    attached = np.zeros(F, dtype=bool)

    def world(i: int, R_loc: np.ndarray, w_loc: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        Rp, tp = part_pose(i)
        return Rp @ R_loc, Rp @ w_loc + tp

    for i in range(F):
        if i <= a0:
            R, w, art = rest0
        elif i <= a1:  # reach: world-space arc from rest to the pre-grasp pose
            s = _phase(i, a0, a1)
            Rg, wg = world(int(np.ceil(a1)), g.rot, pre_wrist)
            R = _slerp(rest0[0], Rg, s)
            w = (1 - s) * rest0[1] + s * wg + np.array([0, 0, 0.05 * np.sin(np.pi * s)])
            art = (1 - s) * rest0[2] + s * g.open_art
        elif i <= c1:  # slide in (first 60 %), then close the fingers
            u = (i - a1) / (c1 - a1)
            sm, sf = float(min_jerk(np.array(u / 0.6))), float(min_jerk(np.array((u - 0.35) / 0.65)))
            R, w = world(i, g.rot, (1 - sm) * pre_wrist + sm * g.wrist)
            art = (1 - sf) * g.open_art + sf * g.art
            attached[i] = u >= 1.0
        elif i <= h1:  # attached
            R, w = world(i, g.rot, g.wrist)
            art = g.art
            attached[i] = True
        elif i <= o1:  # open the fingers (first 80 %), then back off
            u = (i - h1) / (o1 - h1)
            sf, sm = float(min_jerk(np.array(u / 0.8))), float(min_jerk(np.array((u - 0.3) / 0.7)))
            R, w = world(i, g.rot, (1 - sm) * g.wrist + sm * pre_wrist)
            art = (1 - sf) * g.art + sf * g.open_art
        elif i <= e1:  # return to rest
            s = _phase(i, o1, e1)
            Rg, wg = world(int(np.floor(o1)), g.rot, pre_wrist)
            R = _slerp(Rg, rest1[0], s)
            w = (1 - s) * wg + s * rest1[1] + np.array([0, 0, 0.05 * np.sin(np.pi * s)])
            art = (1 - s) * g.open_art + s * rest1[2]
        else:
            R, w, art = rest1
        Rs[i], Ws[i], As[i] = R, w, art
    return Rs, Ws, As, attached


def _depenetrate(
    kit: HandKit,
    betas: np.ndarray,
    R: np.ndarray,
    W: np.ndarray,
    A: np.ndarray,
    attached: np.ndarray,
    theta: np.ndarray,
    Ro: np.ndarray,
    to: np.ndarray,
    boxes: dict[int, RoundedBox],
    back: np.ndarray,
    tol: float = 3e-4,
) -> np.ndarray:
    """Move the wrist out of the object in frames where the hand is not attached.

    Reaching and closing/opening interpolate between collision-free poses, but fingers
    curling round an edge can cut through it on the way; such frames are backed off along
    the grasp's approach axis (the pre-grasp side, collision-free by construction) until
    the depth is below ``tol``.

    Args:
        back: (F, 3) world unit back-off directions (minus the palm normal).

    Returns:
        (F, 3) corrected wrist positions.
    """
    b = torch.as_tensor(np.repeat(np.asarray(betas, np.float64)[None], len(A), 0))
    v, j = kit.local(torch.as_tensor(A), b)
    local = (v - j[:, :1]).numpy()

    def depth(i: int, w: np.ndarray) -> float:
        p = torch.as_tensor((local[i] @ R[i].T + w - to[i]) @ Ro[i])  # canonical frame
        return -object_sdf(p, boxes, torch.as_tensor(rot_z(-theta[i]))).min().item()

    # back-off distance needed per frame
    need = np.zeros(len(W))
    for i in np.flatnonzero(~attached):
        for _ in range(30):
            d = depth(i, W[i] + back[i] * need[i])
            if d <= tol:
                break
            need[i] += d + 0.5 * tol
    if not need.any():
        return W
    # spread each correction over neighbouring frames so that it causes no velocity spike,
    # then top up frames that are still too deep
    smooth = gaussian_filter1d(maximum_filter1d(need, size=7), sigma=1.5)
    smooth[attached] = 0.0
    out = W + back * smooth[:, None]
    for i in np.flatnonzero(~attached):
        for _ in range(30):
            d = depth(i, out[i])
            if d <= tol:
                break
            out[i] = out[i] + back[i] * (d + 0.5 * tol)
    return out


def hands_to_params(kit: HandKit, betas: np.ndarray, R: np.ndarray, wrist: np.ndarray, art: np.ndarray) -> dict:
    """World hand poses -> ARCTIC ``.mano.npy`` entries (float32).

    MANO rotates about the wrist joint J0: wrist = J0(betas) + trans.
    """
    b = torch.as_tensor(np.asarray(betas, np.float64)[None])
    _, j = kit.local(torch.as_tensor(kit.mean[None]), b)
    J0 = j[0, 0].numpy()
    F = R.shape[0]
    return {
        "rot": Rotation.from_matrix(R).as_rotvec().astype(np.float32),
        "pose": (art - kit.mean[None]).astype(np.float32),
        "trans": (wrist - J0[None]).astype(np.float32),
        "shape": np.asarray(betas, np.float32).copy(),
        "fitting_err": np.zeros(F, np.float32),
    }


def build_motion(
    F: int,
    obj: str,
    action: str,
    template: ObjectTemplate,
    kits: dict[str, HandKit],
    betas: np.ndarray,
    rng: np.random.Generator,
    grasp_iters: int = 140,
    grasp_style: float = 0.0,
    style_rng: np.random.Generator | None = None,
) -> SequenceMotion:
    """Generate one sequence: rest, reach, grasp, manipulate, release, rest.

    Time is the frame index t in [0, F-1]. Every phase is interpolated with the minimum-jerk
    profile ``10s^3 - 15s^4 + 6s^5`` (zero velocity and acceleration at both ends), so the
    whole motion is smooth (no jumps) and piecewise-still at phase boundaries.

    Object: rests on the table, then during the manipulation window moves through keyframes
    (lift, rotate about its centre, shift; for ``use`` the articulation θ goes 0 -> θmax -> 0)
    and is put down again. Hands: rest palm-down on the table, reach a pre-grasp pose 5 cm off
    the surface with an open hand (an arc through the air), slide in and close the fingers,
    stay rigidly attached to their part (pose fixed in the part frame, which for the top part
    includes R_z(-θ)), then open, back off and return to a rest pose.

    Outputs are ARCTIC's raw ``raw_seqs`` parameters: object (F, 7) [θ, axis-angle, mm] and
    per hand rot (F,3) / pose (F,45, relative to the MANO mean) / trans (F,3).

    Args:
        F: number of frames.
        obj, action: sequence kind.
        template: the object (as written to ``object_vtemplates``).
        kits: ``right``/``left`` hands.
        betas: (10,) subject shape.
        rng: sequence random stream.
        grasp_iters: optimisation steps per grasp.
        grasp_style: how far the subject's grasps stray from the designs (:func:`styled_spec`).
        style_rng: the subject's grasp-style stream for this sequence (needed when
            ``grasp_style`` > 0; a separate stream, so ``rng`` draws the same either way).
    """
    theta, Rs, ts, (R_rest, t_rest) = _object_track(F, action, template, rng)
    boxes = fit_part_boxes(template)
    table_n = R_rest.T @ np.array([0.0, 0.0, 1.0])
    table_off = TABLE_Z - t_rest[2]
    specs = grasp_specs(obj, action)
    if grasp_style > 0.0:
        if style_rng is None:
            raise ValueError("grasp_style > 0 needs the subject's style_rng")
        specs = {side: styled_spec(specs[side], grasp_style, style_rng) for side in SIDES}
    hands, attached, grasps = {}, {}, {}
    rest_verts = template.verts.astype(np.float64) @ R_rest.T + t_rest
    half_width = float(np.abs(rest_verts[:, 0] - WORKSPACE[0]).max())
    for side in SIDES:
        kit = kits[side]
        sweep = (0.15 * np.pi, 0.3 * np.pi, 0.5 * np.pi) if action == "use" else ()
        g = optimise_grasp(kit, betas, specs[side], boxes, table_n, table_off, iters=grasp_iters, sweep_angles=sweep)
        rest0 = _rest_pose(kit, betas, side, rng, half_width)
        rest1 = _rest_pose(kit, betas, side, rng, half_width)

        def part_pose(i: int, part: int = g.part) -> tuple[np.ndarray, np.ndarray]:
            return _part_pose(part, theta[i], Rs[i], ts[i])

        R, w, art, att = _hand_track(F, _TIMELINES[action][side], g, rest0, rest1, part_pose)
        back = np.stack([-part_pose(i)[0] @ g.normal for i in range(F)])
        w = _depenetrate(kit, betas, R, w, art, att, theta, Rs, ts, boxes, back)
        params = hands_to_params(kit, betas, R, w, art)
        rng.uniform(0.002, 0.008, F)  # (drawn and dropped: keeps every world's random stream as it was)
        # fitting_err stays 0: these labels are exact (world-noise copies record their real error)
        hands[side], attached[side], grasps[side] = params, att, g
    obj_params = np.concatenate([theta[:, None], Rotation.from_matrix(Rs).as_rotvec(), ts * 1000.0], axis=1)
    centre_c = (template.verts.min(0) + template.verts.max(0)).astype(np.float64) / 2
    focus = np.einsum("fij,j->fi", Rs, centre_c) + ts
    return SequenceMotion(object_params=obj_params, hands=hands, attached=attached, grasps=grasps, focus=focus)
