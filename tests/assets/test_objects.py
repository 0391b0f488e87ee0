"""Tests of hogsa_loader.assets.objects: templates I/O, articulation, H2O poses, procedural objects."""

from __future__ import annotations

import dataclasses
import filecmp
import json
import math
import os
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
import trimesh
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from hogsa_loader.assets.objects import (
    BOTTOM,
    OBJECT_NAMES,
    TOP,
    ArticulatedObjectLayer,
    articulate,
    load_object_template,
    load_object_templates,
    parse_h2o_obj_pose_rt,
    pose_rigid,
    read_h2o_obj_pose_rt,
)
from hogsa_loader.assets.objects.template import MAX_MESH_BYTES, bbox_corners, max_pairwise_distance
from hogsa_loader.errors import AssetError
from hogsa_world.object_files import write_object_template
from hogsa_world.objects.catalogue import PROCEDURAL_NAMES, make_object, write_procedural_objects
from hogsa_world.objects.procedural import GAP_MM

F64 = torch.float64

# closed-state extents (x, y, z) in mm: x away from the hinge, y stacking, z along the hinge
EXPECTED_EXTENT_MM = {
    "capsulemachine": (175.0, 295.0, 120.0),
    "box": (70.0, 159.0, 110.0),
    "ketchup": (72.0, 207.0, 50.4),
    "laptop": (210.0, 24.0, 300.0),
    "microwave": (300.0, 234.0, 210.0),
    "mixer": (230.0, 325.0, 140.0),
    "notebook": (148.0, 13.5, 210.0),
    "espressomachine": (215.0, 224.0, 300.0),
    "waffleiron": (270.0, 83.0, 190.0),
    "scissors": (206.9, 91.0, 10.0),
    "phone": (95.0, 21.0, 50.0),
}
#: Axis along which the closed top lies on the bottom: y for lids, z (the pivot) for scissors.
STACK_AXIS = {"scissors": 2}
#: Objects assembled from pieces (hogsa_world.objects.household).
HOUSEHOLD = ("capsulemachine", "ketchup", "microwave", "mixer", "espressomachine", "waffleiron", "scissors")


# --------------------------------------------------------------------------------------
# fixtures
# --------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def templates():
    return {name: make_object(name, seed=0) for name in PROCEDURAL_NAMES}


@pytest.fixture(scope="module")
def meta_dir(tmp_path_factory):
    root = tmp_path_factory.mktemp("meta_a")
    write_procedural_objects(root, names=PROCEDURAL_NAMES, seed=0)
    return root


@pytest.fixture(scope="module")
def layer(templates):
    return ArticulatedObjectLayer(list(templates.values())).to(F64)


def _rz_minus(theta: float) -> np.ndarray:
    """R_z(-θ) written out by hand."""
    c, s = math.cos(theta), math.sin(theta)
    return np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])


def _random_pose(rng: np.random.Generator, batch: int):
    angles = torch.from_numpy(rng.uniform(0, math.pi / 2, (batch, 1)))
    orient = torch.from_numpy(Rotation.random(batch, random_state=rng.integers(1 << 31)).as_rotvec())
    transl = torch.from_numpy(rng.normal(0, 0.5, (batch, 3)))
    return angles, orient, transl


# --------------------------------------------------------------------------------------
# names
# --------------------------------------------------------------------------------------


def test_object_names_follow_arctic_index_order():
    assert OBJECT_NAMES == (
        "capsulemachine",
        "box",
        "ketchup",
        "laptop",
        "microwave",
        "mixer",
        "notebook",
        "espressomachine",
        "waffleiron",
        "scissors",
        "phone",
    )
    assert set(PROCEDURAL_NAMES) <= set(OBJECT_NAMES)


# --------------------------------------------------------------------------------------
# articulation
# --------------------------------------------------------------------------------------


def test_top_moves_bottom_stays(layer, templates):
    names = list(templates)
    batch = len(names)
    zeros = torch.zeros(batch, 3, dtype=F64)
    out = layer(torch.full((batch, 1), 0.6, dtype=F64), zeros, zeros, names)
    for i, name in enumerate(names):
        t = templates[name]
        kp = out["kp3d"][i].numpy()
        assert np.abs(kp[:16] - t.kp_top).max() > 1e-3  # top keypoints moved
        np.testing.assert_allclose(kp[16:], t.kp_bottom, atol=1e-7)
        np.testing.assert_allclose(out["bbox3d"][i, 8:].numpy(), t.bbox_bottom, atol=1e-7)
        v_len = int(out["v_len"][i])
        bottom = out["parts_ids"][i, :v_len] == BOTTOM + 1
        np.testing.assert_allclose(out["v"][i, :v_len][bottom].numpy(), t.verts[t.parts == BOTTOM], atol=1e-7)


