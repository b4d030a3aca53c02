"""(3.4) against the energy (3.2)-(3.3): an exact, integration-free check of every term."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from robots import random_robot

import jsphere
from jsphere.model.dynamics import free_momentum, free_Omega_dot, mass_blocks, required_torques, servo_jump
from jsphere.model.params import derive


def random_state(key, n_wheels=3):
    ks = jax.random.split(key, 4)
    g = jax.random.normal(ks[0], (3,))
    return (
        g / jnp.linalg.norm(g),
        jax.random.normal(ks[1], (3,)),
        jax.random.normal(ks[2], (3,)),
        0.05 * jax.random.normal(ks[3], (n_wheels,)),
    )


ROBOTS = [("paper", None, 3), ("random3", 1, 3), ("random4", 2, 4), ("random5", 3, 5)]


def _robot(spec):
    name, seed, n = spec
    return jsphere.RobotParams.paper() if seed is None else random_robot(jax.random.PRNGKey(seed), n)


@pytest.mark.parametrize("spec", ROBOTS, ids=[r[0] for r in ROBOTS])
def test_energy_rate_equals_motor_power(spec):
    """d(T + U)/dt along (3.4), (3.5) equals sum K_i chi_dot_i, at random states and torques."""
    p = _robot(spec)
    for seed in range(5):
        gamma, omega, Omega, K = random_state(jax.random.PRNGKey(10 + seed), p.n_wheels)
        wd, Wd = jsphere.accelerations(p, gamma, omega, Omega, K)
        gd = jnp.cross(gamma, omega)  # Poisson equation (3.5)
        _, dE = jax.jvp(lambda g, w, W: jsphere.energy(p, g, w, W), (gamma, omega, Omega), (gd, wd, Wd))
        P = jsphere.power(p, omega, Omega, K)
        scale = float(jnp.abs(P)) + 1e-3 * float(jnp.abs(jsphere.kinetic_energy(p, gamma, omega, Omega)))
        assert abs(float(dE - P)) < 1e-10 * scale, (seed, float(dE), float(P))


@pytest.mark.parametrize("spec", ROBOTS, ids=[r[0] for r in ROBOTS])
def test_mass_matrix_is_kinetic_energy_hessian(spec):
    p = _robot(spec)
    d = derive(p)
    gamma, omega, Omega, _ = random_state(jax.random.PRNGKey(3), p.n_wheels)
    H = jax.hessian(lambda u: jsphere.kinetic_energy(p, gamma, u[:3], u[3:]))(jnp.concatenate([omega, Omega]))
    B, D = mass_blocks(p, d, gamma)
    M = jnp.block([[d.A, B], [B.T, D]])
    np.testing.assert_allclose(M, H, rtol=1e-12, atol=1e-14)
    assert np.all(np.linalg.eigvalsh(np.asarray(M)) > 0)


@pytest.mark.parametrize("spec", ROBOTS, ids=[r[0] for r in ROBOTS])
def test_control_free_sum_and_torque_recovery(spec):
    """The torques cancel in the sum of the two equations; either equation recovers them."""
    p = _robot(spec)
    d = derive(p)
    gamma, omega, Omega, K = random_state(jax.random.PRNGKey(5), p.n_wheels)
    K_ln = d.Sk_T_pinv @ (d.Sk.T @ K)  # the least-norm torques with the same effect
    wd, Wd = jsphere.accelerations(p, gamma, omega, Omega, K)
    np.testing.assert_allclose(free_Omega_dot(p, d, gamma, omega, Omega, wd), Wd, rtol=1e-8, atol=1e-12)
    for eq in (1, 2):
        np.testing.assert_allclose(
            required_torques(p, d, gamma, omega, Omega, wd, Wd, equation=eq), K_ln, rtol=1e-8, atol=1e-12
        )
    if p.n_wheels > 3:  # least norm: no component in the null space of Sk^T
        assert np.linalg.norm(K_ln) <= np.linalg.norm(K) + 1e-15


def test_servo_jump_conserves_free_momentum():
    p = _robot(ROBOTS[2])
    d = derive(p)
    gamma, omega, Omega, _ = random_state(jax.random.PRNGKey(7), p.n_wheels)
    w_new = jnp.array([0.3, -0.2, 0.5])
    op, Op = servo_jump(p, d, gamma, omega, Omega, w_new)
    np.testing.assert_allclose(op - Op, w_new, atol=1e-14)
    np.testing.assert_allclose(
        free_momentum(p, d, gamma, op, Op), free_momentum(p, d, gamma, omega, Omega), rtol=1e-12, atol=1e-15
    )


def test_rest_is_an_equilibrium(paper):
    z = jnp.zeros(3)
    wd, Wd = jsphere.accelerations(paper, jnp.array([0.0, 0.0, 1.0]), z, z, jnp.zeros(3))
    np.testing.assert_allclose(np.concatenate([wd, Wd]), 0.0, atol=1e-15)


def test_paper_wheel_factors(paper):
    d = derive(paper)
    np.testing.assert_allclose(d.k, -53.166, atol=1e-3)


def test_energy_conserved_without_torques(paper):
    s0 = jsphere.State.from_axes(
        paper, (1, 0, 0), (0, np.cos(0.3), np.sin(0.3)), omega=(0.1, 0.0, 0.3), Omega=(0.5, 0.2, 0.1)
    )
    tr = jsphere.simulate(
        paper, s0, jsphere.Torques(lambda t: jnp.zeros(3)), 5.0, ts=jnp.linspace(0, 5, 51), rtol=1e-11, atol=1e-13
    )
    E = jsphere.energy_along(paper, tr)
    T0 = float(jsphere.kinetic_energy(paper, tr.gamma[0], tr.omega[0], tr.Omega[0]))
    assert np.max(np.abs(E - E[0])) < 1e-9 * max(abs(float(E[0])), T0)
    res = jsphere.trajectory_residuals(paper, tr)
    assert all(float(v) < 1e-9 for v in res.values()), res


def test_energy_balance_with_torques(paper):
    """E(t) - E(0) = integral of sum K_i chi_dot_i dt along a torque-driven motion."""
    ts = jnp.linspace(0.0, 2.0, 2001)
    tr = jsphere.simulate(
        paper,
        jsphere.State.at_rest(paper),
        jsphere.Torques(lambda t: 0.01 * jnp.sin(jnp.pi * t + jnp.array([0.0, 2.1, 4.2]))),
        2.0,
        ts=ts,
        rtol=1e-11,
        atol=1e-13,
    )
    E = np.asarray(jsphere.energy_along(paper, tr))
    P = np.asarray(jsphere.power_along(paper, tr))
    work = np.concatenate([[0.0], np.cumsum(0.5 * (P[1:] + P[:-1]) * np.diff(np.asarray(ts)))])
    assert np.max(np.abs(E - E[0] - work)) < 1e-5 * np.max(np.abs(work))  # trapezoid rule, h = 1 ms


@pytest.mark.parametrize("spec", ROBOTS[:3], ids=[r[0] for r in ROBOTS[:3]])
def test_energy_rate_with_damping(spec):
    """With rolling resistance and axle friction: d(T + U)/dt = sum K chi_dot - dissipation <= power."""
    p = _robot(spec).replace(c_roll=2e-3, c_axle=5e-4)
    d = derive(p)
    for seed in range(3):
        gamma, omega, Omega, K = random_state(jax.random.PRNGKey(20 + seed), p.n_wheels)
        wd, Wd = jsphere.accelerations(p, gamma, omega, Omega, K)
        _, dE = jax.jvp(
            lambda g, w, W: jsphere.energy(p, g, w, W), (gamma, omega, Omega), (jnp.cross(gamma, omega), wd, Wd)
        )
        P, Dis = jsphere.power(p, omega, Omega, K), jsphere.dissipation(p, gamma, omega, Omega)
        assert float(Dis) > 0
        assert abs(float(dE - (P - Dis))) < 1e-10 * (abs(float(P)) + float(Dis))
        # the motor torques a prescribed motion needs include the friction they overcome
        K_back = required_torques(p, d, gamma, omega, Omega, wd, Wd)
        np.testing.assert_allclose(d.Sk.T @ K_back, d.Sk.T @ K, rtol=1e-8, atol=1e-12)


def test_damping_is_validated(paper):
    with pytest.raises(ValueError, match="RobotParams.c_roll"):
        paper.replace(c_roll=-1.0)
