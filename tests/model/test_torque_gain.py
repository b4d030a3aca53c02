"""The torque gain `k_tau`: the model applies `k_tau K` for commanded torques `K`, in the single
and the batched torque fields alike; the torques it returns are commanded ones; `k_tau` with
every mass and inertia scaled together changes no torque-driven motion."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

import jsphere
from jsphere.model.dynamics import accelerations, required_torques, solve_accelerations
from jsphere.model.params import derive
from jsphere.model.rotations import rotmat
from jsphere.model.state import Flat
from jsphere.solve.batched import components as C


def _state(seed=0):
    ks = jax.random.split(jax.random.PRNGKey(seed), 4)
    q = jax.random.normal(ks[0], (4,))
    q = q / jnp.linalg.norm(q)
    w, W = jax.random.normal(ks[1], (3,)), jax.random.normal(ks[2], (3,))
    return rotmat(q)[2], w, W, 0.05 * jax.random.normal(ks[3], (3,)), q


def test_the_gain_multiplies_the_commanded_torques():
    p = jsphere.RobotParams.paper().replace(c_axle=1e-3)
    g, w, W, K, _ = _state()
    a = accelerations(p.replace(k_tau=0.9), g, w, W, K)
    b = accelerations(p, g, w, W, 0.9 * K)
    for x, y in zip(a, b):
        np.testing.assert_allclose(x, y, rtol=1e-12, atol=1e-15)


def test_the_batched_field_applies_the_gain_as_the_model_does():
    p = jsphere.RobotParams.paper().replace(k_tau=0.85, c_axle=1e-3)
    d = derive(p)
    g, w, W, K, q = _state(1)
    z = jnp.concatenate([q, q, w, W, jnp.zeros(2 + 3)])
    rates = C.torque_field_components(p, d, tuple(K), tuple(z))
    wd, Wd = solve_accelerations(p, d, rotmat(q)[2], w, W, K)
    np.testing.assert_allclose(jnp.array(rates)[Flat.omega], wd, rtol=1e-10, atol=1e-14)
    np.testing.assert_allclose(jnp.array(rates)[Flat.Omega], Wd, rtol=1e-10, atol=1e-14)


def test_returned_torques_are_commanded_ones():
    p = jsphere.RobotParams.paper().replace(k_tau=0.8, c_axle=1e-3)
    d = derive(p)
    g, w, W, K, _ = _state(2)
    wd, Wd = solve_accelerations(p, d, g, w, W, K)
    np.testing.assert_allclose(required_torques(p, d, g, w, W, wd, Wd), K, rtol=1e-9, atol=1e-13)


def test_torque_motion_does_not_change_when_the_gain_and_every_mass_scale_together():
    p = jsphere.RobotParams.paper().replace(c_axle=1e-4)
    s = 1.25
    q = p.replace(k_tau=s, m0=p.m0 * s, m=p.m * s, I0=p.I0 * s, I=p.I * s, j=p.j * s, c_axle=p.c_axle * s)
    u = jsphere.random_inputs(p, 1.5, kind="torques", seed=0)
    ts = np.linspace(0, 1.5, 31)
    a = jsphere.simulate(p, jsphere.State.at_rest(p), u, 1.5, ts=ts, rtol=1e-10, atol=1e-12)
    b = jsphere.simulate(q, jsphere.State.at_rest(q), u, 1.5, ts=ts, rtol=1e-10, atol=1e-12)
    assert float(jnp.max(jnp.abs(a.x))) > 1e-3
    assert float(jnp.max(jnp.abs(a.x - b.x))) < 1e-9 and float(jnp.max(jnp.abs(a.q - b.q))) < 1e-9
    c = jsphere.simulate(p.replace(k_tau=s), jsphere.State.at_rest(p), u, 1.5, ts=ts, rtol=1e-10, atol=1e-12)
    assert float(jnp.max(jnp.abs(a.x - c.x))) > 1e-4  # the gain alone does change it
