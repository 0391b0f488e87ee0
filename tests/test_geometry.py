"""Rotation helpers against scipy's independent implementation."""

from __future__ import annotations

import numpy as np
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from hogsa_loader.geometry import axis_angle_to_matrix, matrix_to_axis_angle

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
