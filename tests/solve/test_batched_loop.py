"""The shared-step Runge-Kutta loop behind batched solves (`jsphere.solve.batched.loop`): its methods are
diffrax's own tableaus and dense output, its step-size rule diffrax's PID defaults. Checked on
problems with known solutions, against `diffrax.diffeqsolve`, and on its failure modes."""

import diffrax as dfx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jsphere
import jsphere.solve.batched.layout as L
import jsphere.solve.batched.loop as R
import jsphere.solve.batched.method as RK

W = jnp.array([1.0, 2.0, 3.5, 5.0])  # one oscillator frequency per trial
TS = jnp.linspace(0.0, 3.0, 7)


def _oscillators(t, y, args=(), batched=()):  # y = (x, v), one column per trial: x'' = -w^2 x
    return jnp.stack([y[1], -(W**2) * y[0]])


def _exact(t):
    return np.stack([np.cos(np.asarray(W) * t), -np.asarray(W) * np.sin(np.asarray(W) * t)])


def _solve(solver, f=_oscillators, y0=None, t1=3.0, ts=TS, max_steps=4096, rtol=1e-8, atol=1e-10):
    y0 = jnp.stack([jnp.ones(4), jnp.zeros(4)]) if y0 is None else y0
    return jax.jit(
        lambda y0: R.solve(f, 0.0, t1, y0, ts, tab=RK.tableau(solver), rtol=rtol, atol=atol, max_steps=max_steps)
    )(y0)


@pytest.mark.parametrize("solver", [dfx.Dopri8(), dfx.Dopri5(), dfx.Tsit5()], ids=lambda s: type(s).__name__)
def test_meets_the_tolerance_at_the_save_times(solver):
    """The saved states (dense output inside steps, the state itself at t1) are the exact
    oscillations to the tolerance's scale, and the step count is that of diffrax's own
    controller on the hardest trial (the same rule; the norm is the worst trial's)."""
    ys, failed, accepted = _solve(solver)
    assert not bool(failed) and ys.shape == (8, 2, 4)
    for k, t in enumerate(TS.tolist()):  # the dense output: diffrax's own is ~8e-7 off here (Dopri8)
        np.testing.assert_allclose(ys[k], _exact(t), rtol=0, atol=2e-6, err_msg=f"t={t}")
    np.testing.assert_allclose(ys[-1], _exact(3.0), rtol=0, atol=2e-7)
    hardest = dfx.diffeqsolve(
        dfx.ODETerm(lambda t, y, a: jnp.array([y[1], -(W[-1] ** 2) * y[0]])),
        solver,
        0.0,
        3.0,
        None,
        jnp.array([1.0, 0.0]),
        stepsize_controller=dfx.PIDController(rtol=1e-8, atol=1e-10),
    )
    n1 = int(hardest.stats["num_accepted_steps"])
    assert n1 <= int(accepted) <= 1.3 * n1 + 2, (int(accepted), n1)


def test_a_trial_left_out_of_the_control_does_not_change_the_others():
    y0 = jnp.stack([jnp.ones(4), jnp.zeros(4)]).at[0, 3].set(jnp.nan)
    ys, failed, accepted = _solve(dfx.Dopri8(), y0=y0)
    ys3, _, accepted3 = _solve(dfx.Dopri8(), f=lambda t, y, *_: jnp.stack([y[1], -(W[:3] ** 2) * y[0]]), y0=y0[:, :3])
    assert not bool(failed) and int(accepted) == int(accepted3)
    np.testing.assert_array_equal(ys[:, :, :3], ys3)
    assert np.all(np.isnan(np.asarray(ys[1:, :, 3])))


def test_failures_are_reported():
    """Out of steps: `failed`, and the save rows it never reached are NaN (not zeros). A trial
    that blows up (y' = y^2 from 1, singular at t = 1) collapses the step size: `failed` long
    before `max_steps`."""
    ys, failed, accepted = _solve(dfx.Dopri8(), max_steps=5)
    assert bool(failed) and int(accepted) <= 5
    assert np.all(np.isnan(np.asarray(ys[-2]))) and np.all(np.isfinite(np.asarray(ys[0])))
    y0 = jnp.ones((1, 3))
    _, failed, accepted = _solve(
        dfx.Dopri8(), f=lambda t, y, *_: y * y, y0=y0, t1=2.0, ts=jnp.array([0.5]), max_steps=100_000
    )
    assert bool(failed) and int(accepted) < 10_000


