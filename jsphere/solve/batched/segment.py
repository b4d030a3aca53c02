"""One segment's solve, and what it becomes under `vmap`: shared steps for the batch.

Under `jax.vmap`, diffrax runs one adaptive controller per trial: every iteration of the
batched while loop carries per-trial times, step sizes, accept/reject selects and save logic,
and the batch runs as many iterations as its slowest trial. `solve` is a
`jax.custom_batching.custom_vmap` around one segment's `diffeqsolve`: unbatched it is the
ordinary solve; in its batching rule the whole batch is *one* ODE system whose state is an
`(n, batch)` array (row i: component i of every trial, the right-hand side of
`jsphere.solve.batched.components` on its rows), integrated with one step sequence whose steps
are accepted only if every trial meets its own tolerance (the error norm is the largest
per-trial RMS norm). For diffrax's Dopri8 (the default), Dopri5 and Tsit5 the integrator is
`jsphere.solve.batched.loop` (the same tableaus and dense output in a loop written for this
layout); for any other solver it is `diffeqsolve` with `SharedPIDController`. (Measurements:
`docs/performance.md`.)

What shared steps change, and why it is still each trial's solution to its tolerance:
- every trial satisfies `rtol`/`atol` at every step (its error is at most the largest);
- results depend on the other trials of the batch, within the tolerance;
- `max_steps` and `num_steps` count the shared steps; a trial that needs tiny steps slows the
  whole batch (under `vmap` it already did: the loop runs until the slowest trial ends);
- a trial whose rates are non-finite at the start (e.g. NaN inputs) is left out of the
  step-size control, so it does not stall the others; it is reported by `Trajectory.status`
  as before. With `Layout.SHARED_STEPS_RETRY`, a batch whose shared steps fail (a trial that
  needs more than `max_steps` steps or turns non-finite: the shared step size collapses) is
  solved again with per-trial steps, so that only the failing trial is reported failed and
  the others get their own solutions, as in a batch without it.

With `Layout.PER_TRIAL_STEPS` the batch loop gives every trial its own steps instead. The rule
falls back to a per-trial `vmap` when the segment's times (`t0`, `t1`, the save times) are
batched: then there is no shared time axis.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Callable

import diffrax as dfx
import equinox as eqx
import jax
import jax.numpy as jnp

from . import loop
from .layout import Layout
from .method import in_branch, tableau


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


def _axes(batched):
    return [0 if b else None for b in batched]


def _rows(out, n):
    """`(T+1, n, batch)` -> `n` arrays `(batch, T+1)`, one per component."""
    return [out[:, i, :].T for i in range(n)]


class _Segment(eqx.Module):
    """One segment's solve as `solve` sets it up: the field and its inputs, the solver's
    settings, the layout, and how the field's `FieldArgs` are rebuilt from their
    array leaves (`static`, `p_def`; `elementwise`: the leaves of `p` and `d` that the fields
    of `jsphere.solve.batched.components` also take as nested tuples of scalars)."""

    field: Callable
    control: Callable
    solver: Any
    rtol: Any
    atol: Any
    max_steps: int
    adjoint: Any
    layout: Layout
    static: Any
    p_def: Any
    elementwise: list

    def rebuild(self, lv, a, b):  # `static` first: a leaf of `lv` may be a tuple of scalars
        args = eqx.combine(self.static, jax.tree_util.tree_unflatten(self.p_def, lv))
        return dataclasses.replace(args, t_start=a, t_end=b)

    def one(self, times, y0, lv):
        """One trial's solve with diffrax: `(ys, failed, num_accepted_steps)`."""
        a, b, ts = times
        sol = dfx.diffeqsolve(
            dfx.ODETerm(self.field),
            self.solver,
            a,
            b,
            None,
            tuple(y0),
            self.rebuild(lv, a, b),
            saveat=dfx.SaveAt(ts=ts, t1=True),
            stepsize_controller=dfx.PIDController(rtol=self.rtol, atol=self.atol),
            max_steps=self.max_steps,
            throw=False,
            adjoint=self.adjoint,
        )
        return list(sol.ys), sol.result != dfx.RESULTS.successful, sol.stats["num_accepted_steps"]

    def batch_field(self, axis_size, adjoint=False):
        """The field on the batch, `f(t, y, args, batched)`: `args = lv + [a, b]`, `batched`
        says which have a trial axis (the discrete adjoint gives shared parameters one); `y`
        is the `(n, batch)` state or the tuple of its rows. `adjoint`: the form the discrete
        adjoint differentiates (`jsphere.solve.batched.components.torque_field_components`)."""

        def inputs(t, args, batched):  # (N, batch), or N vectors of (batch,): each input contiguous
            t_ax = 0 if jnp.ndim(t) else None  # one time per trial (per-trial steps) or one for all
            k = jax.vmap(
                lambda t, l, a, b: self.control(t, self.rebuild(l, a, b)),
                in_axes=(t_ax, _axes(batched[:-2]), *_axes(batched[-2:])),
                axis_size=axis_size,
            )(t, args[:-2], *args[-2:])
            return k if isinstance(k, tuple) else k.T

        def f(t, y, args, batched):
            # The inputs are computed in a branch of their own: XLA cannot fuse them into the
            # field's kernels, which would read a batched `(batch, N)` control output strided.
            # The predicate is true at every finite time; being a run-time value, it keeps XLA
            # from inlining the branch.
            K = in_branch(lambda t, args: inputs(t, args, batched), t, args)
            K = K if isinstance(K, tuple) else tuple(K[i] for i in range(K.shape[0]))
            field = self.field if not adjoint else lambda t, z, args, k: self.field(t, z, args, k, adjoint=True)
            rates = jax.vmap(
                lambda t, z, k, l, a, b: field(t, z, self.rebuild(l, a, b), k),
                in_axes=(0 if jnp.ndim(t) else None, 0, 0, _axes(batched[:-2]), *_axes(batched[-2:])),
                axis_size=axis_size,
            )(t, tuple(y), K, args[:-2], *args[-2:])
            return jnp.stack(rates)

        return f

    def rule(self, axis_size, in_batched, times, y0, lv):
        """The batching rule of `solve`."""
        t_b, y_b, l_b = in_batched
        per_trial = self.layout is Layout.PER_TRIAL_STEPS
        if any(t_b) or (per_trial and tableau(self.solver) is None):  # one solve per trial
            out = jax.vmap(self.one, in_axes=(_axes(t_b), _axes(y_b), _axes(l_b)), axis_size=axis_size)(times, y0, lv)
            return out, jax.tree_util.tree_map(lambda _: True, out)
        a, b, ts = times
        # the batch as one `(n, batch)` array: row i is component i of every trial, contiguous
        # (one leaf: diffrax's per-leaf code once, which compiles faster than a tuple of rows)
        yb = jnp.stack([y if bt else jnp.broadcast_to(y, (axis_size,)) for y, bt in zip(y0, y_b)])
        tab = tableau(self.solver)
        if tab is not None:  # the batch loop (Dopri8, Dopri5, Tsit5)
            out, failed, accepted = loop.solve(
                self.batch_field(axis_size),
                a,
                b,
                yb,
                ts,
                [*lv, a, b],
                [*l_b, False, False],
                tab=tab,
                rtol=self.rtol,
                atol=self.atol,
                max_steps=self.max_steps,
                elementwise=self.elementwise,
                per_trial=per_trial,
                fallback=self.layout is Layout.SHARED_STEPS_RETRY,
                f_adjoint=self.batch_field(axis_size, adjoint=True),
            )
            per = per_trial or self.layout is Layout.SHARED_STEPS_RETRY  # failures and step counts per trial
        else:  # any other diffrax solver, in diffeqsolve
            out, failed, accepted, per = self.in_diffeqsolve(axis_size, times, y0, yb, lv, y_b, l_b)
        ys = _rows(out, len(y0))
        return (ys, failed, accepted), ([True] * len(ys), per, per)

    def in_diffeqsolve(self, axis_size, times, y0, yb, lv, y_b, l_b):
        """Shared steps of any diffrax solver (`SharedPIDController`); with
        `Layout.SHARED_STEPS_RETRY` a failed batch again with per-trial steps (`failed` and the
        step counts per trial, and the last output `True`)."""
        a, b, ts = times
        flags = [*l_b, False, False]
        field = self.batch_field(axis_size)
        sol = dfx.diffeqsolve(
            dfx.ODETerm(lambda t, y, args: field(t, y, args, flags)),
            self.solver,
            a,
            b,
            None,
            yb,
            [*lv, a, b],
            saveat=dfx.SaveAt(ts=ts, t1=True),
            stepsize_controller=SharedPIDController(self.rtol, self.atol),
            max_steps=self.max_steps,
            throw=False,
            adjoint=self.adjoint,
        )
        out, failed, accepted = sol.ys, sol.result != dfx.RESULTS.successful, sol.stats["num_accepted_steps"]
        if self.layout is not Layout.SHARED_STEPS_RETRY:
            return out, failed, accepted, False

        def per_trial_solve():
            in_axes = (None, _axes(y_b), _axes(l_b))
            ys, failed, steps = jax.vmap(self.one, in_axes=in_axes, axis_size=axis_size)(times, y0, lv)
            return jnp.stack(ys, axis=1).transpose(2, 1, 0), failed, steps

        def shared_solve():
            return out, jnp.broadcast_to(failed, (axis_size,)), jnp.broadcast_to(accepted, (axis_size,))

        out, failed, accepted = jax.lax.cond(failed, per_trial_solve, shared_solve)
        return out, failed, accepted, True


