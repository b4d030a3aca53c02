"""A trial that cannot be integrated fails alone in a batch with shared steps (`throw=False`):
the other trials get the results they get in a batch without it, and only it is flagged."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jsphere
from jsphere import RobotParams, State, Torques, simulate, simulate_gaits

B = 32  # the smallest batch that shares one step sequence
BAD = 5


class Amp(eqx.Module):
    """Torques `a sin(t) (1, -0.5, 0.3)`, plus `b` after t = 1 s (NaN `b`: the rates turn
    non-finite in mid-run)."""

    a: jax.Array
    b: jax.Array

    def __call__(self, t):
        return (self.a * jnp.sin(t) + jnp.where(t > 1.0, self.b, 0.0)) * jnp.array([1.0, -0.5, 0.3])


@pytest.fixture(scope="module")
def run():
    p = RobotParams.paper()
    s0 = State.at_rest(p)
    return jax.jit(
        jax.vmap(
            lambda a, b: simulate(
                p, s0, Torques(Amp(a, b)), 2.0, ts=jnp.linspace(0.0, 2.0, 5), throw=False, max_steps=300
            )
        )
    )


@pytest.fixture(scope="module")
def amps():
    return np.linspace(0.01, 0.05, B), np.zeros(B)


def _check_alone(good, tr, bad):
    ok = np.asarray(tr.ok)
    assert ok.shape == (B,)
    np.testing.assert_array_equal(ok, np.arange(B) != bad)
    keep = np.arange(B) != bad
    for field in ("x", "y", "omega", "Omega"):
        np.testing.assert_allclose(
            np.asarray(getattr(tr, field))[keep], np.asarray(getattr(good, field))[keep], rtol=1e-5, atol=1e-6
        )  # shared against per-trial steps
    assert np.all(np.asarray(tr.status)[keep] == 0) and int(np.asarray(tr.status)[bad]) != 0


@pytest.mark.slow
def test_hopeless_trial_fails_alone(run, amps):
    a, b = amps
    good = run(a, b)
    assert bool(np.all(np.asarray(good.ok)))
    a_bad = a.copy()
    a_bad[BAD] = 1e4  # needs far more than max_steps
    _check_alone(good, run(a_bad, b), BAD)


@pytest.mark.slow
def test_diverging_trial_fails_alone(run, amps):
    a, b = amps
    good = run(a, b)
    b_bad = b.copy()
    b_bad[7] = np.nan  # finite at the start, NaN rates after 1 s
    _check_alone(good, run(a, b_bad), 7)


@pytest.mark.slow
def test_with_throw_a_failed_batch_raises():
    """`throw=True` (the default) reports the failure as an error (no per-trial solve)."""
    p = RobotParams.paper()
    s0 = State.at_rest(p)
    a = np.linspace(0.01, 0.05, B)
    a[BAD] = 1e4
    f = jax.jit(jax.vmap(lambda a: simulate(p, s0, Torques(Amp(a, jnp.zeros(()))), 2.0, max_steps=300)))
    with pytest.raises(Exception, match="max_steps"):
        jax.block_until_ready(f(jnp.asarray(a)))


@pytest.mark.slow
def test_gaits_hopeless_trial_fails_alone():
    p = RobotParams.paper()
    ths = np.linspace(0.05, 0.1, B)

    @jax.jit
    @jax.vmap
    def run(th):
        return simulate_gaits(
            p,
            [jsphere.acceleration(theta_max=th), jsphere.braking(theta_max=th)],
            ts=jnp.array([1.0, 4.0]),
            throw=False,
            max_steps=50,
        )

    good = run(ths)
    assert bool(np.all(np.asarray(good.ok)))
    bad = ths.copy()
    bad[BAD] = 1.4  # ~65 steps a segment alone
    tr = run(bad)
    np.testing.assert_array_equal(np.asarray(tr.ok), np.arange(B) != BAD)
    keep = np.arange(B) != BAD
    np.testing.assert_allclose(np.asarray(tr.x)[keep], np.asarray(good.x)[keep], rtol=1e-5, atol=1e-6)


@pytest.mark.slow
def test_gradient_of_the_good_trials(amps):
    """The gradient with a hopeless trial in the batch (masked out of the loss) is the gradient
    without it, and finite."""
    p = RobotParams.paper()
    s0 = State.at_rest(p)
    a, b = amps
    keep = jnp.asarray(np.arange(B) != BAD)

    def loss(scale, a):
        tr = jax.vmap(
            lambda a: simulate(p, s0, Torques(Amp(scale * a, jnp.zeros(()))), 2.0, throw=False, max_steps=300)
        )(a)
        return jnp.sum(jnp.where(keep & tr.ok, tr.x[:, -1], 0.0))

    g = jax.jit(jax.grad(loss))
    a_bad = a.copy()
    a_bad[BAD] = 1e4
    g_good, g_bad = float(g(1.0, a)), float(g(1.0, a_bad))
    assert np.isfinite(g_bad)
    np.testing.assert_allclose(g_bad, g_good, rtol=1e-6)


@pytest.mark.slow
def test_other_solvers_fail_alone_too():
    """A solver outside jsphere's own loop (diffrax's `diffeqsolve` with shared steps) falls
    back to per-trial solves in the same way."""
    import diffrax as dfx

    p = RobotParams.paper()
    s0 = State.at_rest(p)
    run = jax.jit(
        jax.vmap(
            lambda a: simulate(
                p, s0, Torques(Amp(a, jnp.zeros(()))), 2.0, throw=False, max_steps=3000, solver=dfx.Bosh3()
            )
        )
    )
    a = np.linspace(0.01, 0.05, B)
    good = run(a)
    assert bool(np.all(np.asarray(good.ok)))
    a[BAD] = 1e4
    tr = run(a)
    np.testing.assert_array_equal(np.asarray(tr.ok), np.arange(B) != BAD)
    keep = np.arange(B) != BAD
    np.testing.assert_allclose(np.asarray(tr.x)[keep], np.asarray(good.x)[keep], rtol=1e-5, atol=1e-6)
