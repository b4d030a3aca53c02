"""One adaptive Runge-Kutta step sequence for a whole batch, its state an `(n, batch)` array.

This is the integrator behind the batching rule of `jsphere.solve.batched.dispatch.solve` (the default for
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

Reverse mode: `solve` has a discrete adjoint (a `jax.custom_vjp`): the forward pass records
the accepted steps and checkpoints their states (`checkpoints`); the backward pass replays
each stretch between checkpoints and runs its steps, and each step's stages, in reverse, with
one VJP of the field per stage; parameters shared by the batch get per-trial cotangents,
summed once; arguments the field also takes element by element (`elementwise`: the robot's
parameter arrays) are differentiated as tuples of scalars. It matches diffrax's autodiff of
per-trial solves (tests/test_shared_rk.py) and is the gradient of batched `simulate` and
`simulate_gaits` calls that share their steps (`jsphere.solve.simulate.SHARED_ADJOINT`).

The same loop also runs batches with per-trial steps (`batch_steps="per_trial"`): each trial
has its own time and step size, in lockstep (`_forward_per_trial`), so the batch is still one
vectorised loop but no trial depends on another (2x the Monte-Carlo throughput of diffrax's
vmapped loop, benchmarks/NOTES.md session 13); its discrete adjoint runs the recorded
iterations backwards with each trial's own step sizes.
"""

from __future__ import annotations

import contextvars
from typing import Callable, NamedTuple

import diffrax as dfx
import jax
import jax.numpy as jnp
import numpy as np

#: The diffrax solvers this loop implements (explicit, first-same-as-last tableaus whose dense
#: output is built from the stage increments).
SUPPORTED = (dfx.Dopri8, dfx.Dopri5, dfx.Tsit5)


_IN_ADJOINT = contextvars.ContextVar("jsphere_shared_rk_in_adjoint", default=False)


def in_adjoint() -> bool:
    """True while a stage VJP of the backward pass traces the field: a field may then mark
    intermediate values to be materialised that its forward evaluation should not
    (`jsphere.solve.batched.components.adjoint_kept`)."""
    return _IN_ADJOINT.get()


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


