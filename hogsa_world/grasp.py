"""Grasp synthesis: place a MANO-schema hand on an object part and close it onto the surface
(:func:`optimise_grasp`).

Every procedural object part is a rounded box (convex), so the object's signed distance is
the minimum of analytic rounded-box SDFs (:class:`RoundedBox`, fitted to the part's
``mesh.obj`` vertices; the triangle mesh is inscribed, so ``sdf >= 0`` implies "outside the
mesh"). ``R`` maps the hand's MANO frame to the part frame and the hand vertices are
``v = R (v_local - J0) + wrist`` (``v_local``: the articulated hand with zero global
orientation, ``J0`` its wrist joint); right-handed metres.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
import torch
from scipy.spatial.transform import Rotation
from torch import Tensor

from hogsa_loader.assets.hands.anatomy import FINGER_JOINTS, JointAxes, derive_joint_axes
from hogsa_loader.assets.hands.mano import MANOLayer
from hogsa_loader.assets.hands.mano_io import ManoModelData
from hogsa_loader.assets.objects.template import BOTTOM, TOP, ObjectTemplate
from hogsa_loader.geometry.rotations import axis_angle_to_matrix

__all__ = [
    "RoundedBox",
    "HandKit",
    "GraspSpec",
    "Grasp",
    "GRASP_DESIGNS",
    "GRASP_OBJECTS",
    "fit_part_boxes",
    "object_sdf",
    "grasp_specs",
    "styled_spec",
    "optimise_grasp",
    "placement_rotation",
    "rot_z_matrix",
]


# --------------------------------------------------------------------------------------
# Object SDF
# --------------------------------------------------------------------------------------
@dataclass(frozen=True)
class RoundedBox:
    """Axis-aligned box with rounded edges (canonical part frame, metres).

    Attributes:
        centre: (3,); half: (3,) half extents (including the rounding); radius: edge radius.
    """

    centre: np.ndarray
    half: np.ndarray
    radius: float

    def sdf(self, p: Tensor) -> Tensor:
        """Signed distance (negative inside) of points p (..., 3)."""
        c = torch.as_tensor(self.centre, dtype=p.dtype)
        h = torch.as_tensor(self.half - self.radius, dtype=p.dtype)
        q = (p - c).abs() - h
        outside = (q.clamp_min(0.0).pow(2).sum(-1) + 1e-14).sqrt()
        inside = torch.maximum(q[..., 0], torch.maximum(q[..., 1], q[..., 2])).clamp_max(0.0)
        return outside + inside - self.radius

    def point(self, frac: tuple[float, float, float]) -> np.ndarray:
        """Point ``centre + frac * half`` (frac in [-1, 1] per axis)."""
        return self.centre + np.asarray(frac) * self.half


def fit_part_boxes(template: ObjectTemplate) -> dict[int, RoundedBox]:
    """Rounded box of each part, fitted to its vertices (bounds + best radius).

    Raises:
        ValueError: a part is not a rounded box (fit residual > 0.3 mm), i.e. the object is
            not one of the procedural two-slab objects this module supports.
    """
    out = {}
    for part in (TOP, BOTTOM):
        v = template.part_points(part).astype(np.float64)
        lo, hi = v.min(0), v.max(0)
        centre, half = (lo + hi) / 2, (hi - lo) / 2
        pts = torch.as_tensor(v)
        best = (np.inf, 0.0)
        lo_r, hi_r = 0.0, 0.9 * half.min()
        for _ in range(3):  # coarse-to-fine search of the edge radius
            for r in np.linspace(lo_r, hi_r, 25):
                err = RoundedBox(centre, half, float(r)).sdf(pts).abs().max().item()
                if err < best[0]:
                    best = (err, float(r))
            step = (hi_r - lo_r) / 24
            lo_r, hi_r = max(0.0, best[1] - step), min(0.9 * half.min(), best[1] + step)
        if best[0] > 3e-4:
            raise ValueError(f"object {template.name!r} part {part}: not a rounded box (residual {best[0]:.2e} m)")
        out[part] = RoundedBox(centre, half, best[1])
    return out


def object_sdf(points: Tensor, boxes: dict[int, RoundedBox], top_rot: Tensor | None = None) -> Tensor:
    """Object SDF in the canonical frame (min over parts).

    Args:
        points: (..., 3) canonical-frame points.
        top_rot: (3, 3) articulation ``R_z(-θ)`` of the top part (None: θ = 0).
    """
    pt = points if top_rot is None else points @ top_rot  # R^T p, row-vector form
    return torch.minimum(boxes[TOP].sdf(pt), boxes[BOTTOM].sdf(points))


# --------------------------------------------------------------------------------------
# Hand kit
# --------------------------------------------------------------------------------------
@dataclass
class HandKit:
    """What grasping and motion need of one hand model.

    Attributes:
        model: the MANO-schema model; layer: float64 MANOLayer (flat_hand_mean=False).
        axes: joint axes; mean: (45,) ``hands_mean``; pads: finger -> pad vertex ids
            (plus ``palm``).
    """

    model: ManoModelData
    layer: MANOLayer = field(init=False)
    layer32: MANOLayer = field(init=False)
    axes: JointAxes = field(init=False)
    mean: np.ndarray = field(init=False)
    pads: dict = field(init=False)

    def __post_init__(self) -> None:
        self.layer = MANOLayer(self.model, flat_hand_mean=False, dtype=torch.float64)
        self.layer32 = MANOLayer(self.model, flat_hand_mean=False, dtype=torch.float32)
        self.axes = derive_joint_axes(self.model)
        self.mean = np.asarray(self.model.hands_mean, dtype=np.float64)
        self.pads = {k: np.asarray(v) for k, v in self.model.contact_vertex_ids.items()}

    @property
    def side(self) -> str:
        return self.model.side

    def articulation(self, flex: Tensor, abduct: Tensor) -> Tensor:
        """(..., 45) absolute articulation from (..., 15) flexion and abduction angles."""
        fa = torch.as_tensor(self.axes.flex, dtype=flex.dtype)
        aa = torch.as_tensor(self.axes.abduct, dtype=flex.dtype)
        rv = flex[..., None] * fa + abduct[..., None] * aa
        return rv.reshape(rv.shape[:-2] + (45,))

    def local(self, art: Tensor, betas: Tensor) -> tuple[Tensor, Tensor]:
        """Articulated hand with zero global orientation and translation.

        Args:
            art: (B, 45) absolute articulation; betas: (B, 10).

        Returns:
            vertices (B, V, 3) and joints (B, 21, 3), in the dtype of ``art`` (float32 or
            float64 layer).
        """
        mean = torch.as_tensor(self.mean, dtype=art.dtype)
        layer = self.layer32 if art.dtype == torch.float32 else self.layer
        out = layer(hand_pose=art - mean, betas=betas.to(art.dtype))
        return out.vertices, out.joints


# --------------------------------------------------------------------------------------
# Grasp specs
# --------------------------------------------------------------------------------------
@dataclass(frozen=True)
class GraspSpec:
    """Where and how a hand grasps a part (canonical frame of the object).

    Attributes:
        part: ``TOP`` or ``BOTTOM`` (the part the hand stays attached to).
        point: palm-centre target as fractions of the part box (``centre + frac * half``).
        normal: direction from the palm into the object.
        fingers: direction the fingers point (made orthogonal to ``normal``).
        curl: initial finger curl (radians of MCP-equivalent flexion).
        contacts: groups pulled onto the surface of the held part (finger names and/or
            ``palm``).
        standoff: initial palm-to-surface gap (m).
    """

    part: int
    point: tuple[float, float, float]
    normal: tuple[float, float, float]
    fingers: tuple[float, float, float]
    curl: float = 0.25
    contacts: tuple[str, ...] = ("thumb", "index", "middle", "ring", "pinky", "palm")
    standoff: float = 0.004


_ALL = ("thumb", "index", "middle", "ring", "pinky", "palm")


#: (object, action) pairs whose grasps have been designed and checked visually.
GRASP_DESIGNS = (("box", "grab"), ("box", "use"), ("laptop", "grab"), ("notebook", "grab"))
#: Objects with at least one designed grasp.
GRASP_OBJECTS = ("box", "laptop", "notebook")


def grasp_specs(obj: str, action: str) -> dict[str, GraspSpec]:
    """Grasp of each hand for an (object, action); keys ``right``/``left``.

    World placement: objects rest with canonical +y up, canonical +x (the hinge side)
    away from the subject and canonical +z to the subject's right; so the right hand
    works on the +z side, the left hand on the -z side.

    * box grab: palms on the two side faces, fingers wrapped round the back edge.
    * box use: left hand holds the body low on its side; right hand on the lid, fingers
      over the hinge edge (kept out of the body for every opening by the sweep check).
    * laptop / notebook grab: both hands pinch the side edges from above.

    ``use`` of the flat objects is not offered: with the lid closed the base is reachable
    only through its thin side faces, and no holding pose found stays clear of the lid's
    sweep (the holding hand would be inside the opening lid).

    Raises:
        KeyError: an (object, action) without a designed grasp (see :data:`GRASP_DESIGNS`).
    """
    if (obj, action) not in GRASP_DESIGNS:
        raise KeyError(f"no grasps designed for {obj} {action}; designed: {GRASP_DESIGNS}")
    if obj == "box":
        if action == "grab":
            return {
                "right": GraspSpec(BOTTOM, (-0.25, 0.15, 1.0), (0, 0, -1), (1, 0, 0), 0.2, _ALL),
                "left": GraspSpec(BOTTOM, (-0.25, 0.15, -1.0), (0, 0, 1), (1, 0, 0), 0.2, _ALL),
            }
        return {
            "right": GraspSpec(TOP, (-0.55, 1.0, 0.1), (0, -1, 0), (1, 0, 0), 0.15, _ALL),
            "left": GraspSpec(BOTTOM, (-0.25, -0.3, -1.0), (0, 0, 1), (1, 0, 0), 0.2, _ALL),
        }
    return {
        "right": GraspSpec(BOTTOM, (0.0, 1.0, 1.0), (0, -0.5, -0.87), (1, 0, 0), 0.4, _ALL),
        "left": GraspSpec(BOTTOM, (0.0, 1.0, -1.0), (0, -0.5, 0.87), (1, 0, 0), 0.4, _ALL),
    }


def styled_spec(spec: GraspSpec, amount: float, rng: np.random.Generator) -> GraspSpec:
    """One subject's own way of taking a designed grasp (people differ in where and how they hold).

    The palm target slides along the face it is on (every box fraction below 1 moves by up to
    ``0.35 * amount``), the fingers turn about the palm normal (up to ``25° * amount``), the
    palm tilts (up to ``8° * amount``) and the initial curl changes (``-0.1 .. +0.2 rad`` times
    ``amount``). The grasp optimisation then fits the hand to the surface as for the design.
    The same seven numbers are drawn whatever ``amount`` is.

    Args:
        spec: the designed grasp.
        amount: 0 keeps the design exactly; 1 is the full variation.
        rng: the subject's stream for this sequence.
    """
    slide = rng.uniform(-0.35, 0.35, 3)
    turn, tilt_angle, tilt_dir, curl = (
        rng.uniform(-1.0, 1.0),
        rng.uniform(-1.0, 1.0),
        rng.uniform(0, 2 * np.pi),
        rng.uniform(-0.1, 0.2),
    )
    if amount == 0.0:
        return spec
    point = np.asarray(spec.point, np.float64)
    free = np.abs(point) < 0.999
    point[free] = np.clip(point[free] + amount * slide[free], -0.9, 0.9)
    n = np.asarray(spec.normal, np.float64)
    n /= np.linalg.norm(n)
    fingers = np.asarray(spec.fingers, np.float64)
    fingers = Rotation.from_rotvec(n * np.deg2rad(25.0) * amount * turn).apply(fingers)
    side = np.cross(n, fingers)
    side /= np.linalg.norm(side)
    axis = np.cos(tilt_dir) * side + np.sin(tilt_dir) * np.cross(n, side)
    n = Rotation.from_rotvec(axis * np.deg2rad(8.0) * amount * tilt_angle).apply(n)
    return replace(
        spec,
        point=tuple(point.tolist()),
        normal=tuple(n.tolist()),
        fingers=tuple(fingers.tolist()),
        curl=float(max(0.05, spec.curl + amount * curl)),
    )


# --------------------------------------------------------------------------------------
# Optimisation
# --------------------------------------------------------------------------------------
@dataclass
class Grasp:
    """A grasp in the attached part's frame (θ = 0).

    Attributes:
        part: attached part; rot: (3, 3) hand orientation; wrist: (3,) wrist position;
        art: (45,) absolute articulation; open_art: (45,) a more open hand used before
        closing; normal: (3,) palm-into-object direction (for approach / retreat);
        stats: penetration / contact figures at the optimum.
    """

    part: int
    rot: np.ndarray
    wrist: np.ndarray
    art: np.ndarray
    open_art: np.ndarray
    normal: np.ndarray
    stats: dict


def placement_rotation(
    local_fingers: np.ndarray, local_normal: np.ndarray, fingers: np.ndarray, normal: np.ndarray
) -> np.ndarray:
    """Rotation taking the hand's (finger, palm-normal) directions onto target directions."""

    def frame(f: np.ndarray, n: np.ndarray) -> np.ndarray:
        n = n / np.linalg.norm(n)
        f = f - (f @ n) * n
        f = f / np.linalg.norm(f)
        return np.stack([f, n, np.cross(f, n)], axis=1)

    return frame(np.asarray(fingers, float), np.asarray(normal, float)) @ frame(local_fingers, local_normal).T


