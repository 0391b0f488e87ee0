"""MANO layer: equivalence with smplx on the same files, joints, left/right, MANO-HD, gradients."""

from __future__ import annotations

import zlib

import numpy as np
import pytest
import torch

from hogsa_loader.assets.hands.anatomy import NAMED_POSES, named_articulation
from hogsa_loader.assets.hands.mano import MANOLayer
from hogsa_loader.assets.hands.mano_io import load_mano
from hogsa_loader.assets.hands.manohd import subdivide_mesh, subdivide_model, unique_edges


def _smplx():
    """smplx, the independent MANO reference (test extra); a test that needs it is skipped without."""
    return pytest.importorskip("smplx", reason="smplx is the independent reference (test extra)")


def _random_inputs(B: int, n_pose: int, seed: int, dtype=torch.float64):
    g = torch.Generator().manual_seed(seed)
    return dict(
        global_orient=torch.randn(B, 3, generator=g, dtype=dtype) * 0.8,
        hand_pose=torch.randn(B, n_pose, generator=g, dtype=dtype) * 0.6,
        betas=torch.randn(B, 10, generator=g, dtype=dtype) * 1.5,
        transl=torch.randn(B, 3, generator=g, dtype=dtype) * 0.2,
    )


@pytest.mark.parametrize("side", ["right", "left"])
@pytest.mark.parametrize("use_pca", [False, True])
@pytest.mark.parametrize("flat_hand_mean", [False, True])
def test_matches_smplx_on_the_same_pickle(mano_dir, chumpy_shim, side, use_pca, flat_hand_mean):
    ncomps = 12 if use_pca else 45
    path = mano_dir / f"MANO_{side.upper()}.pkl"
    ref = _smplx().MANO(
        str(path),
        is_rhand=side == "right",
        use_pca=use_pca,
        num_pca_comps=ncomps,
        flat_hand_mean=flat_hand_mean,
        dtype=torch.float64,
    )
    ours = MANOLayer(path, use_pca=use_pca, num_pca_comps=ncomps, flat_hand_mean=flat_hand_mean, dtype=torch.float64)
    inp = _random_inputs(6, ncomps, seed=zlib.crc32(repr((side, use_pca, flat_hand_mean)).encode()) % 1000)
    with torch.no_grad():
        r = ref(**inp)
        o = ours(**inp)
    assert o.vertices.shape == r.vertices.shape
    err_v = (o.vertices - r.vertices).abs().max().item()
    err_j = (o.joints[:, :16] - r.joints[:, :16]).abs().max().item()
    assert err_v <= 1e-5 and err_j <= 1e-5, (err_v, err_j)
    # and the test really exercised non-trivial deformation
    assert (r.vertices - r.vertices.mean(1, keepdim=True)).abs().max() > 0.02


@pytest.mark.parametrize("side", ["right", "left"])
def test_arctic_21_joint_smplx_mano_matches_on_the_pickle(mano_dir, chumpy_shim, side):
    """ARCTIC's MANO: smplx's layer on the model folder with the vertex-joint selector enabled,
    which appends the fingertip vertices 744, 320, 443, 554, 671 (thumb..pinky) by id."""
    ref = _smplx().MANO(
        str(mano_dir), is_rhand=side == "right", use_pca=False, flat_hand_mean=False, dtype=torch.float64
    )
    assert ref.vertex_joint_selector.extra_joints_idxs.tolist() == [744, 320, 443, 554, 671]
    ours = MANOLayer(mano_dir, side=side, dtype=torch.float64)
    inp = _random_inputs(6, 45, seed=11 if side == "right" else 12)
    with torch.no_grad():
        r = ref(**inp)
        joints21 = ref.vertex_joint_selector(r.vertices, r.joints)
        o = ours(**inp)
    assert joints21.shape == o.joints.shape == (6, 21, 3)
    assert (o.joints - joints21).abs().max().item() <= 1e-6
    assert (o.vertices - r.vertices).abs().max().item() <= 1e-6