@pytest.mark.parametrize("theta", [0.0, 0.3, math.pi / 2, 2.5, -0.4])
def test_top_rotation_is_rz_minus_theta(layer, templates, theta):
    zeros = torch.zeros(1, 3, dtype=F64)
    out = layer(torch.tensor([[theta]], dtype=F64), zeros, zeros, ["laptop"])
    t = templates["laptop"]
    expected_kp = t.kp_top.astype(np.float64) @ _rz_minus(theta).T
    expected_bb = t.bbox_top.astype(np.float64) @ _rz_minus(theta).T
    np.testing.assert_allclose(out["kp3d"][0, :16].numpy(), expected_kp, atol=1e-7)
    np.testing.assert_allclose(out["bbox3d"][0, :8].numpy(), expected_bb, atol=1e-7)


def test_pose_then_inverse_recovers_template(layer, templates):
    rng = np.random.default_rng(0)
    names = list(templates) * 2
    angles, orient, transl = _random_pose(rng, len(names))
    out = layer(angles, orient, transl, names)
    rot = Rotation.from_rotvec(orient.numpy()).as_matrix()
    for i, name in enumerate(names):
        t = templates[name]
        theta = float(angles[i, 0])
        for key, top_n, top, bottom in (("kp3d", 16, t.kp_top, t.kp_bottom), ("bbox3d", 8, t.bbox_top, t.bbox_bottom)):
            p = out[key][i].numpy()
            canon = (p - transl[i].numpy()) @ rot[i]  # R^T (p - t), row-vector form
            canon[:top_n] = canon[:top_n] @ _rz_minus(-theta).T  # undo R_z(-θ) with R_z(θ)
            np.testing.assert_allclose(canon[:top_n], top, atol=1e-6)
            np.testing.assert_allclose(canon[top_n:], bottom, atol=1e-6)


def test_layer_matches_functional_core_and_scipy(layer, templates):
    rng = np.random.default_rng(1)
    names = ["phone", "box", "laptop", "phone", "notebook"]
    angles, orient, transl = _random_pose(rng, len(names))
    out = layer(angles, orient, transl, names)
    canon = layer.forward_template(names)
    # functional core
    functional = articulate(canon["v"], canon["parts_ids"] == TOP + 1, angles, orient, transl)
    functional = functional * canon["mask"][..., None]
    torch.testing.assert_close(out["v"], functional)
    # independent numpy/scipy implementation on the templates themselves
    for i, name in enumerate(names):
        t = templates[name]
        theta = float(angles[i, 0])
        r_glob = Rotation.from_rotvec(orient[i].numpy())
        r_art = Rotation.from_rotvec(theta * np.array([0.0, 0.0, -1.0]))
        v = t.verts.astype(np.float64)
        top = t.parts == TOP
        posed = np.where(top[:, None], r_glob.apply(r_art.apply(v)), r_glob.apply(v)) + transl[i].numpy()
        np.testing.assert_allclose(out["v"][i, : len(v)].numpy(), posed, atol=1e-9)
        sub = np.concatenate([t.sub_top, t.sub_bottom]).astype(np.float64)
        sub_posed = np.concatenate([r_glob.apply(r_art.apply(sub[:300])), r_glob.apply(sub[300:])]) + transl[i].numpy()
        np.testing.assert_allclose(out["v_sub"][i].numpy(), sub_posed, atol=1e-9)


def test_padding_mask_and_lengths(layer, templates):
    names = ["phone", "laptop"]
    zeros = torch.zeros(2, 3, dtype=F64)
    out = layer(torch.zeros(2, 1, dtype=F64), zeros, torch.ones(2, 3, dtype=F64), names)
    lens = [templates[n].verts.shape[0] for n in names]
    flens = [templates[n].faces.shape[0] for n in names]
    assert lens[0] != lens[1]
    assert out["v"].shape == (2, max(lens), 3)
    assert out["f"].shape == (2, max(flens), 3)
    assert out["v_len"].tolist() == lens and out["f_len"].tolist() == flens
    assert out["mask"].sum(1).tolist() == lens
    for i, n in enumerate(names):
        assert (out["parts_ids"][i, lens[i] :] == 0).all()
        assert (out["v"][i, lens[i] :] == 0).all()
        assert (out["f"][i, flens[i] :] == 0).all()
        np.testing.assert_array_equal(out["parts_ids"][i, : lens[i]].numpy(), templates[n].parts + 1)
        np.testing.assert_array_equal(out["f"][i, : flens[i]].numpy(), templates[n].faces)
    assert out["v_sub"].shape == (2, 600, 3) and out["kp3d"].shape == (2, 32, 3)
    assert out["bbox3d"].shape == (2, 16, 3) and out["diameter"].shape == (2,)
    # sub-points: 300 top then 300 bottom
    assert (out["parts_sub_ids"][:, :300] == TOP + 1).all()
    assert (out["parts_sub_ids"][:, 300:] == BOTTOM + 1).all()