class _Method:
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
        coefficients of its row as constants, so it reads only those rows of the stage buffer
        (Dopri8: 68 row reads per step, against 169 with a traced row of the tableau; problem 1
        of issue 6 ~7 % faster, benchmarks/NOTES.md session 12)."""
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


def _initial_step(m: _Method, args, batched, t0, y0, f0, rms, *, rtol, atol, finite=False):
    """The starting step (diffrax's `_select_initial_step`) with the norm `rms`: one for the
    batch (the largest over trials), or one per trial. `finite`: a non-finite trial's step is
    1e-6 (it then fails alone)."""
    scale = atol + rtol * jnp.abs(y0)
    d0, d1 = rms(y0 / scale), rms(f0 / scale)
    small = (d0 < 1e-5) | (d1 < 1e-5)
    h0 = jnp.where(small, 1e-6, 0.01 * d0 / jnp.where(small, 1.0, d1))
    if finite:
        h0 = jnp.where(jnp.isfinite(h0), h0, 1e-6)
    f1 = m.rates(t0 + h0, y0 + h0 * f0, args, batched)
    d2 = rms((f1 - f0) / scale) / h0
    dmax = jnp.maximum(d1, d2)
    h1 = jnp.where(dmax <= 1e-15, jnp.maximum(1e-6, h0 * 1e-3), (0.01 / jnp.where(dmax <= 1e-15, 1.0, dmax)) ** (1.0 / m.tab.order))
    h_init = jnp.minimum(100 * h0, h1)
    if finite:
        h_init = jnp.where(jnp.isfinite(h_init), h_init, 1e-6)
    return h_init.astype(y0.dtype)


def _control(tab: Tableau, K, y, y1, rms, *, rtol, atol, skip=None):
    """Acceptance and step-size factor of the step `y -> y1` with stage increments `K`: the
    scaled error in the norm `rms` (one for the batch, or one per trial; `skip`: trials
    accepted without control), Hairer's integral rule (module docstring)."""
    err = sum(float(e) * K[i] for i, e in enumerate(tab.b_error) if e != 0.0)
    e = rms(err / (atol + rtol * jnp.maximum(jnp.abs(y), jnp.abs(y1))))
    if skip is not None:
        e = jnp.where(skip, 0.0, e)
    ok = e < 1.0
    inv = jnp.where(jnp.isfinite(e), 1.0 / jnp.maximum(e, jnp.finfo(y.dtype).tiny), 0.0)
    return ok, jnp.clip(0.9 * inv ** (1.0 / tab.order), 0.2, jnp.where(ok, 10.0, 0.9))


def _record_buffers(max_steps, n, B, dtype, per):
    """The empty record of a gradient's forward pass: `C + 1` checkpoint slots of the state,
    each step's time and size (`per`: `()` for shared steps, `(B,)` per trial), the stride
    and the number of slots used (`checkpoints`)."""
    C, _ = checkpoints(max_steps)
    return (jnp.zeros((C + 1, n, B), dtype), jnp.zeros((max_steps,) + per, dtype), jnp.zeros((max_steps,) + per, dtype), jnp.int32(1), jnp.int32(0))


def _keep(rec, t, h, y, k, ok, max_steps):
    """Record the step `k` from `(t, y)` of size `h` (a rejected one is overwritten by its
    retry): always written, to the next free slot, so no copy of the buffers is made."""
    Y, TK, HK, stride, used = rec
    C = Y.shape[0] - 1  # the last slot is scratch, for writes that are not kept
    i = jnp.minimum(k, max_steps - 1)
    TK, HK = TK.at[i].set(t), HK.at[i].set(h)
    due = k % stride == 0

    def compact(Y, stride, used):  # keep every other checkpoint, at twice the stride
        Y = jax.lax.fori_loop(1, C // 2, lambda i, Y: Y.at[i].set(Y[2 * i]), Y)
        return Y, 2 * stride, used // 2

    Y, stride, used = jax.lax.cond(due & (used == C), compact, lambda *a: a, Y, stride, used)
    Y = Y.at[jnp.minimum(used, C)].set(y)
    return Y, TK, HK, stride, used + (ok & due)


def _forward(m: _Method, args, batched, t0, t1, y0, ts, *, rtol, atol, max_steps, record):
    """The integration of `solve`; with `record`, also what its backward pass needs: the
    accepted steps' `(t_k, h_k)`, the states at every `stride`-th of them (`checkpoints`),
    and for each save time the index of the step that saved it (-1: none)."""
    dtype = y0.dtype
    n, B = y0.shape
    T = ts.shape[0]

    f0 = m.rates(t0, y0, args, batched)
    live = jnp.all(jnp.isfinite(y0), axis=0) & jnp.all(jnp.isfinite(f0), axis=0)  # controlled trials

    def rms(x):  # the largest per-trial RMS norm over the controlled trials
        return jnp.sqrt(jnp.max(jnp.where(live, _mean_sq_rows(x), 0.0)))

    h_init = _initial_step(m, args, batched, t0, y0, f0, rms, rtol=rtol, atol=atol)

    def save(t, h, y, y1, K, ys, j, at, k):
        """Dense output at the save times in `(t, t + h]` (step `k`)."""

        def more(c):
            return (c[1] < T) & (ts[jnp.minimum(c[1], T - 1)] <= t + h)

        def one(c):
            ys, j, at = c
            return ys.at[j].set(m.dense(t, h, y, y1, K, ts[j])), j + 1, at.at[j].set(k)

        return jax.lax.while_loop(more, one, (ys, j, at))

    def running(carry):
        t, _, _, _, _, _, _, _, _, steps, bad, _ = carry
        return (t < t1) & (steps < max_steps) & ~bad

    def step(carry):
        t, h, y, k0, K, ys, j, at, accepted, steps, bad, rec = carry
        h = jnp.minimum(h, t1 - t)
        y1, K = m.stages(t, h, y, K.at[0].set(h * k0), args, batched)
        ok, factor = _control(m.tab, K, y, y1, rms, rtol=rtol, atol=atol)
        t_next = jnp.where(ok, jnp.where(h >= t1 - t, t1, t + h), t)
        if T:
            due = ok & (j < T) & (ts[jnp.minimum(j, T - 1)] <= t_next)
            ys, j, at = jax.lax.cond(due, lambda: save(t, h, y, y1, K, ys, j, at, accepted), lambda: (ys, j, at))
        if record:
            rec = _keep(rec, t, h, y, accepted, ok, max_steps)
        h_next = (h * factor).astype(dtype)
        bad = (t_next < t1) & ~(h_next > 10 * jnp.finfo(dtype).eps * jnp.maximum(jnp.abs(t_next), 1.0))
        y = jnp.where(ok, y1, y)
        k0 = jnp.where(ok, K[-1] / h, k0)
        return t_next, h_next, y, k0, K, ys, j, at, accepted + ok, steps + 1, bad, rec

    ys = jnp.where((ts <= t0)[:, None, None], y0[None], jnp.full((T, n, B), jnp.nan, dtype))
    j = jnp.sum(ts <= t0).astype(jnp.int32)
    at = jnp.full((T,), -1, jnp.int32)
    rec = _record_buffers(max_steps, n, B, dtype, ()) if record else ()
    K = jnp.zeros((m.s, n, B), dtype)
    init = (t0, h_init, y0, f0, K, ys, j, at, jnp.int32(0), jnp.int32(0), jnp.bool_(False), rec)
    t, _, y, _, _, ys, _, at, accepted, _, bad, rec = jax.lax.while_loop(running, step, init)
    failed = bad | (t < t1)
    return (jnp.concatenate([ys, y[None]]), failed, accepted), (at, rec)


def _forward_per_trial(m: _Method, args, batched, t0, t1, y0, ts, *, rtol, atol, max_steps, record=False):
    """`_forward` with a step sequence of each trial's own, taken in lockstep: every trial has
    its own time, step size, error norm and acceptance, so its result does not depend on the
    other trials of the batch (the arithmetic is elementwise over trials), while the whole batch
    still runs as one vectorised loop. The loop ends when every trial has reached `t1` or
    failed; a trial that is done takes steps of size zero (no change). A failure (`max_steps`
    attempts, or a step size that collapsed, e.g. a state turned non-finite) is per trial too:
    that trial is frozen, the others go on.

    Returns `(ys, failed, accepted)` with `failed` and `accepted` per trial, and with `record`
    what the backward pass needs: every iteration `k` is recorded with each trial's time and
    *effective* step size (zero where the trial rejected its step, was done or had failed:
    then the iteration leaves it unchanged, and its adjoint is the identity), the states at
    every `stride`-th iteration, for each save time and trial the iteration that saved it, and
    the number of iterations."""
    dtype = y0.dtype
    n, B = y0.shape
    T = ts.shape[0]
    tv0 = jnp.full((B,), t0, dtype)

    def rms(x):  # each trial's RMS norm
        return jnp.sqrt(_mean_sq_rows(x))

    f0 = m.rates(tv0, y0, args, batched)
    h_init = _initial_step(m, args, batched, tv0, y0, f0, rms, rtol=rtol, atol=atol, finite=True)
    trials = jnp.arange(B)

    def save(t, h, y, y1, K, ys, j, at, ok, k):
        """Dense output at each trial's save times in `(t, t + h]` (accepted steps only)."""

        def due(j):
            return ok & (j < T) & (ts[jnp.minimum(j, T - 1)] <= t + h)

        def one(c):
            ys, j, at = c
            d = due(j)
            jj = jnp.minimum(j, T - 1)
            val = m.dense(t, h, y, y1, K, ts[jj])
            ys = ys.at[jj, :, trials].set(jnp.where(d[:, None], val.T, ys[jj, :, trials]))
            return ys, j + d, at.at[jj, trials].set(jnp.where(d, k, at[jj, trials]))

        return jax.lax.while_loop(lambda c: jnp.any(due(c[1])), one, (ys, j, at))

    def running(c):
        t, steps, dead = c[0], c[8], c[9]
        return jnp.any((t < t1) & ~dead) & (steps < max_steps)

    def step(c):
        t, h, y, k0, K, ys, j, at, steps, dead, acc, rec = c
        h = jnp.where(dead, 0.0, jnp.minimum(h, t1 - t)).astype(dtype)
        y1, K = m.stages(t, h, y, K.at[0].set(h * k0), args, batched)
        ok, factor = _control(m.tab, K, y, y1, rms, rtol=rtol, atol=atol, skip=dead)
        t_next = jnp.where(ok, jnp.where(h >= t1 - t, t1, t + h), t)
        moved = ok & (h > 0)
        if T:
            ys, j, at = save(t, h, y, y1, K, ys, j, at, moved, steps)
        if record:  # every iteration, with the step size that moved each trial
            rec = _keep(rec, t, jnp.where(moved, h, 0.0), y, steps, True, max_steps)
        h_next = (h * factor).astype(dtype)
        collapsed = (t_next < t1) & ~(h_next > 10 * jnp.finfo(dtype).eps * jnp.maximum(jnp.abs(t_next), 1.0))
        y = jnp.where(ok, y1, y)
        k0 = jnp.where(moved, K[-1] / jnp.where(h > 0, h, 1.0), k0)
        return t_next, h_next, y, k0, K, ys, j, at, steps + 1, dead | collapsed, acc + moved, rec

    ys = jnp.where((ts <= t0)[:, None, None], y0[None], jnp.full((T, n, B), jnp.nan, dtype))
    j = jnp.full((B,), jnp.sum(ts <= t0), jnp.int32)
    at = jnp.full((T, B), -1, jnp.int32)
    rec = _record_buffers(max_steps, n, B, dtype, (B,)) if record else ()
    K = jnp.zeros((m.s, n, B), dtype)
    init = (tv0, h_init, y0, f0, K, ys, j, at, jnp.int32(0), jnp.zeros((B,), bool), jnp.zeros((B,), jnp.int32), rec)
    t, _, y, _, _, ys, _, at, steps, dead, acc, rec = jax.lax.while_loop(running, step, init)
    return (jnp.concatenate([ys, y[None]]), dead | (t < t1), acc), (at, rec, steps)


def _backward(m: _Method, args, batched, diff, t0, t1, ts, y0, out, at, rec, ct, *, max_steps, times, elementwise=()):
    """The discrete adjoint of `_forward` (or of `_forward_per_trial`: its iterations, with each
    trial's own step sizes): the cotangents of `(y0, args[i] for i in diff)` for
    the cotangent `ct` of the saved states, with the accepted steps' sizes held fixed; if
    `times`, also those of `(t0, t1, ts)` (the exact solution's: `-<lambda(t0), f(t0, y0)>`,
    `<ct(t1), f(t1, y(t1))>`, `<ct_j, f(ts_j, y(ts_j))>`).

    Parameters shared by the batch (`batched[i]` false) are broadcast to one copy per trial,
    so each stage's VJP gives per-trial cotangents with no reduction over the batch; they are
    summed once at the end. The arguments in `elementwise` are differentiated element by
    element: the field is given them as nested tuples of per-trial scalars (`_elements`), so
    that no slice of them is transposed into a pad inside the stage VJPs (XLA fused the
    field's whole VJP into such pads, once per element: benchmarks/NOTES.md, sessions 9-10).
    Their per-trial cotangents leave each stage VJP packed in one `(elements, batch)` buffer
    and accumulate there (one kernel where there was one per element). The replayed steps and
    the recomputed stages (and the rates behind the times' cotangents) take the arguments as
    given (shared ones unbroadcast): only the stage VJPs need per-trial copies (session 11)."""
    ys, _, accepted = out  # with per-trial steps: the number of iterations
    Y, TK, HK, stride, used = rec
    _, S = checkpoints(max_steps)
    n, B = y0.shape
    T = ts.shape[0]
    dtype = y0.dtype
    lockstep = TK.ndim == 2  # each trial's own steps, in lockstep (`_forward_per_trial`)
    trials = jnp.arange(B)

    per_trial = [x if b or i not in diff else jnp.broadcast_to(x, (B,) + jnp.shape(x)) for i, (x, b) in enumerate(zip(args, batched))]
    pt_batched = tuple(b or i in diff for i, b in enumerate(batched))

    def with_diff(dargs):
        full = list(per_trial)
        for i, x in zip(diff, dargs):
            full[i] = x
        return full

    s_ = m.s
    a, c = jnp.asarray(m.tab.a, dtype), jnp.asarray(m.tab.c, dtype)
    dargs0 = [_elements(per_trial[i]) if i in elementwise else per_trial[i] for i in diff]
    d_leaves, d_def = jax.tree_util.tree_flatten(dargs0)
    cols = [i for i, x in enumerate(d_leaves) if x.shape == (B,)]  # per-trial scalars: one (E, B) buffer
    col_set = set(cols)
    rest = [i for i in range(len(d_leaves)) if i not in col_set]

    def pack(leaves):
        return (jnp.stack([leaves[i] for i in cols]) if cols else None, [leaves[i] for i in rest])

    def unpack(packed):
        stacked, others = packed
        leaves = [None] * len(d_leaves)
        for k, i in enumerate(cols):
            leaves[i] = stacked[k]
        for x, i in zip(others, rest):
            leaves[i] = x
        return jax.tree_util.tree_unflatten(d_def, leaves)

    zeros = pack([jnp.zeros_like(x) for x in d_leaves])

    def stage_vjp(ti, yi, g, needed):
        """`(d yi, d args)` of `<g, f(ti, yi)>`, forward and backward in a branch of their own
        (zeros unless `needed`)."""

        def one(ti, yg):  # with respect to the state's rows: no transposed slices (pads)
            yi, g = yg
            rows = tuple(yi[r] for r in range(yi.shape[0]))
            token = _IN_ADJOINT.set(True)
            try:
                _, pull = jax.vjp(lambda y, da: m.f(ti, y, with_diff(da), pt_batched).astype(dtype), rows, dargs0)
            finally:
                _IN_ADJOINT.reset(token)
            dy, da = pull(g)  # rows stay separate buffers: stacked outside the branch
            return dy, pack(jax.tree_util.tree_leaves(da))

        def none(ti, yg):
            return tuple(jnp.zeros_like(yi[0]) for _ in range(yi.shape[0])), zeros

        dy, da = jax.lax.cond(needed & jnp.all(jnp.isfinite(ti)), one, none, ti, (yi, g))
        return jnp.stack(dy), da

    def adjoint_step(k, y, carry):
        """Step `k` from `y` in reverse: its stages are recomputed, then run backwards stage by
        stage (each stage's VJP on its own, so nothing is stacked across stages)."""
        lam, acc, ts_bar, jp = carry
        t, h = TK[k], HK[k]

        def saved_here(j):  # whether save j (one per trial with per-trial steps) is step k's
            return (j >= 0) & (at[jnp.maximum(j, 0), trials] == k) if lockstep else (j >= 0) & (at[jnp.maximum(j, 0)] == k)

        has = jnp.any(saved_here(jp)) if T else jnp.bool_(False)
        # the stages, the last one only if the dense output of this step is saved
        K = jnp.zeros((s_,) + y.shape, dtype).at[0].set(h * m.rates(t, y, args, batched))

        def fwd_stage(i, K):
            return K.at[i].set(h * m.rates(t + c[i] * h, m.stage_arg(i, y, K), args, batched))

        K = jax.lax.fori_loop(1, jnp.where(has, s_, s_ - 1), fwd_stage, K)
        y1 = m.stage_arg(s_ - 1, y, K)

        def more(cc):
            return jnp.any(saved_here(cc[0]))

        def one(cc):
            j, gy, gy1, gK, ts_bar = cc
            if lockstep:  # each trial's next save, if it is this step's
                here = saved_here(j)
                jq = jnp.maximum(j, 0)
                ctj = jnp.where(here, ct[jq, :, trials].T, 0.0)
                tj = ts[jq]
            else:
                jq, ctj, tj = j, ct[j], ts[j]
            yj, ipull = jax.vjp(lambda y, y1, K: m.dense(t, h, y, y1, K, tj), y, y1, K)
            dy, dy1, dK = ipull(ctj)
            if times:
                rate = ctj * m.rates(tj, yj, args, batched)
                if lockstep:
                    ts_bar = ts_bar.at[jq].add(jnp.sum(rate, axis=0))
                else:
                    ts_bar = ts_bar.at[j].set(jnp.sum(rate))
            return (jnp.where(here, j - 1, j) if lockstep else j - 1), gy + dy, gy1 + dy1, gK + dK, ts_bar

        zero = jnp.zeros_like(y)
        if T:
            jp, gy, gy1, G, ts_bar = jax.lax.while_loop(more, one, (jp, zero, zero, jnp.zeros_like(K), ts_bar))
        else:
            gy, gy1, G = zero, zero, jnp.zeros_like(K)
        last_bar = lam + gy1  # the cotangent of y1, the last stage's argument

        def rev(r, cc):
            G, ybar, acc = cc
            i = s_ - 1 - r
            yi = m.stage_arg(i, y, K)
            dyi, da = stage_vjp(t + c[i] * h, yi, h * G[i], (i < s_ - 1) | has)
            dyi = dyi + jnp.where(i == s_ - 1, last_bar, 0.0)
            G = G + a[i][:, None, None] * dyi[None]  # y_i = y + sum_j a_ij K_j
            return G, ybar + dyi, jax.tree_util.tree_map(jnp.add, acc, da)

        _, ybar, acc = jax.lax.fori_loop(0, s_, rev, (G, gy, acc))
        return ybar, acc, ts_bar, jp

    def stretch(r, c):
        """The checkpoint stretch `g = used - 1 - r`: replay its steps from the stored state,
        then run them in reverse."""
        carry, Z = c
        g = used - 1 - r
        k0 = g * stride
        L = jnp.minimum(stride, accepted - k0)
        Z = Z.at[0].set(Y[g])

        def replay(i, Z):
            k = k0 + i - 1
            return Z.at[i].set(m.step(TK[k], HK[k], Z[i - 1], args, batched, last=False)[0])

        Z = jax.lax.fori_loop(1, L, replay, Z)
        carry = jax.lax.fori_loop(0, L, lambda i, cc: adjoint_step(k0 + L - 1 - i, Z[L - 1 - i], cc), carry)
        return carry, Z

    acc = zeros
    direct = (ts <= t0)[:, None, None]  # rows that are y0 itself
    carry = (ct[T], acc, jnp.zeros((T,), dtype), jnp.full((B,) if lockstep else (), T - 1, jnp.int32))
    (lam, acc, ts_bar, _), _ = jax.lax.fori_loop(0, used, stretch, (carry, jnp.zeros((S, n, B), dtype)))
    y0_bar = lam + jnp.sum(jnp.where(direct, ct[:T], 0.0), axis=0) if T else lam
    acc = unpack(acc)
    acc = [_assemble(a) if i in elementwise else a for i, a in zip(diff, acc)]
    args_bar = [a.sum(0) if not batched[i] else a for i, a in zip(diff, acc)]
    time_bars = None
    if times:
        f0 = m.rates(t0, y0, args, batched)
        f1 = m.rates(t1, ys[-1], args, batched)
        time_bars = (-jnp.sum(lam * f0), jnp.sum(ct[T] * f1), ts_bar)
    return y0_bar, args_bar, time_bars


def _elements(x):
    """A `(batch, *shape)` array as nested tuples (one level per axis of `shape`) of its
    `(batch,)` columns; `(batch,)` itself as it is."""
    if x.ndim == 1:
        return x
    return tuple(_elements(x[:, i]) for i in range(x.shape[1]))


def _assemble(e):
    """The inverse of `_elements`."""
    if isinstance(e, tuple):
        return jnp.stack([_assemble(c) for c in e], axis=1)
    return e


def solve(f, t0, t1, y0, ts, args=(), batched=(), *, tab: Tableau, rtol, atol, max_steps: int, elementwise=(), per_trial=False, fallback=False):
    """Integrate `y' = f(t, y, args, batched)` for the `(n, batch)` state `y0` from `t0` to
    `t1 >= t0`, with one step sequence for all columns (trials), saving at the sorted times `ts`
    (within `[t0, t1]`) and at `t1`. `args` is a list of arrays; `batched[i]` says whether
    `args[i]` has a leading trial axis (`f` must accept either).

    Trials (columns) whose state or rates are non-finite at `t0` (e.g. NaN inputs) are
    integrated but left out of the step-size control.

    Returns `(ys, failed, num_accepted_steps)`: `ys` is `(len(ts) + 1, n, batch)`, its last row
    the state at `t1`; `failed` is true if `max_steps` steps (accepted or rejected) were taken
    or the step size collapsed (e.g. a controlled trial turned non-finite) before `t1`; save
    rows never reached are NaN.

    With `per_trial`, each trial (column) takes its own steps instead, in lockstep
    (`_forward_per_trial`): `failed` and the step counts are then per trial, and the discrete
    adjoint runs the recorded iterations backwards with each trial's own step sizes (a
    rejected, finished or failed trial's iteration is the identity).

    With `fallback` (shared steps only), a batch whose shared step sequence fails is solved
    again with per-trial steps, so that one trial that cannot be integrated (it needs more
    than `max_steps` steps, or diverges) fails alone: the other trials get their solutions to
    their own tolerances, as in a batch without it. `failed` and the step counts are then per
    trial (the shared sequence's, repeated, when it succeeded). The gradient follows the solve
    that was kept: the per-trial solve is recomputed in the backward pass, where it is needed.

    Reverse-mode differentiable with respect to `y0`, `args` and the times: a discrete adjoint
    of the accepted steps (sizes held fixed), with states checkpointed in the forward pass
    (`checkpoints`) and replayed stretch by stretch; the cotangents of the times are those of
    the exact solution (`_backward`). Not forward-mode differentiable. `elementwise` lists
    the `args` that `f` also accepts as nested tuples of per-trial scalars (as `_elements`
    makes them; the backward pass differentiates these element by element).
    """
    dtype = y0.dtype
    t0, t1, ts = (jnp.asarray(x, dtype) for x in (t0, t1, ts))
    args, batched = list(args), tuple(bool(b) for b in batched)
    if len(batched) != len(args):
        raise ValueError(f"batched: one flag per entry of args ({len(args)}), got {len(batched)}")
    m = _Method(f, tab, dtype)
    opts = dict(rtol=rtol, atol=atol, max_steps=max_steps)
    cell = {}

    def forward(t0, t1, ts, y0, args, record):
        """`(out, (at, rec, n, fell_back))`: the solve and its record; `n` the number of steps
        (shared) or of iterations (per trial) the backward pass runs through; `fell_back`
        whether the shared solve failed and `out` is the per-trial solve's (its record is
        then recomputed by the backward pass)."""
        if per_trial:
            out, (at, rec, n) = _forward_per_trial(m, args, batched, t0, t1, y0, ts, record=record, **opts)
            return out, (at, rec, n, jnp.bool_(False))
        out, (at, rec) = _forward(m, args, batched, t0, t1, y0, ts, record=record, **opts)
        if not fallback:
            return out, (at, rec, out[2], jnp.bool_(False))
        B = y0.shape[1]
        fell_back = out[1]

        def per_trial_solve():
            return _forward_per_trial(m, args, batched, t0, t1, y0, ts, **opts)[0]

        def shared_solve():
            return out[0], jnp.broadcast_to(out[1], (B,)), jnp.broadcast_to(out[2], (B,)).astype(jnp.int32)

        return jax.lax.cond(fell_back, per_trial_solve, shared_solve), (at, rec, out[2], fell_back)

    @jax.custom_vjp
    def core(t0, t1, ts, y0, args):
        return forward(t0, t1, ts, y0, args, False)[0]

    def fwd(t0, t1, ts, y0, args):
        times = [x.perturbed for x in (t0, t1, ts)]
        cell["times"] = any(times)
        cell["diff"] = [i for i, x in enumerate(args) if x.perturbed and jnp.issubdtype(x.value.dtype, jnp.inexact)]
        t0, t1, ts, y0 = (x.value for x in (t0, t1, ts, y0))
        args = [x.value for x in args]
        out, (at, rec, steps, fell_back) = forward(t0, t1, ts, y0, args, True)
        return out, (t0, t1, ts, y0, args, (out[0], out[1], steps), at, rec, fell_back)

    def bwd(res, ct_out):
        t0, t1, ts, y0, args, out, at, rec, fell_back = res
        ct = ct_out[0]
        if isinstance(ct, jax.custom_derivatives.SymbolicZero):
            ct = jnp.zeros(out[0].shape, dtype)
        diff, times = cell["diff"], cell["times"]
        kw = dict(max_steps=max_steps, times=times, elementwise=set(elementwise))

        def shared_adjoint():
            return _backward(m, args, batched, diff, t0, t1, ts, y0, out, at, rec, ct, **kw)

        def per_trial_adjoint():  # the per-trial solve that `forward` kept, with its record
            out_p, (at_p, rec_p, n_p) = _forward_per_trial(m, args, batched, t0, t1, y0, ts, record=True, **opts)
            return _backward(m, args, batched, diff, t0, t1, ts, y0, (out_p[0], out_p[1], n_p), at_p, rec_p, ct, **kw)

        if fallback and not per_trial:
            y0_bar, d_bar, time_bars = jax.lax.cond(fell_back, per_trial_adjoint, shared_adjoint)
        else:
            y0_bar, d_bar, time_bars = shared_adjoint()
        args_bar = [None] * len(args)
        for i, g in zip(diff, d_bar):
            args_bar[i] = g
        t_bars = time_bars if times else (None, None, None)
        return (*t_bars, y0_bar, args_bar)

    core.defvjp(fwd, bwd, symbolic_zeros=True)
    return core(t0, t1, ts, y0, args)
