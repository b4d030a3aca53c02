"""`jsphere.numerics.lm`: the linear solves against dense linear algebra, the acceptance rule
(noise floor, damping, step cap, non-finite steps, ending), the iteration under jit, vmap and
lax.scan, and a host-driven run restarted from its saved state bit for bit."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from jsphere.numerics.lm import (
    LM_KEYS,
    Dense,
    LevenbergMarquardt,
    LMState,
    arrow_step,
    damp,
    iterate,
    marginal_information,
)


def test_dense_solves_the_damped_normal_equations():
    rng = np.random.default_rng(0)
    J, r, lam = rng.normal(size=(12, 4)), rng.normal(size=12), 0.3
    dx, pred = Dense(floor=1e-9)((jnp.asarray(r), jnp.asarray(J)), lam)
    H, g = J.T @ J, J.T @ r
    ref = -np.linalg.solve(H + lam * np.diag(np.diag(H) + 1e-9), g)
    np.testing.assert_allclose(dx, ref, rtol=1e-12)
    np.testing.assert_allclose(pred, -(g @ ref + 0.5 * ref @ H @ ref), rtol=1e-12)
    # the predicted decrease of an undamped step is the exact decrease of a linear problem
    dx0, pred0 = Dense()((jnp.asarray(r), jnp.asarray(J)), 0.0)
    np.testing.assert_allclose(pred0, 0.5 * r @ r - 0.5 * np.sum((r + J @ np.asarray(dx0)) ** 2), rtol=1e-10)


def test_the_arrow_elimination_equals_the_dense_solve_of_the_whole_system():
    """`T` groups with `n` own parameters each and `P` shared ones: the eliminated step equals
    the dense step of the assembled Jacobian (same damping up to the 1e-12 regulariser)."""
    rng = np.random.default_rng(1)
    T, K, P, n, lam = 3, 9, 2, 3, 0.05
    J = rng.normal(size=(T, K, P + n))
    res = rng.normal(size=(T, K))
    dg, dn, pred = arrow_step(jnp.asarray(res), jnp.asarray(J), lam, P)
    full = np.zeros((T * K, P + T * n))
    for t in range(T):
        full[t * K : (t + 1) * K, :P] = J[t, :, :P]
        full[t * K : (t + 1) * K, P + t * n : P + (t + 1) * n] = J[t, :, P:]
    dx, pred_d = Dense()((jnp.asarray(res.ravel()), jnp.asarray(full)), lam)
    np.testing.assert_allclose(np.concatenate([dg, np.ravel(dn)]), dx, rtol=1e-8)
    np.testing.assert_allclose(pred, pred_d, rtol=1e-8)
    # the information of the shared parameters: the Schur complement of the undamped blocks
    H = full.T @ full
    S = H[:P, :P] - H[:P, P:] @ np.linalg.solve(H[P:, P:], H[P:, :P])
    np.testing.assert_allclose(marginal_information(jnp.asarray(res), jnp.asarray(J), P), S, rtol=1e-9)


def test_damping_adds_to_the_diagonal_only():
    H = jnp.array([[4.0, 1.0], [1.0, 2.0]])
    np.testing.assert_allclose(
        damp(H, 0.5, floor=0.1, shift=1e-3), [[4.0 + 0.5 * 4.1 + 4e-3, 1.0], [1.0, 2.0 + 0.5 * 2.1 + 4e-3]]
    )


def _state(lm, cost=1.0):
    return lm.init(jnp.asarray(cost), (jnp.zeros(1), jnp.eye(1)))


def test_the_noise_floor_accepts_a_small_rise_that_was_predicted_small():
    x, x_new = jnp.zeros(1), jnp.ones(1)
    plain, noisy = LevenbergMarquardt(), LevenbergMarquardt(noise=1e-6)
    for lm, pred, accepted in ((plain, 1e-8, False), (noisy, 1e-8, True), (noisy, 1e-3, False)):
        x_out, st = lm.update(x, x_new, _state(lm), 1.0 + 1e-7, (jnp.ones(1), jnp.eye(1)), pred)
        assert bool(st.rejected == 0) is accepted
        np.testing.assert_array_equal(x_out, x_new if accepted else x)
        np.testing.assert_allclose(st.lam, 1e-3 / 5.0 if accepted else 1e-2)
        np.testing.assert_allclose(st.cost, 1.0 + 1e-7 if accepted else 1.0)


def test_a_long_step_is_shortened_and_a_non_finite_one_is_not_taken():
    lm = LevenbergMarquardt(max_step=2.0, step_scale=(jnp.array([1.0, 10.0]), jnp.inf))
    x = (jnp.zeros(2), jnp.zeros(3))
    (a, b), pred = lm.candidate(x, (jnp.array([4.0, 10.0]), jnp.ones(3)), 0.5)
    np.testing.assert_allclose(a, [2.0, 5.0])
    np.testing.assert_allclose(b, 0.5 * np.ones(3))
    assert pred == jnp.inf  # (the prediction was of the full step)
    (a, b), pred = lm.candidate(x, (jnp.array([0.1, 0.1]), jnp.ones(3)), 0.5)
    np.testing.assert_allclose(a, [0.1, 0.1]) and np.testing.assert_allclose(pred, 0.5)
    (a, b), pred = lm.candidate(x, (jnp.array([jnp.nan, 0.1]), jnp.ones(3)), 0.5)
    np.testing.assert_array_equal(a, 0.0) and np.testing.assert_array_equal(b, 0.0)
    assert jnp.isnan(pred)
    _, st = lm.update(x, (a, b), _state(lm), 0.5, (jnp.ones(1), jnp.eye(1)), pred)
    assert int(st.rejected) == 1  # a lower cost, but no step was taken


def test_rejections_in_a_row_end_a_problem_and_an_ended_problem_takes_no_step():
    lm = LevenbergMarquardt(max_rejected=3)
    st, x = _state(lm), jnp.zeros(1)
    for k in range(3):
        assert not bool(st.converged)
        x, st = lm.update(x, x + 1.0, st, 2.0, (jnp.ones(1), jnp.eye(1)), 1.0)
    assert bool(st.converged) and int(st.it) == 3
    np.testing.assert_allclose(st.lam, 1e-3 * 1e3)
    x, st = lm.update(x, x + 1.0, st, 0.0, (jnp.ones(1), jnp.eye(1)), 1.0)
    assert float(st.cost) == 1.0 and float(x[0]) == 0.0


def _rosenbrock_ev(x):
    r = jnp.stack([10.0 * (x[1] - x[0] ** 2), 1.0 - x[0]])
    return 0.5 * jnp.sum(r**2), (r, jax.jacfwd(lambda z: jnp.stack([10.0 * (z[1] - z[0] ** 2), 1.0 - z[0]]))(x))


def test_the_iteration_runs_under_jit_vmap_and_scan():
    lm = LevenbergMarquardt(rel_done=1e-14, max_rejected=8)

    @jax.jit
    @jax.vmap
    def solve(x0):
        def body(c, _):
            x, st = c
            x_new, pred = lm.propose(x, st)
            x, st = lm.update(x, x_new, st, *_rosenbrock_ev(x_new), pred)
            return (x, st), st.cost

        (x, st), hist = jax.lax.scan(body, (x0, lm.init(*_rosenbrock_ev(x0))), None, length=100)
        return x, st, hist

    x, st, hist = solve(jnp.array([[-1.2, 1.0], [2.0, -1.0], [0.5, 0.5]]))
    np.testing.assert_allclose(x, np.ones((3, 2)), atol=1e-7)
    assert np.all(np.diff(np.asarray(hist), axis=1) <= 0.0)  # only decreases are accepted
    assert np.all(np.asarray(st.converged))


def test_a_host_driven_run_restarted_from_its_saved_state_is_bit_for_bit_the_same():
    """Three problems as one batch (leading axis), driven by `iterate`; the state saved after
    four steps (`LM_KEYS`, `it`, `current`) and the point continue to the same end."""
    lm = LevenbergMarquardt(rel_done=1e-15, max_rejected=8)
    evaluate = jax.jit(jax.vmap(_rosenbrock_ev))
    solve = jax.jit(jax.vmap(Dense()))
    x0 = jnp.array([[-1.2, 1.0], [2.0, -1.0], [0.5, 0.5]])
    runs = list(iterate(lm, evaluate, solve, x0, lm.init(*evaluate(x0)), 60))
    x4, st4, _ = runs[3]
    saved = {k: np.array(v) for k, v in st4.arrays().items()}
    st = LMState(**saved, it=int(st4.it), current=jax.tree_util.tree_map(np.array, st4.current))
    again = list(iterate(lm, evaluate, solve, np.array(x4), st, 60))
    assert len(again) == len(runs) - 4 and sorted(saved) == sorted(LM_KEYS)
    (xa, sa, _), (xb, sb, _) = runs[-1], again[-1]
    np.testing.assert_array_equal(xa, xb)
    for k in LM_KEYS:
        np.testing.assert_array_equal(getattr(sa, k), getattr(sb, k))
    np.testing.assert_allclose(xa[int(np.argmin(sa.cost))], [1.0, 1.0], atol=1e-7)
    assert sa.best_converged


def test_a_start_from_host_values_compiles_nothing(programs_compiled):
    """`init` from NumPy costs (as the fit's host loop gives them) makes its arrays without XLA
    programs: eager, each would be one more program to compile in a fit's first iteration."""
    cost = np.array([1.5, np.inf, 0.25, 3.0, 7.0, 2.0, 0.5])  # (a shape no other test uses)
    state = LevenbergMarquardt(lam0=1e-2).init(cost, {"r": np.ones((7, 3))})
    assert programs_compiled == []
    np.testing.assert_array_equal(np.asarray(state.cost), cost)
    np.testing.assert_array_equal(np.asarray(state.lam), np.full(7, 1e-2))
    assert state.lam.dtype == cost.dtype and not np.asarray(state.converged).any()
    assert np.asarray(state.rejected).tolist() == [0] * 7 and state.it == 0
