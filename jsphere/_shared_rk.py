"""One adaptive Runge-Kutta step sequence for a whole batch, its state an `(n, batch)` array.

This is the integrator behind the batching rule of `jsphere._ensemble.solve` (the default for
batched torque- and gait-mode solves, `batch_steps="shared"`). Its method is a diffrax solver's
own: the Butcher tableau of `diffrax.Dopri8` (or `Dopri5`, `Tsit5`), its dense output
(`solver.interpolation_cls`) for the save times, and an integral step-size controller
(Hairer, Norsett & Wanner, II.4: the next step is `h 0.9 err^(-1/order)`, between 0.2x and 10x
the last one, at most 0.9x after a rejected step; the starting step as diffrax selects it).
Unlike `diffrax.PIDController`, which never shrinks the step after an accepted one, this rule
may: on the issue-6 problem that takes 153 steps for 142 accepted against diffrax's 163 for
141 (benchmarks/NOTES.md, session 8). The error norm is the largest over trials of each
trial's RMS norm, so every trial meets its own tolerance.

Why not `diffrax.diffeqsolve` itself here (profile in benchmarks/NOTES.md, session 8): on CPU
about half of its batched solve is its stage machinery: the stage sums are `dot`s of a tableau
row with a `(14, n, batch)` stage buffer (the largest single kernel), the solution and error
sums are reductions that XLA sends to a library kernel, and each stage adds a
dynamic-update-slice, each step a pad. Here:
- the vector field is evaluated in a `lax.cond` branch of its own (a run-time true predicate),
  so XLA materialises each stage's rates (without it XLA fuses the field into the stage sums:
  1.7x slower, twice the compile time);
- the stage sums are written out as elementwise sums over the stage buffer's rows (one fused
  kernel per stage; a `jnp.sum` over the short stage axis became a library reduction 50x
  slower than that);
- the error norm sums over the state's rows explicitly, for the same reason.

The loop is forward-only: `jsphere._simulate` differentiates batched solves through the
per-trial diffrax adjoint (`_reverse`), never through this loop.
"""

from __future__ import annotations

from typing import Callable, NamedTuple

import diffrax as dfx
import jax
import jax.numpy as jnp
import numpy as np

#: The diffrax solvers this loop implements (explicit, first-same-as-last tableaus whose dense
#: output is built from the stage increments).
SUPPORTED = (dfx.Dopri8, dfx.Dopri5, dfx.Tsit5)


class Tableau(NamedTuple):
    """An explicit, FSAL Runge-Kutta method: `a` (`s x s`, strictly lower), `c`, `b_error`,
    the order of its solution (the controller's exponent is `1/order`, as in diffrax) and
    the dense output `interpolation_cls(t0=, t1=, y0=, y1=, k=)`."""

    a: np.ndarray
    c: np.ndarray
    b_error: np.ndarray
    order: int
    interpolation_cls: Callable


def tableau(solver) -> Tableau | None:
    """The tableau of `solver` if this loop implements it (`SUPPORTED`), else `None`."""
    if type(solver) not in SUPPORTED:
        return None
    tab = solver.tableau
    s = len(tab.a_lower) + 1
    a = np.zeros((s, s))
    for i, row in enumerate(tab.a_lower):
        a[i + 1, : len(row)] = np.asarray(row)
    c = np.concatenate([[0.0], np.asarray(tab.c)])
    # first same as last, solution same as last stage: y1 is the last stage's argument
    assert tab.fsal and tab.ssal and np.array_equal(a[-1], np.asarray(tab.b_sol)) and c[-1] == 1.0
    return Tableau(a, c, np.asarray(tab.b_error), solver.order(None), solver.interpolation_cls)


def _mean_sq_rows(x):
    """Per trial (column) the mean square over the rows of `x`, as an elementwise sum."""
    return sum(x[i] * x[i] for i in range(x.shape[0])) / x.shape[0]


def in_branch(f, t, y):
    """`f(t, y)` evaluated in a `lax.cond` branch of its own: its output is materialised."""

    def nan(t, y):
        return jax.tree_util.tree_map(lambda s: jnp.full(s.shape, jnp.nan, s.dtype), jax.eval_shape(f, t, y))

    return jax.lax.cond(jnp.isfinite(t), f, nan, t, y)


