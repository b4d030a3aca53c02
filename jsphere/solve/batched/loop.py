"""One adaptive Runge-Kutta step sequence for a whole batch, its state an `(n, batch)` array.

This is the integrator behind the batching rule of `jsphere.solve.batched.segment.solve`
(batched torque- and gait-mode solves with shared steps, the default, or with per-trial steps).
Its method is a diffrax solver's own (`jsphere.solve.batched.method`): the Butcher tableau of
`diffrax.Dopri8` (or `Dopri5`, `Tsit5`), its dense output for the save times, and an integral
step-size controller (Hairer, Norsett & Wanner, II.4: the next step is `h 0.9 err^(-1/order)`,
between 0.2x and 10x the last one, at most 0.9x after a rejected step; the starting step as
diffrax selects it). Unlike `diffrax.PIDController`, which never shrinks the step after an
accepted one, this rule may. The error norm is the largest over trials of each trial's RMS
norm, so every trial meets its own tolerance.

Why not `diffrax.diffeqsolve` itself here: on CPU much of its batched solve is its stage
machinery (the stage sums as `dot`s of a tableau row with the stage buffer, the solution and
error sums as library reductions, a dynamic-update-slice per stage). Here:
- the vector field is evaluated in a `lax.cond` branch of its own (a run-time true predicate),
  so XLA materialises each stage's rates instead of fusing the field into the stage sums;
- the stage sums are written out as elementwise sums over the stage buffer's rows (one fused
  kernel per stage);
- the error norm sums over the state's rows explicitly, for the same reason.
(Measurements: `docs/performance.md`.)

Reverse mode: `solve` has a discrete adjoint (`jsphere.solve.batched.adjoint`), which matches
diffrax's autodiff of per-trial solves (tests/solve/test_batched_loop.py).

The same loop also runs batches with per-trial steps (`forward` with `per_trial`): each trial has its
own time and step size, in lockstep, so the batch is still one vectorised loop but no trial
depends on another.
"""

from __future__ import annotations

from typing import Callable

import equinox as eqx
import jax
import jax.numpy as jnp

from .adjoint import Record, backward
from .method import Method, Tableau, checkpoints, mean_sq_rows


def _initial_step(m: Method, args, batched, t0, y0, f0, rms, *, rtol, atol, finite=False):
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
    h1 = jnp.where(
        dmax <= 1e-15, jnp.maximum(1e-6, h0 * 1e-3), (0.01 / jnp.where(dmax <= 1e-15, 1.0, dmax)) ** (1.0 / m.tab.order)
    )
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
    return Record(
        jnp.zeros((C + 1, n, B), dtype),
        jnp.zeros((max_steps,) + per, dtype),
        jnp.zeros((max_steps,) + per, dtype),
        jnp.int32(1),
        jnp.int32(0),
    )


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
    return Record(Y, TK, HK, stride, used + (ok & due))


