"""POM: perturbation ranges, losses, optimisation, metrics, ContactNet, pose bank."""

from __future__ import annotations

import hashlib
import json
import math

import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from hogsa_loader.assets.hands.mano import MANOLayer
from hogsa_loader.assets.objects.template import ObjectTemplate
from hogsa_loader.errors import AssetError
from hogsa_loader.models.pom import (
    ContactNet,
    FingerNoise,
    GraspState,
    HandParams,
    ObjectSet,
    PerturbConfig,
    POMConfig,
    contact_map,
    grasp_metrics,
    hand_infos,
    load_contactnet,
    load_pose_bank,
    optimise_grasps,
    perturb,
    save_contactnet,
    save_pose_bank,
)
from hogsa_loader.models.pom.geometry import ray_parity_inside
from hogsa_loader.models.pom.hands import SIDES
from hogsa_loader.models.pom.losses import hand_contact, hand_in_object, object_in_hand
from hogsa_loader.models.pom.state import canonical_hands, hand_forward

# --------------------------------------------------------------------------------------
# Constructed scene: two boxes (bottom base, small top tab) and the synthetic hands
# --------------------------------------------------------------------------------------
_CUBE_FACES = np.array(
    [
        [0, 2, 1],
        [0, 3, 2],  # z-
        [4, 5, 6],
        [4, 6, 7],  # z+
        [0, 1, 5],
        [0, 5, 4],  # y-
        [3, 7, 6],
        [3, 6, 2],  # y+
        [0, 4, 7],
        [0, 7, 3],  # x-
        [1, 2, 6],
        [1, 6, 5],  # x+
    ]
)


def _box(lo, hi):
    (x0, y0, z0), (x1, y1, z1) = lo, hi
    v = np.array(
        [
            [x0, y0, z0],
            [x1, y0, z0],
            [x1, y1, z0],
            [x0, y1, z0],
            [x0, y0, z1],
            [x1, y0, z1],
            [x1, y1, z1],
            [x0, y1, z1],
        ],
        dtype=np.float32,
    )
    return v, _CUBE_FACES.copy()


def _two_box_template() -> ObjectTemplate:
    vb, fb = _box((-0.12, -0.07, -0.06), (0.0, -0.001, 0.06))
    vt, ft = _box((-0.12, 0.001, -0.06), (-0.09, 0.02, 0.06))
    verts = np.concatenate([vt, vb])
    faces = np.concatenate([ft, fb + len(vt)])
    parts = np.array([0] * len(vt) + [1] * len(vb))
    z3 = lambda n: np.zeros((n, 3), np.float32)  # noqa: E731
    return ObjectTemplate(
        name="twobox",
        verts=verts,
        faces=faces,
        parts=parts,
        kp_top=z3(16),
        kp_bottom=z3(16),
        bbox_top=z3(8),
        bbox_bottom=z3(8),
        mocap_top=z3(0),
        mocap_bottom=z3(0),
        sub_top=z3(300),
        sub_bottom=z3(300),
        diameter=0.2,
    )


@pytest.fixture(scope="module")
def scene(hand_pair):
    right, left = hand_pair
    layers = {"right": MANOLayer(right, flat_hand_mean=False), "left": MANOLayer(left, flat_hand_mean=False)}
    infos = hand_infos(layers)
    objects = ObjectSet({"twobox": _two_box_template()}, n_points=1024, sdf_voxel=0.003)
    objects.geometry("twobox")
    return infos, objects


def _state(infos, centers: dict, B: int = 1, arti: float = 0.0) -> GraspState:
    """Hands at rest pose whose vertex centroid sits at ``centers[side]`` (object at identity)."""
    hands = {}
    for s in SIDES:
        z = lambda n: torch.zeros(B, n)  # noqa: E731
        p = HandParams(z(3), z(45), z(3), z(10))
        c = hand_forward(infos[s], p).vertices.mean(1)
        p.trans = torch.as_tensor(centers[s], dtype=torch.float32).expand(B, 3) - c
        hands[s] = p
    return GraspState(hands, ["twobox"] * B, torch.full((B,), arti), torch.zeros(B, 3), torch.zeros(B, 3))


FAR = {"right": (0.4, 0.3, 0.0), "left": (-0.5, 0.3, 0.0)}
INSIDE = {"right": (-0.06, -0.035, 0.0), "left": (-0.5, 0.3, 0.0)}


# --------------------------------------------------------------------------------------
# Geometry
# --------------------------------------------------------------------------------------
def test_contact_map_values():
    d = torch.tensor([0.0, 0.01, 0.02, 0.03])
    np.testing.assert_allclose(contact_map(d).numpy(), [1.0, 0.2384, 0.0360, 0.0049], atol=2e-4)


def test_sdf_sign_matches_ray_parity(scene):
    _, objects = scene
    g = torch.Generator().manual_seed(0)
    pts = torch.rand(1, 2000, 3, generator=g) * torch.tensor([0.2, 0.14, 0.16]) - torch.tensor([0.16, 0.09, 0.08])
    sdf = objects.sdf(pts, ["twobox"], torch.zeros(1))[0]
    geo = objects.geometry("twobox")
    inside = ray_parity_inside(pts[0].double(), geo.tris[0]) | ray_parity_inside(pts[0].double(), geo.tris[1])
    clear = sdf.abs() > 0.004  # away from the surface the grid sign is exact
    assert bool(((sdf < 0) == inside)[clear].all())
    assert 0.2 < float(inside.float().mean()) < 0.8