def rot_z_matrix(angle: float) -> np.ndarray:
    """(3, 3) rotation about +z (R_z(-θ) is the top part's articulation)."""
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


class _Adam:
    """Minimal Adam over (tensor, learning rate) pairs (no torch.optim import cost)."""

    def __init__(self, params: list[tuple[Tensor, float]], betas=(0.9, 0.999), eps: float = 1e-8) -> None:
        self.params, self.b1, self.b2, self.eps, self.t = params, betas[0], betas[1], eps, 0
        self.m = [torch.zeros_like(p) for p, _ in params]
        self.v = [torch.zeros_like(p) for p, _ in params]

    def zero_grad(self) -> None:
        for p, _ in self.params:
            p.grad = None

    @torch.no_grad()
    def step(self) -> None:
        self.t += 1
        for (p, lr), m, v in zip(self.params, self.m, self.v):
            if p.grad is None:
                continue
            m.mul_(self.b1).add_(p.grad, alpha=1 - self.b1)
            v.mul_(self.b2).addcmul_(p.grad, p.grad, value=1 - self.b2)
            mh = m / (1 - self.b1**self.t)
            vh = v / (1 - self.b2**self.t)
            p.sub_(lr * mh / (vh.sqrt() + self.eps))


_FLEX_LIMITS = {"thumb": (-0.3, 1.3), "other": (-0.15, 1.75)}


