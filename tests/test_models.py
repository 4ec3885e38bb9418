"""Robot models: (Single) Euler step, unicycle Euler step and the (NID) transform."""

import numpy as np
import pytest

from vtube_fleet.core.models import (
    control_point_velocity,
    nid_control_point,
    nid_inputs,
    single_integrator_step,
    unicycle_step,
    wrap_angle,
)


def test_single_integrator_step():
    p = np.array([[0.0, 1.0], [2.0, -1.0]])
    v = np.array([[1.0, 0.5], [-2.0, 0.0]])
    np.testing.assert_allclose(single_integrator_step(p, v, 0.1), [[0.1, 1.05], [1.8, -1.0]])
    assert np.array_equal(p, [[0.0, 1.0], [2.0, -1.0]])  # inputs untouched
    with pytest.raises(ValueError):
        single_integrator_step(p, v, 0.0)
    with pytest.raises(ValueError):
        single_integrator_step(p, v[:1], 0.1)


def test_nid_control_point_is_ahead_of_the_robot():
    p = np.array([[1.0, 2.0], [0.0, 0.0]])
    theta = np.array([0.0, np.pi / 2])
    np.testing.assert_allclose(nid_control_point(p, theta, 0.05), [[1.05, 2.0], [0.0, 0.05]],
                               atol=1e-15)
    with pytest.raises(ValueError):
        nid_control_point(p, theta, 0.0)


def test_nid_inputs_match_the_papers_matrix_and_invert_the_kinematics():
    rng = np.random.default_rng(0)
    theta = rng.uniform(-np.pi, np.pi, 50)
    vc = rng.normal(size=(50, 2))
    s = 0.07
    v, omega = nid_inputs(theta, vc, s)
    for i in range(50):
        c, sn = np.cos(theta[i]), np.sin(theta[i])
        mat = np.array([[c, sn], [-sn / s, c / s]])  # (NID)
        np.testing.assert_allclose([v[i], omega[i]], mat @ vc[i], rtol=1e-12, atol=1e-12)
    # the control point then moves exactly with v_c
    np.testing.assert_allclose(control_point_velocity(v, omega, theta, s), vc, atol=1e-12)


def test_unicycle_euler_step_moves_the_control_point_with_v_c():
    rng = np.random.default_rng(1)
    p = rng.normal(size=(20, 2))
    theta = rng.uniform(-np.pi, np.pi, 20)
    vc = rng.normal(size=(20, 2))
    s, dt = 0.05, 1e-5
    v, omega = nid_inputs(theta, vc, s)
    p1, th1 = unicycle_step(p, theta, v, omega, dt)
    # Euler step of the unicycle itself
    np.testing.assert_allclose(p1, p + dt * v[:, None] * np.c_[np.cos(theta), np.sin(theta)])
    np.testing.assert_allclose(wrap_angle(th1 - theta - dt * omega), 0.0, atol=1e-12)
    # control point displacement ≈ v_c dt (first order)
    moved = nid_control_point(p1, th1, s) - nid_control_point(p, theta, s)
    np.testing.assert_allclose(moved / dt, vc, rtol=0, atol=1e-3 * (1 + np.abs(vc).max()))
    with pytest.raises(ValueError):
        unicycle_step(p, theta, v, omega, -1.0)


def test_wrap_angle():
    np.testing.assert_allclose(wrap_angle([0.0, np.pi, -np.pi, 3 * np.pi, 7.0]),
                               [0.0, -np.pi, -np.pi, -np.pi, 7.0 - 2 * np.pi])