def test_forward_template_is_canonical(layer, templates):
    out = layer.forward_template(["box"])
    t = templates["box"]
    np.testing.assert_allclose(out["v"][0].numpy(), t.verts, atol=1e-7)
    np.testing.assert_allclose(out["kp3d"][0, :16].numpy(), t.kp_top, atol=1e-7)
    assert float(out["diameter"][0]) == pytest.approx(t.diameter)


def test_gradients_flow_and_dtype(templates):
    layer32 = ArticulatedObjectLayer([templates["phone"], templates["box"]])
    assert layer32.v.dtype == torch.float32
    angles = torch.tensor([[0.4], [1.0]], requires_grad=True)
    orient = torch.zeros(2, 3, requires_grad=True)  # gradient at the identity too
    transl = torch.zeros(2, 3, requires_grad=True)
    out = layer32(angles, orient, transl, ["phone", "box"])
    assert out["v"].dtype == torch.float32
    (out["v"][..., 0].sum() + out["kp3d"].pow(2).sum()).backward()
    for g in (angles.grad, orient.grad, transl.grad):
        assert g is not None and torch.isfinite(g).all() and g.abs().sum() > 0
    # angle-shaped (B,) input is accepted too
    layer64 = layer32.to(F64)
    out64 = layer64(torch.tensor([0.4, 1.0], dtype=F64), torch.zeros(2, 3, dtype=F64), None, ["phone", "box"])
    assert out64["v"].dtype == F64 and out64["diameter"].dtype == F64
    with pytest.raises(KeyError):
        layer64.forward_template(["microwave"])


def test_articulate_gradcheck():
    gen = torch.Generator().manual_seed(0)
    pts = torch.randn(2, 5, 3, dtype=F64, generator=gen)
    is_top = torch.tensor([True, False, True, True, False])

    def fn(angle, orient, transl):
        return articulate(pts, is_top, angle, orient, transl)

    inputs = (
        torch.tensor([0.3, -1.2], dtype=F64, requires_grad=True),
        torch.randn(2, 3, dtype=F64, generator=gen).requires_grad_(),
        torch.randn(2, 3, dtype=F64, generator=gen).requires_grad_(),
    )
    assert torch.autograd.gradcheck(fn, inputs)


_angle = st.floats(-math.pi, math.pi, allow_nan=False)
_vec = st.tuples(*[st.floats(-3.0, 3.0, allow_nan=False)] * 3)


@settings(max_examples=40, deadline=None, database=None)
@given(theta=_angle, orient=_vec, transl=_vec, seed=st.integers(0, 2**16))
def test_articulation_is_rigid_within_each_part(theta, orient, transl, seed):
    rng = np.random.default_rng(seed)
    pts = torch.from_numpy(rng.normal(0, 0.2, (1, 12, 3)))
    is_top = torch.from_numpy(rng.random(12) < 0.5)
    out = articulate(
        pts,
        is_top,
        torch.tensor([theta], dtype=F64),
        torch.tensor([orient], dtype=F64),
        torch.tensor([transl], dtype=F64),
    )[0]
    for mask in (is_top, ~is_top):
        before = torch.cdist(pts[0][mask], pts[0][mask])
        after = torch.cdist(out[mask], out[mask])
        torch.testing.assert_close(after, before, atol=1e-9, rtol=0)
    # the hinge axis (z line through the origin) is fixed by the articulation alone
    axis_pts = torch.tensor([[[0.0, 0.0, -0.1], [0.0, 0.0, 0.3]]], dtype=F64)
    moved = articulate(
        axis_pts, torch.tensor([True, True]), torch.tensor([theta], dtype=F64), torch.zeros(1, 3, dtype=F64), None
    )
    torch.testing.assert_close(moved, axis_pts)


# --------------------------------------------------------------------------------------
# template I/O
# --------------------------------------------------------------------------------------


