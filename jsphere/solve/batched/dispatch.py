"""Batched solves with one step-size sequence for the whole batch ("ensemble" integration).

Under `jax.vmap`, diffrax runs one adaptive controller per trial: every iteration of the
batched while loop carries per-trial times, step sizes, accept/reject selects and save logic,
and the batch runs as many iterations as its slowest trial. `solve` is a
`jax.custom_batching.custom_vmap` around one segment's `diffeqsolve`: unbatched it is the
ordinary solve; in its batching rule the whole batch is *one* ODE system whose state is an
`(n, batch)` array (row i: component i of every trial, the right-hand side of `jsphere.solve.batched.components`
on its rows), integrated with one step sequence whose steps are accepted only if every trial
meets its own tolerance (the error norm is the largest per-trial RMS norm). For diffrax's
Dopri8 (the default), Dopri5 and Tsit5 the integrator is `jsphere.solve.batched.loop` (the same
tableaus and dense output in a loop written for this layout); for any other solver it is
`diffeqsolve` with `SharedPIDController`. At 1024 trials of the issue-6 problem the shared
steps were 2.5x faster than per-trial steps with `diffeqsolve` (benchmarks/NOTES.md,
session 5: a few more steps, the smallest any trial needs at each time, at a third of the
cost per trial-step), and `_shared_rk` is another ~1.7x (session 8).

What it changes, and why it is still each trial's solution to its tolerance:
- every trial satisfies `rtol`/`atol` at every step (its error is at most the largest);
- results depend on the other trials of the batch, within the tolerance (~1e-9 m here);
- `max_steps` and `num_steps` count the shared steps; a trial that needs tiny steps slows the
  whole batch (under `vmap` it already did: the loop runs until the slowest trial ends);
- a trial whose rates are non-finite at the start (e.g. NaN inputs) is left out of the
  step-size control, so it does not stall the others; it is reported by `Trajectory.status`
  as before. A batch whose shared steps fail (a trial that needs more than `max_steps` steps
  or turns non-finite: the shared step size collapses) is solved again with per-trial steps
  (`fallback`), so that only the failing trial is reported failed and the others get their
  own solutions, as in a batch without it.

The rule falls back to a per-trial `vmap` when the segment's times (`t0`, `t1`, the save
times) are batched: then there is no shared time axis.
"""

from __future__ import annotations

from typing import Callable

import diffrax as dfx
import equinox as eqx
import jax
import jax.numpy as jnp

from . import loop as _shared_rk


def _trial_ok(y) -> jax.Array:
    """Per trial (the columns of a `(n, batch)` state): all components finite."""
    return jnp.all(jnp.isfinite(y), axis=0)


def _mask(y, ok):
    return jnp.where(ok, y, jnp.zeros_like(y))


def worst_trial_rms(err) -> jax.Array:
    """The largest over trials of each trial's RMS norm; `err` is `(n, batch)`."""
    return jnp.sqrt(jnp.max(jnp.mean(err * err, axis=0)))


class SharedPIDController(dfx.AbstractAdaptiveStepSizeController):
    """`diffrax.PIDController` for a batch sharing one step: the error norm is the worst trial's
    RMS norm. Trials that cannot be integrated at any step size (non-finite rates at the
    start, e.g. NaN inputs, or a non-finite state) are left out of the control."""

    pid: dfx.PIDController
    rtol: float
    atol: float
    norm: Callable = worst_trial_rms

    def __init__(self, rtol, atol):
        self.rtol, self.atol = rtol, atol
        self.pid = dfx.PIDController(rtol=rtol, atol=atol, norm=worst_trial_rms)

    def wrap(self, direction):
        return eqx.tree_at(lambda c: c.pid, self, self.pid.wrap(direction))

    def init(self, terms, t0, t1, y0, dt0, args, func, error_order):
        live = _trial_ok(y0) & _trial_ok(func(terms, t0, y0, args))

        def masked_func(terms_, t, y, args_):
            return _mask(func(terms_, t, y, args_), live)

        dt, state = self.pid.init(terms, t0, t1, _mask(y0, live), dt0, args, masked_func, error_order)
        return dt, (state, live)

    def adapt_step_size(self, t0, t1, y0, y1_candidate, args, y_error, error_order, controller_state):
        state, live = controller_state
        ok = live & _trial_ok(y0)
        keep, t_next, t_after, jump, state, result = self.pid.adapt_step_size(
            t0, t1, _mask(y0, ok), _mask(y1_candidate, ok), args, _mask(y_error, ok), error_order, state
        )
        return keep, t_next, t_after, jump, (state, live), result


