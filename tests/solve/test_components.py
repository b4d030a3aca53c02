"""The batched form of (3.4) (`jsphere.solve.batched.components`, scalar components for the
shared-step engine) term by term against the physics (`jsphere.model.dynamics`) at random
states, for the paper's three-wheel robot and a four-wheel robot, with rolling and axle
friction switched on so that every term of (3.4) is checked."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jsphere
from jsphere.model.dynamics import forces, free_Omega_dot, mass_blocks, solve_accelerations
from jsphere.model.params import derive
from jsphere.model.rotations import quat_rate_body, quat_rate_fixed, rotmat
from jsphere.model.state import Flat
from jsphere.solve.batched import components as C

STATES = 6


def _four_wheels():
    phis = 2 * np.pi * np.arange(4) / 4
    return jsphere.RobotParams(
        R0=0.15,
        m0=0.8,
        I0=0.012,
        Rw=0.07,
        wheel_r=0.057 * np.stack([np.cos(phis), np.sin(phis), -np.ones(4)], -1),
        wheel_n=np.stack([np.cos(phis), np.sin(phis), np.ones(4)], -1) / np.sqrt(2),
        wheel_alpha=np.stack([np.cos(phis - np.pi / 4), np.sin(phis - np.pi / 4), np.ones(4)], -1) / np.sqrt(2),
        m=2.5,
        I=np.diag([0.016, 0.016, 0.023]),
        r_m=[0.004, -0.002, -0.027],
        j=2.7e-4,
    )


@pytest.fixture(params=["paper", "four wheels"], scope="module")
def robot(request):
    p = jsphere.RobotParams.paper() if request.param == "paper" else _four_wheels()
    # rolling and axle friction on, so that their terms are compared too
    return eqx.tree_at(lambda q: (q.c_roll, q.c_axle), p, (jnp.asarray(3e-3), jnp.asarray(1e-3)))


def _random_states(p, n=STATES, seed=0):
    """`n` flat states with random unit quaternions, rates of order 1/s, positions and wheel
    angles, and `n` random torque vectors."""
    N = p.n_wheels
    ks = jax.random.split(jax.random.PRNGKey(seed), 6)
    q = jax.random.normal(ks[0], (n, 4))
    qs = jax.random.normal(ks[1], (n, 4))
    q, qs = q / jnp.linalg.norm(q, axis=1, keepdims=True), qs / jnp.linalg.norm(qs, axis=1, keepdims=True)
    w, W = 2.0 * jax.random.normal(ks[2], (n, 3)), 2.0 * jax.random.normal(ks[3], (n, 3))
    xy_chi = jax.random.normal(ks[4], (n, 2 + N))
    z = jnp.concatenate([q, qs, w, W, xy_chi], axis=1)
    return z, 0.05 * jax.random.normal(ks[5], (n, N))


def test_blocks_and_forces_match_the_model(robot):
    """`B`, `D` (mass blocks) and `r1`, `r2` (right-hand sides) of (3.4)."""
    p, d = robot, derive(robot)
    zs, _ = _random_states(p)
    for z in zs:
        g, w, W = rotmat(z[Flat.q])[2], z[Flat.omega], z[Flat.Omega]
        B, D, r1, r2 = C._blocks_and_forces(p, d, tuple(g), tuple(w), tuple(W))
        B_ref, D_ref = mass_blocks(p, d, g)
        r1_ref, r2_ref = forces(p, d, g, w, W)
        np.testing.assert_allclose(jnp.array(B), B_ref, rtol=1e-12, atol=1e-15)
        np.testing.assert_allclose(jnp.array(D), D_ref, rtol=1e-12, atol=1e-15)
        np.testing.assert_allclose(jnp.array(r1), r1_ref, rtol=1e-10, atol=1e-14)
        np.testing.assert_allclose(jnp.array(r2), r2_ref, rtol=1e-10, atol=1e-14)


def test_torque_field_matches_the_model(robot):
    """Every rate of the torque-mode field: accelerations (3.4)/(3.5), quaternion kinematics of
    platform and shell, rolling (2.3) and wheel rates (2.4)."""
    p, d = robot, derive(robot)
    zs, Ks = _random_states(p, seed=1)
    for z, K in zip(zs, Ks):
        rates = jnp.array(C.torque_field_components(p, d, tuple(K), C.to_components(z)))
        R = rotmat(z[Flat.q])
        g, w, W = R[2], z[Flat.omega], z[Flat.Omega]
        wd, Wd = solve_accelerations(p, d, g, w, W, K)
        np.testing.assert_allclose(rates[Flat.omega], wd, rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(rates[Flat.Omega], Wd, rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(rates[Flat.q], quat_rate_body(z[Flat.q], w), rtol=1e-12, atol=1e-15)
        np.testing.assert_allclose(rates[Flat.q_shell], quat_rate_fixed(z[Flat.q_shell], R @ W), rtol=1e-12, atol=1e-15)
        v = R @ (p.R0 * jnp.cross(W, g))
        np.testing.assert_allclose(rates[Flat.x], v[0], rtol=1e-12, atol=1e-15)
        np.testing.assert_allclose(rates[Flat.y], v[1], rtol=1e-12, atol=1e-15)
        np.testing.assert_allclose(rates[Flat.chi], -d.Sk @ (w - W), rtol=1e-12, atol=1e-15)


def test_adjoint_form_has_the_same_values(robot):
    """The form the discrete adjoint differentiates (`adjoint=True`, with `one = unit(t)`) gives
    the same rates."""
    p, d = robot, derive(robot)
    zs, Ks = _random_states(p, n=4, seed=2)
    for z, K in zip(zs, Ks):
        a = jnp.array(C.torque_field_components(p, d, tuple(K), C.to_components(z)))
        b = jnp.array(C.torque_field_components(p, d, tuple(K), C.to_components(z), C.unit(0.3), adjoint=True))
        np.testing.assert_allclose(a, b, rtol=1e-13, atol=1e-16)


def test_gait_field_matches_the_model(robot):
    """Gait mode: `Omega_dot` of the control-free sum of (3.4) (`free_Omega_dot`) with the
    prescribed `gamma`, `omega`, `omega_dot`, and the kinematic rates."""
    p, d = robot, derive(robot)
    zs, _ = _random_states(p, seed=3)
    kins = jax.random.normal(jax.random.PRNGKey(4), (zs.shape[0], 9))
    for z, kin in zip(zs, kins):
        g = kin[0:3] / jnp.linalg.norm(kin[0:3])
        w, wd = kin[3:6], kin[6:9]
        rates = jnp.array(C.gait_field_components(p, d, (*g, *w, *wd), C.to_components(z)))
        np.testing.assert_allclose(rates[Flat.omega], wd, rtol=1e-12, atol=1e-15)
        Wd = free_Omega_dot(p, d, g, w, z[Flat.Omega], wd)
        np.testing.assert_allclose(rates[Flat.Omega], Wd, rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(rates[Flat.q], quat_rate_body(z[Flat.q], w), rtol=1e-12, atol=1e-15)
        v = rotmat(z[Flat.q]) @ (p.R0 * jnp.cross(z[Flat.Omega], g))
        np.testing.assert_allclose(rates[Flat.x], v[0], rtol=1e-12, atol=1e-15)
        np.testing.assert_allclose(rates[Flat.chi], -d.Sk @ (w - z[Flat.Omega]), rtol=1e-12, atol=1e-15)


def test_layout_round_trip(robot):
    z, _ = _random_states(robot, n=3, seed=5)
    c = C.to_components(z)
    assert len(c) == 16 + robot.n_wheels
    np.testing.assert_array_equal(C.from_components(c), z)