def test_template_reads_are_cached_as_copies_and_follow_file_changes(meta_dir, tmp_path):
    from hogsa_loader.assets.objects import template as tmod

    folder = tmp_path / "object_vtemplates" / "box"
    shutil.copytree(meta_dir / "object_vtemplates" / "box", folder)
    first = tmod.load_object_template(folder)
    key = next(k for k in tmod._TEMPLATE_CACHE if k[0] == str(folder.resolve()))
    first.verts[:] = 0.0  # a caller's change reaches neither the cache nor later reads
    second = tmod.load_object_template(folder)
    assert np.abs(second.verts).max() > 0 and second.verts is not tmod._TEMPLATE_CACHE[key].verts
    # a changed file is read again, also when its size stays the same
    params_path = folder / "object_params.json"
    params = json.loads(params_path.read_text())
    params["keypoints_top"] = (np.asarray(params["keypoints_top"]) + 1.0).tolist()
    text = json.dumps(params)
    params_path.write_text(text)
    third = tmod.load_object_template(folder)
    np.testing.assert_allclose(third.kp_top, second.kp_top + 1e-3, atol=1e-9)
    at = text.index('"keypoints_top": [[') + len('"keypoints_top": [[')
    at += 1 if text[at] == "-" else 0  # the first digit of the first coordinate, one higher
    same_size = text[:at] + str((int(text[at]) + 1) % 10) + text[at + 1 :]
    params_path.write_text(same_size)
    assert params_path.stat().st_size == len(text)
    fourth = tmod.load_object_template(folder)
    new = json.loads(same_size)["keypoints_top"][0][0] / 1000.0
    assert fourth.kp_top[0, 0] == pytest.approx(new) and new != pytest.approx(third.kp_top[0, 0])
    # textures are part of the key: with and without are two entries
    assert tmod.load_object_template(folder, load_texture=False).texture is None


@pytest.mark.parametrize("name", PROCEDURAL_NAMES)
def test_write_load_round_trip(templates, meta_dir, name):
    t = templates[name]
    got = load_object_templates(meta_dir, names=[name])[name]
    assert got.name == name
    np.testing.assert_allclose(got.verts, t.verts, atol=1e-7, rtol=0)
    np.testing.assert_array_equal(got.faces, t.faces)
    np.testing.assert_array_equal(got.parts, t.parts)
    for key in (
        "kp_top",
        "kp_bottom",
        "bbox_top",
        "bbox_bottom",
        "mocap_top",
        "mocap_bottom",
        "sub_top",
        "sub_bottom",
        "tex_verts",
    ):
        np.testing.assert_allclose(getattr(got, key), getattr(t, key), atol=1e-7, rtol=0, err_msg=key)
    np.testing.assert_array_equal(got.tex_faces, t.tex_faces)
    np.testing.assert_array_equal(got.tex_parts, t.tex_parts)
    np.testing.assert_allclose(got.tex_uv, t.tex_uv, atol=1e-6, rtol=0)
    assert got.texture.shape == t.texture.shape
    assert np.abs(got.texture.astype(float) - t.texture).mean() < 3.0  # JPEG q95
    assert got.diameter == pytest.approx(t.diameter, abs=1e-8)
    # the separate part meshes are written in mm too
    top = trimesh.load(meta_dir / "object_vtemplates" / name / "top.obj", process=False, force="mesh")
    np.testing.assert_allclose(np.asarray(top.vertices) / 1000.0, t.verts[t.parts == TOP], atol=1e-7)


def test_load_all_orders_by_arctic_index(meta_dir):
    got = load_object_templates(meta_dir, load_texture=False)
    assert list(got) == [n for n in OBJECT_NAMES if n in PROCEDURAL_NAMES]
    meta = json.loads((meta_dir / "object_meta.json").read_text())
    for name, t in got.items():
        assert t.diameter == meta[name]["diameter"]
        assert not t.has_texture


def test_diameter_computed_without_meta(meta_dir):
    t = load_object_template(meta_dir / "object_vtemplates" / "phone", load_texture=False)
    assert t.diameter == pytest.approx(max_pairwise_distance(t.verts), rel=1e-6)


def _json_edit(path: Path, fn):
    data = json.loads(path.read_text())
    fn(data)
    path.write_text(json.dumps(data))


def _set_nan(data):
    data["keypoints_top"][3][1] = float("nan")


def _break_mesh(folder: Path):
    (folder / "mesh.obj").write_text("v 0 0 0\nv 1 0 0\n")


