"""Integration over consecutive segments (control pieces between jumps, or gaits), sampled at
the output times: `solve_segments`."""

from __future__ import annotations

import diffrax as dfx
import equinox as eqx
import jax
import jax.numpy as jnp

from ..model.params import Derived, RobotParams
from .batched import segment as _segment
from .batched.components import from_components, to_components
from .batched.layout import Layout
from .field_args import FieldArgs
from .fields import _torque_control
from .status import RESULTS
from .trajectory import assemble


def _sample_masks(ts_out, a, b, last: bool):
    """Which output times segment `[a, b]` reports. A time on a boundary goes to the later
    segment, except that a time stamp given twice gives the left limit first, then the right."""
    first_dup = jnp.concatenate([ts_out[1:] == ts_out[:-1], jnp.zeros((1,), bool)])
    starts = (ts_out > a) | ((ts_out == a) & ~first_dup)
    ends = (ts_out < b) | ((ts_out == b) & (first_dup | last))
    return starts & ends


def _homogeneous(controls):
    """Stack per-segment controls if they share their structure and static parts."""
    parts = [eqx.partition(c, eqx.is_array) for c in controls]
    dyn0, st0 = parts[0]
    tdef = jax.tree_util.tree_structure(dyn0)
    for dyn, st in parts[1:]:
        if jax.tree_util.tree_structure(dyn) != tdef or not eqx.tree_equal(st, st0):
            return None
        if any(
            jnp.shape(u) != jnp.shape(v)
            for u, v in zip(jax.tree_util.tree_leaves(dyn), jax.tree_util.tree_leaves(dyn0))
        ):
            return None
    stacked = jax.tree_util.tree_map(lambda *xs: jnp.stack([jnp.asarray(x) for x in xs]), *[d for d, _ in parts])
    return stacked, st0


def _primal(tree):
    """`tree` with its arrays held out of differentiation, for a check whose tangents nothing
    reads: under `jvp` (the fit's forward-mode Jacobians) they would still be traced."""
    arrays, rest = eqx.partition(tree, eqx.is_array)
    return eqx.combine(jax.lax.stop_gradient(arrays), rest)


def _status(failed, bad_start, finite):
    """The segment's `RESULTS` code. diffrax fills the save points it never reached with inf, so
    its result decides first."""
    nonfinite, max_steps = int(RESULTS.nonfinite), int(RESULTS.max_steps_reached)
    ok = int(RESULTS.successful)
    return jnp.where(failed, jnp.where(bad_start, nonfinite, max_steps), jnp.where(finite, ok, nonfinite))


