"""Eager calls: their programs' compiler options, and gradients with respect to few inputs in
forward mode (`jsphere.solve.batched.dispatch`), which must equal reverse mode's."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jsphere
from jsphere._runtime import quick_compile
from jsphere.solve.batched import dispatch


def test_eager_jit_options_only_for_concrete_calls(monkeypatch):
    calls = []

    @quick_compile.eager_jit
    def f(x):
        calls.append(1)
        return jnp.sin(x) * 2

    assert float(f(1.0)) == pytest.approx(2 * np.sin(1.0))
    # under jit, grad and vmap the plain function is traced in (nested compiler options are an error)
    assert float(jax.jit(lambda x: f(x) + 1)(1.0)) == pytest.approx(2 * np.sin(1.0) + 1)
    assert float(jax.grad(f)(1.0)) == pytest.approx(2 * np.cos(1.0))
    np.testing.assert_allclose(jax.vmap(f)(jnp.ones(3)), 2 * np.sin(1.0) * np.ones(3))
    if jax.default_backend() == "cpu":
        assert quick_compile.options() == quick_compile.CPU_OPTIONS
    monkeypatch.setenv(quick_compile.DEFAULTS_VARIABLE, "1")
    assert quick_compile.options() is None


def _stop(p, theta_max, ts=(4.0,)):
    gaits = [jsphere.acceleration(theta_max=theta_max), jsphere.braking(theta_max=theta_max)]
    tr = jsphere.simulate_gaits(p, gaits, ts=jnp.array(ts))
    return tr.x[-1] + 0.5 * tr.y[-1] + 0.01 * jnp.sum(tr.K[-1])


def test_eager_gradient_of_few_inputs_is_forward_mode(monkeypatch):
    p = jsphere.RobotParams.paper()
    seen = []
    original = dispatch._flat_jacfwd
    monkeypatch.setattr(dispatch, "_flat_jacfwd", lambda *a: seen.append(1) or original(*a))
    g = float(jax.grad(lambda th: _stop(p, th))(0.1))
    assert seen, "a gradient with respect to one amplitude should take the forward-mode path"
    h = 1e-6
    fd = (float(_stop(p, 0.1 + h)) - float(_stop(p, 0.1 - h))) / (2 * h)
    assert g == pytest.approx(fd, rel=1e-6)
    # the pullback of the same forward pass, applied to a cotangent traced by `jit`
    y, pull = jax.vjp(lambda th: _stop(p, th), jnp.asarray(0.1))
    assert float(jax.jit(pull)(jnp.asarray(2.0))[0]) == pytest.approx(2 * g, rel=1e-12)


def _end(p, a, j):
    q = eqx.tree_at(lambda q: q.j, p, j)
    tq = jsphere.Torques(lambda t: a * jnp.sin(jnp.pi * t + jnp.array([0.0, 2.1, 4.2])))
    tr = jsphere.simulate(q, jsphere.State.at_rest(q), tq, 0.5, rtol=1e-9, atol=1e-11)
    return tr.x[-1] ** 2 + tr.y[-1] ** 2


def test_a_traced_gradient_of_few_inputs_is_forward_mode(monkeypatch):
    """`jit(grad)` of one solve with respect to a scalar (the wheels' inertia, which leaves the
    state at rest as it is) takes forward mode and agrees with reverse mode; under `vmap` the
    batch keeps its discrete adjoint."""
    p, a = jsphere.RobotParams.paper(), jnp.array([0.05, 0.04, 0.06])
    seen = []
    original = dispatch._flat_jacfwd
    monkeypatch.setattr(dispatch, "_flat_jacfwd", lambda *args: seen.append(1) or original(*args))
    g = float(jax.jit(jax.grad(lambda j: _end(p, a, j)))(3e-4))
    assert seen, "a jitted gradient with respect to one scalar should take the forward-mode path"
    seen.clear()
    monkeypatch.setattr(dispatch, "TRACED_FORWARD_MAX_INPUTS", 0)
    assert float(jax.jit(jax.grad(lambda j: _end(p, a, j)))(3e-4)) == pytest.approx(g, rel=1e-10)
    assert not seen
    monkeypatch.setattr(dispatch, "TRACED_FORWARD_MAX_INPUTS", 4)
    batch = jax.jit(jax.grad(lambda j: jnp.sum(jax.vmap(lambda ai: _end(p, ai, j))(jnp.stack([a, 0.9 * a])))))
    assert np.isfinite(float(batch(3e-4))) and not seen


@pytest.mark.slow
def test_forward_and_reverse_eager_gradients_agree(monkeypatch):
    """The checkpointed adjoint and forward mode differentiate the same discretised solve."""
    p = jsphere.RobotParams.paper()

    def loss(th):
        return _stop(p, th)

    forward = float(jax.grad(loss)(0.08))  # the forward program of the test above (same shapes)
    monkeypatch.setattr(dispatch, "FORWARD_MAX_INPUTS", 0)
    monkeypatch.setattr(dispatch, "_flat_jacfwd", None)  # must not be used
    reverse = float(jax.grad(loss)(0.08))
    assert forward == pytest.approx(reverse, rel=1e-9)