BAD_CASES = {
    "missing_parts": ("parts.json", lambda f: (f / "parts.json").unlink()),
    "parts_too_short": ("parts.json", lambda f: _json_edit(f / "parts.json", lambda d: d.pop())),
    "parts_bad_value": ("parts.json", lambda f: _json_edit(f / "parts.json", lambda d: d.__setitem__(0, 2))),
    "parts_no_bottom": (
        "parts.json",
        lambda f: (f / "parts.json").write_text(json.dumps([0] * len(json.loads((f / "parts.json").read_text())))),
    ),
    "nan_keypoint": ("object_params.json", lambda f: _json_edit(f / "object_params.json", _set_nan)),
    "kp_count": (
        "object_params.json",
        lambda f: _json_edit(f / "object_params.json", lambda d: d["keypoints_bottom"].pop()),
    ),
    "bbox_shape": (
        "object_params.json",
        lambda f: _json_edit(
            f / "object_params.json", lambda d: d.__setitem__("bbox_top", [p[:2] for p in d["bbox_top"]])
        ),
    ),
    "missing_key": ("object_params.json", lambda f: _json_edit(f / "object_params.json", lambda d: d.pop("mocap_top"))),
    "bad_json": ("top_keypoints_300.json", lambda f: (f / "top_keypoints_300.json").write_text('{"keypoints": [[1, 2')),
    "sub_count": (
        "bottom_keypoints_300.json",
        lambda f: _json_edit(f / "bottom_keypoints_300.json", lambda d: d["keypoints"].pop()),
    ),
    "missing_mesh": ("mesh.obj", lambda f: (f / "mesh.obj").unlink()),
    "mesh_no_faces": ("mesh.obj", _break_mesh),
    # a file too large to parse (sparse: no disk used), refused before trimesh reads it
    "mesh_too_large": ("mesh.obj", lambda f: os.truncate(f / "mesh.obj", MAX_MESH_BYTES + 1)),
    "missing_texture_image": ("material.jpg", lambda f: (f / "material.jpg").unlink()),
}


@pytest.mark.parametrize("case", list(BAD_CASES))
def test_loader_errors_name_the_file(meta_dir, tmp_path, case):
    filename, damage = BAD_CASES[case]
    folder = tmp_path / "box"
    shutil.copytree(meta_dir / "object_vtemplates" / "box", folder)
    damage(folder)
    with pytest.raises(AssetError) as info:
        load_object_template(folder, load_texture=(case == "missing_texture_image"))
    assert filename in str(info.value)
    assert Path(info.value.path).name == filename


def test_bad_object_meta_names_the_file(meta_dir, tmp_path):
    root = tmp_path / "meta"
    shutil.copytree(meta_dir / "object_vtemplates" / "phone", root / "object_vtemplates" / "phone")
    (root / "object_meta.json").write_text(json.dumps({"phone": {"diameter": "wide"}}))
    with pytest.raises(AssetError, match="object_meta.json"):
        load_object_templates(root, load_texture=False)


# --------------------------------------------------------------------------------------
# procedural objects
# --------------------------------------------------------------------------------------


@pytest.mark.parametrize("name", PROCEDURAL_NAMES)
def test_parts_are_watertight_closed_solids(templates, name):
    t = templates[name]
    for part in (TOP, BOTTOM):
        v, f = t.part_mesh(part)
        mesh = trimesh.Trimesh(v, f, process=False)
        assert mesh.is_watertight and mesh.is_winding_consistent
        assert mesh.volume > 0
        # every vertex of the part is used by its faces
        assert np.unique(f).size == v.shape[0]
    assert 2000 <= t.verts.shape[0] <= 10000


@pytest.mark.parametrize("name", PROCEDURAL_NAMES)
def test_sizes_and_gap(templates, name):
    t = templates[name]
    extent_mm = (t.verts.max(0) - t.verts.min(0)) * 1000
    np.testing.assert_allclose(extent_mm, EXPECTED_EXTENT_MM[name], rtol=0.02)
    top, bottom = t.part_points(TOP), t.part_points(BOTTOM)
    gap = cKDTree(bottom).query(top)[0].min() * 1000
    assert 0.9 * GAP_MM <= gap <= 1.6 * GAP_MM
    diag = np.linalg.norm(extent_mm) / 1000
    assert t.diameter == pytest.approx(max_pairwise_distance(t.verts), rel=1e-6)
    assert extent_mm.max() / 1000 * (1 - 1e-6) <= t.diameter <= diag * (1 + 1e-6)


