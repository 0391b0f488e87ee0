"""Tests of the HOGS Gaussian models (hogsa_loader.models.gaussians): mesh-bound GaMeS /
GaussianAvatars Gaussians, hand and object parts, free 3DGS Gaussians, scene composition
and rendering, checkpoints."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from hogsa_loader.assets.hands import MANOLayer, subdivide_model
from hogsa_loader.assets.objects import ObjectTemplate
from hogsa_loader.assets.objects.articulated import articulation_matrix
from hogsa_loader.errors import AssetError
from hogsa_loader.geometry.quaternion import matrix_to_quat, quat_to_matrix
from hogsa_loader.geometry.rotations import axis_angle_to_matrix
from hogsa_loader.models.gaussians import (
    BindingConfig,
    FreeGaussians,
    GaussianSet,
    HandGaussians,
    MeshGaussians,
    ObjectGaussians,
    avatar_gaussians_from_faces,
    compose,
    gaussians_from_faces,
    headlight_colors,
    load_part,
    load_state,
    render_scene,
    save_part,
    surface_samples,
    template_hash,
)
from hogsa_loader.models.gaussians.checkpoint import MANIFEST_FILE, TENSORS_FILE
from hogsa_loader.models.gaussians.gaussian_set import sh_to_rgb
from hogsa_loader.models.gaussians.mesh_bound import face_frames, face_moment_scales
from hogsa_loader.render.gaussians import render_gaussians
from hogsa_loader.render.mesh_raster import camera_look_at
from hogsa_loader.render.settings import RenderSettings, SplatInputs

D64 = torch.float64


# --------------------------------------------------------------------------------------
# helpers
# --------------------------------------------------------------------------------------


def _random_rotation(seed: int, dtype=D64) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    q, r = torch.linalg.qr(torch.randn(3, 3, generator=g, dtype=D64))
    q = q * torch.sign(torch.diagonal(r))
    if torch.det(q) < 0:
        q[:, 0] = -q[:, 0]
    return q.to(dtype)


def _bumpy_sphere(dtype=D64) -> tuple[torch.Tensor, torch.Tensor]:
    """A small closed mesh with triangles of varied shapes and sizes."""
    import trimesh

    s = trimesh.creation.icosphere(subdivisions=1, radius=0.05)
    v = torch.tensor(s.vertices, dtype=D64)
    g = torch.Generator().manual_seed(3)
    v = v * (1.0 + 0.25 * torch.rand(v.shape[0], 1, generator=g, dtype=D64))
    return v.to(dtype), torch.tensor(s.faces, dtype=torch.long)


CUBE_COLOURS = {  # face key -> RGB
    "+x": (0.9, 0.1, 0.1),
    "-x": (0.1, 0.9, 0.1),
    "+y": (0.1, 0.1, 0.9),
    "-y": (0.9, 0.9, 0.1),
    "+z": (0.9, 0.2, 0.8),
    "-z": (0.1, 0.8, 0.9),
}


def cube_template(half: float = 0.05, n: int = 12, colours=CUBE_COLOURS, name: str = "cube") -> ObjectTemplate:
    """A textured cube: each face an n x n grid chart mapped to one solid-colour atlas cell."""
    cell, margin = 16, 4
    tex = np.zeros((2 * cell, 3 * cell, 3), np.uint8)
    verts, faces, uvs = [], [], []
    g = np.linspace(-half, half, n + 1)
    a, b = np.meshgrid(g, g, indexing="xy")
    a, b = a.reshape(-1), b.reshape(-1)
    quads = []
    for i in range(n):
        for j in range(n):
            p = i * (n + 1) + j
            quads += [[p, p + 1, p + n + 2], [p, p + n + 2, p + n + 1]]
    quads = np.array(quads)
    for idx, (key, rgb) in enumerate(colours.items()):
        axis, sign = "xyz".index(key[1]), 1.0 if key[0] == "+" else -1.0
        others = [d for d in range(3) if d != axis]
        v = np.zeros(((n + 1) ** 2, 3))
        v[:, axis] = sign * half
        v[:, others[0]], v[:, others[1]] = a, b
        cx, cy = (idx % 3) * cell, (idx // 3) * cell
        tex[cy : cy + cell, cx : cx + cell] = np.round(np.array(rgb) * 255).astype(np.uint8)
        fu = (a + half) / (2 * half)
        fv = (b + half) / (2 * half)
        u = (cx + margin + fu * (cell - 2 * margin)) / tex.shape[1]
        vv = 1.0 - (cy + margin + (1 - fv) * (cell - 2 * margin)) / tex.shape[0]
        faces.append(quads + sum(x.shape[0] for x in verts))
        verts.append(v)
        uvs.append(np.stack([u, vv], 1))
    verts, faces, uvs = np.concatenate(verts), np.concatenate(faces), np.concatenate(uvs)
    z3 = np.zeros((0, 3))
    return ObjectTemplate(
        name=name,
        verts=verts,
        faces=faces,
        parts=np.ones(verts.shape[0], np.int64),
        kp_top=np.zeros((16, 3)),
        kp_bottom=np.zeros((16, 3)),
        bbox_top=np.zeros((8, 3)),
        bbox_bottom=np.zeros((8, 3)),
        mocap_top=z3,
        mocap_bottom=z3,
        sub_top=np.zeros((300, 3)),
        sub_bottom=np.zeros((300, 3)),
        diameter=2 * math.sqrt(3) * half,
        tex_verts=verts,
        tex_faces=faces,
        tex_uv=uvs,
        texture=tex,
        tex_parts=np.ones(verts.shape[0], np.int64),
    )


def _head_on_camera(dist: float, f: float, size: int) -> tuple[torch.Tensor, torch.Tensor]:
    vm = camera_look_at((0.0, 0.0, dist), (0.0, 0.0, 0.0), (0.0, 1.0, 0.0))
    K = torch.tensor([[f, 0.0, size / 2], [0.0, f, size / 2], [0.0, 0.0, 1.0]])
    return vm[None, None], K[None, None]


def _pixel_centres(size: int) -> torch.Tensor:
    return torch.arange(size, dtype=torch.float64) + 0.5


@pytest.fixture(scope="module")
def right_hand(hand_pair):
    return hand_pair[0]


@pytest.fixture(scope="module")
def box_template():
    from hogsa_world.objects.catalogue import make_object

    return make_object("box")


# --------------------------------------------------------------------------------------
# quaternions and the per-face construction
# --------------------------------------------------------------------------------------


def test_matrix_quat_round_trip_including_half_turns():
    g = torch.Generator().manual_seed(0)
    q = torch.randn(500, 4, generator=g, dtype=D64)
    # rotations by (almost) pi about random axes, where a naive w-based formula fails
    axes = torch.nn.functional.normalize(torch.randn(20, 3, generator=g, dtype=D64), dim=-1)
    q = torch.cat(
        [
            q,
            torch.cat([torch.zeros(20, 1, dtype=D64), axes], 1),
            torch.cat([torch.full((20, 1), 1e-7, dtype=D64), axes], 1),
        ]
    )
    q = torch.nn.functional.normalize(q, dim=-1)
    out = matrix_to_quat(quat_to_matrix(q))
    assert (out[:, 0] >= 0).all()
    err = torch.minimum((out - q).norm(dim=-1), (out + q).norm(dim=-1))
    assert err.max() < 1e-9
    assert torch.allclose(quat_to_matrix(out), quat_to_matrix(q), atol=1e-12)


def test_games_single_triangle_explicit_values():
    # right triangle in the xy plane: e = x, t = y, n = z
    tri = torch.tensor([[[0.0, 0.0, 0.0], [2.0, 0.0, 0.0], [0.0, 1.0, 0.0]]], dtype=D64)
    faces = torch.tensor([[0, 1, 2]])
    bary = torch.tensor([[[0.2, 0.3, 0.5]]], dtype=D64)
    means, quats, scales = gaussians_from_faces(tri, faces, bary, torch.tensor([[1.5]], dtype=D64), normal_eps=1e-8)
    assert torch.allclose(means[0, 0], torch.tensor([0.6, 0.5, 0.0], dtype=D64))
    assert torch.allclose(quat_to_matrix(quats[0, 0]), torch.eye(3, dtype=D64), atol=1e-12)
    # sigma_e^2 = 1/12 * sum (x_i - 2/3)^2 = 2/9, sigma_t^2 = 1/18
    expect = torch.tensor([1.5 * math.sqrt(2 / 9) + 1e-8, 1.5 * math.sqrt(1 / 18) + 1e-8, 1e-8], dtype=D64)
    assert torch.allclose(scales[0, 0], expect, rtol=1e-9, atol=0)


def test_moment_scales_are_the_std_of_uniform_points_on_the_triangle():
    g = torch.Generator().manual_seed(1)
    tri = torch.randn(1, 3, 3, generator=g, dtype=D64)
    rot, _ = face_frames(tri)
    sig = face_moment_scales(tri, rot)[0]
    u = torch.rand(400_000, 2, generator=g, dtype=D64)
    flip = u.sum(1) > 1
    u[flip] = 1 - u[flip]
    pts = tri[0, 0] + u[:, :1] * (tri[0, 1] - tri[0, 0]) + u[:, 1:] * (tri[0, 2] - tri[0, 0])
    mc = (pts @ rot[0][:, :2]).std(0)
    assert torch.allclose(sig, mc, rtol=5e-3)


@pytest.mark.parametrize("variant", ["games", "avatars"])
def test_means_on_faces_weights_sum_to_one(variant):
    v, f = _bumpy_sphere()
    m = MeshGaussians(v, f, k=3, sh_degree=1, variant=variant, dtype=D64)
    with torch.no_grad():
        if variant == "games":
            m.bary_logits.normal_(0.0, 2.0, generator=torch.Generator().manual_seed(0))
    w = m.barycentric_weights()
    assert torch.allclose(w.sum(-1), torch.ones(w.shape[:2], dtype=D64))
    assert (w > 0).all()
    gs = m(v[None])
    tri = v[f]  # (F, 3, 3)
    mu = gs.means[0].reshape(f.shape[0], 3, 3)
    # in the face plane
    n = torch.nn.functional.normalize(torch.linalg.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), dim=-1)
    assert ((mu - tri[:, None, 0]) * n[:, None]).sum(-1).abs().max() < 1e-12
    # barycentric coordinates recovered from the means are the weights (inside the triangle)
    A = torch.stack([tri[:, 0], tri[:, 1], tri[:, 2]], -1)  # columns p0, p1, p2
    rec = torch.linalg.lstsq(A[:, None].expand(-1, 3, 3, 3), mu[..., None]).solution[..., 0]
    assert torch.allclose(rec, w, atol=1e-9)
    assert (rec > 0).all()
    # the normals of the set are smooth shading normals: area-weighted vertex normals
    # (accumulated face by face here) interpolated with the Gaussians' weights
    vn = torch.zeros_like(v)
    for fi in range(f.shape[0]):
        a, b, c = v[f[fi]]
        vn[f[fi]] += torch.linalg.cross(b - a, c - a)
    ref = torch.einsum("fkc,fcd->fkd", w, vn[f])
    ref = ref / ref.norm(dim=-1, keepdim=True)
    assert torch.allclose(gs.normals[0].reshape(-1, 3, 3), ref, atol=1e-12)
    assert not gs.normals.requires_grad  # shading never deforms the geometry


@pytest.mark.parametrize("variant", ["games", "avatars"])
def test_rigid_motion_is_equivariant(variant):
    v, f = _bumpy_sphere()
    m = MeshGaussians(v, f, k=2, sh_degree=0, variant=variant, dtype=D64)
    with torch.no_grad():  # move away from the initial state so that every parameter matters
        for p in m.parameters():
            p.add_(0.1 * torch.randn(p.shape, generator=torch.Generator().manual_seed(p.numel()), dtype=D64))
    Q = _random_rotation(5)
    t = torch.tensor([0.3, -0.2, 0.5], dtype=D64)
    verts = m.canonical_vertices().detach()[None]
    a = m(verts)
    b = m(verts @ Q.T + t)
    assert torch.allclose(b.means, a.means @ Q.T + t, atol=1e-12)
    assert torch.allclose(quat_to_matrix(b.quats), Q @ quat_to_matrix(a.quats), atol=1e-10)
    assert torch.allclose(b.scales, a.scales, rtol=1e-10)
    assert torch.allclose(b.normals, a.normals @ Q.T, atol=1e-10)


@pytest.mark.parametrize("variant", ["games", "avatars"])
def test_scales_follow_face_size(variant):
    v, f = _bumpy_sphere()
    eps = 1e-8
    m = MeshGaussians(v, f, k=2, sh_degree=0, variant=variant, normal_eps=eps, dtype=D64)
    a = m(v[None])
    b = m(2.5 * v[None])
    assert torch.allclose(b.means, 2.5 * a.means, atol=1e-14)
    if variant == "games":  # in-plane scales x 2.5, the normal epsilon stays
        assert torch.allclose(b.scales - eps, 2.5 * (a.scales - eps), rtol=1e-9, atol=1e-15)
        assert torch.allclose(b.scales[..., 2], torch.full_like(b.scales[..., 2], eps))
    else:  # everything in units of the face scale
        assert torch.allclose(b.scales, 2.5 * a.scales, rtol=1e-9)


def test_avatars_start_equal_to_games_and_follow_their_formula():
    v, f = _bumpy_sphere()
    games = MeshGaussians(v, f, k=2, sh_degree=0, variant="games", dtype=D64)
    av = MeshGaussians(v, f, k=2, sh_degree=0, variant="avatars", dtype=D64)
    Q, t = _random_rotation(9), torch.tensor([0.1, 0.2, 0.3], dtype=D64)
    for verts in (v[None], v[None] @ Q.T + t):
        a, b = games(verts), av(verts)
        assert torch.allclose(a.means, b.means, atol=1e-12)
        assert torch.allclose(quat_to_matrix(a.quats), quat_to_matrix(b.quats), atol=1e-10)
        assert torch.allclose(a.scales, b.scales, rtol=1e-9)
    # explicit GaussianAvatars formula for arbitrary local parameters on one face
    g = torch.Generator().manual_seed(2)
    lm, lq, ls = (
        torch.randn(1, 1, 3, generator=g, dtype=D64),
        torch.randn(1, 1, 4, generator=g, dtype=D64),
        torch.randn(1, 1, 3, generator=g, dtype=D64),
    )
    tri = torch.tensor([[[0.0, 0.0, 0.0], [0.0, 0.0, 3.0], [1.0, 0.0, 1.0]]], dtype=D64)  # first edge along z
    mu, q, s = avatar_gaussians_from_faces(tri, torch.tensor([[0, 1, 2]]), lm, lq, ls)
    e, n = torch.tensor([0.0, 0.0, 1.0], dtype=D64), torch.tensor([0.0, 1.0, 0.0], dtype=D64)
    Rf = torch.stack([e, torch.linalg.cross(n, e), n], 1)
    kf = (3.0 + 1.0) / 2  # (edge length + height) / 2
    c = tri[0].mean(0)
    assert torch.allclose(mu[0, 0], kf * Rf @ lm[0, 0] + c)
    assert torch.allclose(s[0, 0], kf * torch.exp(ls[0, 0]))
    assert torch.allclose(quat_to_matrix(q[0, 0]), Rf @ quat_to_matrix(lq[0, 0]), atol=1e-12)


@pytest.mark.parametrize("variant", ["games", "avatars"])
def test_gradients_reach_every_parameter_through_the_renderer(variant):
    tpl = cube_template(half=0.05, n=2)
    m = MeshGaussians(tpl.verts, tpl.faces, k=2, sh_degree=1, variant=variant, init_opacity=0.6)
    vm, K = _head_on_camera(0.4, 60.0, 32)
    Q = axis_angle_to_matrix(torch.tensor([0.4, 0.5, 0.0]))
    gs = m((m.canonical_vertices() @ Q.T)[None])
    out = render_gaussians(
        SplatInputs(gs.means, gs.quats, gs.scales, gs.opacities, gs.sh, vm, K, 32, 32),
        RenderSettings(sh_degree=1, render_mode="RGB+ED"),
    )
    w = torch.rand(out.rgb.shape, generator=torch.Generator().manual_seed(0))
    ((out.rgb * w).sum() + out.depth.sum()).backward()
    for name, p in m.named_parameters():
        assert p.grad is not None and torch.isfinite(p.grad).all(), name
        assert p.grad.abs().sum() > 0, f"no gradient reaches {name}"


def test_avatar_regularisers_follow_gaussianavatars():
    v, f = _bumpy_sphere()
    m = MeshGaussians(v, f, k=1, sh_degree=0, variant="avatars", dtype=D64)
    reg = m.regularisers()
    assert set(reg) == {"offset", "xyz", "scale"}
    assert all(r.item() == 0.0 for r in reg.values())  # init: inside the face, scales < 0.6 k_f
    with torch.no_grad():
        m.local_means[0, 0] = torch.tensor([3.0, 0.0, 0.0], dtype=D64)  # 2 face units too far
        m.local_log_scales[1, 0] = torch.log(torch.tensor([1.0, 0.6, 0.6], dtype=D64))
    reg = m.regularisers()
    assert reg["xyz"].item() == pytest.approx(2.0 / f.shape[0])
    assert reg["scale"].item() == pytest.approx(0.4 / f.shape[0])


def test_offset_regulariser_is_mean_distance_to_template():
    v, f = _bumpy_sphere()
    m = MeshGaussians(v, f, k=1, sh_degree=0, dtype=D64)
    assert m.offset_regulariser().item() == 0.0
    with torch.no_grad():
        m.offsets[:5] = torch.tensor([0.0, 0.003, 0.004], dtype=D64)
    expect = 5 * 0.005 / v.shape[0]
    assert m.offset_regulariser().item() == pytest.approx(expect, rel=1e-12)
    assert torch.allclose((m.canonical_vertices() - v).norm(dim=-1).mean(), m.offset_regulariser())


# --------------------------------------------------------------------------------------
# hands
# --------------------------------------------------------------------------------------


def _hand_pose(B: int, seed: int) -> dict:
    g = torch.Generator().manual_seed(seed)
    return dict(
        global_orient=0.6 * torch.randn(B, 3, generator=g),
        hand_pose=0.4 * torch.randn(B, 45, generator=g),
        betas=torch.randn(B, 10, generator=g),
        transl=0.1 * torch.randn(B, 3, generator=g),
    )


@pytest.mark.parametrize("levels", [0, 1])
def test_hand_gaussians_equal_recomputation_from_mano_layer(right_hand, levels):
    hand = HandGaussians(right_hand, BindingConfig(subdivide_levels=levels, k=2, sh_degree=1))
    model = subdivide_model(right_hand, levels) if levels else right_hand
    assert hand.splats.num_faces == model.faces.shape[0] == right_hand.faces.shape[0] * 4**levels
    pose = _hand_pose(2, 0)
    ref_verts = MANOLayer(model)(**pose).vertices
    gs = hand(**pose)
    assert torch.allclose(hand.posed_vertices(**pose), ref_verts, atol=1e-6)
    faces = torch.as_tensor(model.faces)
    ref = gaussians_from_faces(ref_verts, faces, hand.splats.barycentric_weights(), hand.splats.scale_factor())
    assert torch.allclose(gs.means, ref.means, atol=1e-6)
    assert torch.allclose(quat_to_matrix(gs.quats), quat_to_matrix(ref.quats), atol=1e-4)
    assert torch.allclose(gs.scales, ref.scales, rtol=1e-4, atol=1e-9)
    assert gs.part_ids.unique().tolist() == [0] and hand.part_type == "hand_right"
    # initial colours: the model's skin albedo interpolated at each Gaussian
    vc = torch.as_tensor(model.vertex_colors, dtype=torch.float32)
    expect = torch.einsum("fkc,fcd->fkd", hand.splats.init_bary, vc[faces]).reshape(-1, 3)
    assert torch.allclose(sh_to_rgb(hand.splats.sh_dc[:, 0]), expect, atol=1e-5)
    assert (hand.splats.sh_rest == 0).all()


def test_hand_offsets_are_added_before_lbs_and_regularised(right_hand):
    hand = HandGaussians(right_hand, BindingConfig(k=1, sh_degree=0))
    assert hand.offset_regulariser().item() == 0.0
    g = torch.Generator().manual_seed(4)
    with torch.no_grad():
        hand.splats.offsets.copy_(0.002 * torch.randn(hand.splats.offsets.shape, generator=g))
    assert hand.offset_regulariser().item() > 1e-3
    pose = _hand_pose(2, 1)
    offset_model = right_hand.replace(v_template=right_hand.v_template + hand.splats.offsets.detach().double().numpy())
    ref_verts = MANOLayer(offset_model)(**pose).vertices  # offsets also move the regressed joints
    assert torch.allclose(hand.posed_vertices(**pose), ref_verts, atol=2e-6)
    ref = gaussians_from_faces(
        ref_verts, hand.binding_faces, hand.splats.barycentric_weights(), hand.splats.scale_factor()
    )
    assert torch.allclose(hand(**pose).means, ref.means, atol=2e-6)
    # gradients of L_R and of the posed means reach the offsets
    (hand(**pose).means.sum() + hand.offset_regulariser()).backward()
    assert hand.splats.offsets.grad.abs().sum() > 0


def test_left_hand_part_and_layer_input(hand_pair):
    left = hand_pair[1]
    layer = MANOLayer(left, flat_hand_mean=True)
    hand = HandGaussians(layer, BindingConfig(variant="avatars", k=1, sh_degree=0))
    assert hand.part_type == "hand_left" and hand.part_id == 1 and hand.layer is layer
    assert hand.config()["flat_hand_mean"] is True
    gs = hand(hand_pose=torch.zeros(1, 45))
    assert torch.allclose(
        hand.posed_vertices(hand_pose=torch.zeros(1, 45)), layer(hand_pose=torch.zeros(1, 45)).vertices
    )
    assert gs.part_ids.unique().tolist() == [1]


# --------------------------------------------------------------------------------------
# objects
# --------------------------------------------------------------------------------------


@pytest.mark.parametrize("variant", ["games", "free"])
def test_object_top_part_rotates_with_angle_bottom_does_not(box_template, variant):
    obj = ObjectGaussians(box_template, BindingConfig(variant=variant, k=1, sh_degree=0), dtype=D64)
    assert obj.binding_mesh == "mesh_tex as is" and obj.part_id == 2
    if variant == "games":
        top = obj.binding_is_top[obj.binding_faces].all(1).repeat_interleave(obj.k)
        bottom = (~obj.binding_is_top[obj.binding_faces]).all(1).repeat_interleave(obj.k)
    else:
        top, bottom = obj.binding_is_top[obj.splats.binding], ~obj.binding_is_top[obj.splats.binding]
    assert top.sum() > 100 and bottom.sum() > 100
    theta = torch.tensor([0.0, 0.8], dtype=D64)
    omega = torch.tensor([[0.0, 0.0, 0.0], [0.3, -0.2, 0.5]], dtype=D64)
    transl = torch.tensor([[0.0, 0.0, 0.0], [0.1, 0.0, -0.2]], dtype=D64)
    rest = obj(theta[:1], omega[:1], transl[:1])
    gs = obj(theta, omega, transl)
    assert torch.allclose(gs.means[0], rest.means[0])
    Rg = axis_angle_to_matrix(omega[1])
    Rt = Rg @ articulation_matrix(theta[1:])[0]
    m0, R0 = rest.means[0], quat_to_matrix(rest.quats[0])
    assert torch.allclose(gs.means[1, top], m0[top] @ Rt.T + transl[1], atol=1e-12)
    assert torch.allclose(gs.means[1, bottom], m0[bottom] @ Rg.T + transl[1], atol=1e-12)
    R1 = quat_to_matrix(gs.quats[1])
    assert torch.allclose(R1[top], Rt @ R0[top], atol=1e-9)
    assert torch.allclose(R1[bottom], Rg @ R0[bottom], atol=1e-9)
    assert torch.allclose(gs.scales[1], rest.scales[0], rtol=1e-9)
    # the lid really moved
    assert (gs.means[1, top] - (m0[top] @ Rg.T + transl[1])).norm(dim=-1).max() > 0.03


def test_object_subdivided_texture_binding_keeps_geometry(box_template):
    obj = ObjectGaussians(box_template, BindingConfig(subdivide_levels=1, k=1, sh_degree=0))
    assert obj.binding_mesh == "mesh_tex subdivide_mesh levels=1"
    assert obj.splats.num_faces == 4 * box_template.tex_faces.shape[0]
    assert obj.template_hash == template_hash(box_template.verts, box_template.faces)
    theta, omega, t = torch.tensor([0.5]), torch.tensor([[0.1, 0.2, 0.3]]), torch.tensor([[0.0, 0.1, 0.0]])
    from hogsa_loader.assets.objects import articulate

    ref = articulate(
        torch.as_tensor(box_template.verts)[None], torch.as_tensor(box_template.parts == 0), theta, omega, t
    )
    assert torch.allclose(obj.posed_geometry(theta, omega, t), ref)
    # Gaussian colours are the texture sampled at their uv: the atlas is not flat grey
    rgb = sh_to_rgb(obj.splats.sh_dc[:, 0])
    assert rgb.std(0).min() > 0.05


@pytest.mark.parametrize("levels", [0, 1])
def test_object_uv_seam_copies_share_their_offset(box_template, levels):
    """The textured binding mesh repeats vertices along UV seams; their offsets are tied
    (one mean offset per position), so optimised offsets never open the seams."""
    obj = ObjectGaussians(box_template, BindingConfig(subdivide_levels=levels, k=1, sh_degree=0), dtype=D64)
    m = obj.splats
    tpl = m.template
    assert m.weld_group is not None and int(m.weld_count.max()) > 1  # the box has seam copies
    with torch.no_grad():
        m.offsets.copy_(1e-3 * torch.randn(tpl.shape, generator=torch.Generator().manual_seed(0), dtype=D64))
    cv = m.canonical_vertices()
    groups, inv = torch.unique(tpl, dim=0, return_inverse=True)
    _, inv_cv = torch.unique(cv, dim=0, return_inverse=True)
    # copies of a position stay together, distinct positions stay distinct: the same partition
    pairs = torch.unique(torch.stack([inv, inv_cv], 1), dim=0)
    assert pairs.shape[0] == groups.shape[0] == int(inv_cv.max()) + 1
    members = (m.weld_group == int(torch.nonzero(m.weld_count > 1)[0])).nonzero().squeeze(-1)
    assert torch.allclose(cv[members[0]] - tpl[members[0]], m.offsets[members].mean(0))  # the mean of their offsets
    cv.sum().backward()
    assert torch.allclose(m.offsets.grad, torch.ones_like(m.offsets))  # every copy still gets its gradient
    # a mesh without repeated positions is untouched
    v, f = _bumpy_sphere()
    sphere = MeshGaussians(v, f, k=1, sh_degree=0, dtype=D64)
    assert sphere.weld_group is None


def test_checkpoints_without_weld_seams_are_refused(box_template, tmp_path):
    """New checkpoints record ``weld_seams`` and load welded; a pre-1.0 checkpoint whose config
    lacks it (trained with one free offset per vertex) is refused with a clear error."""
    obj = ObjectGaussians(box_template, BindingConfig(k=1, sh_degree=0))
    with torch.no_grad():
        obj.splats.offsets.copy_(
            1e-3 * torch.randn(obj.splats.offsets.shape, generator=torch.Generator().manual_seed(1))
        )
    save_part(obj, tmp_path / "new")
    assert json.loads((tmp_path / "new" / MANIFEST_FILE).read_text())["config"]["weld_seams"] is True
    new = load_part(tmp_path / "new", box_template)
    assert torch.equal(new.canonical_vertices(), obj.canonical_vertices())
    # the same file without weld_seams in its config
    save_part(obj, tmp_path / "old")
    man = json.loads((tmp_path / "old" / MANIFEST_FILE).read_text())
    del man["config"]["weld_seams"]
    (tmp_path / "old" / MANIFEST_FILE).write_text(json.dumps(man))
    with pytest.raises(AssetError, match=r"manifest.json: config.weld_seams is missing from the checkpoint.*train"):
        load_part(tmp_path / "old", box_template)
    with pytest.raises(AssetError, match=r"config.weld_seams is missing from the checkpoint"):
        load_state(ObjectGaussians(box_template, BindingConfig(k=1, sh_degree=0)), tmp_path / "old")


# --------------------------------------------------------------------------------------
# free Gaussians
# --------------------------------------------------------------------------------------


def test_free_hand_follows_mano_and_moves_rigidly(right_hand):
    hand = HandGaussians(right_hand, BindingConfig(variant="free", sh_degree=0), flat_hand_mean=True)
    assert hand.num_gaussians == right_hand.num_verts  # one per vertex, bound to it
    assert torch.equal(hand.splats.binding, torch.arange(right_hand.num_verts))
    layer = MANOLayer(right_hand, flat_hand_mean=True)
    # zero pose: canonical
    rest = hand()
    assert torch.allclose(rest.means[0], hand.splats.means, atol=1e-7)
    assert torch.allclose(quat_to_matrix(rest.quats[0]), quat_to_matrix(hand.splats.quats), atol=1e-6)
    # any pose: a Gaussian initialised at a vertex moves exactly like the vertex
    pose = _hand_pose(2, 3)
    assert torch.allclose(hand(**pose).means, layer(**pose).vertices, atol=1e-6)
    # pure global rotation + translation: rigid
    g = torch.Generator().manual_seed(1)
    with torch.no_grad():  # random orientations so that the rotation check is not trivial
        hand.splats.quats.copy_(torch.randn(hand.splats.quats.shape, generator=g))
    rest = hand()
    aa, t = torch.tensor([[0.4, -1.1, 0.7]]), torch.tensor([[0.05, -0.1, 0.2]])
    moved = hand(global_orient=aa, transl=t)
    Q = axis_angle_to_matrix(aa)[0]
    d = moved.means[0] - rest.means[0] @ Q.T
    assert (d - d.mean(0)).abs().max() < 1e-6  # same translation for every Gaussian
    assert torch.allclose(quat_to_matrix(moved.quats[0]), Q @ quat_to_matrix(rest.quats[0]), atol=1e-5)
    assert torch.allclose(moved.scales, rest.scales)
    assert torch.allclose(moved.normals[0], rest.normals[0] @ Q.T, atol=1e-5)


def test_free_faces_init_matches_games_at_rest(box_template):
    games = ObjectGaussians(box_template, BindingConfig(variant="games", k=2, sh_degree=0))
    free = ObjectGaussians(box_template, BindingConfig(variant="free", free_init="faces", k=2, sh_degree=0))
    a = games(torch.zeros(1), torch.zeros(1, 3))
    b = free(torch.zeros(1), torch.zeros(1, 3))
    assert torch.allclose(a.means, b.means, atol=1e-6)
    assert torch.allclose(a.scales, b.scales, rtol=1e-5)
    assert torch.allclose(quat_to_matrix(a.quats), quat_to_matrix(b.quats), atol=1e-5)
    assert torch.allclose(games.splats.sh_dc, free.splats.sh_dc, atol=1e-5)


def test_surface_samples_vertices_cover_each_used_vertex_once():
    faces = torch.tensor([[0, 1, 2], [2, 1, 4]])  # vertex 3 unused
    face_idx, bary = surface_samples(faces, 5, "vertices")
    corners = faces[face_idx, bary.argmax(1)]
    assert corners.tolist() == [0, 1, 2, 4]
    assert face_idx.tolist() == [0, 0, 0, 1]
    v = torch.randn(5, 3, dtype=D64)
    fg = FreeGaussians(v, faces, sh_degree=0)
    assert fg.binding.tolist() == [0, 1, 2, 4]
    assert torch.allclose(fg.means.double(), v[[0, 1, 2, 4]], atol=1e-6)


# --------------------------------------------------------------------------------------
# scene composition and rendering
# --------------------------------------------------------------------------------------


def _toy_set(B: int, N: int, deg: int, part: int, seed: int) -> GaussianSet:
    g = torch.Generator().manual_seed(seed)
    sh = torch.randn(N, (deg + 1) ** 2, 3, generator=g)
    return GaussianSet(
        means=torch.randn(B, N, 3, generator=g) * 0.05 + torch.tensor([0.0, 0.0, 0.5]),
        quats=torch.randn(B, N, 4, generator=g),
        scales=torch.full((B, N, 3), 0.01),
        opacities=torch.full((B, N), 0.5),
        sh=sh[None].expand(B, N, -1, 3),
        sh_degree=deg,
        part_ids=torch.full((N,), part, dtype=torch.long),
    )


def test_compose_pads_sh_keeps_part_ids_and_broadcasts():
    a, b = _toy_set(2, 5, 0, 0, 0), _toy_set(1, 7, 2, 2, 1)
    s = compose([a, b])
    assert s.batch_size == 2 and s.num_gaussians == 12 and s.sh_degree == 2
    assert s.part_ids.tolist() == [0] * 5 + [2] * 7
    assert torch.equal(s.sh[:, :5, :1], a.sh) and (s.sh[:, :5, 1:] == 0).all()
    assert torch.equal(s.means[1, 5:], b.means[0])
    with pytest.raises(ValueError, match="SH degrees"):
        compose([a, b], sh_policy="strict")
    with pytest.raises(ValueError):
        compose([a, _toy_set(3, 2, 0, 1, 2)])
    # zero padding does not change the rendered colours
    vm = torch.eye(4)[None, None].expand(2, 1, 4, 4)
    K = torch.tensor([[40.0, 0, 16], [0, 40.0, 16], [0, 0, 1]])[None, None].expand(2, 1, 3, 3)
    alone = render_gaussians(
        SplatInputs(a.means, a.quats, a.scales, a.opacities, a.sh, vm, K, 32, 32),
        RenderSettings(sh_degree=0, render_mode="RGB+ED"),
    )
    padded = render_scene(compose([a, _toy_set(2, 0, 2, 1, 3)]), vm, K, 32, 32)
    assert torch.allclose(alone.rgb, padded.rgb, atol=1e-6)


def test_render_scene_of_an_empty_set():
    """No Gaussians: background only, zero alpha, no parts (it used to be refused)."""
    vm = torch.eye(4)[None, None]
    K = torch.tensor([[40.0, 0, 16], [0, 40.0, 16], [0, 0, 1]])[None, None]
    bg = torch.tensor([0.2, 0.4, 0.6])[None, None]
    out = render_scene(_toy_set(1, 0, 0, 0, 0), vm, K, 16, 16, backgrounds=bg)
    assert (out.alpha == 0).all() and torch.allclose(out.rgb, bg[:, :, None, None].expand(1, 1, 16, 16, 3))
    assert out.part_alpha is None or out.part_alpha.shape[-1] == 0


def test_headlight_shading_uses_normal_and_view_direction():
    gs = _toy_set(1, 3, 1, 0, 4)
    gs.means = torch.tensor([[[0.0, 0.0, 1.0], [0.0, 0.0, 1.0], [0.0, 0.0, 1.0]]])
    gs.normals = torch.tensor([[[0.0, 0.0, -1.0], [1.0, 0.0, 0.0], [0.0, 0.6, 0.8]]])
    vm = torch.eye(4)[None, None]  # camera at the origin looking down +z
    out = headlight_colors(gs, vm, ambient=0.3)
    from hogsa_loader.render.gaussians import sh_colors

    base = (sh_colors(1, gs.means[0], gs.sh[0]) + 0.5).clamp(min=0)
    assert torch.allclose(out[0, 0], base * torch.tensor([[1.0], [0.3], [0.3 + 0.7 * 0.8]]), atol=1e-6)


def test_hogs_model_headlight_without_learned_light():
    """HogsModel.render(headlight=...) shades with the camera light whether or not the model
    has a learned light (the normals are kept for it), and darkens the grazing surfaces."""
    from hogsa_loader.models.gaussians.hogs_model import HogsModel
    from hogsa_world.hand import synthetic_hand_pair
    from hogsa_world.objects.catalogue import make_object

    r, l = synthetic_hand_pair()
    m = HogsModel(
        HandGaussians(r, BindingConfig(sh_degree=0)),
        HandGaussians(l, BindingConfig(sh_degree=0)),
        ObjectGaussians(make_object("phone"), BindingConfig(sh_degree=0)),
    )
    assert m.light is None
    poses = {
        k: torch.zeros(1, n)
        for k, n in (
            ("right_rot", 3),
            ("right_pose", 45),
            ("right_betas", 10),
            ("right_trans", 3),
            ("left_rot", 3),
            ("left_pose", 45),
            ("left_betas", 10),
            ("left_trans", 3),
            ("obj_arti", 1),
            ("obj_rot", 3),
            ("obj_trans", 3),
        )
    }
    poses["left_trans"][0, 0] = 0.3  # (the hands apart, the object in front)
    vm = torch.eye(4)[None, None].clone()
    vm[..., 2, 3] = 0.6
    K = torch.tensor([[[[40.0, 0, 16], [0, 40, 16], [0, 0, 1]]]])
    assert m.scene(poses).normals is None and m.scene(poses, keep_normals=True).normals is not None
    with torch.no_grad():
        plain = m.render(poses, vm, K, 32, 32, backend="torch")
        lit = m.render(poses, vm, K, 32, 32, headlight=0.45, backend="torch")
    torch.testing.assert_close(lit.alpha, plain.alpha)
    assert (lit.rgb <= plain.rgb + 1e-5).all() and float((plain.rgb - lit.rgb).max()) > 0.05


def test_render_textured_cube_matches_analytic_projection():
    half, dist, f, size = 0.05, 0.5, 160.0, 64
    cube = ObjectGaussians(cube_template(half), BindingConfig(k=2, sh_degree=0))
    scene = compose([cube(torch.zeros(1), torch.zeros(1, 3))])
    vm, K = _head_on_camera(dist, f, size)
    out = render_scene(scene, vm, K, size, size)
    rgb, alpha, depth = out.rgb[0, 0], out.alpha[0, 0, ..., 0], out.depth[0, 0, ..., 0]
    # projected front square (z = +half, depth dist - half); the camera looks down -z
    r = f * half / (dist - half)
    c = _pixel_centres(size) - size / 2
    inside = torch.minimum(r - c.abs()[:, None], r - c.abs()[None, :])  # signed px distance to the edge
    assert (alpha[inside > 1.0] > 0.5).all()
    assert (alpha[inside < -1.0] < 0.5).all()
    # sub-pixel position of the alpha = 0.5 crossing on the middle row / column, both sides
    mid = size // 2
    for profile in (alpha[mid], alpha[:, mid], alpha[mid].flip(0), alpha[:, mid].flip(0)):
        j = int(torch.nonzero(profile > 0.5)[0])
        x = j - 0.5 + (0.5 - profile[j - 1].item()) / (profile[j] - profile[j - 1]).item()  # pixel centres j + 0.5
        assert abs((size / 2 - x) - r) < 1.5  # measured: about 1.2 px outside (Gaussian blur + eps2d)
    # the front face (+z) colour in the centre, and its depth
    centre = inside > r / 2
    front = torch.tensor(CUBE_COLOURS["+z"])
    assert (rgb[centre] - front).abs().max() < 0.02
    assert (depth[centre] - (dist - half)).abs().max() < 2e-3
    assert out.part_alpha.shape[-1] == 3 and torch.allclose(out.part_alpha[..., 2], out.alpha[..., 0], atol=1e-5)


def test_two_overlapping_parts_nearer_one_wins():
    dist, f, size = 0.6, 150.0, 64
    red = {k: (0.9, 0.1, 0.1) for k in CUBE_COLOURS}
    green = {k: (0.1, 0.8, 0.2) for k in CUBE_COLOURS}
    far = ObjectGaussians(cube_template(0.05, 12, red, "far"), BindingConfig(k=2, sh_degree=0), part_id=0)
    near = ObjectGaussians(cube_template(0.03, 8, green, "near"), BindingConfig(k=2, sh_degree=1), part_id=1)
    zero = torch.zeros(1, 3)
    scene = compose(
        [
            far(torch.zeros(1), zero, torch.tensor([[-0.03, 0.0, 0.0]])),
            near(torch.zeros(1), zero, torch.tensor([[0.02, 0.0, 0.15]])),
        ]
    )
    vm, K = _head_on_camera(dist, f, size)
    out = render_scene(scene, vm, K, size, size)
    rgb, depth, pa = out.rgb[0, 0], out.depth[0, 0, ..., 0], out.part_alpha[0, 0]
    u = _pixel_centres(size) - size / 2  # camera x = world x, camera y = -world y
    cols = u[None, :].expand(size, size)
    rows = u[:, None].expand(size, size)

    def px_box(cx, half, z, margin):  # pixels > margin px inside the front face at world z, centre x cx
        d = dist - z
        lo, hi = f * (cx - half) / d, f * (cx + half) / d
        return (cols > lo + margin) & (cols < hi - margin) & (rows.abs() < f * half / d - margin)

    far_face, near_face = (-0.03, 0.05, 0.05), (0.02, 0.03, 0.15 + 0.03)
    both = px_box(*near_face, 1.5) & px_box(*far_face, 1.5)
    far_only = px_box(*far_face, 1.5) & ~px_box(*near_face, -2.0)  # 2 px clear of the near cube
    assert both.sum() > 50 and far_only.sum() > 50
    assert (rgb[both] - torch.tensor([0.1, 0.8, 0.2])).abs().max() < 0.03
    assert (depth[both] - (dist - 0.18)).abs().max() < 3e-3
    assert (pa[both][:, 1] > 0.98).all() and (pa[both][:, 0] < 0.02).all()
    assert (rgb[far_only] - torch.tensor([0.9, 0.1, 0.1])).abs().max() < 0.03
    assert (depth[far_only] - (dist - 0.05)).abs().max() < 3e-3
    assert (pa[far_only][:, 0] > 0.98).all() and (pa[far_only][:, 1] < 0.02).all()
    assert torch.allclose(pa.sum(-1), out.alpha[0, 0, ..., 0], atol=1e-5)


# --------------------------------------------------------------------------------------
# checkpoints
# --------------------------------------------------------------------------------------


def _perturb(part, seed: int) -> None:
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for p in part.splats.parameters():
            p.add_(0.01 * torch.randn(p.shape, generator=g, dtype=p.dtype))


def _state_bytes(part) -> dict[str, bytes]:
    return {k: v.detach().cpu().numpy().tobytes() for k, v in part.splats.state_dict().items()}


@pytest.mark.parametrize("variant", ["games", "avatars", "free"])
def test_checkpoint_round_trip_is_bit_exact(tmp_path, right_hand, variant):
    hand = HandGaussians(right_hand, BindingConfig(variant=variant, k=1, sh_degree=1))
    _perturb(hand, 0)
    folder = save_part(
        hand,
        tmp_path / "right",
        dataset="arctic",
        subject="s01",
        sequence="box_grab_01",
        extra={"iterations": 30000, "note": "test"},
    )
    assert sorted(p.name for p in folder.iterdir()) == [TENSORS_FILE, MANIFEST_FILE]  # no temp files left
    manifest = json.loads((folder / MANIFEST_FILE).read_text())
    assert manifest["part_type"] == "hand_right" and manifest["variant"] == variant
    assert manifest["source"] == {"dataset": "arctic", "subject": "s01", "sequence": "box_grab_01"}
    assert manifest["template_hash"] == template_hash(right_hand.v_template, right_hand.faces)
    assert manifest["num_gaussians"] == hand.num_gaussians and manifest["binding_mesh"] == "model mesh"
    assert b"pickle" not in (folder / TENSORS_FILE).read_bytes()[:200]
    loaded = load_part(folder, right_hand, expected_part_type="hand_right")
    assert _state_bytes(loaded) == _state_bytes(hand)
    pose = _hand_pose(1, 2)
    a, b = hand(**pose), loaded(**pose)
    assert torch.equal(a.means, b.means) and torch.equal(a.sh, b.sh) and torch.equal(a.opacities, b.opacities)


def test_checkpoint_object_round_trip_and_sh_degree_zero(tmp_path):
    tpl = cube_template(0.05, 3)
    obj = ObjectGaussians(tpl, BindingConfig(variant="avatars", subdivide_levels=1, k=1, sh_degree=0))
    _perturb(obj, 1)
    save_part(obj, tmp_path / "obj")
    loaded = load_part(tmp_path / "obj", tpl)
    assert loaded.binding_mesh == "mesh_tex subdivide_mesh levels=1"
    assert _state_bytes(loaded) == _state_bytes(obj)


def _rewrite_tensors(folder: Path, edit) -> None:
    """Replace the tensors file by an edited one and keep the manifest consistent with it
    (so that only the validation under test can catch the problem)."""
    import hashlib

    from safetensors.torch import load, save

    tensors = load((folder / TENSORS_FILE).read_bytes())
    edit(tensors)
    blob = save(tensors)
    (folder / TENSORS_FILE).write_bytes(blob)
    m = json.loads((folder / MANIFEST_FILE).read_text())
    m["tensors_sha256"] = hashlib.sha256(blob).hexdigest()
    m["tensors"] = {
        n: {"shape": list(t.shape), "dtype": str(t.dtype).removeprefix("torch.")} for n, t in tensors.items()
    }
    (folder / MANIFEST_FILE).write_text(json.dumps(m))


def _edit_manifest(folder: Path, **changes) -> None:
    m = json.loads((folder / MANIFEST_FILE).read_text())
    m.update(changes)
    (folder / MANIFEST_FILE).write_text(json.dumps(m))


def test_checkpoint_validation_errors_name_the_file(tmp_path, hand_pair):
    right, left = hand_pair
    hand = HandGaussians(right, BindingConfig(k=1, sh_degree=0))
    ref = save_part(hand, tmp_path / "ref")

    def fresh(name: str) -> Path:
        import shutil

        return Path(shutil.copytree(ref, tmp_path / name))

    def expect(folder: Path, filename: str, words: str, fn=None):
        with pytest.raises(AssetError) as info:
            (fn or (lambda: load_state(HandGaussians(right, BindingConfig(k=1, sh_degree=0)), folder)))()
        assert filename in str(info.value) and words in str(info.value), str(info.value)
        assert Path(info.value.path).name == filename

    # missing files
    d = fresh("no_manifest")
    (d / MANIFEST_FILE).unlink()
    expect(d, MANIFEST_FILE, "missing")
    d = fresh("no_tensors")
    (d / TENSORS_FILE).unlink()
    expect(d, TENSORS_FILE, "missing")
    # schema version and format
    d = fresh("schema")
    _edit_manifest(d, schema_version=99)
    expect(d, MANIFEST_FILE, "schema_version 99")
    d = fresh("nokey")
    m = json.loads((d / MANIFEST_FILE).read_text())
    del m["template_hash"]
    (d / MANIFEST_FILE).write_text(json.dumps(m))
    expect(d, MANIFEST_FILE, "template_hash")
    # wrong part type: a right-hand checkpoint for the left hand / for an object
    d = fresh("side")
    expect(d, MANIFEST_FILE, "part_type", lambda: load_part(d, left))
    expect(d, MANIFEST_FILE, "part_type", lambda: load_state(HandGaussians(left, BindingConfig(k=1, sh_degree=0)), d))
    expect(d, MANIFEST_FILE, "object", lambda: load_part(d, right, expected_part_type="object"))
    # template hash mismatch
    bent = right.replace(v_template=right.v_template + 1e-4)
    expect(d, MANIFEST_FILE, "template hash mismatch", lambda: load_part(d, bent))
    # settings that do not match the model the caller built
    expect(d, MANIFEST_FILE, "k is 1", lambda: load_state(HandGaussians(right, BindingConfig(k=2, sh_degree=0)), d))
    # tensor shape mismatch (manifest kept consistent)
    d = fresh("shape")
    _rewrite_tensors(d, lambda t: t.__setitem__("opacity_logits", t["opacity_logits"][:-1].clone()))
    expect(d, TENSORS_FILE, "opacity_logits")
    # NaN
    d = fresh("nan")

    def put_nan(t):
        t["sh_dc"] = t["sh_dc"].clone()
        t["sh_dc"][3, 0, 1] = float("nan")

    _rewrite_tensors(d, put_nan)
    expect(d, TENSORS_FILE, "NaN")
    # torn pair: tensors changed without the manifest
    d = fresh("torn")
    (d / TENSORS_FILE).write_bytes((d / TENSORS_FILE).read_bytes()[:-8] + b"\0" * 8)
    expect(d, TENSORS_FILE, "sha256")
    # not JSON / not safetensors
    d = fresh("badjson")
    (d / MANIFEST_FILE).write_text("{not json")
    expect(d, MANIFEST_FILE, "malformed JSON")
    d = fresh("nanjson")  # Python's json reads NaN; strict JSON (and our writer) has none
    m = json.loads((d / MANIFEST_FILE).read_text())
    m["extra"] = {"loss": float("nan")}
    (d / MANIFEST_FILE).write_text(json.dumps(m))
    expect(d, MANIFEST_FILE, "NaN is not a JSON value")
    d = fresh("tensor_entry")
    m = json.loads((d / MANIFEST_FILE).read_text())
    m["tensors"]["opacity_logits"] = [4, 3]
    (d / MANIFEST_FILE).write_text(json.dumps(m))
    expect(d, MANIFEST_FILE, "tensors['opacity_logits'] must be an object")
    d = fresh("badst")
    blob = b"garbage" * 10
    (d / TENSORS_FILE).write_bytes(blob)
    import hashlib

    _edit_manifest(d, tensors_sha256=hashlib.sha256(blob).hexdigest())
    expect(d, TENSORS_FILE, "safetensors")
    # the untouched checkpoint still loads
    load_state(HandGaussians(right, BindingConfig(k=1, sh_degree=0)), ref)


def test_hand_checkpoint_refuses_a_renumbered_hand(tmp_path, hand_pair):
    """Same surface, other vertex order (e.g. another synthetic-hand version): a clear refusal."""
    from hogsa_loader.assets.hands.mano_io import reorder_vertices

    right = hand_pair[0]
    folder = save_part(HandGaussians(right, BindingConfig(k=1, sh_degree=0)), tmp_path / "right")
    renumbered = reorder_vertices(right, np.roll(np.arange(right.num_verts), 1))
    with pytest.raises(AssetError, match="template hash mismatch.*vertices in their order.*trained again"):
        load_part(folder, renumbered)


def test_checkpoint_save_is_all_or_nothing_for_bad_metadata(tmp_path, right_hand):
    hand = HandGaussians(right_hand, BindingConfig(k=1, sh_degree=0))
    with pytest.raises(ValueError):
        save_part(hand, tmp_path / "x", extra={"loss": float("nan")})
    assert not (tmp_path / "x").exists()  # nothing written, not even the folder
    save_part(hand, tmp_path / "y")
    before = {p.name: p.read_bytes() for p in (tmp_path / "y").iterdir()}
    with torch.no_grad():
        next(hand.parameters()).fill_(float("nan"))
    with pytest.raises(ValueError, match="NaN or infinity; not saved"):  # NaN weights: the old checkpoint stays
        save_part(hand, tmp_path / "y")
    assert {p.name: p.read_bytes() for p in (tmp_path / "y").iterdir()} == before