def test_grid_inside_matches_ray_parity_along_z():
    """The grid test (each triangle against the columns in its bounding box, in chunks of
    pairs) gives every node the parity of Möller–Trumbore crossings of a +z ray from it, on
    stacked shells (20 crossings per column) and on a box; with fewer counted crossings than a
    column has, the same flags as testing every column against every triangle."""
    import trimesh

    from hogsa_loader.models.pom.geometry import grid_inside

    s = trimesh.creation.icosphere(2)
    v = np.concatenate([np.asarray(s.vertices) * 0.3 + [0.05 * i, 0, 0.7 * i] for i in range(10)])
    f = np.concatenate([np.asarray(s.faces) + len(s.vertices) * i for i in range(10)])
    vb, fb = _box((-0.05, -0.04, -0.03), (0.05, 0.04, 0.03))
    shells = (np.linspace(-0.4, 0.9, 19), np.linspace(-0.4, 0.4, 15), np.linspace(-0.51, 7.0, 61))
    box = (np.linspace(-0.061, 0.06, 23), np.linspace(-0.05, 0.051, 17), np.linspace(-0.041, 0.04, 13))
    for tris, axes in ((v[f], shells), (vb[fb].astype(np.float64), box)):
        Z, Y, X = np.meshgrid(axes[2], axes[1], axes[0], indexing="ij")
        nodes = np.stack([X + 1.2345e-7, Y + 2.3456e-7, Z], -1).reshape(-1, 3)  # the grid's ray offsets
        ref = ray_parity_inside(torch.as_tensor(nodes), torch.as_tensor(tris), direction=(0.0, 0.0, 1.0))
        ref = ref.numpy().reshape(Z.shape)
        assert 0.05 < ref.mean() < 0.6
        for chunk in (40, 2_000_000):
            np.testing.assert_array_equal(grid_inside(tris, *axes, chunk=chunk), ref)
    for k in (3, 6, 32):  # the k lowest crossings of a column counted, against every column x every triangle
        for chunk in (40, 2_000_000):
            got = grid_inside(v[f], *shells, max_cross=k, chunk=chunk)
            np.testing.assert_array_equal(got, _dense(v[f], *shells, k))
    with pytest.raises(ValueError, match="zs must be ascending"):
        grid_inside(v[f], shells[0], shells[1], shells[2][::-1])


def _dense(tris, xs, ys, zs, k):
    """Every column against every triangle: crossing heights, the ``k`` lowest (a missing one
    counts as +inf, above every node), the parity of those above each node."""
    X, Y = np.meshgrid(xs + 1.2345e-7, ys + 2.3456e-7, indexing="xy")
    px, py = X.reshape(-1, 1), Y.reshape(-1, 1)
    a, b, c = tris[:, 0], tris[:, 1], tris[:, 2]
    den = (b[:, 1] - c[:, 1]) * (a[:, 0] - c[:, 0]) + (c[:, 0] - b[:, 0]) * (a[:, 1] - c[:, 1])
    l1 = ((b[:, 1] - c[:, 1]) * (px - c[:, 0]) + (c[:, 0] - b[:, 0]) * (py - c[:, 1])) / den
    l2 = ((c[:, 1] - a[:, 1]) * (px - c[:, 0]) + (a[:, 0] - c[:, 0]) * (py - c[:, 1])) / den
    l3 = 1 - l1 - l2
    z = np.where((l1 >= 0) & (l2 >= 0) & (l3 >= 0), l1 * a[:, 2] + l2 * b[:, 2] + l3 * c[:, 2], np.inf)
    above = (np.sort(z, axis=1)[:, :k, None] > zs).sum(1)
    return (above % 2 == 1).reshape(len(ys), len(xs), len(zs)).transpose(2, 0, 1)


def test_sdf_grid_of_a_mesh_is_built_once_per_setting(monkeypatch):
    """A second build for the same mesh and settings returns the kept grid, which equals a fresh
    build; another voxel size or a moved mesh builds a new one."""
    from hogsa_loader.models.pom import geometry

    v, f = _box((-0.05, -0.04, -0.03), (0.05, 0.04, 0.03))
    monkeypatch.setattr(geometry, "_SDF_GRIDS", type(geometry._SDF_GRIDS)())
    first = geometry.build_sdf_grid(v, f, voxel=0.01, max_samples=20_000)
    assert geometry.build_sdf_grid(v.copy(), f.copy(), voxel=0.01, max_samples=20_000) is first
    other = geometry.build_sdf_grid(v, f, voxel=0.008, max_samples=20_000)
    moved = geometry.build_sdf_grid(v + 0.01, f, voxel=0.01, max_samples=20_000)
    assert other is not first and moved is not first
    assert tuple(other.values.shape) != tuple(first.values.shape)
    torch.testing.assert_close(moved.lo, first.lo + 0.01)
    monkeypatch.setattr(geometry, "_SDF_GRIDS", type(geometry._SDF_GRIDS)())
    fresh = geometry.build_sdf_grid(v, f, voxel=0.01, max_samples=20_000)
    assert fresh is not first
    torch.testing.assert_close(fresh.values, first.values, rtol=0, atol=0)
    assert float(first.values.min()) < 0 < float(first.values.max())


def test_capped_hand_is_closed(scene):
    import trimesh

    infos, _ = scene
    for s in SIDES:
        v = infos[s].capped.verts(infos[s].layer().vertices[0])
        mesh = trimesh.Trimesh(v.detach().numpy(), infos[s].capped.faces.numpy(), process=False)
        assert mesh.is_watertight and mesh.volume > 0
        assert 0 < len(infos[s].prior_ids) < infos[s].num_verts


