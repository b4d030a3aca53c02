"""One explicit Runge-Kutta method on a batch's `(n, batch)` state: a diffrax solver's tableau
and dense output, its stages written for this layout (the building block of
`jsphere.solve.batched.loop` and `jsphere.solve.batched.adjoint`)."""

from __future__ import annotations

from typing import Callable, NamedTuple

import diffrax as dfx
import jax
import jax.numpy as jnp
import numpy as np

from ..._runtime.private import rk_tableau

#: The diffrax solvers this method implements (explicit, first-same-as-last tableaus whose
#: dense output is built from the stage increments); a user's own such method runs in it too
#: (`tableau`).
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
    """The tableau of `solver` if this method implements it, else `None`: diffrax's solvers in
    `SUPPORTED`, and a user's own explicit Runge-Kutta method (a subclass of
    `diffrax.AbstractERK` defined outside diffrax) whose tableau is first same as last, its
    solution the last stage's argument (`y1 = y + sum_j a_sj K_j`, `c_s = 1`)."""
    cls = type(solver)
    own = isinstance(solver, dfx.AbstractERK) and not cls.__module__.startswith("diffrax")
    if cls not in SUPPORTED and not own:
        return None
    tab = rk_tableau(solver)
    s = len(tab.a_lower) + 1
    a = np.zeros((s, s))
    for i, row in enumerate(tab.a_lower):
        a[i + 1, : len(row)] = np.asarray(row)
    c = np.concatenate([[0.0], np.asarray(tab.c)])
    # first same as last, solution same as last stage: y1 is the last stage's argument
    fits = tab.fsal and tab.ssal and np.array_equal(a[-1], np.asarray(tab.b_sol)) and c[-1] == 1.0
    if not fits:
        assert own, cls  # diffrax's own solvers in SUPPORTED all fit
        return None
    return Tableau(a, c, np.asarray(tab.b_error), solver.order(None), solver.interpolation_cls)


def mean_sq_rows(x):
    """Per trial (column) the mean square over the rows of `x`, as an elementwise sum."""
    return sum(x[i] * x[i] for i in range(x.shape[0])) / x.shape[0]


def in_branch(f, t, y):
    """`f(t, y)` evaluated in a `lax.cond` branch of its own: its output is materialised. `t`
    is the time, or one time per trial (NaN output if any is non-finite)."""

    def nan(t, y):
        return jax.tree_util.tree_map(lambda s: jnp.full(s.shape, jnp.nan, s.dtype), jax.eval_shape(f, t, y))

    return jax.lax.cond(jnp.all(jnp.isfinite(t)), f, nan, t, y)


#: Checkpoints the forward pass of a gradient keeps (`checkpoints`): states at most this
#: many accepted steps apart are stored, every step while the solve is short.
CHECKPOINTS = 256


def checkpoints(max_steps: int) -> tuple[int, int]:
    """`(C, S)`: the forward pass of a gradient stores the state at every `s`-th accepted step
    in `C` slots (`s = 1`, doubled whenever the slots are full, so `s < 2 N / C` after `N`
    steps); the backward pass replays one stretch of `s` steps at a time into `S` slots."""
    C = max(2, min(CHECKPOINTS, max_steps))
    C += C % 2
    return C, max(1, -(-2 * max_steps // C))


class Method:
    """One Runge-Kutta method on an `(n, batch)` state, for the field
    `f(t, y, args, batched)` (`batched[i]`: whether `args[i]` has a leading trial axis)."""

    def __init__(self, f, tab: Tableau, dtype):
        self.f, self.tab, self.dtype = f, tab, dtype  # no arrays here: rules trace later
        self.s = tab.a.shape[0]

    def rates(self, t, y, args, batched):
        """`f(t, y)` in the state's dtype, materialised (`in_branch`)."""
        return in_branch(lambda t, y: self.f(t, y, args, batched).astype(self.dtype), t, y)

    def stages(self, t, h, y, K, args, batched, last=True):
        """The stage increments `K[i] = h f(t + c_i h, y + sum_j a_ij K[j])` for `i >= 1`, `K[0]`
        given, and `y1` (the last stage's argument: first same as last). With `last=False`
        the last stage's rates are not evaluated (`K[-1]` is left as given)."""
        c, s = jnp.asarray(self.tab.c, self.dtype), self.s

        def body(i, carry):
            K, _ = carry
            yi = self.stage_arg(i, y, K)
            return K.at[i].set(h * self.rates(t + c[i] * h, yi, args, batched)), yi

        if last:
            K, y1 = jax.lax.fori_loop(1, s, body, (K, y))
        else:
            K, _ = jax.lax.fori_loop(1, s - 1, body, (K, y))
            y1 = y + sum(float(a_j) * K[j] for j, a_j in enumerate(self.tab.a[-1]) if a_j != 0.0)
        return y1, K

    def stage_arg(self, i, y, K):
        """Stage `i`'s argument `y + sum_{j<i} a_ij K[j]` (`0 <= i < s`; `y` for `i = 0`), written out
        as elementwise terms: one `lax.switch` branch per stage, each with the nonzero
        coefficients of its row as constants, so it reads only those rows of the stage buffer."""
        a = self.tab.a

        def row(r):
            terms = [(float(a[r, j]), j) for j in range(r) if a[r, j] != 0.0]
            return lambda y, K: y + sum(a_rj * K[j] for a_rj, j in terms)

        if isinstance(i, int):
            return row(i)(y, K)
        return jax.lax.switch(i, [row(r) for r in range(self.s)], y, K)

    def step(self, t, h, y, args, batched, last=True):
        """One step from `(t, y)`, its first stage evaluated here: `(y1, K)`."""
        K = jnp.zeros((self.s,) + y.shape, self.dtype).at[0].set(h * self.rates(t, y, args, batched))
        return self.stages(t, h, y, K, args, batched, last)

    def dense(self, t, h, y, y1, K, tj):
        """The dense output of the step `(t, t + h]` at `tj`; with `t`, `h`, `tj` one per trial
        (`(batch,)`), each trial's own."""
        if jnp.ndim(t):
            one = lambda t, h, y, y1, K, tj: self.dense(t, h, y, y1, K, tj)  # noqa: E731
            return jax.vmap(one, in_axes=(0, 0, 1, 1, 2, 0), out_axes=1)(t, h, y, y1, K, tj)
        return self.tab.interpolation_cls(t0=t, t1=t + h, y0=y, y1=y1, k=K).evaluate(tj).astype(self.dtype)