def test_an_empty_interval_and_float32():
    y0 = jnp.stack([jnp.ones(4), jnp.zeros(4)])
    ys, failed, accepted = jax.jit(
        lambda y0: R.solve(
            _oscillators,
            1.0,
            1.0,
            y0,
            jnp.array([1.0]),
            tab=RK.tableau(dfx.Dopri8()),
            rtol=1e-8,
            atol=1e-10,
            max_steps=16,
        )
    )(y0)
    assert not bool(failed) and int(accepted) == 0
    np.testing.assert_array_equal(ys, jnp.stack([y0, y0]))
    ys32, failed32, _ = _solve(dfx.Tsit5(), y0=y0.astype(jnp.float32), rtol=1e-5, atol=1e-7)
    assert ys32.dtype == jnp.float32 and not bool(failed32)
    np.testing.assert_allclose(ys32[-1], _exact(3.0), rtol=0, atol=2e-4)


@pytest.mark.parametrize("solver", [dfx.Dopri8(), dfx.Dopri5(), dfx.Tsit5()], ids=lambda s: type(s).__name__)
def test_stage_arguments_are_the_tableau_rows(solver):
    """`stage_arg` (one switch branch per row, nonzero terms only) is `y + sum_j a_ij K[j]` for
    every stage, `y` itself at stage 0, with the stage index traced or a Python int."""
    tab = RK.tableau(solver)
    m = RK.Method(None, tab, jnp.float64)
    rng = np.random.default_rng(0)
    y, K = rng.standard_normal((3, 5)), rng.standard_normal((m.s, 3, 5))
    traced = jax.jit(lambda i: m.stage_arg(i, y, K))
    for i in range(m.s):
        want = y + np.tensordot(tab.a[i, :i], K[:i], axes=1)
        np.testing.assert_allclose(traced(i), want, rtol=1e-14, atol=1e-14)
        np.testing.assert_allclose(m.stage_arg(i, y, K), want, rtol=1e-14, atol=1e-14)
    np.testing.assert_array_equal(traced(0), y)


def test_only_diffrax_methods_it_implements():
    assert RK.tableau(dfx.Dopri8()) is not None and RK.tableau(dfx.Bosh3()) is None


class _OwnDopri5(dfx.AbstractERK):
    """A user's own method: Dopri5's tableau, declared outside diffrax."""

    tableau = dfx.Dopri5.tableau
    interpolation_cls = dfx.Dopri5.interpolation_cls

    def order(self, terms):
        return 5


class _OwnHeun(dfx.AbstractERK):
    """A user's own method that is not first same as last."""

    tableau = dfx.Heun.tableau
    interpolation_cls = dfx.Heun.interpolation_cls

    def order(self, terms):
        return 2


def test_a_users_own_first_same_as_last_method_runs_in_the_loop():
    """A user-defined explicit method with a first-same-as-last tableau is implemented (the
    same tableau as diffrax's solver of that tableau, and the same solve to the last bit); one
    that is not first same as last is left to `diffeqsolve`."""
    own, ref = RK.tableau(_OwnDopri5()), RK.tableau(dfx.Dopri5())
    np.testing.assert_array_equal(own.a, ref.a)
    np.testing.assert_array_equal(own.b_error, ref.b_error)
    assert own.order == 5 and RK.tableau(_OwnHeun()) is None
    ys, failed, accepted = _solve(_OwnDopri5())
    want = _solve(dfx.Dopri5())
    assert not bool(failed) and int(accepted) == int(want[2])
    np.testing.assert_array_equal(ys, want[0])