def _angle_init(kit: HandKit, curl: float) -> tuple[np.ndarray, np.ndarray]:
    flex = np.zeros(15)
    abd = np.zeros(15)
    for name, (j1, j2, j3) in FINGER_JOINTS.items():
        if name == "thumb":
            flex[[j1 - 1, j2 - 1, j3 - 1]] = [0.2 * curl, 0.3 * curl, 0.4 * curl]
        else:
            flex[[j1 - 1, j2 - 1, j3 - 1]] = [curl, 1.2 * curl, 0.8 * curl]
    return flex, abd


@dataclass
class _Placement:
    """The initial grasp: articulation angles, hand rotation and wrist, float32 tensors."""

    flex0: Tensor  # (15,) flexion angles
    abd0: Tensor  # (15,) abduction angles
    R0: Tensor  # (3, 3) hand rotation (MANO frame -> part frame)
    J0: Tensor  # (3,) wrist joint of the local hand
    wrist0: Tensor  # (3,) wrist position
    normal: np.ndarray  # (3,) unit palm-into-object direction


def _place(kit: HandKit, b: Tensor, spec: GraspSpec, boxes: dict[int, RoundedBox]) -> _Placement:
    """Palm centre at the spec's target point, backed off along the palm normal to the surface
    (``spec.standoff`` outside it), fingers along the spec's finger direction."""
    dt = b.dtype
    flex0, abd0 = _angle_init(kit, spec.curl)
    flex0_t, abd0_t = torch.tensor(flex0, dtype=dt), torch.tensor(abd0, dtype=dt)
    v_loc, j_loc = kit.local(kit.articulation(flex0_t, abd0_t)[None], b)
    J0 = j_loc[0, 0].double().numpy()
    local_fingers = (j_loc[0, 4] - j_loc[0, 0]).double().numpy()
    R0 = placement_rotation(local_fingers, kit.axes.palm_normal, np.array(spec.fingers), np.array(spec.normal))
    normal = np.asarray(spec.normal, float) / np.linalg.norm(spec.normal)
    palm = torch.as_tensor(kit.pads["palm"])
    pc = v_loc[0, palm].mean(0).double().numpy()
    target = boxes[spec.part].point(spec.point)
    wrist0 = target - R0 @ (pc - J0)
    probe = torch.as_tensor(target[None], dtype=dt)
    depth = -object_sdf(probe, boxes).item()  # > 0 when the target is inside
    wrist0 = wrist0 - (depth + spec.standoff) * normal
    return _Placement(
        flex0_t,
        abd0_t,
        torch.as_tensor(R0, dtype=dt),
        torch.as_tensor(J0, dtype=dt),
        torch.as_tensor(wrist0, dtype=dt),
        normal,
    )