@pytest.mark.parametrize("name", PROCEDURAL_NAMES)
def test_top_opens_without_entering_bottom(templates, name):
    t = templates[name]
    top = torch.from_numpy(t.part_points(TOP).astype(np.float64))[None]
    bottom = t.part_points(BOTTOM)
    lo, hi = bottom.min(0) + 1e-4, bottom.max(0) - 1e-4  # 0.1 mm tolerance
    thetas = np.linspace(0.01 * math.pi, 0.5 * math.pi, 15)
    zeros = torch.zeros(1, 3, dtype=F64)
    centre_bottom = bottom.mean(0)
    dist = []
    for theta in [0.0, *thetas]:
        posed = articulate(
            top, torch.ones(top.shape[1], dtype=torch.bool), torch.tensor([theta], dtype=F64), zeros, zeros
        )[0].numpy()
        inside = ((posed > lo) & (posed < hi)).all(axis=1)
        assert not inside.any(), f"theta={theta:.3f}: {inside.sum()} top vertices inside the bottom box"
        dist.append(np.linalg.norm(posed.mean(0) - centre_bottom))
    assert np.all(np.diff(dist) > 0)  # the lid moves away from the base as it opens
    # closed at θ = 0: the top lies on the bottom (along y, or the pivot for scissors)
    top_np = t.part_points(TOP)
    axis = STACK_AXIS.get(name, 1)
    assert top_np[:, axis].min() > bottom[:, axis].max()
    if axis == 1:  # lids: footprints (x, z) overlap
        overlap = np.prod(
            np.clip(np.minimum(top_np.max(0), bottom.max(0)) - np.maximum(top_np.min(0), bottom.min(0)), 0, None)[
                [0, 2]
            ]
        )
        area = np.prod((top_np.max(0) - top_np.min(0))[[0, 2]])
        assert overlap > 0.95 * area


@pytest.mark.parametrize("name", PROCEDURAL_NAMES)
def test_keypoints_bbox_and_samples(templates, name):
    t = templates[name]
    for part, kp, bbox, sub, mocap in (
        (TOP, t.kp_top, t.bbox_top, t.sub_top, t.mocap_top),
        (BOTTOM, t.kp_bottom, t.bbox_bottom, t.sub_bottom, t.mocap_bottom),
    ):
        pts = t.part_points(part)
        tree = cKDTree(pts)
        assert kp.shape == (16, 3) and sub.shape == (300, 3) and 4 <= mocap.shape[0] <= 6
        for samples in (kp, sub, mocap):
            assert tree.query(samples)[0].max() < 1e-7  # on the part's surface
        assert len(np.unique(sub, axis=0)) == 300
        np.testing.assert_allclose(bbox, bbox_corners(pts))
        np.testing.assert_allclose(bbox[0], pts.min(0))
        np.testing.assert_allclose(bbox[7], pts.max(0))
        # farthest-point keypoints are spread: nearest pair at least half the spacing of 16
        # points evenly covering the part's surface
        v, f = t.part_mesh(part)
        area = trimesh.Trimesh(v, f, process=False).area
        d = np.linalg.norm(kp[:, None] - kp[None], axis=-1) + np.eye(16)
        assert d.min() > 0.5 * math.sqrt(area / 16)


@pytest.mark.parametrize("name", PROCEDURAL_NAMES)
def test_textured_mesh_shares_the_surface(templates, name):
    t = templates[name]
    dist, nearest = cKDTree(t.verts).query(t.tex_verts)
    assert dist.max() < 1e-9
    np.testing.assert_array_equal(t.tex_parts, t.parts[nearest])
    mapped = np.sort(nearest[t.tex_faces], axis=1)
    assert {tuple(r) for r in mapped.tolist()} == {tuple(r) for r in np.sort(t.faces, axis=1).tolist()}
    assert t.tex_uv.min() >= 0 and t.tex_uv.max() <= 1
    assert t.texture.shape == (1024, 1024, 3) and t.texture.dtype == np.uint8
    assert (t.texture.reshape(-1, 3).std(0) > 20).all()  # not flat
    # each chart is painted: colours under the UVs vary within a part
    h, w = t.texture.shape[:2]
    cols = t.texture[((1 - t.tex_uv[:, 1]) * (h - 1)).astype(int), (t.tex_uv[:, 0] * (w - 1)).astype(int)]
    assert cols.astype(float).std(0).min() > 10