@pytest.mark.parametrize(
    "solver", [pytest.param(dfx.Tsit5(), marks=pytest.mark.slow), dfx.Bosh3()], ids=lambda s: type(s).__name__
)
@pytest.mark.slow
def test_other_solvers_through_simulate(monkeypatch, solver):
    """A batched `simulate` with another solver: Tsit5 in this loop, Bosh3 (not implemented
    here) in `diffeqsolve` with the shared controller; both as close to the per-trial solve as
    the tolerance allows."""
    monkeypatch.setattr(L, "SHARED_MIN_BATCH", 2)
    p = jsphere.RobotParams.paper()
    amp = 0.05 * (1 + 0.1 * jax.random.normal(jax.random.PRNGKey(1), (3, 3)))

    def sim(a, steps):
        tq = jsphere.Torques(lambda t: a * jnp.sin(jnp.pi * t + jnp.array([0.0, 2.1, 4.2])))
        return jsphere.simulate(
            p, jsphere.State.at_rest(p), tq, 0.5, rtol=1e-7, atol=1e-9, solver=solver, batch_steps=steps
        )

    shared = jax.jit(jax.vmap(lambda a: sim(a, "shared")))(amp)
    alone = jax.jit(jax.vmap(lambda a: sim(a, "per_trial")))(amp)
    assert np.all(np.asarray(shared.ok)) and len(set(np.asarray(shared.num_steps).tolist())) == 1
    np.testing.assert_allclose(shared.x, alone.x, rtol=0, atol=1e-8)
    np.testing.assert_allclose(shared.Omega, alone.Omega, rtol=0, atol=1e-7)


def _damped(t, y, args, batched):  # per-trial frequency w, shared damping c, forced
    w, c = args
    return jnp.stack([y[1], -(w**2) * y[0] - c * y[1] + jnp.sin(t)])


def _weighted(ys):
    return jnp.sum((jnp.arange(ys.size).reshape(ys.shape) % 7 + 1.0) * jnp.sin(ys))


def _loss_shared(w, c, y0, t1, ts, rtol=1e-12, atol=1e-14):
    ys, _, _ = R.solve(
        _damped,
        0.0,
        t1,
        y0,
        ts,
        [w, c],
        [True, False],
        tab=RK.tableau(dfx.Dopri8()),
        rtol=rtol,
        atol=atol,
        max_steps=4096,
    )
    return _weighted(ys)


def _loss_diffrax(w, c, y0, t1, ts):
    def one(wi, y0i):
        term = dfx.ODETerm(lambda t, y, a: jnp.stack([y[1], -(wi**2) * y[0] - c * y[1] + jnp.sin(t)]))
        sol = dfx.diffeqsolve(
            term,
            dfx.Dopri8(),
            0.0,
            t1,
            None,
            y0i,
            saveat=dfx.SaveAt(ts=ts, t1=True),
            stepsize_controller=dfx.PIDController(rtol=1e-12, atol=1e-14),
            max_steps=100_000,
        )
        return sol.ys

    return _weighted(jax.vmap(one, in_axes=(0, 1), out_axes=2)(w, y0))


@pytest.mark.slow
@pytest.mark.parametrize("capacity", [256, 2], ids=["every-step", "replayed"])
def test_the_discrete_adjoint_matches_diffrax(monkeypatch, capacity):
    """Reverse mode through the shared loop (its discrete adjoint) against diffrax's own
    (autodiff of per-trial solves) at a tight tolerance: per-trial and shared arguments, the
    initial state, and the times (the exact solution's cotangents). With 2 checkpoint slots the
    stride doubles ~6 times and the backward pass replays stretches from them: same values."""
    monkeypatch.setattr(RK, "CHECKPOINTS", capacity)
    w, c = jnp.array([1.0, 2.0, 3.5, 5.0]), jnp.array(0.3)
    y0 = jnp.stack([jnp.ones(4), jnp.linspace(-0.5, 0.5, 4)])
    ts = jnp.linspace(0.05, 2.75, 7)
    argnums = (0, 1, 2, 3, 4)
    ours = jax.jit(jax.grad(_loss_shared, argnums))(w, c, y0, 3.0, ts)
    theirs = jax.jit(jax.grad(_loss_diffrax, argnums))(w, c, y0, 3.0, ts)
    for name, a, b in zip(["w", "c", "y0", "t1", "ts"], ours, theirs):
        np.testing.assert_allclose(a, b, rtol=1e-6, atol=1e-6, err_msg=name)
    assert np.max(np.abs(np.asarray(ours[0]))) > 1.0  # not trivially zero