class _GraspFit:
    """The hand posed by (flex, abd, drot, dpos) around a placement, and the object it must
    touch without entering (also at every opening of ``sweep_angles``)."""

    def __init__(
        self,
        kit: HandKit,
        b: Tensor,
        spec: GraspSpec,
        boxes: dict[int, RoundedBox],
        pl: _Placement,
        sweep_angles: tuple[float, ...],
    ) -> None:
        dt = b.dtype
        self.kit, self.b, self.spec, self.boxes, self.pl = kit, b, spec, boxes, pl
        self.sweep = [torch.as_tensor(rot_z_matrix(-a), dtype=dt) for a in sweep_angles]
        self.lo = torch.tensor(
            [(_FLEX_LIMITS["thumb"] if j >= 12 else _FLEX_LIMITS["other"])[0] for j in range(15)], dtype=dt
        )
        self.hi = torch.tensor(
            [(_FLEX_LIMITS["thumb"] if j >= 12 else _FLEX_LIMITS["other"])[1] for j in range(15)], dtype=dt
        )
        self.groups = {g: torch.as_tensor(kit.pads[g]) for g in spec.contacts}
        self.n_t = torch.as_tensor(pl.normal, dtype=dt)

    def pose(self, flex: Tensor, abd: Tensor, drot: Tensor, dpos: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """(V, 3) vertices, (3, 3) rotation and (3,) wrist of the hand."""
        R = axis_angle_to_matrix(drot) @ self.pl.R0
        v, _ = self.kit.local(self.kit.articulation(flex, abd)[None], self.b)
        verts = (v[0] - self.pl.J0) @ R.T + self.pl.wrist0 + dpos
        return verts, R, self.pl.wrist0 + dpos

    def moving_part(self, v: Tensor, Rs: Tensor) -> Tensor:
        """SDF of the part that turns relative to the hand, at one opening."""
        boxes = self.boxes
        return boxes[BOTTOM].sdf(v @ Rs.T) if self.spec.part == TOP else boxes[TOP].sdf(v @ Rs)

    def field(self, v: Tensor) -> Tensor:
        """(N,) distance to the object at rest and at every opening."""
        d = object_sdf(v, self.boxes)
        for Rs in self.sweep:
            d = torch.minimum(d, self.moving_part(v, Rs))
        return d

    def loss(self, flex: Tensor, abd: Tensor, drot: Tensor, dpos: Tensor, tn: Tensor, table_offset: float) -> Tensor:
        """Penetration (object, turning part, table), contact of the spec's pad groups with the
        held part, and priors on the angles and the correction."""
        verts, _, _ = self.pose(flex, abd, drot, dpos)
        d = object_sdf(verts, self.boxes)
        loss = 3e3 * torch.relu(-d).pow(2).sum()
        d_held = self.boxes[self.spec.part].sdf(verts)  # contacts are made with the part that is held
        for Rs in self.sweep:  # stay out of the part that turns relative to the hand, at every opening
            loss = loss + 3e3 * torch.relu(-self.moving_part(verts, Rs)).pow(2).sum()
        height = verts @ tn - table_offset
        loss = loss + 3e3 * torch.relu(0.003 - height).pow(2).sum()
        for g, ids in self.groups.items():
            dg = d_held[ids]
            k = min(8 if g != "palm" else 40, dg.shape[0])
            near = torch.topk(dg, k, largest=False).values
            loss = loss + (near.clamp_min(0.0).pow(2).mean() + 0.2 * dg.clamp_min(0.0).pow(2).mean()) * 5e2
        loss = loss + 1e-3 * ((flex - self.pl.flex0) ** 2).sum() + 2e-2 * ((abd - self.pl.abd0) ** 2).sum()
        loss = loss + 1.0 * (torch.relu(flex - self.hi) ** 2 + torch.relu(self.lo - flex) ** 2).sum()
        dtan = dpos - (dpos @ self.n_t) * self.n_t
        return loss + 2.0 * (dtan**2).sum() + 1e-3 * (drot**2).sum()

    @torch.no_grad()
    def push_out(self, verts: Tensor, wrist: Tensor, max_depth: float) -> tuple[Tensor, Tensor]:
        """Shift the hand along the SDF gradient of its deepest vertex until the residual
        penetration is at most ``max_depth`` (20 steps at most)."""
        for _ in range(20):
            d = self.field(verts)
            if -d.min().item() <= max_depth:
                break
            with torch.enable_grad():
                p = verts[d.argmin()].clone().requires_grad_(True)
                (g,) = torch.autograd.grad(self.field(p[None]).sum(), p)
            shift = g / g.norm() * (-d.min() - 0.5 * max_depth)
            verts = verts + shift
            wrist = wrist + shift
        return verts, wrist


def optimise_grasp(
    kit: HandKit,
    betas: np.ndarray,
    spec: GraspSpec,
    boxes: dict[int, RoundedBox],
    table_normal: np.ndarray,
    table_offset: float,
    iters: int = 140,
    max_depth: float = 1e-3,
    sweep_angles: tuple[float, ...] = (),
) -> Grasp:
    """Find a grasp in the frame of the part it attaches to, at articulation θ = 0.

    1. Placement from ``spec`` (:func:`_place`): the palm centre (mean of the palm
       contact-prior vertices) goes to a point of the part, the palm normal along the spec's
       direction into the object, the fingers along the spec's finger direction.
    2. Optimisation (Adam, autograd through the MANO layer; :meth:`_GraspFit.loss`) of a small
       global correction and per-joint flexion/abduction angles so that the finger pads and
       palm touch the surface (SDF -> 0), no vertex enters the object (SDF < 0 penalised) or
       the table, joints stay in range and near the initial curl.
    3. A final push-out along the SDF gradient (:meth:`_GraspFit.push_out`) removes any
       residual penetration deeper than ``max_depth``.

    Args:
        kit: the hand.
        betas: (10,) shape.
        spec: where to grasp.
        boxes: the object's parts (canonical frame).
        table_normal, table_offset: the table in the canonical frame at the object's rest
            pose, as the half-space ``n · p >= offset`` the hand must stay in.
        iters: Adam steps.
        max_depth: residual penetration allowed before the final push-out (m).
        sweep_angles: openings θ the object goes through while the hand holds it: a hand on
            the top part (turning with it) must stay out of the bottom part at each, a hand
            on the bottom part out of the opened top part. Empty when θ stays 0.

    Returns:
        the grasp, in the frame of ``spec.part`` (= canonical frame at θ = 0).
    """
    dt = torch.float32  # float32 optimisation (2x faster); results are returned as float64
    b = torch.as_tensor(np.asarray(betas, np.float64)[None], dtype=dt)
    pl = _place(kit, b, spec, boxes)
    fit = _GraspFit(kit, b, spec, boxes, pl, sweep_angles)
    tn = torch.as_tensor(np.asarray(table_normal, float), dtype=dt)
    flex = pl.flex0.clone().requires_grad_(True)
    abd = pl.abd0.clone().requires_grad_(True)
    drot = torch.zeros(3, dtype=dt, requires_grad=True)
    dpos = torch.zeros(3, dtype=dt, requires_grad=True)
    opt = _Adam([(flex, 0.04), (abd, 0.04), (drot, 0.01), (dpos, 0.002)])
    for _ in range(iters):
        opt.zero_grad()
        fit.loss(flex, abd, drot, dpos, tn, table_offset).backward()
        opt.step()
    with torch.no_grad():
        flex_c = torch.minimum(torch.maximum(flex, fit.lo), fit.hi)
        verts, R, wrist = fit.pose(flex_c, abd, drot, dpos)
        verts, wrist = fit.push_out(verts, wrist, max_depth)
        height = verts @ tn - table_offset
        stats = {
            "max_depth_m": float(max(0.0, -fit.field(verts).min().item())),
            "min_table_clearance_m": float(height.min().item()),
            "contact_groups": {
                g: float(boxes[spec.part].sdf(verts[ids]).min().item()) for g, ids in fit.groups.items()
            },
        }
        art = kit.articulation(flex_c.double(), abd.double()).numpy()
        open_art = kit.articulation(pl.flex0.double() * 0.3 - 0.05, pl.abd0.double() * 0.5).numpy()
        u, _, vt = np.linalg.svd(R.double().numpy())  # re-orthonormalise the float32 rotation
        rot = u @ vt
    return Grasp(
        part=spec.part, rot=rot, wrist=wrist.double().numpy(), art=art, open_art=open_art, normal=pl.normal, stats=stats
    )