def test_reorder_vertices_renumbers_everything(hand_pair):
    from hogsa_loader.assets.hands.mano_io import reorder_vertices

    model = hand_pair[1]
    order = np.random.default_rng(0).permutation(model.num_verts)
    moved = reorder_vertices(model, order)
    inp = _random_inputs(3, 45, seed=5)
    with torch.no_grad():
        a = MANOLayer(model, dtype=torch.float64)(**inp)
        b = MANOLayer(moved, dtype=torch.float64)(**inp)
    assert (b.vertices - a.vertices[:, order]).abs().max() < 1e-12
    assert (b.joints - a.joints).abs().max() < 1e-12
    np.testing.assert_array_equal(moved.v_template[moved.faces], model.v_template[model.faces])
    np.testing.assert_array_equal(moved.vertex_colors, model.vertex_colors[order])
    for k, ids in model.contact_vertex_ids.items():
        np.testing.assert_array_equal(np.sort(order[moved.contact_vertex_ids[k]]), ids)
    with pytest.raises(ValueError, match="permutation"):
        reorder_vertices(model, order[:-1])


def test_npz_model_matches_smplx_npz(mano_dir, tmp_path):
    from hogsa_loader.assets.hands.mano_io import convert_mano_to_npz

    npz = tmp_path / "MANO_RIGHT.npz"
    convert_mano_to_npz(mano_dir / "MANO_RIGHT.pkl", npz)
    ref = _smplx().MANO(str(npz), is_rhand=True, use_pca=False, flat_hand_mean=False, ext="npz", dtype=torch.float64)
    ours = MANOLayer(npz, dtype=torch.float64)
    inp = _random_inputs(3, 45, seed=7)
    with torch.no_grad():
        assert (ours(**inp).vertices - ref(**inp).vertices).abs().max() <= 1e-5


def test_fingertips_follow_arctic_order(hand_pair):
    for model in hand_pair:  # MANO's fingertip ids, which smplx and ARCTIC read by id
        assert model.tip_vertex_ids.tolist() == [744, 320, 443, 554, 671]
    layer = MANOLayer(hand_pair[0], flat_hand_mean=True, dtype=torch.float64)
    out = layer()
    J = out.joints[0].numpy()
    assert J.shape == (21, 3)
    np.testing.assert_array_equal(out.joints[0, 16:].numpy(), out.vertices[0, hand_pair[0].tip_vertex_ids].numpy())
    # thumb, index, middle, ring, pinky tips sit just beyond distal joints 15, 3, 6, 12, 9
    for tip, distal in zip(range(16, 21), (15, 3, 6, 12, 9)):
        d = np.linalg.norm(J[:16] - J[tip], axis=1)
        assert int(d.argmin()) == distal


def test_left_is_mirror_of_right_with_mirrored_pose(hand_pair):
    right, left = hand_pair
    R = MANOLayer(right, dtype=torch.float64)
    L = MANOLayer(left, dtype=torch.float64)
    inp = _random_inputs(4, 45, seed=3)
    inp["betas"].zero_()
    m = torch.tensor([-1.0, 1.0, 1.0], dtype=torch.float64)
    mirrored = dict(
        global_orient=inp["global_orient"] * -m,
        hand_pose=inp["hand_pose"] * (-m).repeat(15),
        betas=inp["betas"],
        transl=inp["transl"] * m,
    )
    with torch.no_grad():
        vr = R(**inp).vertices
        vl = L(**mirrored).vertices
    assert (vl - vr * m).abs().max() < 1e-9


def test_fix_left_shapedirs_option(hand_pair):
    right, left = hand_pair
    assert left.meta["left_shapedirs_x_unmirrored"] is True
    betas = torch.tensor([[1.5, -1.0, 0.8, 0.5, -0.7, 0.9, 1.1, -0.4, 0.3, 0.6]], dtype=torch.float64)
    m = torch.tensor([-1.0, 1.0, 1.0], dtype=torch.float64)
    vr = MANOLayer(right, dtype=torch.float64)(betas=betas).vertices
    as_file = MANOLayer(left, dtype=torch.float64)(betas=betas).vertices
    fixed = MANOLayer(left, fix_left_shapedirs=True, dtype=torch.float64)(betas=betas).vertices
    assert (fixed - vr * m).abs().max() < 1e-9  # fixed: exact mirror of the right hand
    assert (as_file - vr * m).abs().max() > 1e-3  # as shipped: not a mirror (release behaviour)
    # the option never touches a right hand
    assert (MANOLayer(right, fix_left_shapedirs=True, dtype=torch.float64)(betas=betas).vertices - vr).abs().max() == 0


