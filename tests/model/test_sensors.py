"""The onboard sensors' measurement model: at rest the accelerometer reads gravity; along a
simulated motion it reads the finite difference of its point's velocity less gravity, and the
gyro the platform's angular velocity, both in the IMU's axes."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jsphere
from jsphere.model.rotations import rotmat
from jsphere.model.sensors import Mounting, imu_readings

#: an IMU off the centre, turned about a skew axis (scalar-first, IMU -> platform)
POSITION = (0.03, -0.02, -0.05)
ROTATION = (np.cos(0.4), *(np.sin(0.4) * np.array([1.0, 2.0, -2.0]) / 3.0))


def test_a_level_imu_at_rest_reads_plus_g_on_its_up_axis(paper):
    s = jsphere.State.at_rest(paper)
    for position in ((0.0, 0.0, 0.0), POSITION):
        gyro, acc = imu_readings(paper, Mounting(position), s.gamma, s.omega, s.Omega, jnp.zeros(3))
        np.testing.assert_allclose(gyro, 0.0, atol=1e-15)
        np.testing.assert_allclose(acc, [0.0, 0.0, paper.g], atol=1e-12)


def test_a_turned_imu_at_rest_reads_gravity_in_its_own_axes(paper):
    s = jsphere.State.at_rest(paper)
    m = Mounting(POSITION, ROTATION)
    _, acc = imu_readings(paper, m, s.gamma, s.omega, s.Omega, jnp.zeros(3))
    R = np.asarray(rotmat(jnp.asarray(ROTATION)))
    np.testing.assert_allclose(R @ np.asarray(acc), paper.g * np.asarray(s.gamma), atol=1e-12)
    assert abs(np.linalg.norm(acc) - paper.g) < 1e-12


@pytest.fixture(scope="module")
def motion(paper):
    """A torque-driven motion sampled every `h` on a fine grid, solved tightly."""
    h = 2e-3
    ts = jnp.arange(0.0, 2.0 + h / 2, h)
    torques = jsphere.random_inputs(paper, 2.0, kind="torques", seed=3)
    tr = jsphere.simulate(paper, jsphere.State.at_rest(paper), torques, 2.0, ts=ts, rtol=1e-12, atol=1e-13)
    return h, tr


def test_along_a_motion_the_accelerometer_reads_the_point_velocity_s_rate_less_gravity(paper, motion):
    """The IMU point's fixed-frame velocity `R (R0 Omega x gamma + omega x r)`, differentiated by
    a five-point stencil, less gravity `-g e_z`, turned into the IMU's axes."""
    h, tr = motion
    m = Mounting(POSITION, ROTATION)
    gyro, acc = imu_readings(paper, m, tr.gamma, tr.omega, tr.Omega, tr.K)
    R_plat = np.asarray(rotmat(tr.q))  # platform -> fixed
    R_imu = np.asarray(rotmat(jnp.asarray(ROTATION)))  # IMU -> platform
    gamma, omega, Omega = (np.asarray(a) for a in (tr.gamma, tr.omega, tr.Omega))
    v_plat = paper.R0 * np.cross(Omega, gamma) + np.cross(omega, POSITION)
    v = np.einsum("tij,tj->ti", R_plat, v_plat)
    a = (v[:-4] - 8 * v[1:-3] + 8 * v[3:-1] - v[4:]) / (12 * h)
    f_fixed = a + np.array([0.0, 0.0, paper.g])
    expected = np.einsum("ji,tjk,tk->ti", R_imu, R_plat[2:-2].transpose(0, 2, 1), f_fixed)
    np.testing.assert_allclose(np.asarray(acc)[2:-2], expected, atol=1e-6 * np.abs(expected).max())
    # the motion moves the reading well away from gravity alone (the check has teeth)
    assert np.abs(np.linalg.norm(np.asarray(acc), axis=1) - paper.g).max() > 1e-2
    np.testing.assert_allclose(np.asarray(gyro), omega @ R_imu, atol=1e-15)


def test_the_shell_centre_moves_in_the_plane(paper, motion):
    """At the centre (the platform frame's origin) the specific force less gravity, seen from the
    fixed frame, has no vertical part: the centre rolls on the plane."""
    _, tr = motion
    _, acc = imu_readings(paper, Mounting(), tr.gamma, tr.omega, tr.Omega, tr.K)
    vertical = np.einsum("ti,ti->t", np.asarray(acc), np.asarray(tr.gamma)) - paper.g
    assert np.abs(vertical).max() < 1e-12 * paper.g


def test_readings_are_differentiable_in_the_mounting_and_the_parameters(paper, motion):
    _, tr = motion

    def loss(position, m0):
        p = jsphere.set_value(paper, "m0", m0)
        _, acc = imu_readings(p, Mounting(position, ROTATION), tr.gamma[:50], tr.omega[:50], tr.Omega[:50], tr.K[:50])
        return jnp.sum(acc**2)

    g_pos, g_m0 = jax.jit(jax.grad(loss, argnums=(0, 1)))(jnp.asarray(POSITION), paper.m0)
    assert np.all(np.isfinite(g_pos)) and np.abs(g_pos).max() > 0
    assert np.isfinite(g_m0) and g_m0 != 0
