"""SE(3)/SO(3) helpers: round trips and the numerically hard ends (angles near 0 and near pi)."""

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from sim.geometry import (
    compose,
    invert_T,
    look_at,
    make_T,
    rotation_angle,
    se3_exp,
    se3_log,
    so3_exp,
    so3_log,
    transform_points,
)

unit = st.lists(st.floats(-1, 1), min_size=3, max_size=3).filter(lambda v: np.linalg.norm(v) > 1e-3)
# Angles concentrated at the ends where naive formulas break.
angle = st.one_of(
    st.floats(0.0, 1e-6),
    st.floats(1e-6, 1e-2),
    st.floats(0.0, np.pi),
    st.floats(np.pi - 1e-3, np.pi),
    st.just(np.pi),
)


@settings(max_examples=300, deadline=None)
@given(unit, angle)
def test_so3_exp_log_round_trip_from_zero_to_pi(axis, theta):
    axis = np.asarray(axis) / np.linalg.norm(axis)
    R = so3_exp(axis * theta)
    assert np.allclose(R @ R.T, np.eye(3), atol=1e-12)
    assert np.isclose(np.linalg.det(R), 1.0)
    w = so3_log(R)
    assert np.all(np.isfinite(w))
    assert np.linalg.norm(w) <= np.pi + 1e-12
    assert np.allclose(so3_exp(w), R, atol=1e-9)
    assert abs(np.linalg.norm(w) - theta) < 1e-7


def test_so3_log_at_exactly_pi_returns_axis_up_to_sign():
    for axis in np.eye(3):
        w = so3_log(so3_exp(axis * np.pi))
        assert np.isclose(np.linalg.norm(w), np.pi)
        assert np.isclose(abs(w @ axis), np.pi)


def test_so3_exp_torch_matches_numpy_and_has_finite_gradient_at_zero():
    rv = torch.zeros(4, 3, dtype=torch.float64, requires_grad=True)
    R = so3_exp(rv)
    R[..., 0, 1].sum().backward()
    assert torch.isfinite(rv.grad).all()
    x = np.random.default_rng(0).normal(size=(5, 3))
    assert np.allclose(so3_exp(torch.from_numpy(x)).numpy(), so3_exp(x), atol=1e-12)


@settings(max_examples=100, deadline=None)
@given(st.lists(st.floats(-2, 2), min_size=3, max_size=3), unit, angle)
def test_se3_exp_log_round_trip(v, axis, theta):
    axis = np.asarray(axis) / np.linalg.norm(axis)
    xi = np.concatenate([v, axis * min(theta, np.pi - 1e-6)])
    T = se3_exp(xi)
    assert np.allclose(se3_exp(se3_log(T)), T, atol=1e-8)


def test_batch_shapes_and_inverse_compose():
    xi = np.random.default_rng(1).normal(size=(2, 3, 6))
    T = se3_exp(xi)
    assert T.shape == (2, 3, 4, 4)
    assert np.allclose(compose(T, invert_T(T)), np.eye(4), atol=1e-12)
    pts = np.random.default_rng(2).normal(size=(2, 3, 5, 3))
    back = transform_points(invert_T(T), transform_points(T, pts))
    assert np.allclose(back, pts, atol=1e-12)


def test_look_at_points_opencv_z_at_target_and_y_down():
    T = look_at([0.3, 0.0, 0.5], [0.0, 0.0, 0.0])
    z = T[:3, 2]
    assert np.allclose(z, -np.array([0.3, 0.0, 0.5]) / np.linalg.norm([0.3, 0.0, 0.5]))
    assert T[:3, 1] @ np.array([0, 0, 1.0]) < 0  # image-down points toward world-down
    straight_down = look_at([0.0, 0.0, 1.0], [0.0, 0.0, 0.0])
    assert np.all(np.isfinite(straight_down))
    assert np.isclose(np.linalg.det(straight_down[:3, :3]), 1.0)
    with pytest.raises(ValueError):
        look_at([0, 0, 0], [0, 0, 0])


def test_rotation_angle_is_geodesic():
    R1 = so3_exp(np.array([0.0, 0.0, 0.2]))
    R2 = so3_exp(np.array([0.0, 0.0, -0.3]))
    assert np.isclose(rotation_angle(R1, R2), 0.5)
    assert np.isclose(rotation_angle(make_T(R1, [0, 0, 0])[:3, :3], R1), 0.0)