def solve(field, control, solver, rtol, atol, max_steps, adjoint, y0, args, t_save, per_trial=False, fallback=False):
    """One segment of `solve_segments`: `diffeqsolve(field)` of the component tuple `y0` from
    `args[3]` to `args[4]` (`args = (p, d, control, a, b)`), saving at `t_save` and `t1`.
    `field(t, y, args, K=None)` may be given the inputs `K = control(t, args)` (a `(N,)`
    array or an `N`-tuple of scalars per trial) as a tuple of scalars.

    Returns `(ys, failed, num_accepted_steps)` with `ys` the tuple of saved components. Batched
    (under `vmap`), trials share one step sequence (module docstring); with `per_trial` (a
    solver of `jsphere.solve.batched.loop.SUPPORTED`) each trial takes its own steps, in lockstep
    (`_shared_rk._forward_per_trial`, with its own discrete adjoint), and `failed` and the
    step counts are per trial.

    With `fallback` (shared steps), a batch whose shared step sequence fails (one trial needs
    more than `max_steps` steps, or diverges) is solved again with per-trial steps, so that
    the failing trial fails alone and the others keep their solutions; `failed` and the step
    counts are then per trial as well.
    """
    dyn, static = eqx.partition(args[:3], eqx.is_array)
    p_leaves, p_def = jax.tree_util.tree_flatten(dyn)
    times = [args[3], args[4], t_save]

    # leaves of `p` and `d` that the fields (`jsphere.solve.batched.components`) also take as nested tuples of scalars
    n_pd = len(jax.tree_util.tree_leaves(dyn[:2]))
    elementwise = [i for i in range(n_pd) if jnp.ndim(p_leaves[i]) >= 1]

    def rebuild(lv, a, b):  # `static` first: a leaf of `lv` may be such a tuple
        return (*eqx.combine(static, jax.tree_util.tree_unflatten(p_def, lv)), a, b)

    def one(times, y0, lv):
        a, b, ts = times
        sol = dfx.diffeqsolve(
            dfx.ODETerm(field), solver, a, b, None, tuple(y0), rebuild(lv, a, b),
            saveat=dfx.SaveAt(ts=ts, t1=True), stepsize_controller=dfx.PIDController(rtol=rtol, atol=atol),
            max_steps=max_steps, throw=False, adjoint=adjoint,
        )  # fmt: skip
        return list(sol.ys), sol.result != dfx.RESULTS.successful, sol.stats["num_accepted_steps"]

    @jax.custom_batching.custom_vmap
    def f(times, y0, lv):
        return one(times, y0, lv)

    @f.def_vmap
    def _rule(axis_size, in_batched, times, y0, lv):
        t_b, y_b, l_b = in_batched
        if any(t_b) or (per_trial and _shared_rk.tableau(solver) is None):  # one solve per trial
            out = jax.vmap(one, in_axes=([0 if b else None for b in t_b], [0 if b else None for b in y_b], [0 if b else None for b in l_b]), axis_size=axis_size)(times, y0, lv)  # fmt: skip
            return out, jax.tree_util.tree_map(lambda _: True, out)
        a, b, ts = times
        # the batch as one `(n, batch)` array: row i is component i of every trial, contiguous
        # (one leaf: diffrax's per-leaf code once, compiles ~1.5x faster than a tuple of rows)
        yb = jnp.stack([y if bt else jnp.broadcast_to(y, (axis_size,)) for y, bt in zip(y0, y_b)])

        def axes(batched):
            return [0 if bt else None for bt in batched]

        def inputs(t, args, batched):  # (N, batch), or N vectors of (batch,): each input contiguous
            t_ax = 0 if jnp.ndim(t) else None  # one time per trial (per-trial steps) or one for all
            k = jax.vmap(lambda t, l, a, b: control(t, rebuild(l, a, b)), in_axes=(t_ax, axes(batched[:-2]), *axes(batched[-2:])), axis_size=axis_size)(t, args[:-2], *args[-2:])  # fmt: skip
            return k if isinstance(k, tuple) else k.T

        def batch_field(t, y, args, batched):
            """The field on the batch; `args = lv + [a, b]`, `batched` says which have a
            trial axis (the backward pass of `_shared_rk` gives shared parameters one); `y`
            is the `(n, batch)` state or the tuple of its rows."""
            # The inputs are computed in a branch of their own: XLA cannot fuse them into the
            # field's kernels, which would read a batched `(batch, N)` control output strided
            # (2.4x slower at 1024 trials, benchmarks/NOTES.md session 5). The predicate is true
            # at every finite time; being a run-time value, it keeps XLA from inlining the branch.
            K = _shared_rk.in_branch(lambda t, args: inputs(t, args, batched), t, args)
            K = K if isinstance(K, tuple) else tuple(K[i] for i in range(K.shape[0]))
            rates = jax.vmap(
                lambda t, z, k, l, a, b: field(t, z, rebuild(l, a, b), k),
                in_axes=(0 if jnp.ndim(t) else None, 0, 0, axes(batched[:-2]), *axes(batched[-2:])), axis_size=axis_size,
            )(t, tuple(y), K, args[:-2], *args[-2:])  # fmt: skip
            return jnp.stack(rates)

        tab = _shared_rk.tableau(solver)
        if tab is not None:  # the lean loop (Dopri8, Dopri5, Tsit5)
            out, failed, accepted = _shared_rk.solve(
                batch_field, a, b, yb, ts, [*lv, a, b], [*l_b, False, False], tab=tab, rtol=rtol, atol=atol,
                max_steps=max_steps, elementwise=elementwise, per_trial=per_trial, fallback=fallback,
            )  # fmt: skip
            if per_trial or fallback:  # failures and step counts per trial
                ys = [out[:, i, :].T for i in range(len(y0))]
                return (ys, failed, accepted), ([True] * len(ys), True, True)
        else:  # any other diffrax solver, in diffeqsolve
            flags = [*l_b, False, False]
            sol = dfx.diffeqsolve(
                dfx.ODETerm(lambda t, y, args: batch_field(t, y, args, flags)), solver, a, b, None, yb, [*lv, a, b],
                saveat=dfx.SaveAt(ts=ts, t1=True), stepsize_controller=SharedPIDController(rtol, atol),
                max_steps=max_steps, throw=False, adjoint=adjoint,
            )  # fmt: skip
            out, failed, accepted = sol.ys, sol.result != dfx.RESULTS.successful, sol.stats["num_accepted_steps"]
            if fallback:  # a failed batch again with per-trial steps: `failed` per trial

                def per_trial_solve():
                    ys, failed, steps = jax.vmap(one, in_axes=(None, axes(y_b), axes(l_b)), axis_size=axis_size)(times, y0, lv)
                    return jnp.stack(ys, axis=1).transpose(2, 1, 0), failed, steps

                def shared_solve():
                    return out, jnp.broadcast_to(failed, (axis_size,)), jnp.broadcast_to(accepted, (axis_size,))

                out, failed, accepted = jax.lax.cond(failed, per_trial_solve, shared_solve)
                ys = [out[:, i, :].T for i in range(len(y0))]
                return (ys, failed, accepted), ([True] * len(ys), True, True)
        ys = [out[:, i, :].T for i in range(len(y0))]  # (T+1, n, batch) -> n x (batch, T+1)
        return (ys, failed, accepted), ([True] * len(ys), False, False)

    ys, failed, steps = f(times, list(y0), p_leaves)
    return tuple(ys), failed, steps