def solve(field, control, solver, rtol, atol, max_steps, adjoint, y0, args, t_save, layout: Layout):
    """One segment of `jsphere.solve.segments.solve_segments` in a batch layout
    (`layout.batch_solve`): `diffeqsolve(field)` of the component tuple `y0` from
    `args.t_start` to `args.t_end` (`args` a `jsphere.solve.field_args.FieldArgs`), saving at
    `t_save` and `t1`.
    `field(t, y, args, K=None, adjoint=False)` may be given the inputs `K = control(t, args)`
    (a `(N,)` array or an `N`-tuple of scalars per trial) as a tuple of scalars.

    Returns `(ys, failed, num_accepted_steps)` with `ys` the tuple of saved components.
    Unbatched, this is diffrax's solve. Batched (under `vmap`): with `Layout.SHARED_STEPS` the
    trials share one step sequence (module docstring); with `Layout.PER_TRIAL_STEPS` (a
    solver of `jsphere.solve.batched.method.SUPPORTED`) each trial takes its own steps, in
    lockstep (`jsphere.solve.batched.loop.forward`, `per_trial`, with its own discrete adjoint),
    and `failed` and the step counts are per trial. With `Layout.SHARED_STEPS_RETRY`, a batch
    whose shared step sequence fails (one trial needs more than `max_steps` steps, or
    diverges) is solved again with per-trial steps, so that the failing trial fails alone and
    the others keep their solutions; `failed` and the step counts are then per trial as well.
    """
    dyn, static = eqx.partition(dataclasses.replace(args, t_start=None, t_end=None), eqx.is_array)
    p_leaves, p_def = jax.tree_util.tree_flatten(dyn)
    times = [args.t_start, args.t_end, t_save]
    n_pd = len(jax.tree_util.tree_leaves((dyn.params, dyn.derived)))
    elementwise = [i for i in range(n_pd) if jnp.ndim(p_leaves[i]) >= 1]
    seg = _Segment(field, control, solver, rtol, atol, max_steps, adjoint, layout, static, p_def, elementwise)

    @jax.custom_batching.custom_vmap
    def f(times, y0, lv):
        return seg.one(times, y0, lv)

    f.def_vmap(seg.rule)
    ys, failed, steps = f(times, list(y0), p_leaves)
    return tuple(ys), failed, steps