@pytest.mark.slow
def test_the_adjoint_of_a_batch_with_a_saved_start_and_no_save_times():
    """Rows saved at `t0` are `y0` itself (cotangent straight to `y0`); no save times at all."""
    y0 = jnp.stack([jnp.ones(4), jnp.zeros(4)])
    tab = RK.tableau(dfx.Dopri5())

    def loss(y0, ts):
        ys, _, _ = R.solve(_oscillators, 0.0, 1.0, y0, ts, tab=tab, rtol=1e-10, atol=1e-12, max_steps=4096)
        return jnp.sum(ys[0] * ys[-1])

    g = jax.grad(loss)(y0, jnp.array([0.0]))
    x1, v1 = _exact(1.0)
    # d/dx0 of x0 * x(1) + v0 * v(1) at (1, 0): x(1) + x0 dx(1)/dx0 = 2 cos w; d/dv0: v(1) + x0 dx(1)/dv0
    np.testing.assert_allclose(g[0], 2 * x1[0] * 0 + x1 + np.cos(np.asarray(W)), rtol=1e-7, atol=1e-8)
    np.testing.assert_allclose(g[1], v1 + np.sin(np.asarray(W)) / np.asarray(W), rtol=1e-7, atol=1e-8)
    g_none = jax.grad(
        lambda y0: jnp.sum(
            R.solve(_oscillators, 0.0, 1.0, y0, jnp.zeros((0,)), tab=tab, rtol=1e-10, atol=1e-12, max_steps=4096)[0][
                -1, 0
            ]
        )
    )(y0)
    np.testing.assert_allclose(g_none[0], np.cos(np.asarray(W)), rtol=1e-7)


def _linear(t, y, args, batched):  # y' = M y, M (2, 2) per trial or shared, or nested tuples of its elements
    (M,) = args
    rows = M if isinstance(M, tuple) else tuple(tuple(M[..., i, j] for j in range(2)) for i in range(2))
    return jnp.stack([rows[i][0] * y[0] + rows[i][1] * y[1] for i in range(2)])


@pytest.mark.parametrize("batched", [pytest.param(True, marks=pytest.mark.slow), False], ids=["per-trial", "shared"])
def test_the_adjoint_of_an_argument_taken_element_by_element(batched):
    """An argument in `elementwise` reaches the field's VJPs as nested tuples of per-trial
    scalars (`_elements`): the same gradient as the array itself, and as central differences."""
    y0 = jnp.stack([jnp.ones(3), jnp.linspace(-1.0, 1.0, 3)])
    M0 = jnp.array([[-0.3, 1.0], [-2.0, -0.1]])
    M = jnp.stack([M0, 1.1 * M0, 0.9 * M0]) if batched else M0
    ts = jnp.linspace(0.5, 2.0, 4)

    def loss(M, elementwise):
        ys, _, _ = R.solve(
            _linear,
            0.0,
            2.0,
            y0,
            ts,
            [M],
            [batched],
            tab=RK.tableau(dfx.Dopri5()),
            rtol=1e-11,
            atol=1e-13,
            max_steps=4096,
            elementwise=elementwise,
        )
        return _weighted(ys)

    g_el = jax.jit(jax.grad(lambda M: loss(M, [0])))(M)
    g_arr = jax.jit(jax.grad(lambda M: loss(M, [])))(M)
    assert g_el.shape == M.shape
    np.testing.assert_allclose(g_el, g_arr, rtol=1e-12, atol=1e-13)
    f = jax.jit(lambda M: loss(M, []))
    idx = (1, 0, 1) if batched else (0, 1)
    h = 1e-6
    e = jnp.zeros_like(M).at[idx].set(h)
    fd = (float(f(M + e)) - float(f(M - e))) / (2 * h)
    assert abs(float(g_el[idx]) - fd) < 1e-6 * max(1.0, abs(fd))