# --------------------------------------------------------------------------------------
# Perturbation (property tests)
# --------------------------------------------------------------------------------------
@settings(max_examples=8, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(seed=st.integers(0, 2**31 - 1))
def test_perturbation_ranges(scene, seed):
    infos, objects = scene
    B = 4
    state = _state(infos, {"right": (-0.05, 0.05, 0.1), "left": (-0.08, -0.02, -0.12)}, B=B)
    state.obj_rot = torch.randn(B, 3, generator=torch.Generator().manual_seed(seed)) * 0.5
    new, rec = perturb(state, infos, objects, torch.Generator().manual_seed(seed))
    lo, hi = 0.01 * math.pi, 0.2 * math.pi
    assert bool(((new.obj_arti >= lo - 1e-6) & (new.obj_arti <= hi + 1e-6)).all())
    assert float(rec.jitter["object"].norm(dim=-1).max()) <= 0.06 + 1e-6
    assert torch.allclose(new.obj_trans - state.obj_trans, rec.jitter["object"], atol=1e-6)
    assert torch.equal(new.obj_rot, state.obj_rot)
    for s in SIDES:
        assert float(rec.angles[s].abs().max()) <= math.radians(20) + 1e-6
        assert float(rec.jitter[s].norm(dim=-1).max()) <= 0.06 + 1e-6
        w0 = rec.wrist_before[s]
        torch.testing.assert_close(rec.root_shift[s], 0.05 * (w0 - rec.center), atol=1e-6, rtol=0)
        # root moved away from the object by exactly 5 % of its distance
        d0 = (w0 - rec.center).norm(dim=-1)
        torch.testing.assert_close((w0 + rec.root_shift[s] - rec.center).norm(dim=-1), 1.05 * d0, atol=1e-6, rtol=0)
        # the rotation turns the hand about its wrist; the wrist only gets shift + jitter
        w1 = hand_forward(infos[s], new.hands[s]).joints[:, 0]
        torch.testing.assert_close(w1, w0 + rec.root_shift[s] + rec.jitter[s], atol=2e-5, rtol=0)
        # the orientation change is the drawn rotation (angle <= sqrt(3) * 20 deg)
        from hogsa_loader.geometry.rotations import axis_angle_to_matrix
        from hogsa_loader.models.pom.perturb import euler_xyz_matrix

        R = axis_angle_to_matrix(new.hands[s].rot) @ axis_angle_to_matrix(state.hands[s].rot).transpose(-1, -2)
        torch.testing.assert_close(R, euler_xyz_matrix(rec.angles[s]), atol=1e-5, rtol=0)
        assert torch.equal(new.hands[s].pose, state.hands[s].pose)
    again, _ = perturb(state, infos, objects, torch.Generator().manual_seed(seed))
    assert torch.equal(again.hands["right"].trans, new.hands["right"].trans)


def test_perturbation_scale_zero_keeps_rotation(scene):
    infos, objects = scene
    state = _state(infos, FAR, B=3)
    new, rec = perturb(
        state, infos, objects, torch.Generator().manual_seed(1), PerturbConfig(scale=0.0, arti_range=None)
    )
    assert float(rec.angles["right"].abs().max()) == 0.0
    assert torch.equal(new.obj_arti, state.obj_arti)


def _planted_poses(n: int, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    """(n, 45) poses varying along two orthonormal directions (std 0.3 and 0.1 rad) plus
    1e-3 isotropic noise, and those (2, 45) directions."""
    g = torch.Generator().manual_seed(seed)
    dirs, _ = torch.linalg.qr(torch.randn(45, 2, generator=g, dtype=torch.float64))
    coef = torch.randn(n, 2, generator=g, dtype=torch.float64) * torch.tensor([0.3, 0.1], dtype=torch.float64)
    mean = torch.randn(45, generator=g, dtype=torch.float64) * 0.2
    return mean + coef @ dirs.T + 1e-3 * torch.randn(n, 45, generator=g, dtype=torch.float64), dirs.T


def test_finger_noise_follows_the_annotated_hands_principal_directions():
    poses, dirs = _planted_poses(4000, 0)
    noise = FingerNoise.fit({"right": poses, "left": poses[:, torch.randperm(45)]}, components=2, scale=0.5)
    basis = noise.basis["right"]
    assert basis.shape == (2, 45) and noise.basis["left"].shape == (2, 45)
    cos = torch.nn.functional.cosine_similarity(basis, dirs, dim=1).abs()
    assert bool((cos > 0.999).all()), cos
    torch.testing.assert_close(basis.norm(dim=1), torch.tensor([0.3, 0.1], dtype=torch.float64), rtol=0.05, atol=0)
    x = noise.sample("right", 20000, torch.Generator().manual_seed(1), torch.float64)
    assert x.shape == (20000, 45) and x.dtype == torch.float64
    # nothing outside the two directions; along them, 0.5 x the poses' own spread
    residual = x - (x @ dirs.T) @ dirs
    assert float(residual.abs().max()) < 0.002
    torch.testing.assert_close((x @ dirs.T).std(0), torch.tensor([0.15, 0.05], dtype=torch.float64), rtol=0.05, atol=0)
    assert torch.equal(x, noise.sample("right", 20000, torch.Generator().manual_seed(1), torch.float64))
    with pytest.raises(ValueError, match="right finger poses"):
        FingerNoise.fit({"right": poses[:2]}, components=2)
    with pytest.raises(ValueError, match=r"\(100, 44\)"):
        FingerNoise.fit({"right": poses[:100, :44]}, components=2)
    for bad in ({"components": 0}, {"components": 46}, {"scale": -0.1}):
        with pytest.raises(ValueError, match="components|scale"):
            FingerNoise.fit({"right": poses}, **bad)
    from hogsa_loader.train.pom_config import BankPOMConfig

    with pytest.raises(ValueError, match="finger_scale"):
        BankPOMConfig(finger_scale=-1.0)


@pytest.mark.parametrize("bad", [{"per_sequence": 0}, {"variants": 0}])
def test_bank_data_config_refuses_no_frames_or_no_starts(bad):
    from hogsa_loader.train.pom_config import BankDataConfig

    with pytest.raises(ValueError, match="per_sequence and variants must be >= 1"):
        BankDataConfig(root="r", contactnet="c", **bad)
    with pytest.raises(ValueError, match="frames must be 'contact' or 'all'"):
        BankDataConfig(root="r", contactnet="c", frames="grasps")


def test_finger_noise_changes_only_the_fingers(scene):
    infos, objects = scene
    state = _state(infos, {"right": (-0.05, 0.05, 0.1), "left": (-0.08, -0.02, -0.12)}, B=5)
    noise = FingerNoise.fit({s: _planted_poses(200, i)[0] for i, s in enumerate(SIDES)}, components=2, scale=1.0)
    plain, rec0 = perturb(state, infos, objects, torch.Generator().manual_seed(3))
    noisy, rec = perturb(state, infos, objects, torch.Generator().manual_seed(3), fingers=noise)
    assert rec0.fingers is None
    assert torch.equal(noisy.obj_trans, plain.obj_trans) and torch.equal(noisy.obj_arti, plain.obj_arti)
    for s in SIDES:
        for k in ("rot", "trans", "betas"):
            assert torch.equal(getattr(noisy.hands[s], k), getattr(plain.hands[s], k)), (s, k)
        torch.testing.assert_close(noisy.hands[s].pose - state.hands[s].pose, rec.fingers[s])
        assert float(rec.fingers[s].abs().max()) > 0.05
        basis = noise.basis[s].to(torch.float32)
        coef = torch.linalg.lstsq(basis.T, rec.fingers[s].T).solution  # in the span of the directions
        torch.testing.assert_close(coef.T @ basis, rec.fingers[s], atol=1e-5, rtol=0)
    with pytest.raises(ValueError, match="a basis for each"):
        perturb(state, infos, objects, torch.Generator(), fingers=FingerNoise({"right": noise.basis["right"]}))


# --------------------------------------------------------------------------------------
# Losses and metrics on constructed cases
# --------------------------------------------------------------------------------------
def _losses(scene, centers):
    infos, objects = scene
    state = _state(infos, centers)
    hands = canonical_hands(state, infos)
    obj, _ = objects.points(state.obj_names, state.obj_arti)
    out = {}
    for s in SIDES:
        v = hands[s].vertices
        c, dist, idx = hand_contact(obj, v)
        l_in, sdf = hand_in_object(v, objects, state.obj_names, state.obj_arti)
        l_oh = object_in_hand(obj, v, infos[s].layer.faces, idx, dist)
        out[s] = (float(l_in), float(l_oh), float(c.max()), float(sdf.min()))
    return out, state


def test_losses_zero_when_far(scene):
    out, _ = _losses(scene, FAR)
    for s in SIDES:
        l_in, l_oh, cmax, sdf_min = out[s]
        assert l_in == 0.0 and l_oh == 0.0
        assert cmax < 1e-6 and sdf_min > 0.1


def test_losses_positive_when_inside(scene):
    out, _ = _losses(scene, INSIDE)
    l_in, _, cmax, sdf_min = out["right"]
    assert l_in > 0.0 and sdf_min < -0.005 and cmax > 0.9
    assert out["left"][0] == 0.0


def test_metrics_far_and_inside(scene):
    infos, objects = scene
    far = grasp_metrics(_state(infos, FAR), infos, objects)
    assert far["penetration_depth"][0] == 0.0 and far["intersection"][0] == 0.0
    assert far["contact_ratio"][0] == 0.0 and not far["accept"][0]
    inside = grasp_metrics(_state(infos, INSIDE), infos, objects)
    assert inside["penetration_depth"][0] > 0.005
    assert inside["intersection"][0] > 4e-6 and not inside["accept"][0]
    assert inside["contact_right"][0] and not inside["contact_left"][0]


def test_metrics_accept_a_frame_without_contact_on_intersection_alone(scene):
    """A frame whose source has no touching hand needs no contact, only a small intersection;
    a frame with a touching source hand still needs that hand to touch."""
    infos, objects = scene
    none = {s: torch.tensor([False]) for s in SIDES}
    right = {"right": torch.tensor([True]), "left": torch.tensor([False])}
    far = _state(infos, FAR)
    assert grasp_metrics(far, infos, objects, none)["accept"][0]
    assert not grasp_metrics(far, infos, objects, right)["accept"][0]
    assert not grasp_metrics(_state(infos, INSIDE), infos, objects, none)["accept"][0]


def test_optimisation_reduces_penetration(scene):
    infos, objects = scene
    start = _state(infos, {"right": (-0.06, -0.075, 0.0), "left": (-0.5, 0.3, 0.0)}, B=2)
    start.hands["right"].trans[1, 0] += 0.01  # two different samples, one batch

    def depth(state):
        hands = canonical_hands(state, infos)
        return torch.relu(-objects.sdf(hands["right"].vertices, state.obj_names, state.obj_arti)).amax(1)

    d0 = depth(start)
    assert bool((d0 > 0.005).all())
    # the paper's Adam loop alone (no rigid projection), translation lr raised for a short run
    cfg = POMConfig(iters=25, snap=False, final_push=False, lr_trans=1.5e-3, lr_rot=3e-3, n_obj_points=384)
    res = optimise_grasps(start, infos, objects, None, cfg)
    assert res.history[-1] < res.history[0]
    assert bool((depth(res.state) < 0.5 * d0).all())
    # the default pipeline (projection + 200 iterations shortened to 5 + final push)
    full = optimise_grasps(start, infos, objects, None, POMConfig(iters=5, n_obj_points=384))
    assert bool(full.keep.all()) and sum(full.dropped.values()) == 0
    m = grasp_metrics(full.state, infos, objects)
    assert float(m["penetration_depth"].max()) < 0.002 and bool(m["accept"].all())


def test_free_hand_is_not_pulled_onto_the_object(scene):
    """A hand that did not touch the object in the source frame keeps its distance: the
    max-normalised ContactNet map and the hand-centric term apply only to active hands."""
    infos, objects = scene
    # left hand free, 8 mm from the object; right hand far away
    start = _touching(infos, objects, "left", (-0.06, -0.035, 0.12), (0.0, 0.0, -1.0), gap=0.008)
    torch.manual_seed(0)
    net = ContactNet().eval()  # any network: its map is normalised by its maximum
    cfg = POMConfig(iters=40, snap=False, final_push=False, lr_trans=1e-3, lr_rot=2e-3, n_obj_points=384)

    def gap(state):
        v = canonical_hands(state, infos)["left"].vertices
        return float(objects.sdf(v, state.obj_names, state.obj_arti).min())

    assert abs(gap(start) - 0.008) < 5e-4
    free = {"right": torch.tensor([False]), "left": torch.tensor([False])}
    held = {"right": torch.tensor([False]), "left": torch.tensor([True])}
    res_free = optimise_grasps(start, infos, objects, net, cfg, active=free)
    res_held = optimise_grasps(start, infos, objects, net, cfg, active=held)
    assert abs(gap(res_free.state) - 0.008) < 1e-3  # stays where it was
    assert gap(res_held.state) < 0.004  # the same hand, marked as touching, is pulled in


def _touching(infos, objects, side: str, center, direction, gap: float = 0.002) -> GraspState:
    """A hand at ``center`` moved along ``direction`` until its closest vertex is ``gap`` from the object."""
    state = _state(infos, {**FAR, side: center})
    d = torch.as_tensor(direction, dtype=torch.float32)
    v = canonical_hands(state, infos)[side].vertices
    lo, hi = 0.0, 0.3  # bisection on the travel distance
    for _ in range(40):
        mid = 0.5 * (lo + hi)
        m = float(objects.sdf(v + mid * d, state.obj_names, state.obj_arti).min())
        lo, hi = (mid, hi) if m > gap else (lo, mid)
    state.hands[side].trans = state.hands[side].trans + lo * d
    return state


def test_rigid_move_hand_matches_vertex_motion(scene):
    from hogsa_loader.geometry.rotations import axis_angle_to_matrix
    from hogsa_loader.models.pom.regrasp import rigid_move_hand

    infos, _ = scene
    g = torch.Generator().manual_seed(3)
    p = HandParams(
        torch.randn(4, 3, generator=g) * 0.7,
        torch.randn(4, 45, generator=g) * 0.2,
        torch.randn(4, 3, generator=g) * 0.1,
        torch.randn(4, 10, generator=g),
    )
    M = axis_angle_to_matrix(torch.randn(4, 3, generator=g))
    c = torch.randn(4, 3, generator=g) * 0.1
    for s in SIDES:
        v0 = hand_forward(infos[s], p).vertices
        v1 = hand_forward(infos[s], rigid_move_hand(infos[s], p, M, c)).vertices
        torch.testing.assert_close(v1, v0 @ M.transpose(-1, -2) + c[:, None], atol=2e-5, rtol=0)


def test_regrasp_restores_source_contacts(scene):
    from hogsa_loader.geometry.rotations import axis_angle_to_matrix
    from hogsa_loader.models.pom.regrasp import regrasp, rigid_move_hand, source_contacts

    infos, objects = scene
    src = _touching(infos, objects, "right", (-0.06, -0.16, 0.0), (0.0, 1.0, 0.0))
    con = source_contacts(src, infos, objects)
    C = con.mask["right"][0]
    assert int(C.sum()) >= 5 and not bool(con.active("left")[0])
    # move the hand off and into the object: 15 degrees about its wrist, 2 cm sideways, 2 cm in
    M = axis_angle_to_matrix(torch.tensor([[0.0, 0.0, math.radians(15)]]))
    w = hand_forward(infos["right"], src.hands["right"]).joints[:, 0]
    moved = rigid_move_hand(infos["right"], src.hands["right"], M, w - w @ M[0].T + torch.tensor([[0.02, 0.02, 0.0]]))
    start = GraspState({**src.hands, "right": moved}, src.obj_names, src.obj_arti, src.obj_rot, src.obj_trans)

    def sdf(state):
        return objects.sdf(canonical_hands(state, infos)["right"].vertices, state.obj_names, state.obj_arti)[0]

    d_src, d0 = sdf(src), sdf(start)
    assert float((d0[C] - d_src[C]).abs().mean()) > 0.005 and float(d0.min()) < -0.005
    out = regrasp(start, con, infos, objects)
    d1 = sdf(out)
    assert float((d1[C] - d_src[C].clamp_min(0.001)).abs().mean()) < 0.002  # contacts back at their distances
    assert float(d1.min()) > -0.001  # no penetration
    assert torch.equal(out.hands["left"].trans, start.hands["left"].trans)  # no contacts: untouched
    # a stiff rotation prior keeps the perturbed orientation (translation only)
    stiff = regrasp(start, con, infos, objects, rot_weight=1e6)
    torch.testing.assert_close(
        axis_angle_to_matrix(stiff.hands["right"].rot), axis_angle_to_matrix(moved.rot), atol=1e-4, rtol=0
    )


def test_hand_on_top_part_follows_articulation(scene):
    from hogsa_loader.assets.objects.template import TOP
    from hogsa_loader.models.pom.regrasp import carry_with_part, source_contacts

    infos, objects = scene
    src = _touching(infos, objects, "right", (-0.105, 0.12, 0.0), (0.0, -1.0, 0.0))  # on the top tab
    con = source_contacts(src, infos, objects)
    assert bool(con.on_top["right"][0]) and int(con.mask["right"][0].sum()) >= 3
    new = GraspState(src.hands, src.obj_names, torch.tensor([0.4]), src.obj_rot, src.obj_trans)
    out = carry_with_part(new, src.obj_arti, con, infos)

    def top_sdf(state):
        v = canonical_hands(state, infos)["right"].vertices
        return objects.part_sdf(v, state.obj_names, state.obj_arti)[TOP][0]

    torch.testing.assert_close(top_sdf(out), top_sdf(src), atol=1e-5, rtol=0)
    assert float((top_sdf(new) - top_sdf(src)).abs().max()) > 0.01  # not carried: contact lost
    assert torch.equal(out.hands["left"].trans, src.hands["left"].trans)


def test_hand_layers_follow_the_parameters_device(scene):
    """The optimisation may run on another device than the caller's MANO layers (CUDA POM
    with CPU layers): hand_forward uses a cached copy there and leaves the caller's layer."""
    infos, _ = scene
    info = infos["right"]
    assert info.layer_on("cpu") is info.layer
    meta = info.layer_on(torch.device("meta"))
    assert meta is not info.layer and meta.v_template.device.type == "meta"
    assert info.layer.v_template.device.type == "cpu" and info.layer_on("meta") is meta  # cached, original untouched
    z = lambda n: torch.zeros(2, n)  # noqa: E731
    out = hand_forward(info, HandParams(z(3), z(45), z(3), z(10)))
    assert out.vertices.device.type == "cpu" and out.vertices.shape == (2, info.num_verts, 3)


def test_pose_bank_variant_seeds_are_distinct():
    from hogsa_loader.train.pom_jobs import variant_seed

    names = [f"s{n // 40:02d}/box_use_{n % 40:02d}" for n in range(200)]
    seeds = {variant_seed(0, name, v) for name in names for v in range(4)}
    assert len(seeds) == 800 and all(0 <= x < 2**31 for x in seeds)  # (the old seed + 1000·v + frames collided)
    # a sequence's draws depend on its id, not on which other sequences are selected
    assert (
        variant_seed(0, "s01/box_use_01", 1)
        == variant_seed(0, "s01/box_use_01", 1)
        != variant_seed(1, "s01/box_use_01", 1)
    )


def test_nonfinite_samples_are_dropped(scene):
    infos, objects = scene
    start = _state(infos, FAR, B=3)
    start.hands["left"].pose[1, 0] = float("nan")
    res = optimise_grasps(start, infos, objects, None, POMConfig(iters=3, snap=False, n_obj_points=256))
    assert res.keep.tolist() == [True, False, True]
    assert res.dropped["nonfinite"] == 1
    assert torch.isfinite(res.state.hands["right"].trans[[0, 2]]).all()


# --------------------------------------------------------------------------------------
# ContactNet
# --------------------------------------------------------------------------------------
def test_contactnet_any_topology_and_roundtrip(tmp_path):
    torch.manual_seed(0)
    net = ContactNet().eval()
    for n_obj, n_hand in ((100, 778), (333, 2565), (50, 12)):
        out = net(
            torch.rand(2, n_obj, 3) * 0.1,
            torch.rand(2, n_hand, 3) * 0.1,
            torch.rand(n_hand) > 0.7,
            torch.tensor([1.0, -1.0]),
        )
        assert out.shape == (2, n_obj) and bool(((out > 0) & (out < 1)).all())
    save_contactnet(net, tmp_path / "run")
    back = load_contactnet(tmp_path / "run")
    x = (torch.rand(1, 64, 3), torch.rand(1, 200, 3), torch.zeros(200, dtype=torch.bool), torch.ones(1))
    torch.testing.assert_close(back(*x), net(*x))
    man = json.loads((tmp_path / "run" / "manifest.json").read_text())
    (tmp_path / "run" / "manifest.json").write_text(json.dumps({**man, "schema_version": 99}))
    with pytest.raises(AssetError, match="schema_version"):
        load_contactnet(tmp_path / "run")
    # strict manifests: NaN is not JSON (the writer refuses it before writing anything)
    (tmp_path / "run" / "manifest.json").write_text(json.dumps({**man, "training": {"loss": float("nan")}}))
    with pytest.raises(AssetError, match="NaN is not a JSON value"):
        load_contactnet(tmp_path / "run")
    with pytest.raises(ValueError, match="NaN"):
        save_contactnet(net, tmp_path / "run2", {"training": {"loss": float("nan")}})
    assert not (tmp_path / "run2" / "contactnet.safetensors").exists()
    # non-finite weights: refused on reading and on writing
    from safetensors.torch import load_file, save_file

    (tmp_path / "run" / "manifest.json").write_text(json.dumps(man))
    w = load_file(str(tmp_path / "run" / "contactnet.safetensors"))
    key = next(iter(w))
    w[key][..., 0] = float("inf")
    save_file(w, str(tmp_path / "run" / "contactnet.safetensors"))
    # the manifest's checksum catches a replaced weights file first ...
    with pytest.raises(AssetError, match="contactnet.safetensors.*sha256 does not match manifest.json"):
        load_contactnet(tmp_path / "run")
    # ... a manifest without one (pre-1.0) is refused ...
    (tmp_path / "run" / "manifest.json").write_text(json.dumps({k: v for k, v in man.items() if k != "tensors_sha256"}))
    with pytest.raises(AssetError, match="manifest.json.*tensors_sha256"):
        load_contactnet(tmp_path / "run")
    # ... and with a matching checksum the content checks still hold
    sha = hashlib.sha256((tmp_path / "run" / "contactnet.safetensors").read_bytes()).hexdigest()
    (tmp_path / "run" / "manifest.json").write_text(json.dumps({**man, "tensors_sha256": sha}))
    with pytest.raises(AssetError, match=f"contactnet.safetensors.*{key}"):
        load_contactnet(tmp_path / "run")
    with torch.no_grad():
        next(net.parameters())[...] = float("nan")
    with pytest.raises(ValueError, match="NaN or infinity"):
        save_contactnet(net, tmp_path / "run3")
    assert not (tmp_path / "run3" / "manifest.json").exists()


def _touching_grasps(infos, objects, n: int, seed: int) -> GraspState:
    """n grasps with both hands touching the two-box object from random directions."""
    from hogsa_loader.geometry.rotations import matrix_to_axis_angle
    from hogsa_loader.models.pom.optimize import snap_hands
    from hogsa_loader.models.pom.perturb import random_directions

    g = torch.Generator().manual_seed(seed)
    state = _state(infos, FAR, B=n)
    for s in SIDES:
        q = torch.linalg.qr(torch.randn(n, 3, 3, generator=g)).Q
        q = q * torch.sign(torch.linalg.det(q))[:, None, None]
        state.hands[s].rot = matrix_to_axis_angle(q)
        c = hand_forward(infos[s], state.hands[s]).vertices.mean(1)
        target = torch.tensor([-0.06, -0.035, 0.0]) + 0.15 * random_directions(n, g)
        state.hands[s].trans = state.hands[s].trans + target - c
    active = {s: torch.ones(n, dtype=torch.bool) for s in SIDES}
    return snap_hands(state, infos, objects, active, steps=4, margin=0.001)


def test_tiny_contactnet_training_lowers_val_loss(scene):
    from hogsa_loader.train.contactnet import ContactData, TrainConfig, train_contactnet

    infos, objects = scene
    both = _touching_grasps(infos, objects, 11, seed=1)
    train = ContactData(both.select(torch.arange(8)), [("t", "train", i) for i in range(8)])
    val = ContactData(both.select(torch.arange(8, 11)), [("v", "val", i) for i in range(3)])
    d = objects.sdf(canonical_hands(val.state, infos)["right"].vertices, val.state.obj_names, val.state.obj_arti)
    assert float(d.min(1).values.abs().max()) < 0.003  # the constructed hands touch the object
    torch.manual_seed(0)
    model, hist = train_contactnet(
        train, val, infos, objects, TrainConfig(iters=15, batch=3, points=192, lr=3e-3, val_every=15)
    )
    first, last = hist["val"][0][1], hist["val"][-1][1]
    assert last["loss"] < 0.7 * first["loss"]
    assert last["mae"] < first["mae"]


@pytest.mark.slow
def test_tiny_world_frames_to_bank(tiny_world, tmp_path):
    """Real (generated) ARCTIC frames: contact frames -> perturb -> optimise -> bank round trip."""
    from hogsa_loader.assets import ArcticRoot
    from hogsa_loader.models.pom.metrics import grasp_metrics as metrics
    from hogsa_loader.models.pom.pipeline import augment, contact_frames

    root = ArcticRoot(tiny_world)
    infos = hand_infos(root.mano_layers())
    seq = root.sequences()[0]
    sid, name = seq.split("/")
    objects = ObjectSet(root.object_templates(load_texture=False), n_points=512, sdf_voxel=0.004)
    frames = contact_frames(root, [seq], infos, objects, per_sequence=2)
    assert frames.state.batch == 2 and all(a == sid and b == name for a, b, _ in frames.sources)
    sd = root.sequence(sid, name)
    f = frames.sources[0][2]
    np.testing.assert_allclose(frames.state.hands["left"].pose[0].numpy(), sd.left.pose[f], atol=1e-6)
    aug = augment(frames, infos, objects, None, POMConfig(iters=3, n_obj_points=256), seed=0, batch=2)
    m = metrics(aug.result, infos, objects, frames.active)
    save_pose_bank(tmp_path / "bank", aug.result, frames.sources, m)
    bank = load_pose_bank(tmp_path / "bank")
    assert bank.sources == frames.sources
    torch.testing.assert_close(bank.state.hands["right"].trans, aug.result.hands["right"].trans)


def test_frames_all_keeps_the_frames_without_contact(tiny_world):
    """``frames="all"``: every frame of the sequence but the first and last 10 (ARCTIC's loaders
    never use them; evenly spaced with ``per_sequence``), those without a touching hand included;
    ``"contact"``: the frames where a hand touches; ``frame_margin=0``: the ends too."""
    from hogsa_loader.assets import ArcticRoot
    from hogsa_loader.models.pom.pipeline import contact_frames

    root = ArcticRoot(tiny_world)
    infos = hand_infos(root.mano_layers())
    objects = ObjectSet(root.object_templates(load_texture=False), n_points=512, sdf_voxel=0.004)
    seq = root.sequences()[0]
    n = len(root.sequence(*seq.split("/")).right.pose)
    every = contact_frames(root, [seq], infos, objects, frames="all")
    grasps = contact_frames(root, [seq], infos, objects)
    assert [f for *_, f in every.sources] == list(range(10, n - 10))
    touching = (every.active["right"] | every.active["left"]).tolist()
    assert 0 < sum(touching) < n - 20
    assert [f for *_, f in grasps.sources] == [f for (*_, f), t in zip(every.sources, touching) if t]
    spaced = contact_frames(root, [seq], infos, objects, per_sequence=5, frames="all")
    assert [f for *_, f in spaced.sources] == (10 + np.linspace(0, n - 21, 5).round().astype(int)).tolist()
    ends = contact_frames(root, [seq], infos, objects, frames="all", frame_margin=0)
    assert [f for *_, f in ends.sources] == list(range(n))
    with pytest.raises(ValueError, match="frames must be 'contact' or 'all'"):
        contact_frames(root, [seq], infos, objects, frames="grasps")
    with pytest.raises(ValueError, match="margin must be >= 0"):
        contact_frames(root, [seq], infos, objects, frame_margin=-1)


@pytest.mark.slow
def test_pose_bank_over_all_frames_keeps_frames_without_contact(tiny_world, tmp_path):
    """A bank built with ``frames="all"`` keeps grasps whose source frame has no touching hand
    (accepted on intersection alone) and records its frame selection."""
    from hogsa_loader.assets import ArcticRoot
    from hogsa_loader.models.pom.pipeline import contact_frames
    from hogsa_loader.train.pom_config import BankDataConfig, BankPOMConfig, BankRunConfig, PoseBankConfig
    from hogsa_loader.train.pom_jobs import build_pose_bank

    torch.manual_seed(0)
    save_contactnet(ContactNet().eval(), tmp_path / "cn", {})
    root = ArcticRoot(tiny_world)
    seq = root.sequences()[0]
    cfg = PoseBankConfig(
        data=BankDataConfig(
            root=str(tiny_world), contactnet=str(tmp_path / "cn"), sequences=(seq,), per_sequence=8, frames="all"
        ),
        pom=BankPOMConfig(iters=0),
        run=BankRunConfig(out=str(tmp_path / "bank")),
    )
    build_pose_bank(cfg, progress=False)
    infos = hand_infos(root.mano_layers())
    objects = ObjectSet(root.object_templates(load_texture=False))
    every = contact_frames(root, [seq], infos, objects, frames="all")
    free = {f for (*_, f), r, l in zip(every.sources, every.active["right"], every.active["left"]) if not (r or l)}
    kept = {f for *_, f in load_pose_bank(tmp_path / "bank").sources}
    assert kept & free and kept - free
    n = root.sequence(*seq.split("/")).num_frames
    assert all(10 <= f < n - 10 for f in kept)  # the margin of the loader's annotated ("perturb") poses
    info = json.loads((tmp_path / "bank" / "manifest.json").read_text())["info"]
    assert info["frames"] == "all" and info["frame_margin"] == 10


@pytest.mark.slow
def test_pose_bank_keeps_the_annotated_articulation(tiny_world, tmp_path):
    """The bank's start perturbation keeps each frame's annotated θ unless a range is asked for."""
    from hogsa_loader.assets import ArcticRoot
    from hogsa_loader.train.pom_config import BankDataConfig, BankPOMConfig, BankRunConfig, PoseBankConfig
    from hogsa_loader.train.pom_jobs import build_pose_bank

    torch.manual_seed(0)
    save_contactnet(ContactNet().eval(), tmp_path / "cn", {})
    root = ArcticRoot(tiny_world)
    seq = root.sequences()[0]

    def cfg(out, arti_range=None) -> PoseBankConfig:
        return PoseBankConfig(
            data=BankDataConfig(
                root=str(tiny_world), contactnet=str(tmp_path / "cn"), sequences=(seq,), per_sequence=3
            ),
            pom=BankPOMConfig(iters=1, keep_rejected=True, arti_range=arti_range),
            run=BankRunConfig(out=str(tmp_path / out)),
        )

    build_pose_bank(cfg("keep"), progress=False)
    bank = load_pose_bank(tmp_path / "keep")
    sid, name = seq.split("/")
    annotated = root.sequence(sid, name).object.arti
    expect = [annotated[f] for _, _, f in bank.sources]
    np.testing.assert_allclose(bank.state.obj_arti.numpy(), expect, atol=1e-6)
    assert json.loads((tmp_path / "keep" / "manifest.json").read_text())["info"]["perturbation"]["arti_range"] is None
    build_pose_bank(cfg("paper", arti_range=(0.3, 0.4)), progress=False)
    drawn = load_pose_bank(tmp_path / "paper").state.obj_arti
    assert bool(((drawn >= 0.3) & (drawn <= 0.4)).all())


@pytest.mark.slow
def test_pose_bank_finger_noise_moves_fingers_along_the_annotated_directions(tiny_world, tmp_path):
    """With ``finger_scale`` (and no optimisation steps) a bank grasp's fingers are its source
    frame's plus noise in the span of the sequences' principal directions; without, the
    source frame's."""
    from hogsa_loader.assets import ArcticRoot
    from hogsa_loader.train.pom_config import BankDataConfig, BankPOMConfig, BankRunConfig, PoseBankConfig
    from hogsa_loader.train.pom_jobs import bank_finger_noise, build_pose_bank

    torch.manual_seed(0)
    save_contactnet(ContactNet().eval(), tmp_path / "cn", {})
    root = ArcticRoot(tiny_world)
    seq = root.sequences()[0]
    sid, name = seq.split("/")
    annotated = root.sequence(sid, name)

    def cfg(out, finger_scale) -> PoseBankConfig:
        return PoseBankConfig(
            data=BankDataConfig(
                root=str(tiny_world), contactnet=str(tmp_path / "cn"), sequences=(seq,), per_sequence=4
            ),
            pom=BankPOMConfig(iters=0, keep_rejected=True, finger_scale=finger_scale, finger_components=3),
            run=BankRunConfig(out=str(tmp_path / out)),
        )

    build_pose_bank(cfg("plain", 0.0), progress=False)
    build_pose_bank(cfg("fingers", 0.5), progress=False)
    assert bank_finger_noise(root, [seq], cfg("plain", 0.0)) is None
    noise = bank_finger_noise(root, [seq], cfg("fingers", 0.5))
    info = json.loads((tmp_path / "fingers" / "manifest.json").read_text())["info"]["finger_noise"]
    assert info["scale"] == 0.5 and info["components"] == 3
    np.testing.assert_allclose(info["std"]["left"], noise.basis["left"].norm(dim=1).numpy(), rtol=1e-6)
    assert json.loads((tmp_path / "plain" / "manifest.json").read_text())["info"]["finger_noise"] is None
    plain, noisy = load_pose_bank(tmp_path / "plain"), load_pose_bank(tmp_path / "fingers")
    assert plain.sources == noisy.sources and len(noisy.sources) > 0
    for side in SIDES:
        source = np.stack([getattr(annotated, side).pose[f] for _, _, f in noisy.sources])
        np.testing.assert_allclose(plain.state.hands[side].pose.numpy(), source, atol=1e-6)
        delta = noisy.state.hands[side].pose.double() - torch.as_tensor(source, dtype=torch.float64)
        basis = noise.basis[side]
        assert float(delta.abs().max()) > 0.01
        coef = torch.linalg.lstsq(basis.T, delta.T).solution
        torch.testing.assert_close(coef.T @ basis, delta, atol=1e-5, rtol=0)


# --------------------------------------------------------------------------------------
# Pose bank
# --------------------------------------------------------------------------------------
def _bank(scene, tmp_path):
    infos, objects = scene
    state = _state(infos, FAR, B=3)
    state.obj_arti = torch.tensor([0.1, 0.2, 0.3])
    metrics = {
        "penetration_depth": [0.0, 0.001, 0.0],
        "intersection": [0.0, 1e-6, 0.0],
        "contact_ratio": [0.1, 0.2, 0.0],
        "accept": [1.0, 1.0, 0.0],
    }
    src = [("s01", "box_grab_01", 3), ("s01", "box_grab_01", 9), ("s02", "box_use_01", 0)]
    save_pose_bank(tmp_path / "bank", state, src, metrics, {"note": "test"})
    return state, src


def test_pose_bank_writer_refuses_nan(scene, tmp_path):
    infos, _ = scene
    state = _state(infos, FAR, B=2)
    src = [("s01", "box_grab_01", 3), ("s01", "box_grab_01", 9)]
    ok = {
        "penetration_depth": [0.0, 0.0],
        "intersection": [0.0, 0.0],
        "contact_ratio": [0.1, 0.2],
        "accept": [1.0, 1.0],
    }
    with pytest.raises(ValueError, match="NaN"):  # a bank its reader would refuse is never written
        save_pose_bank(tmp_path / "a", state, src, {**ok, "contact_ratio": [float("nan"), 0.2]})
    with pytest.raises(ValueError, match="NaN"):
        save_pose_bank(tmp_path / "b", state, src, ok, {"loss": float("nan")})
    assert not (tmp_path / "a" / "manifest.json").exists() and not (tmp_path / "b" / "poses.safetensors").exists()


def test_pose_bank_roundtrip(scene, tmp_path):
    state, src = _bank(scene, tmp_path)
    bank = load_pose_bank(tmp_path / "bank")
    assert len(bank) == 3 and bank.sources == src and bank.info["note"] == "test"
    assert bank.state.obj_names == ["twobox"] * 3
    for s in SIDES:
        for k in ("rot", "pose", "trans", "betas"):
            torch.testing.assert_close(getattr(bank.state.hands[s], k), getattr(state.hands[s], k))
    torch.testing.assert_close(bank.state.obj_arti, state.obj_arti)
    torch.testing.assert_close(bank.metrics["contact_ratio"], torch.tensor([0.1, 0.2, 0.0]))
    assert load_pose_bank(tmp_path / "bank" / "manifest.json").state.batch == 3


def test_pose_bank_bad_files(scene, tmp_path):
    from safetensors.torch import load_file, save, save_file

    _bank(scene, tmp_path)
    d = tmp_path / "bank"
    man_path, t_path = d / "manifest.json", d / "poses.safetensors"
    man = json.loads(man_path.read_text())
    tensors = load_file(str(t_path))

    def expect(match):
        with pytest.raises(AssetError, match=match):
            load_pose_bank(d)

    man_path.write_text(json.dumps({**man, "schema_version": 2}))
    expect("schema_version")
    man_path.write_text(json.dumps({**man, "schema": "other"}))
    expect("not a pose bank")
    man_path.write_text(json.dumps({**man, "entries": man["entries"][:2]}))
    expect("entries")
    man_path.write_text("{not json")
    expect("malformed JSON")
    man_path.write_text(json.dumps({**man, "info": {"loss": float("nan")}}))
    expect("NaN is not a JSON value")
    bad = dict(tensors)
    bad["right_pose"] = bad["right_pose"][:, :10].contiguous()
    save_file(bad, str(t_path))
    man_path.write_text(json.dumps(man))
    expect("poses.safetensors.*sha256 does not match")  # the checksum catches any replaced tensors file
    # a manifest without a checksum (pre-1.0) is refused
    man_path.write_text(json.dumps({k: v for k, v in man.items() if k != "tensors_sha256"}))
    expect("manifest.json.*tensors_sha256")

    def put(blob: bytes) -> None:  # a tensors file with a matching checksum: the content checks still hold
        t_path.write_bytes(blob)
        man_path.write_text(json.dumps({**man, "tensors_sha256": hashlib.sha256(blob).hexdigest()}))

    put(t_path.read_bytes())
    expect("right_pose.*shape")
    bad = dict(tensors)
    bad["obj_trans"] = bad["obj_trans"].clone()
    bad["obj_trans"][0, 0] = float("nan")
    put(save(bad))
    expect("NaN")
    bad = {k: v for k, v in tensors.items() if k != "left_betas"}
    put(save(bad))
    expect("left_betas.*missing")
    put(b"garbage" * 3)
    expect("not a valid safetensors file")
    t_path.unlink()
    expect("missing")
    man_path.unlink()
    expect("missing")