def _welded_obj(verts: np.ndarray, faces: np.ndarray, uv: np.ndarray, path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Write a textured mesh the way scan exports do: positions welded (one ``v`` per
    point), one ``vt`` per face corner (``f a/b`` with ``a != b`` at seams). Returns the
    per-corner positions and UVs (F, 3, 3), (F, 3, 2)."""
    key = np.round(verts, 6)
    uniq, inv = np.unique(key, axis=0, return_inverse=True)
    inv = inv.reshape(-1)
    lines = [f"v {x:.6f} {y:.6f} {z:.6f}" for x, y, z in uniq]
    lines += [f"vt {u:.6f} {v:.6f}" for u, v in uv[faces].reshape(-1, 2)]
    lines += [
        " ".join(["f"] + [f"{inv[faces[i, c]] + 1}/{3 * i + c + 1}" for c in range(3)]) for i in range(len(faces))
    ]
    path.write_text("\n".join(lines) + "\n")
    return uniq[inv[faces]], uv[faces]


@pytest.mark.parametrize("name", ["box"])
def test_textured_mesh_with_welded_uv_seams(templates, meta_dir, tmp_path, name):
    """A mesh_tex.obj with UV seams (several vt per position) loads with every face corner's
    own texture coordinate (the seam vertices are split), for ARCTIC and H2O readers."""
    from hogsa_loader.assets.h2o_meshes import load_h2o_object

    t = templates[name]
    folder = tmp_path / name
    shutil.copytree(meta_dir / "object_vtemplates" / name, folder)
    corner_xyz, corner_uv = _welded_obj(t.tex_verts * 1000.0, t.tex_faces, t.tex_uv, folder / "mesh_tex.obj")
    assert len(np.unique(np.round(t.tex_verts * 1000, 6), axis=0)) < len(t.tex_verts)  # there are seams
    got = load_object_template(folder)
    assert len(got.tex_verts) == len(t.tex_verts)  # one vertex per (position, UV): not a triangle soup
    np.testing.assert_allclose(got.tex_verts[got.tex_faces] * 1000.0, corner_xyz, atol=1e-5)
    np.testing.assert_allclose(got.tex_uv[got.tex_faces], corner_uv, atol=1e-5)
    # H2O meshes (metres) go through the same kind of loader
    h2o = tmp_path / "h2o" / "book"
    h2o.mkdir(parents=True)
    _welded_obj(t.tex_verts, t.tex_faces, t.tex_uv, h2o / "book.obj")
    (h2o / "book.obj").write_text("mtllib book.mtl\nusemtl m\n" + (h2o / "book.obj").read_text())
    (h2o / "book.mtl").write_text("newmtl m\nmap_Kd material.jpg\n")
    shutil.copy(folder / "material.jpg", h2o / "material.jpg")
    m = load_h2o_object(tmp_path / "h2o", "book")
    assert m.has_texture and len(m.tex_verts) == len(t.tex_verts)
    np.testing.assert_allclose(m.tex_uv[m.tex_faces], corner_uv, atol=1e-5)


def test_determinism_and_seed_variation(meta_dir, tmp_path):
    from hogsa_world.objects import catalogue

    catalogue._kept_object.cache_clear()  # made afresh, not the kept ones
    again = tmp_path / "again"
    other = tmp_path / "other"
    write_procedural_objects(again, names=PROCEDURAL_NAMES, seed=0)
    write_procedural_objects(other, names=PROCEDURAL_NAMES, seed=1)
    files = sorted(p.relative_to(meta_dir) for p in meta_dir.rglob("*") if p.is_file())
    assert len(files) == 1 + 10 * len(PROCEDURAL_NAMES)
    for rel in files:
        assert filecmp.cmp(meta_dir / rel, again / rel, shallow=False), rel
    for name in PROCEDURAL_NAMES:
        rel = Path("object_vtemplates") / name / "material.jpg"
        assert not filecmp.cmp(meta_dir / rel, other / rel, shallow=False)
        # geometry does not depend on the seed
        assert filecmp.cmp(
            meta_dir / "object_vtemplates" / name / "mesh.obj",
            other / "object_vtemplates" / name / "mesh.obj",
            shallow=False,
        )


def test_write_template_without_texture(templates, tmp_path):
    t = templates["phone"]
    bare = dataclasses.replace(t, tex_verts=None, tex_faces=None, tex_uv=None, texture=None, tex_parts=None)
    write_object_template(bare, tmp_path / "phone")
    assert not (tmp_path / "phone" / "mesh_tex.obj").exists()
    got = load_object_template(tmp_path / "phone")
    assert not got.has_texture
    np.testing.assert_allclose(got.kp_top, t.kp_top, atol=1e-7)


def test_unknown_procedural_name():
    with pytest.raises(KeyError):
        make_object("mug")


def test_every_arctic_object_is_procedural_and_distinct(templates):
    assert PROCEDURAL_NAMES == OBJECT_NAMES
    extents = {n: np.round((t.verts.max(0) - t.verts.min(0)) * 1000).tolist() for n, t in templates.items()}
    counts = {n: t.verts.shape[0] for n, t in templates.items()}
    for a in PROCEDURAL_NAMES:
        for b in PROCEDURAL_NAMES:
            if a < b:
                assert extents[a] != extents[b] or counts[a] != counts[b], (a, b)
    for name, t in templates.items():
        assert 0.1 <= t.diameter <= 0.45, name  # ARCTIC's objects are 10-40 cm
        assert len(t.faces) > 1000 and (t.parts == TOP).sum() > 300 and (t.parts == BOTTOM).sum() > 300


@pytest.mark.parametrize("name", HOUSEHOLD)
def test_household_objects_fit_arctic_vertex_budget(templates, name):
    """ARCTIC's InterField upsamples object distances to 4000 vertices and masks them with
    the object's padded vertex mask, so an object must have at most 4000 vertices."""
    assert templates[name].verts.shape[0] <= 4000


# --------------------------------------------------------------------------------------
# H2O rigid objects
# --------------------------------------------------------------------------------------


def _h2o_line(class_id: float, transform: np.ndarray) -> str:
    return " ".join(f"{x:.8f}" for x in [class_id, *transform.reshape(-1)])


def _transform(seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    T = np.eye(4)
    T[:3, :3] = Rotation.random(random_state=seed).as_matrix()
    T[:3, 3] = rng.normal(0, 0.3, 3)
    return T


def test_h2o_parse_and_pose(tmp_path):
    T = _transform(3)
    cls, got = parse_h2o_obj_pose_rt(_h2o_line(5, T))
    assert cls == 5
    np.testing.assert_allclose(got, T, atol=1e-8)
    # sequences of numbers and files work the same
    cls2, got2 = parse_h2o_obj_pose_rt([5.0, *T.reshape(-1)])
    assert cls2 == 5 and np.allclose(got2, T)
    path = tmp_path / "000123.txt"
    path.write_text(_h2o_line(2, T) + "\n")
    assert read_h2o_obj_pose_rt(path)[0] == 2
    # posing: p_cam = R p + t, batched
    pts = torch.randn(2, 7, 3, dtype=F64)
    Ts = torch.from_numpy(np.stack([T, _transform(4)]))
    posed = pose_rigid(pts, Ts)
    for b in range(2):
        ref = pts[b].numpy() @ Ts[b, :3, :3].numpy().T + Ts[b, :3, 3].numpy()
        np.testing.assert_allclose(posed[b].numpy(), ref, atol=1e-12)
    # no object: class 0 with a zero matrix
    cls0, zero = parse_h2o_obj_pose_rt("0 " + " ".join(["0"] * 16))
    assert cls0 == 0 and not zero.any()


def _scaled(T):
    T = T.copy()
    T[:3, :3] *= 1.1
    return T


def _reflected(T):
    T = T.copy()
    T[:3, 0] *= -1
    return T


def _with_nan(T):
    T = T.copy()
    T[0, 3] = float("nan")
    return T


def _bad_last_row(T):
    T = T.copy()
    T[3, 0] = 0.5
    return T


BAD_H2O = {
    "too_short": lambda T: _h2o_line(1, T).rsplit(" ", 1)[0],
    "too_long": lambda T: _h2o_line(1, T) + " 1.0",
    "not_a_number": lambda T: _h2o_line(1, T).replace(" ", " x", 1),
    "nan": lambda T: _h2o_line(1, _with_nan(T)),
    "scaled_rotation": lambda T: _h2o_line(1, _scaled(T)),
    "reflection": lambda T: _h2o_line(1, _reflected(T)),
    "last_row": lambda T: _h2o_line(1, _bad_last_row(T)),
    "fractional_class": lambda T: _h2o_line(2.5, T),
    "class_out_of_range": lambda T: _h2o_line(9, T),
}


@pytest.mark.parametrize("case", list(BAD_H2O))
def test_h2o_rejects_bad_lines(case):
    line = BAD_H2O[case](_transform(1))
    with pytest.raises(AssetError) as info:
        parse_h2o_obj_pose_rt(line, path="cam4/obj_pose_rt/000042.txt")
    assert "000042.txt" in str(info.value)


def test_a_mesh_file_too_large_is_refused_before_it_is_parsed(meta_dir, tmp_path):
    folder = tmp_path / "box"
    shutil.copytree(meta_dir / "object_vtemplates" / "box", folder)
    os.truncate(folder / "mesh.obj", MAX_MESH_BYTES + 1)  # sparse: no disk used
    with pytest.raises(
        AssetError, match=rf"mesh file of {MAX_MESH_BYTES + 1} bytes, more than the {MAX_MESH_BYTES} read"
    ):
        load_object_template(folder, load_texture=False)