def test_gradcheck_and_dtypes(hand_pair):
    layer = MANOLayer(hand_pair[0], use_pca=True, num_pca_comps=6, dtype=torch.float64)
    sub = torch.arange(0, layer.num_verts, 97)

    def f(go, hp, b):
        return layer(global_orient=go, hand_pose=hp, betas=b).vertices[:, sub]

    args = (
        torch.randn(1, 3, dtype=torch.float64, requires_grad=True),
        torch.randn(1, 6, dtype=torch.float64, requires_grad=True),
        torch.randn(1, 10, dtype=torch.float64, requires_grad=True),
    )
    assert torch.autograd.gradcheck(f, args, eps=1e-6, atol=1e-6)
    # zero pose is differentiable too (Rodrigues at the identity)
    z = torch.zeros(1, 3, dtype=torch.float64, requires_grad=True)
    layer(global_orient=z).vertices.sum().backward()
    assert torch.isfinite(z.grad).all()
    l32 = MANOLayer(hand_pair[0], dtype=torch.float32)
    out = l32(hand_pose=torch.zeros(2, 45), betas=torch.zeros(2, 10))
    assert out.vertices.dtype == torch.float32


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cuda_matches_cpu(hand_pair):
    cpu = MANOLayer(hand_pair[0], dtype=torch.float32)
    gpu = MANOLayer(hand_pair[0], dtype=torch.float32).cuda()
    inp = {k: v.float() for k, v in _random_inputs(8, 45, seed=1).items()}
    a = cpu(**inp).vertices
    b = gpu(**{k: v.cuda() for k, v in inp.items()}).vertices.cpu()
    assert (a - b).abs().max() < 1e-5


# --------------------------------------------------------------------------------------
# MANO-HD
# --------------------------------------------------------------------------------------
def test_subdivision_counts_follow_the_formula(hand_pair):
    base = hand_pair[0]
    V, F = base.num_verts, base.faces.shape[0]
    E = unique_edges(base.faces).shape[0]
    # the hand is a disc topologically (one open boundary at the wrist): E = V + F - 1,
    # the relation that gives 778 -> 3093 -> 12337 on the official MANO mesh
    assert E == V + F - 1
    hd1 = subdivide_model(base, 1)
    hd2 = subdivide_model(base, 2)
    assert hd1.num_verts == V + E and hd1.faces.shape[0] == 4 * F
    E1 = unique_edges(hd1.faces).shape[0]
    assert E1 == 2 * E + 3 * F
    assert hd2.num_verts == hd1.num_verts + E1 and hd2.faces.shape[0] == 16 * F
    # MANO's own numbers from the same formulas
    V_m, F_m = 778, 1538
    E_m = V_m + F_m - 1
    assert V_m + E_m == 3093 and V_m + E_m + 2 * E_m + 3 * F_m == 12337


def test_subdivision_matches_trimesh_geometry():
    import trimesh

    ico = trimesh.creation.icosahedron()
    faces, op = subdivide_mesh(np.asarray(ico.faces), len(ico.vertices))
    ours = np.asarray(op @ ico.vertices)
    ref_v, ref_f = trimesh.remesh.subdivide(ico.vertices, ico.faces)
    assert ours.shape == ref_v.shape and faces.shape == ref_f.shape
    key = lambda a: np.round(a, 9)[np.lexsort(np.round(a, 9).T)]  # noqa: E731
    np.testing.assert_allclose(key(ours), key(np.asarray(ref_v)), atol=1e-9)
    mesh = trimesh.Trimesh(ours, faces, process=False)
    assert mesh.is_watertight and mesh.is_winding_consistent and mesh.volume > 0


def test_hd_lbs_at_rest_equals_subdivided_rest_mesh(hand_pair):
    base = hand_pair[1]
    hd = subdivide_model(base, 2)
    layer = MANOLayer(hd, flat_hand_mean=True, dtype=torch.float64)
    rest = layer().vertices[0].numpy()
    np.testing.assert_allclose(rest, hd.v_template, atol=1e-12)
    # midpoints of the original rest mesh
    edges = unique_edges(base.faces)
    np.testing.assert_allclose(
        hd.v_template[base.num_verts : base.num_verts + len(edges)], base.v_template[edges].mean(1), atol=1e-12
    )