def forward(m: Method, args, batched, t0, t1, y0, ts, *, rtol, atol, max_steps, record=False, per_trial=False):
    """The integration of `solve`: one step sequence for the batch, or with `per_trial` one of
    each trial's own, taken in lockstep (every trial has its own time, step size, error norm
    and acceptance, so its result does not depend on the other trials, while the batch still
    runs as one vectorised loop; a trial that is done or failed takes steps of size zero). A
    failure (`max_steps` iterations, or a step size that collapsed, e.g. a state turned
    non-finite) is then per trial too: that trial is frozen, the others go on.

    Returns `(ys, failed, accepted)` (per trial with `per_trial`) and `(at, rec, n)`: with
    `record`, what the backward pass needs: the recorded steps' `(t_k, h_k)` (shared: the
    accepted steps; per trial: every iteration, with each trial's *effective* step size, zero
    where it rejected its step, was done or had failed: its adjoint is then the identity), the
    states at every `stride`-th of them (`checkpoints`), for each save time (and trial) the
    index of the step that saved it (-1: none), and `n` the number of recorded steps."""
    dtype = y0.dtype
    n, B = y0.shape
    T = ts.shape[0]
    per = (B,) if per_trial else ()
    tv0 = jnp.full(per, t0, dtype)
    f0 = m.rates(tv0, y0, args, batched)
    if per_trial:

        def rms(x):  # each trial's RMS norm
            return jnp.sqrt(mean_sq_rows(x))
    else:
        live = jnp.all(jnp.isfinite(y0), axis=0) & jnp.all(jnp.isfinite(f0), axis=0)  # controlled trials

        def rms(x):  # the largest per-trial RMS norm over the controlled trials
            return jnp.sqrt(jnp.max(jnp.where(live, mean_sq_rows(x), 0.0)))

    h_init = _initial_step(m, args, batched, tv0, y0, f0, rms, rtol=rtol, atol=atol, finite=per_trial)
    save = _save_per_trial if per_trial else _save_shared

    def running(c):
        t, steps, dead = c[0], c[8], c[9]
        return jnp.any((t < t1) & ~dead) & (steps < max_steps)

    def step(c):
        t, h, y, k0, K, ys, j, at, steps, dead, acc, rec = c
        h = jnp.where(dead, 0.0, jnp.minimum(h, t1 - t)).astype(dtype) if per_trial else jnp.minimum(h, t1 - t)
        y1, K = m.stages(t, h, y, K.at[0].set(h * k0), args, batched)
        ok, factor = _control(m.tab, K, y, y1, rms, rtol=rtol, atol=atol, skip=dead if per_trial else None)
        t_next = jnp.where(ok, jnp.where(h >= t1 - t, t1, t + h), t)
        moved = ok & (h > 0)
        if T:
            ys, j, at = save(m, ts, t, h, t_next, y, y1, K, ys, j, at, moved, steps if per_trial else acc)
        if record and per_trial:  # every iteration, with the step size that moved each trial
            rec = _keep(rec, t, jnp.where(moved, h, 0.0), y, steps, True, max_steps)
        elif record:
            rec = _keep(rec, t, h, y, acc, ok, max_steps)
        h_next = (h * factor).astype(dtype)
        collapsed = (t_next < t1) & ~(h_next > 10 * jnp.finfo(dtype).eps * jnp.maximum(jnp.abs(t_next), 1.0))
        y = jnp.where(ok, y1, y)
        k0 = jnp.where(moved, K[-1] / jnp.where(h > 0, h, 1.0), k0) if per_trial else jnp.where(ok, K[-1] / h, k0)
        return t_next, h_next, y, k0, K, ys, j, at, steps + 1, dead | collapsed, acc + moved, rec

    ys = jnp.where((ts <= t0)[:, None, None], y0[None], jnp.full((T, n, B), jnp.nan, dtype))
    j = jnp.full(per, jnp.sum(ts <= t0), jnp.int32)
    at = jnp.full((T,) + per, -1, jnp.int32)
    rec = _record_buffers(max_steps, n, B, dtype, per) if record else ()
    K = jnp.zeros((m.s, n, B), dtype)
    init = (tv0, h_init, y0, f0, K, ys, j, at, jnp.int32(0), jnp.zeros(per, bool), jnp.zeros(per, jnp.int32), rec)
    t, _, y, _, _, ys, _, at, steps, dead, acc, rec = jax.lax.while_loop(running, step, init)
    return (jnp.concatenate([ys, y[None]]), dead | (t < t1), acc), (at, rec, steps if per_trial else acc)


def _save_shared(m: Method, ts, t, h, t_next, y, y1, K, ys, j, at, ok, k):
    """Dense output at the save times in `(t, t + h]` of the accepted shared step `k`."""
    T = ts.shape[0]

    def more(c):
        return (c[1] < T) & (ts[jnp.minimum(c[1], T - 1)] <= t + h)

    def one(c):
        ys, j, at = c
        return ys.at[j].set(m.dense(t, h, y, y1, K, ts[j])), j + 1, at.at[j].set(k)

    due = ok & (j < T) & (ts[jnp.minimum(j, T - 1)] <= t_next)
    return jax.lax.cond(due, lambda: jax.lax.while_loop(more, one, (ys, j, at)), lambda: (ys, j, at))


def _save_per_trial(m: Method, ts, t, h, t_next, y, y1, K, ys, j, at, ok, k):
    """Dense output at each trial's save times in `(t, t + h]` (its accepted steps only)."""
    T = ts.shape[0]
    trials = jnp.arange(y.shape[1])

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


class _Residuals(eqx.Module):
    """What `solve`'s backward pass needs: the inputs, the solve and its record (arrays), and
    which inputs are differentiated (static: the backward pass is traced for them)."""

    t0: jax.Array
    t1: jax.Array
    ts: jax.Array
    y0: jax.Array
    args: list
    out: tuple  # (ys, failed, steps): `steps` the number of recorded steps or iterations
    at: jax.Array
    rec: Record
    fell_back: jax.Array
    diff: tuple[int, ...] = eqx.field(static=True)  # the differentiated `args`
    times: bool = eqx.field(static=True)  # whether `(t0, t1, ts)` are differentiated


