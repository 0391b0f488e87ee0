"""The paper's perturbation of an annotated bimanual frame (as described by the HOGSA paper and its supplement)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Mapping, Optional

import torch
from torch import Tensor

from hogsa_loader.geometry.rotations import axis_angle_to_matrix, matrix_to_axis_angle
from hogsa_loader.models.pom.hands import SIDES, HandInfo
from hogsa_loader.models.pom.objects import ObjectSet, to_world
from hogsa_loader.models.pom.state import GraspState, HandParams, hand_forward

__all__ = [
    "PerturbConfig",
    "KEEP_ARTICULATION",
    "FingerNoise",
    "PerturbRecord",
    "perturb",
    "euler_xyz_matrix",
    "random_directions",
]


@dataclass(frozen=True)
class PerturbConfig:
    """Ranges of :func:`perturb` (the paper's values by default).

    Attributes:
        max_rot_deg: largest rotation about each of x, y, z (degrees).
        root_away: fraction of the root-object distance the root is moved away.
        max_jitter: largest jitter length (m) of each hand and of the object.
        arti_range: (lo, hi) articulation angle (rad); None keeps the original θ.
        scale: multiplies rotation and jitter ranges (1 = paper; < 1 for milder training
            perturbations).
    """

    max_rot_deg: float = 20.0
    root_away: float = 0.05
    max_jitter: float = 0.06
    arti_range: Optional[tuple[float, float]] = (0.01 * math.pi, 0.2 * math.pi)
    scale: float = 1.0


KEEP_ARTICULATION = PerturbConfig(arti_range=None)
"""The paper's rotation, root and jitter ranges; θ stays the annotated angle."""


@dataclass(frozen=True, eq=False)
class FingerNoise:
    """Gaussian noise on the 45 finger values of each hand, along the principal directions
    of annotated hands: a finger pose moves only the ways the annotated hands vary, by a
    set fraction of how much they vary.

    Attributes:
        basis: side -> (K, 45) principal directions of annotated finger poses, each scaled
            by the standard deviation of the poses along it (rad).
        scale: standard deviation of the noise along each direction, in units of the
            poses' own standard deviation along it (0 adds nothing).
    """

    basis: Mapping[str, Tensor]
    scale: float = 0.5

    @classmethod
    def fit(cls, poses: Mapping[str, Tensor], components: int = 6, scale: float = 0.5) -> "FingerNoise":
        """Principal directions of annotated finger poses.

        Args:
            poses: side -> (N, 45) finger poses (axis-angle, rad), N > ``components``.
            components: K directions kept per side (those of the largest variance), 1 to 45.
            scale: see the class attributes (>= 0).

        Returns:
            the noise, its basis on the CPU in float64.

        Raises:
            ValueError: ``components`` outside 1..45, a negative ``scale``, fewer than
                ``components + 1`` poses of a side, or poses not (N, 45).
        """
        if not 1 <= components <= 45:
            raise ValueError(f"components must be in 1..45, got {components}")
        if scale < 0:
            raise ValueError(f"scale must be >= 0, got {scale}")
        basis = {}
        for side, x in poses.items():
            x = torch.as_tensor(x).to("cpu", torch.float64)
            if x.ndim != 2 or x.shape[1] != 45 or x.shape[0] <= components:
                raise ValueError(
                    f"{side} finger poses: need (N, 45) with N > {components} to fit {components} directions, "
                    f"got {tuple(x.shape)}"
                )
            _, sv, vt = torch.linalg.svd(x - x.mean(0), full_matrices=False)
            basis[side] = vt[:components] * (sv[:components, None] / math.sqrt(x.shape[0] - 1))
        return cls(basis, scale)

    def sample(self, side: str, n: int, generator: torch.Generator, dtype: torch.dtype = torch.float32) -> Tensor:
        """(n, 45) noise for ``side`` on the CPU: ``scale · z @ basis``, z ~ N(0, I_K) drawn
        from ``generator`` (a CPU generator)."""
        b = self.basis[side].to("cpu", torch.float64)
        z = torch.randn(n, b.shape[0], generator=generator, dtype=torch.float64)
        return (self.scale * z @ b).to(dtype)


@dataclass
class PerturbRecord:
    """What :func:`perturb` drew.

    Attributes:
        angles: side -> (B, 3) signed angles about x, y, z (rad).
        root_shift: side -> (B, 3) the 5 % root move (m).
        jitter: ``right``/``left``/``object`` -> (B, 3) translation jitter (m).
        wrist_before: side -> (B, 3) original wrist joint (m).
        center: (B, 3) object centre used for the root move (m).
        arti: (B,) new θ.
        fingers: side -> (B, 45) finger noise added (None: no :class:`FingerNoise`).
    """

    angles: dict[str, Tensor]
    root_shift: dict[str, Tensor]
    jitter: dict[str, Tensor]
    wrist_before: dict[str, Tensor]
    center: Tensor
    arti: Tensor
    fingers: Optional[dict[str, Tensor]] = None


def euler_xyz_matrix(angles: Tensor) -> Tensor:
    """(B, 3) angles (x, y, z) -> (B, 3, 3) ``R_z R_y R_x``."""
    eye = torch.eye(3, dtype=angles.dtype, device=angles.device)
    mats = [axis_angle_to_matrix(angles[:, i : i + 1] * eye[i]) for i in range(3)]
    return mats[2] @ mats[1] @ mats[0]


def random_directions(n: int, generator: torch.Generator, dtype: torch.dtype = torch.float32) -> Tensor:
    """(n, 3) unit vectors uniform on the sphere."""
    v = torch.randn(n, 3, generator=generator, dtype=torch.float64)
    v = v / v.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    return v.to(dtype)


def _uniform(n: int, lo: float, hi: float, generator: torch.Generator, dtype: torch.dtype) -> Tensor:
    return (lo + (hi - lo) * torch.rand(n, generator=generator, dtype=torch.float64)).to(dtype)


def object_centers(state: GraspState, objects: ObjectSet) -> Tensor:
    """(B, 3) world centroid of each object's surface samples (its current pose)."""
    dtype = state.obj_trans.dtype
    pts, _ = objects.points(state.obj_names, state.obj_arti)
    c = pts.mean(1, keepdim=True).to(dtype)
    return to_world(c, state.obj_rot, state.obj_trans)[:, 0]


def _add_finger_noise(
    hands: dict[str, HandParams], fingers: FingerNoise, generator: torch.Generator
) -> dict[str, Tensor]:
    """Add ``fingers`` noise to each hand's (B, 45) pose in place; the noise per side."""
    if set(SIDES) - set(fingers.basis):
        raise ValueError(f"finger noise needs a basis for each of {SIDES}, has {sorted(fingers.basis)}")
    noise = {}
    for s in SIDES:
        pose = hands[s].pose
        noise[s] = fingers.sample(s, pose.shape[0], generator, pose.dtype).to(pose.device)
        hands[s].pose = pose + noise[s]
    return noise


def perturb(
    state: GraspState,
    infos: Mapping[str, HandInfo],
    objects: ObjectSet,
    generator: torch.Generator,
    config: PerturbConfig = PerturbConfig(),
    fingers: Optional[FingerNoise] = None,
) -> tuple[GraspState, PerturbRecord]:
    """Perturb B grasps as in the HOGSA paper.

    For every sample, in this order:

    1. each hand's global orientation is rotated by ``R = R_z(γ) R_y(β) R_x(α)`` with each of
       α, β, γ of magnitude uniform in [0°, 20°] (random sign), applied on the left of the
       original orientation (world axes), i.e. about the hand's root joint;
    2. each hand root (wrist joint) is moved 5 % of its distance away from the object centre
       (the centroid of the object's surface samples, original object pose);
    3. each hand and the object get a translation jitter: uniform direction, length uniform in
       [0, 6 cm];
    4. the articulation angle θ is drawn uniformly in [0.01π, 0.2π] (ARCTIC objects), or kept;
    5. with ``fingers`` (not in the paper), each hand's finger pose gets
       :class:`FingerNoise`. It is drawn after everything above, so steps 1–4 draw the
       same values with and without it.

    The paper's θ draw never gives a closed object (θ = 0), although most annotated frames
    hold one; a model trained on such grasps learns a biased θ. :data:`KEEP_ARTICULATION`
    (the paper's ranges with the annotated θ kept) is what pose banks and online POM use.

    All draws come from one seeded :class:`torch.Generator`; :class:`PerturbRecord` returns
    them so tests can check the ranges.

    Args:
        state: original grasps (world frame).
        infos: hand models (for the wrist joint of each hand).
        objects: object geometry (for the object centre).
        generator: seeded CPU generator (all draws).
        config: ranges.
        fingers: finger-pose noise (None: fingers kept).

    Returns:
        the perturbed state (new tensors) and the :class:`PerturbRecord`.
    """
    B = state.batch
    dtype = state.obj_trans.dtype
    device = state.obj_trans.device
    max_rot = math.radians(config.max_rot_deg) * config.scale
    max_jit = config.max_jitter * config.scale
    with torch.no_grad():
        center = object_centers(state, objects)
        hands, rec_angles, rec_shift, rec_jit, rec_wrist = {}, {}, {}, {}, {}
        for side in SIDES:
            p = state.hands[side]
            mag = _uniform(B * 3, 0.0, max_rot, generator, dtype).reshape(B, 3)
            sign = torch.where(torch.rand(B, 3, generator=generator) < 0.5, -1.0, 1.0).to(dtype)
            angles = (mag * sign).to(device)
            R = euler_xyz_matrix(angles)
            rot = matrix_to_axis_angle(R @ axis_angle_to_matrix(p.rot))
            wrist = hand_forward(infos[side], p).joints[:, 0]
            shift = config.root_away * (wrist - center)
            jit = (random_directions(B, generator, dtype) * _uniform(B, 0.0, max_jit, generator, dtype)[:, None]).to(
                device
            )
            hands[side] = HandParams(rot, p.pose.clone(), p.trans + shift + jit, p.betas.clone())
            rec_angles[side], rec_shift[side], rec_jit[side], rec_wrist[side] = angles, shift, jit, wrist
        ojit = (random_directions(B, generator, dtype) * _uniform(B, 0.0, max_jit, generator, dtype)[:, None]).to(
            device
        )
        rec_jit["object"] = ojit
        if config.arti_range is not None:
            arti = _uniform(B, config.arti_range[0], config.arti_range[1], generator, dtype).to(device)
        else:
            arti = state.obj_arti.clone()
        rec_fingers = None if fingers is None else _add_finger_noise(hands, fingers, generator)
    new = GraspState(hands, list(state.obj_names), arti, state.obj_rot.clone(), state.obj_trans + ojit)
    return new, PerturbRecord(rec_angles, rec_shift, rec_jit, rec_wrist, center, arti, rec_fingers)