def solve_segments(
    field,
    outputs,
    p: RobotParams,
    d: Derived,
    segments: list,
    z0,
    ts_out,
    method: tuple,
    *,
    jump_fn=None,
    layout: Layout = Layout.FLAT,
    component_field=None,
    component_control=None,
):
    """Integrate `field(t, z, FieldArgs(params=p, derived=d, control=control, t_start=a, t_end=b))` over consecutive segments
    `(control, a, b)`, restarting at each (after `z = jump_fn(k, a, z, control)` if given),
    and sample the flat state and `outputs(t, z, args)` at `ts_out`, with the adaptive
    `method = (solver, rtol, atol, max_steps, adjoint)`.

    Segments whose controls share a structure (e.g. the paper's gaits) run in one
    `lax.scan`, so compile time does not grow with their number. `layout`
    (`jsphere.solve.batched.layout.Layout`): with a component layout the solver carries the
    state as a tuple of scalars and integrates `component_field` (the same field on that
    tuple, `jsphere.solve.batched.components`), whose inputs are `component_control(t, args)`
    (default: the torques); the batch loop's layouts solve each segment with
    `jsphere.solve.batched.segment.solve`. With `Layout.SHARED_STEPS_RETRY` a trial that failed
    in an earlier segment is left out of the later ones' step control.

    Returns the `Trajectory` (`assemble`).
    """
    n_seg, T, dt = len(segments), ts_out.shape[0], z0.dtype
    fields = (field, component_field, component_control or _torque_control)

    def one_segment(carry, k, control, a, b):
        z, zs, om, cd, Ks, seg, code, steps = carry
        args = FieldArgs(params=p, derived=d, control=control, t_start=a, t_end=b)
        if jump_fn is not None:
            z = jump_fn(k, a, z, control)
        if layout is Layout.SHARED_STEPS_RETRY:  # a trial failed in an earlier segment: out of the step control
            z = jnp.where(code != 0, jnp.nan, z)
        t_save = jnp.clip(ts_out, a, b)
        ys, failed, n_acc = _solve_one(fields, method, layout, z, args, t_save)
        mask = _sample_masks(ts_out, a, b, k == n_seg - 1)
        out = jax.vmap(lambda t, zz: outputs(t, zz, args))(t_save, ys[:-1])
        zs, om, cd, Ks = (jnp.where(mask[:, None], new, old) for new, old in zip((ys[:-1], *out), (zs, om, cd, Ks)))
        seg = jnp.where(mask, k, seg)
        bad_start = ~jnp.all(jnp.isfinite(field(a, *_primal((z, args)))))
        finite = jnp.all(jnp.isfinite(ys)) & jnp.all(jnp.isfinite(out[2]))
        code = jnp.where(code != 0, code, _status(failed, bad_start, finite))
        return (ys[-1], zs, om, cd, Ks, seg, code, steps + n_acc)

    N = d.k.shape[0]
    zeros = (jnp.zeros((T, z0.shape[0]), dt), jnp.zeros((T, 3), dt), jnp.zeros((T, N), dt), jnp.zeros((T, N), dt))
    carry = (z0, *zeros, jnp.zeros((T,), jnp.int32), jnp.array(0, jnp.int32), jnp.array(0, jnp.int32))
    return assemble(p, d, ts_out, *_over_segments(one_segment, carry, segments)[1:])


def _solve_one(fields, method, layout: Layout, z, args: FieldArgs, t_save):
    """One segment's solve from `z` with the field's `args`, saved at `t_save` and at its end:
    `(ys (T+1, 16+N), failed, accepted steps)`. `fields`: `(field, component_field,
    component_control)` (`solve_segments`); `method`: `(solver, rtol, atol, max_steps,
    adjoint)`."""
    field, component_field, component_control = fields
    solver, rtol, atol, max_steps, adjoint = method
    if layout.batch_solve:
        ys, failed, n_acc = _segment.solve(
            component_field, component_control, *method, to_components(z), args, t_save, layout
        )
        return from_components(ys), failed, n_acc
    term, y0 = (dfx.ODETerm(component_field), to_components(z)) if layout.components else (dfx.ODETerm(field), z)
    sol = dfx.diffeqsolve(
        term,
        solver,
        args.t_start,
        args.t_end,
        None,
        y0,
        args,
        saveat=dfx.SaveAt(ts=t_save, t1=True),
        stepsize_controller=dfx.PIDController(rtol=rtol, atol=atol),
        max_steps=max_steps,
        throw=False,
        adjoint=adjoint,
    )
    ys = from_components(sol.ys) if layout.components else sol.ys
    return ys, sol.result != dfx.RESULTS.successful, sol.stats["num_accepted_steps"]


def _over_segments(one_segment, carry, segments):
    """`carry = one_segment(carry, k, control, a, b)` for every segment `k`: in one `lax.scan`
    when their controls can be stacked (`_homogeneous`), else one after the other."""
    n_seg = len(segments)
    stacked = _homogeneous([c for c, _, _ in segments]) if n_seg > 1 else None
    if stacked is None:
        for k, (control, a, b) in enumerate(segments):
            carry = one_segment(carry, jnp.array(k, jnp.int32), control, a, b)
        return carry
    dyn, static = stacked
    xs = (
        jnp.arange(n_seg, dtype=jnp.int32),
        dyn,
        jnp.stack([a for _, a, _ in segments]),
        jnp.stack([b for _, _, b in segments]),
    )

    def body(c, x):
        k, dc, a, b = x
        return one_segment(c, k, eqx.combine(dc, static), a, b), None

    carry, _ = jax.lax.scan(body, carry, xs)
    return carry
