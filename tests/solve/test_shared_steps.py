"""Batched torque- and gait-mode solves with one step sequence for the batch (`batch_steps="shared"`,
the default under `vmap`; jsphere.solve.batched.segment).

Every trial must still be integrated to its own tolerance: the tests compare each trial with a
tight solve of the same trial, against the error the per-trial controller makes, and check
that a failing trial neither stalls nor poisons the others.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jsphere
import jsphere.solve.batched.layout as L

PH = jnp.array([0.0, 2.1, 4.2])


class Sines(eqx.Module):
    a: jax.Array

    def __call__(self, t):
        return self.a * jnp.sin(jnp.pi * t + PH)


class Flip(eqx.Module):
    """`K = a` before t = 1 s, `-a` after: a jump (the solve restarts there)."""

    a: jax.Array

    def __call__(self, t):
        return jnp.where(t < 1.0, self.a, -self.a)


@pytest.fixture(autouse=True)
def _share_small_batches(monkeypatch):
    """The batches here are a few trials; by default only batches of `SHARED_MIN_BATCH` share."""
    monkeypatch.setattr(L, "SHARED_MIN_BATCH", 2)


P = jsphere.RobotParams.paper()
A = 0.05 * (1 + 0.1 * jax.random.normal(jax.random.PRNGKey(0), (4, 3)))
TS = jnp.linspace(0.0, 2.0, 5)


def _sim(a, *, t1=2.0, ctrl=Sines, jump_ts=(), **kw):
    return jsphere.simulate(P, jsphere.State.at_rest(P), jsphere.Torques(ctrl(a), jump_ts=jump_ts), t1, ts=TS, **kw)


@pytest.mark.slow
def test_shared_steps_meet_each_trials_tolerance():
    """The batch shares its steps (one `num_steps`), and each trial stays as close to a tight
    solve of itself as the per-trial controller gets it (both ~1e-9 m, `docs/model.md` section 9;
    bound 1e-8 m, 1e5 times below the paper's 1 mm scale)."""
    # the closure form of the benchmark's problem 1: a traced amplitude inside a lambda
    shared = jax.jit(jax.vmap(lambda a: _sim(a, ctrl=lambda a: lambda t: a * jnp.sin(jnp.pi * t + PH))))(A)
    tight = jax.jit(jax.vmap(lambda a: _sim(a, rtol=1e-12, atol=1e-14, batch_steps="per_trial")))(A)
    assert np.all(np.asarray(shared.ok))
    assert len(set(np.asarray(shared.num_steps).tolist())) == 1
    for name in ("x", "y"):
        err = np.max(np.abs(np.asarray(getattr(shared, name) - getattr(tight, name))))
        assert err < 1e-8, (name, err)
    for name in ("gamma", "omega", "Omega", "chi", "chi_dot", "K", "q", "q_shell"):
        np.testing.assert_allclose(getattr(shared, name), getattr(tight, name), rtol=1e-6, atol=1e-8, err_msg=name)


@pytest.mark.slow
def test_shared_steps_across_jumps_and_batched_times_fall_back():
    """A control with a jump (two segments, each with a shared step sequence), and batched final
    times (no shared time axis: one step sequence per trial)."""
    tr = jax.vmap(lambda a: _sim(a, ctrl=Flip, jump_ts=(1.0,)))(A[:3])
    for i in range(3):
        one = _sim(A[i], ctrl=Flip, jump_ts=(1.0,))
        np.testing.assert_allclose(tr.x[i], one.x, rtol=0, atol=1e-8)
        assert int(tr.segment[i, -1]) == 1 and bool(tr.ok[i])
    t1 = jnp.array([1.5, 2.0])
    tb = jax.vmap(lambda a, t: _sim(a, t1=t, ctrl=Flip, jump_ts=(1.0,)).x[-1])(A[:2], t1)
    for i in range(2):
        assert abs(float(tb[i] - _sim(A[i], t1=t1[i], ctrl=Flip, jump_ts=(1.0,)).x[-1])) < 1e-9


@pytest.mark.slow
def test_shared_steps_over_initial_states_with_one_control():
    """Only the states batched (the control is the same for every trial)."""
    s0 = [jsphere.State.at_rest(P, x=0.1), jsphere.State.from_axes(P, Omega=(0.0, 0.5, 0.0))]
    S0 = jax.tree_util.tree_map(lambda *x: jnp.stack(x), *s0)
    out = jax.vmap(lambda s: jsphere.simulate(P, s, jsphere.Torques(jsphere.Zero(P.n_wheels)), 1.0))(S0)
    for i, s in enumerate(s0):
        np.testing.assert_allclose(
            out.x[i, -1],
            jsphere.simulate(P, s, jsphere.Torques(jsphere.Zero(P.n_wheels)), 1.0).x[-1],
            rtol=0,
            atol=1e-8,
        )


@pytest.mark.slow
def test_a_failing_trial_does_not_stall_the_batch():
    """A trial with NaN inputs is left out of the step-size control: the others finish as they
    would alone, and it alone is reported as failed (throw=False)."""
    An = A[:3].at[1, 0].set(jnp.nan)
    tr = jax.vmap(lambda a: _sim(a, throw=False))(An)
    assert tr.ok.tolist() == [True, False, True]
    valid = jax.vmap(lambda a: _sim(a, throw=False))(A[:3])  # same program, no NaN
    np.testing.assert_allclose(tr.x[::2], valid.x[::2], rtol=0, atol=1e-8)
    # throw=True under vmap: equinox raises at run time, or poisons the output with NaN where
    # equinox's on-error mode is "nan" (as the CLI sets it; an earlier test may have)
    try:
        x = jax.vmap(lambda a: _sim(a).x)(An)
        assert not np.all(np.isfinite(np.asarray(x)))
    except Exception as e:  # noqa: BLE001
        assert "NaN" in str(e) or "max_steps" in str(e)


def test_batch_steps_is_checked():
    with pytest.raises(ValueError, match="batch_steps"):
        _sim(A[0], batch_steps="together")


def _theta_loss(theta, steps):
    """Problem 3 of benchmarks/ in small: the batch-summed squared final distance, as a
    function of `(j, r_m[2], I[0, 0])`."""
    q = eqx.tree_at(lambda q: (q.j, q.r_m, q.I), P, (theta[0], P.r_m.at[2].set(theta[1]), P.I.at[0, 0].set(theta[2])))
    tr = jax.vmap(
        lambda a: jsphere.simulate(
            q, jsphere.State.at_rest(q), jsphere.Torques(Sines(a)), 1.0, rtol=1e-10, atol=1e-12, batch_steps=steps
        )
    )(A[:3])
    return jnp.sum(tr.x[:, -1] ** 2 + tr.y[:, -1] ** 2)


THETA = jnp.stack([P.j, P.r_m[2], P.I[0, 0]])


@pytest.mark.slow
def test_gradient_of_a_batch_sharing_its_steps():
    """The gradient of a batch that shares its steps is the discrete adjoint of the shared solve
    (`jsphere.solve.batched.loop`, the parameter arrays element by element): central differences of
    the same batched solve (their error: the tolerance over the step, ~1e-7 here)."""
    g = jax.jit(jax.grad(lambda th: _theta_loss(th, "shared")))(THETA)
    f = jax.jit(lambda th: _theta_loss(th, "shared"))
    for k in range(3):
        h = 1e-4 * abs(float(THETA[k]))
        e = jnp.zeros(3).at[k].set(h)
        fd = (float(f(THETA + e)) - float(f(THETA - e))) / (2 * h)
        assert abs(float(g[k]) - fd) < 1e-5 * abs(fd), (k, float(g[k]), fd)


@pytest.mark.slow
def test_gradient_of_a_shared_batch_is_the_per_trial_one():
    """The shared adjoint and the per-trial VJP differentiate two discretisations of one
    solution: their gradients agree to the tolerance."""
    g = jax.jit(jax.grad(lambda th: _theta_loss(th, "shared")))(THETA)
    g1 = jax.jit(jax.grad(lambda th: _theta_loss(th, "per_trial")))(THETA)
    np.testing.assert_allclose(g, g1, rtol=1e-6)


@pytest.mark.slow
def test_gradient_of_shared_gaits_is_the_per_trial_one():
    """Gait mode: the shared adjoint w.r.t. a parameter and the vmapped gait parameter equals
    the per-trial gradient (measured: 8 digits; central differences agree as well)."""
    th = jnp.array([0.06, 0.1, 0.13])

    def loss(j, th, steps):
        q = eqx.tree_at(lambda q: q.j, P, j)
        gaits = lambda t: [jsphere.acceleration(theta_max=t), jsphere.braking(theta_max=t)]  # noqa: E731
        tr = jax.vmap(lambda t: jsphere.simulate_gaits(q, gaits(t), ts=jnp.array([0.0, 4.0]), batch_steps=steps))(th)
        return jnp.sum(tr.x[:, -1] ** 2 + tr.y[:, -1])

    g = jax.jit(jax.grad(lambda j, th: loss(j, th, "shared"), argnums=(0, 1)))(P.j, th)
    g1 = jax.jit(jax.grad(lambda j, th: loss(j, th, "per_trial"), argnums=(0, 1)))(P.j, th)
    np.testing.assert_allclose(g[0], g1[0], rtol=1e-7)
    np.testing.assert_allclose(g[1], g1[1], rtol=1e-7)


@pytest.mark.slow
def test_shared_steps_for_gaits():
    """`simulate_gaits` under `vmap` over a gait parameter (problem 2 of benchmarks/): one step
    sequence for the batch on the component layout, each trial as a single call gives it (the
    gait tolerances rtol 1e-10, atol 1e-12: agreement ~1e-12 m); a reset between the gaits."""
    th = jnp.array([0.05, 0.08, 0.11, 0.15])
    ts = jnp.linspace(0.0, 4.0, 9)

    def run(t):
        return jsphere.simulate_gaits(
            P, [jsphere.acceleration(theta_max=t), jsphere.braking(theta_max=t)], ts=ts, reset=True
        )

    tr = jax.jit(jax.vmap(run))(th)
    assert np.all(np.asarray(tr.ok)) and len(set(np.asarray(tr.num_steps).tolist())) == 1
    for i in (0, 3):
        one = run(th[i])
        for name in ("x", "y", "gamma", "omega", "Omega", "chi_dot", "K", "q_shell"):
            np.testing.assert_allclose(getattr(tr, name)[i], getattr(one, name), rtol=1e-8, atol=1e-10, err_msg=name)
        assert int(one.num_steps) <= int(tr.num_steps[i])
    with pytest.raises(ValueError, match="batch_steps"):
        jsphere.simulate_gaits(P, [jsphere.acceleration()], batch_steps="together")


A7 = jnp.concatenate([A, 0.05 * (1 + 0.1 * jax.random.normal(jax.random.PRNGKey(1), (3, 3)))])


@pytest.mark.slow
def test_per_trial_steps_do_not_depend_on_the_batch():
    """`batch_steps="per_trial"` runs a batch in the same vectorised loop with each trial's own
    step sequence, in lockstep (`jsphere.solve.batched.loop.forward`, `per_trial`): a trial's result is bitwise
    the same whatever the other trials of its batch, its step count is its own, and it is as
    close to a tight solve of itself as the shared steps get (interior save times included:
    each trial's own dense output)."""
    run = jax.jit(jax.vmap(lambda a: _sim(a, batch_steps="per_trial")))
    big = run(A7)
    other = run(jnp.concatenate([A7[4:], A7[:1]]))  # three of the trials in a smaller batch
    for name in ("x", "y", "q", "Omega", "chi", "num_steps"):
        np.testing.assert_array_equal(getattr(other, name)[:3], getattr(big, name)[4:], err_msg=name)
    assert np.all(np.asarray(big.ok)) and len(set(np.asarray(big.num_steps).tolist())) > 1
    tight = jax.jit(jax.vmap(lambda a: _sim(a, rtol=1e-12, atol=1e-14)))(A7)
    for name in ("x", "y"):
        err = np.max(np.abs(np.asarray(getattr(big, name) - getattr(tight, name))))
        assert err < 1e-8, (name, err)
    # a single call (diffrax's loop and controller) agrees to the tolerance as well
    one = _sim(A7[5])
    assert np.max(np.abs(np.asarray(one.x - big.x[5]))) < 1e-8


@pytest.mark.slow
def test_a_failing_trial_leaves_per_trial_steps_alone():
    """A trial with NaN inputs fails alone; every other trial is bitwise what it is without it."""
    run = jax.jit(jax.vmap(lambda a: _sim(a, throw=False, batch_steps="per_trial")))
    tr, valid = run(A7.at[2, 1].set(jnp.nan)), run(A7)
    assert tr.ok.tolist() == [True, True, False, True, True, True, True]
    keep = np.array([0, 1, 3, 4, 5, 6])
    for name in ("x", "y", "Omega", "num_steps"):
        np.testing.assert_array_equal(
            np.asarray(getattr(tr, name))[keep], np.asarray(getattr(valid, name))[keep], err_msg=name
        )


def _saved_loss(theta, steps):
    """`_theta_loss` over every save time of `TS` (interior saves: the dense output's adjoint)."""
    q = eqx.tree_at(lambda q: (q.j, q.r_m, q.I), P, (theta[0], P.r_m.at[2].set(theta[1]), P.I.at[0, 0].set(theta[2])))
    tr = jax.vmap(
        lambda a: jsphere.simulate(
            q,
            jsphere.State.at_rest(q),
            jsphere.Torques(Sines(a)),
            2.0,
            ts=TS,
            rtol=1e-10,
            atol=1e-12,
            batch_steps=steps,
        )
    )(A7)
    return jnp.sum(tr.x**2 + tr.y**2)


@pytest.mark.slow
@pytest.mark.parametrize("loss", [_theta_loss, _saved_loss], ids=["final", "saved"])
def test_gradient_of_per_trial_steps(monkeypatch, loss):
    """The gradient of a batch with per-trial steps is the discrete adjoint of its lockstep
    iterations (each trial's own step sizes; a rejected or finished trial's iteration is the
    identity): its value is the forward solve's, it matches central differences of the same
    solve (their error ~1e-7 here), and the per-trial VJP of diffrax's loop (flat layout,
    small batches) to the tolerance."""
    f = jax.jit(lambda th: loss(th, "per_trial"))
    v, g = jax.jit(jax.value_and_grad(lambda th: loss(th, "per_trial")))(THETA)
    assert float(v) == float(f(THETA))
    for k in range(3):
        h = 1e-4 * abs(float(THETA[k]))
        e = jnp.zeros(3).at[k].set(h)
        fd = (float(f(THETA + e)) - float(f(THETA - e))) / (2 * h)
        assert abs(float(g[k]) - fd) < 1e-5 * abs(fd), (k, float(g[k]), fd)
    monkeypatch.setattr(L, "SHARED_MIN_BATCH", 10**9)  # diffrax's loop per trial
    g_flat = jax.jit(jax.grad(lambda th: loss(th, "per_trial")))(THETA)
    np.testing.assert_allclose(g, g_flat, rtol=1e-6)