def solve(f, t0, t1, y0, ts, *, tab: Tableau, rtol, atol, max_steps: int):
    """Integrate `y' = f(t, y)` for the `(n, batch)` state `y0` from `t0` to `t1 >= t0`, with one
    step sequence for all columns (trials), saving at the sorted times `ts` (within
    `[t0, t1]`) and at `t1`.

    Trials (columns) whose state or rates are non-finite at `t0` (e.g. NaN inputs) are
    integrated but left out of the step-size control.

    Returns `(ys, failed, num_accepted_steps)`: `ys` is `(len(ts) + 1, n, batch)`, its last row
    the state at `t1`; `failed` is true if `max_steps` steps (accepted or rejected) were taken
    or the step size collapsed (e.g. a controlled trial turned non-finite) before `t1`; save
    rows never reached are NaN.
    """
    dtype = y0.dtype
    n, B = y0.shape
    s = tab.a.shape[0]
    T = ts.shape[0]
    t0, t1, ts = jnp.asarray(t0, dtype), jnp.asarray(t1, dtype), jnp.asarray(ts, dtype)
    a, c = jnp.asarray(tab.a, dtype), jnp.asarray(tab.c, dtype)

    def rates(t, y):  # in the state's dtype
        return f(t, y).astype(dtype)

    f0 = in_branch(rates, t0, y0)
    live = jnp.all(jnp.isfinite(y0), axis=0) & jnp.all(jnp.isfinite(f0), axis=0)  # controlled trials

    def rms(x):  # the largest per-trial RMS norm over the controlled trials
        return jnp.sqrt(jnp.max(jnp.where(live, _mean_sq_rows(x), 0.0)))

    # the starting step (diffrax's `_select_initial_step`, with this norm)
    scale = atol + rtol * jnp.abs(y0)
    d0, d1 = rms(y0 / scale), rms(f0 / scale)
    small = (d0 < 1e-5) | (d1 < 1e-5)
    h0 = jnp.where(small, 1e-6, 0.01 * d0 / jnp.where(small, 1.0, d1))
    f1 = in_branch(rates, t0 + h0, y0 + h0 * f0)
    d2 = rms((f1 - f0) / scale) / h0
    dmax = jnp.maximum(d1, d2)
    h1 = jnp.where(dmax <= 1e-15, jnp.maximum(1e-6, h0 * 1e-3), (0.01 / jnp.where(dmax <= 1e-15, 1.0, dmax)) ** (1.0 / tab.order))
    h_init = jnp.minimum(100 * h0, h1).astype(dtype)

    def stages(t, h, y, k0, K):
        """One step's stage increments `K[i] = h f(t + c_i h, y + sum_j a_ij K[j])`."""
        K = K.at[0].set(h * k0)

        def body(i, carry):
            K, _ = carry
            ai = a[i]
            yi = y + sum(jnp.where(j < i, ai[j] * K[j], 0.0) for j in range(s - 1))
            return K.at[i].set(h * in_branch(rates, t + c[i] * h, yi)), yi

        K, y1 = jax.lax.fori_loop(1, s, body, (K, y))
        err = sum(float(e) * K[j] for j, e in enumerate(tab.b_error) if e != 0.0)
        return y1, err, K

    def save(t, h, y, y1, K, ys, j):
        """Dense output at the save times in `(t, t + h]`."""
        interp = tab.interpolation_cls(t0=t, t1=t + h, y0=y, y1=y1, k=K)

        def more(cj):
            return (cj[1] < T) & (ts[jnp.minimum(cj[1], T - 1)] <= t + h)

        def one(cj):
            ys, j = cj
            return ys.at[j].set(interp.evaluate(ts[j]).astype(dtype)), j + 1

        return jax.lax.while_loop(more, one, (ys, j))

    def running(carry):
        t, _, _, _, _, _, _, _, steps, bad = carry
        return (t < t1) & (steps < max_steps) & ~bad

    def step(carry):
        t, h, y, k0, K, ys, j, accepted, steps, bad = carry
        h = jnp.minimum(h, t1 - t)
        y1, err, K = stages(t, h, y, k0, K)
        e = rms(err / (atol + rtol * jnp.maximum(jnp.abs(y), jnp.abs(y1))))
        ok = e < 1.0
        inv = jnp.where(jnp.isfinite(e), 1.0 / jnp.maximum(e, jnp.finfo(dtype).tiny), 0.0)
        factor = jnp.clip(0.9 * inv ** (1.0 / tab.order), 0.2, jnp.where(ok, 10.0, 0.9))
        t_next = jnp.where(ok, jnp.where(h >= t1 - t, t1, t + h), t)
        if T:
            due = ok & (j < T) & (ts[jnp.minimum(j, T - 1)] <= t_next)
            ys, j = jax.lax.cond(due, lambda: save(t, h, y, y1, K, ys, j), lambda: (ys, j))
        h_next = (h * factor).astype(dtype)
        bad = (t_next < t1) & ~(h_next > 10 * jnp.finfo(dtype).eps * jnp.maximum(jnp.abs(t_next), 1.0))
        y = jnp.where(ok, y1, y)
        k0 = jnp.where(ok, K[-1] / h, k0)
        return t_next, h_next, y, k0, K, ys, j, accepted + ok, steps + 1, bad

    ys = jnp.where((ts <= t0)[:, None, None], y0[None], jnp.full((T, n, B), jnp.nan, dtype))
    j = jnp.sum(ts <= t0).astype(jnp.int32)
    K = jnp.zeros((s, n, B), dtype)
    init = (t0, h_init, y0, f0, K, ys, j, jnp.int32(0), jnp.int32(0), jnp.bool_(False))
    t, _, y, _, _, ys, _, accepted, _, bad = jax.lax.while_loop(running, step, init)
    failed = bad | (t < t1)
    return jnp.concatenate([ys, y[None]]), failed, accepted
