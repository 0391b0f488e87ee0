"""Geometry helpers: rotations against scipy, mesh normals against trimesh, camera placement."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from hogsa_loader.geometry import axis_angle_to_matrix, matrix_to_axis_angle
from hogsa_loader.geometry.cameras import look_at
from hogsa_loader.geometry.meshes import face_normals, vertex_normals, vertex_normals_np

vec = st.lists(st.floats(-3.0, 3.0, allow_nan=False), min_size=3, max_size=3)


@settings(max_examples=200, deadline=None)
@given(vec)
def test_axis_angle_matches_scipy(v):
    R = axis_angle_to_matrix(torch.tensor(v, dtype=torch.float64)).numpy()
    np.testing.assert_allclose(R, Rotation.from_rotvec(v).as_matrix(), atol=1e-12)


@settings(max_examples=200, deadline=None)
@given(vec)
def test_matrix_to_axis_angle_round_trip(v):
    R = torch.tensor(Rotation.from_rotvec(v).as_matrix())
    back = axis_angle_to_matrix(matrix_to_axis_angle(R))
    np.testing.assert_allclose(back.numpy(), R.numpy(), atol=1e-9)


def test_near_pi_and_identity():
    for v in ([np.pi, 0, 0], [0, -np.pi + 1e-9, 0], [1e-12, 0, 0], [0, 0, 0]):
        R = torch.tensor(Rotation.from_rotvec(v).as_matrix())
        np.testing.assert_allclose(axis_angle_to_matrix(matrix_to_axis_angle(R)).numpy(), R.numpy(), atol=1e-9)


def test_gradient_at_identity_is_the_cross_matrix():
    v = torch.zeros(3, dtype=torch.float64, requires_grad=True)
    R = axis_angle_to_matrix(v)
    # dR/dv_x at 0 is [e_x]_x: d R[2,1]/d v_x = 1
    (g,) = torch.autograd.grad(R[2, 1], v)
    np.testing.assert_allclose(g.numpy(), [1.0, 0.0, 0.0])


def _mesh() -> tuple[np.ndarray, np.ndarray]:
    """An icosphere with one vertex used by no face."""
    import trimesh

    m = trimesh.creation.icosphere(subdivisions=2, radius=0.3)
    v = np.concatenate([m.vertices * [1.0, 0.7, 1.3], [[9.0, 9.0, 9.0]]])
    return v, np.asarray(m.faces)


def test_vertex_normals_are_trimesh_area_weighted_normals():
    import trimesh.geometry

    v, f = _mesh()
    fn = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])  # length = 2 x area
    ref = trimesh.geometry.mean_vertex_normals(len(v), f, fn)
    out = vertex_normals(torch.tensor(v), torch.tensor(f))
    np.testing.assert_allclose(out.numpy(), ref, atol=1e-12)
    assert torch.equal(out[-1], torch.zeros(3, dtype=out.dtype))  # unreferenced vertex
    np.testing.assert_array_equal(vertex_normals_np(v, f), out.numpy())
    np.testing.assert_allclose(face_normals(torch.tensor(v), torch.tensor(f)).numpy(), fn, atol=1e-15)


def test_vertex_normals_batch_like_single_meshes_and_differentiate():
    v, f = _mesh()
    rng = np.random.default_rng(0)
    batch = torch.tensor(v[None] + rng.normal(0, 0.01, (4, 2) + v.shape)).requires_grad_()
    out = vertex_normals(batch, torch.tensor(f))
    assert out.shape == batch.shape
    for i in range(4):
        for j in range(2):
            assert torch.equal(out[i, j], vertex_normals(batch[i, j].detach(), torch.tensor(f)))
    out[..., 0].sum().backward()
    assert torch.isfinite(batch.grad).all() and batch.grad[..., :-1, :].abs().sum() > 0


def test_look_at_points_the_camera_at_its_target():
    rng = np.random.default_rng(1)
    eye, target = rng.normal(0, 1, (64, 3)), rng.normal(0, 0.1, (64, 3))
    up, roll = np.array([0.0, 0.0, 1.0]), rng.uniform(-0.5, 0.5, 64)
    M = look_at(eye, target, up, roll)
    R, t = M[:, :3, :3], M[:, :3, 3]
    np.testing.assert_allclose(R @ R.transpose(0, 2, 1), np.broadcast_to(np.eye(3), R.shape), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-12)
    np.testing.assert_allclose(np.einsum("bij,bj->bi", R, eye) + t, 0.0, atol=1e-12)  # eye -> origin
    tc = np.einsum("bij,bj->bi", R, target) + t
    np.testing.assert_allclose(tc[:, :2], 0.0, atol=1e-12)  # target on the optical axis, in front
    assert (tc[:, 2] > 0).all()
    # unrolled, world up is image-up (-y) and has no image-x part; the roll turns x toward y
    R0 = look_at(eye, target, up)[:, :3, :3]
    assert (R0[:, 1] @ up < 0).all() and np.allclose(R0[:, 0] @ up, 0.0, atol=1e-12)
    np.testing.assert_allclose(R[:, 0], np.cos(roll)[:, None] * R0[:, 0] + np.sin(roll)[:, None] * R0[:, 1], atol=1e-12)
    # looking straight down the up axis still gives a rotation
    Md = look_at(np.array([[0.0, 0.0, 2.0]]), np.zeros((1, 3)), up)[0]
    np.testing.assert_allclose(Md[:3, :3] @ Md[:3, :3].T, np.eye(3), atol=1e-12)
    np.testing.assert_allclose(Md[2, :3], [0.0, 0.0, -1.0], atol=1e-12)


def test_the_world_rigs_roll_turns_image_x_toward_image_minus_y():
    from hogsa_world.cameras import _look_at

    eye, target, roll = np.array([1.2, -0.4, 0.6]), np.array([0.0, 0.1, 0.0]), 0.3
    R0 = look_at(eye[None], target[None], np.array([0.0, 0.0, 1.0]))[0, :3, :3]
    c, s = np.cos(roll), np.sin(roll)
    expected = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]) @ R0
    np.testing.assert_allclose(_look_at(eye, target, roll)[:3, :3], expected, atol=1e-15)


def test_camera_look_at_takes_the_direction_of_up_only():
    from hogsa_loader.render.mesh_raster import camera_look_at

    a = camera_look_at((0.0, 0.0, 0.0), (0.0, 0.0, 1.0), (0.0, 1.0, 0.0))
    b = camera_look_at((0.0, 0.0, 0.0), (0.0, 0.0, 1.0), (0.0, 1e-7, 0.0))
    assert torch.equal(a, b)
    with pytest.raises(ValueError, match="parallel"):
        camera_look_at((0.0, 0.0, 0.0), (0.0, 0.0, 1.0), (0.0, 1e-7, 1.0))