class _Passes:
    """`solve`'s forward pass (`run`) and the two halves of its custom VJP (`fwd`, `bwd`), for
    one method and its settings (trace-time context only)."""

    def __init__(self, m: Method, batched, opts, per_trial, fallback, elementwise, f_adjoint):
        self.m, self.batched, self.opts = m, batched, opts
        self.per_trial, self.fallback, self.elementwise, self.f_adjoint = per_trial, fallback, elementwise, f_adjoint

    def run(self, t0, t1, ts, y0, args, record):
        """`(out, (at, rec, n, fell_back))`: the solve and its record; `n` the number of steps
        (shared) or of iterations (per trial) the backward pass runs through; `fell_back`
        whether the shared solve failed and `out` is the per-trial solve's (its record is
        then recomputed by the backward pass)."""
        m, batched, opts = self.m, self.batched, self.opts
        out, (at, rec, n) = forward(m, args, batched, t0, t1, y0, ts, record=record, per_trial=self.per_trial, **opts)
        if self.per_trial or not self.fallback:
            return out, (at, rec, n, jnp.bool_(False))
        B = y0.shape[1]

        def per_trial_solve():
            return forward(m, args, batched, t0, t1, y0, ts, per_trial=True, **opts)[0]

        def shared_solve():
            return out[0], jnp.broadcast_to(out[1], (B,)), jnp.broadcast_to(out[2], (B,)).astype(jnp.int32)

        return jax.lax.cond(out[1], per_trial_solve, shared_solve), (at, rec, n, out[1])

    def fwd(self, t0, t1, ts, y0, args):
        times = any(x.perturbed for x in (t0, t1, ts))
        diff = tuple(i for i, x in enumerate(args) if x.perturbed and jnp.issubdtype(x.value.dtype, jnp.inexact))
        t0, t1, ts, y0 = (x.value for x in (t0, t1, ts, y0))
        args = [x.value for x in args]
        out, (at, rec, steps, fell_back) = self.run(t0, t1, ts, y0, args, True)
        return out, _Residuals(t0, t1, ts, y0, args, (out[0], out[1], steps), at, rec, fell_back, diff, times)

    def bwd(self, res: _Residuals, ct_out):
        m, batched = self.m, self.batched
        ct = ct_out[0]
        if isinstance(ct, jax.custom_derivatives.SymbolicZero):
            ct = jnp.zeros(res.out[0].shape, res.y0.dtype)
        kw = dict(
            max_steps=self.opts["max_steps"], times=res.times, elementwise=self.elementwise, f_adjoint=self.f_adjoint
        )
        common = (m, res.args, batched, list(res.diff), res.t0, res.t1, res.ts, res.y0)

        def shared_adjoint():
            return backward(*common, res.out, res.at, res.rec, ct, **kw)

        def per_trial_adjoint():  # the per-trial solve that `run` kept, with its record
            out_p, (at_p, rec_p, n_p) = forward(
                m, res.args, batched, res.t0, res.t1, res.y0, res.ts, record=True, per_trial=True, **self.opts
            )
            return backward(*common, (out_p[0], out_p[1], n_p), at_p, rec_p, ct, **kw)

        if self.fallback and not self.per_trial:
            y0_bar, d_bar, time_bars = jax.lax.cond(res.fell_back, per_trial_adjoint, shared_adjoint)
        else:
            y0_bar, d_bar, time_bars = shared_adjoint()
        args_bar = [None] * len(res.args)
        for i, g in zip(res.diff, d_bar):
            args_bar[i] = g
        t_bars = time_bars if res.times else (None, None, None)
        return (*t_bars, y0_bar, args_bar)


def solve(
    f,
    t0,
    t1,
    y0,
    ts,
    args=(),
    batched=(),
    *,
    tab: Tableau,
    rtol,
    atol,
    max_steps: int,
    elementwise=(),
    per_trial=False,
    fallback=False,
    f_adjoint: Callable | None = None,
):
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
    (`forward` with `per_trial`): `failed` and the step counts are then per trial, and the discrete
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
    the exact solution (`jsphere.solve.batched.adjoint.backward`). Not forward-mode
    differentiable. `elementwise` lists the `args` that `f` also accepts as nested tuples of
    per-trial scalars (the backward pass differentiates these element by element);
    `f_adjoint`, if given, is the field the backward pass differentiates instead of `f` (the
    same values; it may materialise more intermediate values).
    """
    dtype = y0.dtype
    t0, t1, ts = (jnp.asarray(x, dtype) for x in (t0, t1, ts))
    args, batched = list(args), tuple(bool(b) for b in batched)
    if len(batched) != len(args):
        raise ValueError(f"batched: one flag per entry of args ({len(args)}), got {len(batched)}")
    opts = dict(rtol=rtol, atol=atol, max_steps=max_steps)
    passes = _Passes(Method(f, tab, dtype), batched, opts, per_trial, fallback, set(elementwise), f_adjoint)
    core = jax.custom_vjp(lambda t0, t1, ts, y0, args: passes.run(t0, t1, ts, y0, args, False)[0])
    core.defvjp(passes.fwd, passes.bwd, symbolic_zeros=True)
    return core(t0, t1, ts, y0, args)