def test_hd_old_vertices_and_joints_follow_the_base_model(hand_pair):
    base = hand_pair[0]
    hd = subdivide_model(base, 1)
    inp = _random_inputs(3, 45, seed=11)
    with torch.no_grad():
        a = MANOLayer(base, dtype=torch.float64)(**inp)
        b = MANOLayer(hd, dtype=torch.float64)(**inp)
    np.testing.assert_allclose(b.vertices[:, : base.num_verts], a.vertices, atol=1e-10)
    np.testing.assert_allclose(b.joints, a.joints, atol=1e-10)
    # each new vertex stays close to the midpoint of its posed edge (weights interpolate)
    edges = unique_edges(base.faces)
    mids = a.vertices[:, edges].mean(2)
    gap = (b.vertices[:, base.num_verts :] - mids).norm(dim=-1)
    assert gap.max() < 3e-3


def test_hd_refined_weights_hook(hand_pair):
    base = hand_pair[0]
    hd = subdivide_model(base, 1)
    W = np.random.default_rng(0).random(hd.weights.shape) * 2 - 0.5
    hd2 = subdivide_model(base, 1, lbs_weights=W)
    assert np.allclose(hd2.weights.sum(1), 1.0) and hd2.weights.min() >= 0
    assert not np.allclose(hd2.weights, hd.weights)
    with pytest.raises(ValueError, match="lbs_weights"):
        subdivide_model(base, 1, lbs_weights=W[:10])


def test_hd_round_trips_through_the_pickle(tmp_path, hand_pair):
    from hogsa_world.mano_pickle import write_mano_pickle

    hd = subdivide_model(hand_pair[0], 1)
    write_mano_pickle(hd, tmp_path / "MANO_RIGHT.pkl")
    got = load_mano(tmp_path / "MANO_RIGHT.pkl")
    assert got.num_verts == hd.num_verts and got.meta["manohd"]["levels"] == 1
    np.testing.assert_array_equal(got.tip_vertex_ids, hand_pair[0].tip_vertex_ids)


# --------------------------------------------------------------------------------------
# The synthetic hand looks and moves like a hand
# --------------------------------------------------------------------------------------
def _edge_stretch(model, art: np.ndarray) -> float:
    layer = MANOLayer(model, flat_hand_mean=True, dtype=torch.float64)
    v = layer(hand_pose=torch.tensor(art)[None]).vertices[0].numpy()
    e = unique_edges(model.faces)
    rest = np.linalg.norm(np.diff(model.v_template[e], axis=1)[:, 0], axis=1)
    posed = np.linalg.norm(np.diff(v[e], axis=1)[:, 0], axis=1)
    return float((posed / rest).max())


def test_synthetic_hand_is_hand_like(hand_pair):
    right, _ = hand_pair
    assert 1000 <= right.num_verts <= 3000
    ext = right.v_template.max(0) - right.v_template.min(0)
    J = right.J_regressor @ right.v_template
    middle_len = np.linalg.norm(J[4] - J[0]) + np.linalg.norm(J[5] - J[4]) + np.linalg.norm(J[6] - J[5])
    assert 0.14 < middle_len + 0.02 < 0.22  # wrist to middle fingertip, adult-sized
    assert ext.max() < 0.25
    # regressor reproduces a skeleton inside the surface and is sparse
    assert (right.J_regressor > 0).sum() < 16 * 200
    # shape directions change size and proportions
    layer = MANOLayer(right, dtype=torch.float64)
    big = layer(betas=torch.tensor([[2.0] + [0.0] * 9], dtype=torch.float64)).joints[0].numpy()
    rest = layer().joints[0].numpy()
    assert np.linalg.norm(big[18] - big[0]) > 1.08 * np.linalg.norm(rest[18] - rest[0])
    assert right.contact_vertex_ids["palm"].size > 50
    assert all(right.contact_vertex_ids[f].size > 10 for f in ("thumb", "index", "middle", "ring", "pinky"))


@pytest.mark.parametrize("pose", [p for p in NAMED_POSES if p != "flat"])
def test_named_poses_deform_without_tearing(hand_pair, pose):
    right, _ = hand_pair
    art = named_articulation(right, pose)
    assert _edge_stretch(right, art) < 2.6  # fused fingers measured 4.7 here


def test_synthetic_hand_is_deterministic(tmp_path, hand_pair):
    from hogsa_world.hand import synthetic_hand_pair
    from hogsa_world.mano_pickle import write_mano_pickle

    again, _ = synthetic_hand_pair()
    write_mano_pickle(hand_pair[0], tmp_path / "a.pkl")
    write_mano_pickle(again, tmp_path / "b.pkl")
    assert (tmp_path / "a.pkl").read_bytes() == (tmp_path / "b.pkl").read_bytes()
