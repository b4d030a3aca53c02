"""What a solve becomes under `vmap`: the batching rule that picks its layout.

Under `vmap`, torque- and gait-mode solves carry the state as a tuple of scalar components
(`jsphere.solve.batched.components`): each component is then one contiguous `(batch,)` vector
and XLA on CPU vectorises the right-hand side (3.4) over the batch, while the flat
`(16+N,)` layout is faster for a single trial. A solve cannot see a `vmap` from inside, so the
choice is made by `jax.custom_batching.custom_vmap` (`_dispatched`): the unbatched call runs
`Layout.FLAT`, the batching rule the layout of `BatchedSolve.layout_for` (the batch loop's
layouts from `SHARED_MIN_BATCH` trials, components from `COMPONENT_MIN_BATCH`), in chunks of
`batch_chunk()` trials (1024 on a CPU).

As `custom_vmap` has no reverse mode, the default adjoint wraps it in a custom VJP
(`_reverse`). Its forward pass is the solve in the layout chosen by batching and keeps only
the inputs; its backward pass recomputes the VJP of just the outputs whose cotangents are not
zero: unbatched and in small batches the flat layout with diffrax's own VJP, in one compiled
program; batches in the batch loop through its discrete adjoint (`_loop_vjp`,
`jsphere.solve.batched.adjoint`); other large batches the flat VJP per trial, in chunks of
`GRAD_CHUNK` trials. An eager `jax.grad` (no `jit` or `vmap` around) thus compiles two
programs, the solve and its VJP (both through `jsphere._runtime.quick_compile.run_program`); with
at most `FORWARD_MAX_INPUTS` perturbed input scalars (a gradient with respect to a gait's
amplitude, say) it compiles one, the solve with its Jacobian in forward mode (`_flat_jacfwd`).
`diffrax.ForwardMode` uses the `custom_vmap` directly (its `jvp` is supported).

Only traced calls come here (`jsphere.solve.simulate`): a call with concrete inputs cannot be
under `vmap`, and takes diffrax's path directly.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Any, Callable

import diffrax as dfx
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.custom_derivatives import SymbolicZero

from ..._runtime.arrays import traced, transformed
from ..._runtime.quick_compile import eager_jit, run_program
from ...model.params import Derived, derive
from . import layout as _layout
from .layout import Layout
from .method import tableau

#: An eager `jax.grad` with at most this many perturbed input scalars computes the Jacobian
#: with respect to them in forward mode (`_reverse_fwd`; `docs/performance.md`).
FORWARD_MAX_INPUTS = 8
#: The same for an unbatched gradient traced by `jit` (no `vmap` around the solve): there no
#: compilation is saved, and forward mode is faster than the reverse pass only for few
#: tangents (`docs/decisions/an-eager-gradient-of-few-inputs.md`).
TRACED_FORWARD_MAX_INPUTS = 4


def has_tracer(tree) -> bool:
    return any(isinstance(x, jax.core.Tracer) for x in jax.tree_util.tree_leaves(tree))


class BatchedSolve(eqx.Module):
    """One solve as the batch engine runs it: `fn(*args, *flat, layout=, derived=)` of the
    traced leaves `leaves` of `args` (its other parts, `static`, are constants), for a layout.

    - `rebuild`: the solve's output (a `Trajectory`) from its leaves;
    - `flat`: `(solver, rtol, atol, max_steps, adjoint)`;
    - `derived`: the `Derived` constants when the parameters are concrete (folded by XLA);
    - `steps`: the layout a batch of at least `SHARED_MIN_BATCH` trials asks for
      (`jsphere.solve.batched.layout.steps_layout`);
    - `loop`: whether the batch loop (`jsphere.solve.batched.loop`) integrates this solver in
      reverse mode, so that batches take it and their gradient is its discrete adjoint.
    """

    fn: Callable
    rebuild: Callable
    treedef: Any = eqx.field(static=True)
    static: Any
    flat: tuple
    derived: Derived | None
    steps: Layout = eqx.field(static=True)
    loop: bool = eqx.field(static=True)

    def __call__(self, leaves, layout: Layout):
        args = eqx.combine(jax.tree_util.tree_unflatten(self.treedef, leaves), self.static)
        return self.fn(*args, *self.flat, layout=layout, derived=self.derived)

    @property
    def name(self) -> str:
        """The solve's name (its function's), naming its programs (`run_program`)."""
        return getattr(self.fn, "__qualname__", "solve")

    def unnamed(self) -> "BatchedSolve":
        """This solve without its functions (`fn`, `rebuild`)."""
        return dataclasses.replace(self, fn=None, rebuild=None)

    @property
    def shared(self) -> bool:
        """Whether batches share their steps (not in forward mode)."""
        return self.steps.shared and not isinstance(self.flat[-1], dfx.ForwardMode)

    def layout_for(self, axis_size: int) -> Layout:
        """The layout of a batch of `axis_size` trials."""
        if axis_size >= _layout.SHARED_MIN_BATCH and (self.shared or self.loop):
            return self.steps if self.shared else Layout.PER_TRIAL_STEPS
        return Layout.COMPONENTS if axis_size >= _layout.COMPONENT_MIN_BATCH else Layout.FLAT

    def loop_grad(self, axis_size, in_batched) -> bool:
        """Whether a batch's gradient is the discrete adjoint of the batch loop."""
        return (
            _layout.SHARED_ADJOINT
            and self.loop
            and self.layout_for(axis_size).batch_solve
            and any(jax.tree_util.tree_leaves(in_batched))
        )


def solve(fn, rebuild, args, flat, steps: Layout):
    """`fn(*args, *flat, layout=..., derived=...)` with the layout chosen by batching: the flat
    state for a single call, components under `vmap` (with shared steps or per-trial steps in
    the batch loop from `SHARED_MIN_BATCH` trials, as `steps` asks); reverse mode through
    `_reverse`, forward mode (`flat[-1]` a `diffrax.ForwardMode`) through `_dispatched`.
    `args[0]` are the `RobotParams`; `flat` ends with the adjoint."""
    adjoint = flat[-1]
    # only traced leaves are inputs of the dispatched solve; concrete ones stay constants (folded by XLA)
    dyn, static = eqx.partition(args, lambda x: isinstance(x, jax.core.Tracer))
    leaves, treedef = jax.tree_util.tree_flatten(dyn)
    derived = None
    if not has_tracer(args[0]):  # concrete parameters: (2.4), (3.4)'s constants as constants (folded by XLA)
        with jax.ensure_compile_time_eval():
            derived = _derive(args[0])
    forward_mode = isinstance(adjoint, dfx.ForwardMode)
    loop = tableau(flat[0]) is not None and not forward_mode
    engine = BatchedSolve(fn, rebuild, treedef, static, flat, derived, steps, loop)
    if forward_mode:
        return _dispatched(engine)(leaves)
    return _reverse(engine, leaves)


#: `derive` as one compiled program (for concrete parameters: not one small program per operation)
_derive = eqx.filter_jit(derive)


def _dispatched(engine: BatchedSolve):
    """`engine(leaves, layout)` as a `custom_vmap` over a flat list of arrays: the flat layout
    unbatched, the batch's layout batched. (A flat list: `custom_vmap`'s JVP rule does not
    accept `None` nodes in its inputs.)"""

    @jax.custom_batching.custom_vmap
    def f(leaves):
        return _flat_primal(engine, leaves)

    @f.def_vmap
    def _rule(axis_size, in_batched, leaves):
        if not any(jax.tree_util.tree_leaves(in_batched)):  # e.g. the primal part of a batched jvp
            out = _flat_primal(engine, leaves)
            return out, jax.tree_util.tree_map(lambda _: False, out)
        layout = engine.layout_for(axis_size)
        out = _chunked_vmap(lambda lv: engine(lv, layout), axis_size, in_batched, leaves)
        return out, jax.tree_util.tree_map(lambda _: True, out)

    return f


def _chunked_vmap(fn, axis_size, in_batched, *args, chunk=None):
    """`vmap(fn)` over the batched leaves of `args`, in chunks of at most `chunk` trials
    (default `batch_chunk()`; which trials share a chunk: `to_chunks`); a batch of one is the
    unbatched call with the axis added."""
    chunk = chunk or _layout.batch_chunk()
    if axis_size == 1:  # e.g. `jax.jacfwd` of one scalar: the call itself, not a size-1 `vmap` of it
        one = tuple(jax.tree_util.tree_map(lambda x, b: x[0] if b else x, a, b) for a, b in zip(args, in_batched))
        return jax.tree_util.tree_map(lambda x: x[None], fn(*one))
    in_axes = tuple(jax.tree_util.tree_map(lambda b: 0 if b else None, b) for b in in_batched)
    if axis_size <= chunk:
        return jax.vmap(fn, in_axes=in_axes, axis_size=axis_size)(*args)
    n = -(-axis_size // chunk)
    batched = [eqx.partition(a, b) for a, b in zip(args, in_batched)]
    chunks = tuple(jax.tree_util.tree_map(lambda x: to_chunks(x, n, chunk), bt) for bt, _ in batched)

    def one(ch):
        full = tuple(eqx.combine(c, un) for c, (_, un) in zip(ch, batched))
        return jax.vmap(fn, in_axes=in_axes, axis_size=chunk)(*full)

    out = jax.lax.map(one, chunks)
    return jax.tree_util.tree_map(lambda x: from_chunks(x, axis_size), out)


def chunk_parts(chunk: int) -> int:
    """Into how many parts `to_chunks` divides a chunk: the number of devices of JAX's
    default backend where it divides `chunk` (one per core after `jsphere.use_cpu_cores`),
    else 1."""
    d = len(jax.devices())
    return d if chunk % d == 0 else 1


def to_chunks(x, n: int, chunk: int, zero: bool = False):
    """The batch `x (B, ...)` as `n` chunks of `chunk` trials, `(n, chunk, ...)`, padded to `n
    chunk` trials with copies of its last trial (valid inputs) or with zeros (`zero`). With one
    device, chunk `b` holds trials `b chunk ... (b + 1) chunk - 1`. With `D = chunk_parts(chunk)`
    devices, the padded batch is `D` equal parts, and chunk `b` holds the `b`-th run of `chunk /
    D` trials of every part: a batch split over the devices along its trial axis
    (`jsphere.shard_trials`) stays split, each device running its own trials of every chunk."""
    pad = n * chunk - x.shape[0]
    if pad:
        x = jnp.concatenate([x, jnp.zeros_like(x[-pad:]) if zero else jnp.repeat(x[-1:], pad, axis=0)])
    d = chunk_parts(chunk)
    x = jnp.swapaxes(x.reshape((d, n, chunk // d) + x.shape[1:]), 0, 1)
    return x.reshape((n, chunk) + x.shape[3:])


def from_chunks(y, axis_size: int):
    """`to_chunks` undone: `(n, chunk, ...)` -> the first `axis_size` trials, in order."""
    n, chunk = y.shape[:2]
    d = chunk_parts(chunk)
    y = jnp.swapaxes(y.reshape((n, d, chunk // d) + y.shape[2:]), 0, 1)
    return y.reshape((n * chunk,) + y.shape[3:])[:axis_size]


def _large(axis_size, in_batched) -> bool:
    return axis_size >= _layout.COMPONENT_MIN_BATCH and any(jax.tree_util.tree_leaves(in_batched))


@functools.partial(jax.custom_vjp, nondiff_argnums=(0,))
def _reverse(engine: BatchedSolve, leaves):
    return _dispatched(engine)(leaves)


def _reverse_fwd(engine: BatchedSolve, leaves):
    """The primal with the layout chosen by batching; the residuals are the inputs only (the
    backward pass recomputes what it needs, `_reverse_bwd`). An eager call with at most
    `FORWARD_MAX_INPUTS` perturbed input scalars, or an unbatched one traced by `jit` alone
    with at most `TRACED_FORWARD_MAX_INPUTS`, computes its Jacobian with respect to them in
    forward mode instead, with the primal (`_flat_jacfwd`; one program when eager): the
    residual is that Jacobian, and the backward pass a product with it."""
    values = [x.value for x in leaves]
    perturbed = tuple(
        bool(x.perturbed) and jnp.issubdtype(jnp.result_type(v), jnp.inexact) for x, v in zip(leaves, values)
    )
    n = sum(int(np.size(v)) for v, p in zip(values, perturbed) if p)
    eager = not traced(values)
    if 0 < n <= FORWARD_MAX_INPUTS and eager:
        program = _exportable(_flat_jacfwd, engine)
        out, jac = run_program(
            f"jacfwd:{engine.name}",
            program,
            _with_jacobian(engine.rebuild),
            engine.unnamed(),
            perturbed,
            values,
        )
        return out, (values, perturbed, jac)
    if 0 < n <= TRACED_FORWARD_MAX_INPUTS and not eager and not transformed(values):  # under `jit` alone
        out, jac = _flat_jacfwd(engine, perturbed, values)
        return out, (values, perturbed, jac)
    return _primal(engine, values), _Inputs(values, perturbed)


class _Inputs(eqx.Module):
    """The residuals of `_reverse_fwd` without a Jacobian: the inputs, and which of them are
    differentiated (the backward pass takes the VJP with respect to those only)."""

    values: list
    perturbed: tuple = eqx.field(static=True)


def _primal(engine: BatchedSolve, leaves):
    """The solve of `_reverse`'s forward pass. With concrete inputs (an eager `jax.grad`: no
    `vmap` or `jit` around) one compiled program, `_flat_primal` (`run_program`); otherwise
    the `custom_vmap` of `_dispatched`."""
    if not traced(leaves):
        primal = _exportable(_flat_primal, engine)
        return run_program(f"primal:{engine.name}", primal, engine.rebuild, engine.unnamed(), leaves)
    return _dispatched(engine)(leaves)


def _reverse_bwd(engine: BatchedSolve, res, ct):
    """The cotangents of the leaves: the VJP of only the outputs whose cotangent is not a
    symbolic zero (the rest of the solve's outputs, and what only they need, are never
    differentiated), with respect to only the perturbed inputs (the others get zeros),
    recomputed from the inputs. Unbatched and in small batches: the flat
    layout's VJP (diffrax's checkpointed adjoint), one compiled program (`_flat_vjp`). In
    batches in the batch loop (`BatchedSolve.loop_grad`): the VJP of the batched solve, whose
    steps have a discrete adjoint, in chunks of `batch_chunk()` trials (`_loop_vjp`). In other
    large batches: the flat layout's VJP per trial, in chunks of `GRAD_CHUNK` trials."""
    flat_ct = jax.tree_util.tree_leaves(ct, is_leaf=lambda c: isinstance(c, SymbolicZero))
    if isinstance(res, tuple):  # the forward pass kept the Jacobian (`_flat_jacfwd`)
        return (_jacobian_transpose(*res, flat_ct),)
    leaves, perturbed = res.values, res.perturbed
    keep = tuple(not isinstance(c, SymbolicZero) and jnp.result_type(c) != jax.dtypes.float0 for c in flat_ct)
    cts = [c for k, c in zip(keep, flat_ct) if k]
    if not any(keep) or not any(perturbed):
        return ([_zero_cotangent(x) for x in leaves],)
    if not traced((leaves, cts)):
        vjp = _exportable(_flat_vjp, engine)
        args = (engine.unnamed(), keep, perturbed, leaves, cts)
        return (run_program(f"vjp:{engine.name}", vjp, _keep, *args),)

    @jax.custom_batching.custom_vmap
    def f(lv, cs):
        return _flat_vjp(engine, keep, perturbed, lv, cs)

    @f.def_vmap
    def _rule(axis_size, in_batched, lv, cs):
        if engine.loop_grad(axis_size, in_batched[0]):
            out = _loop_vjp(engine, keep, perturbed, axis_size, in_batched[0], in_batched[1], lv, cs)
        else:
            chunk = _layout.GRAD_CHUNK if _large(axis_size, in_batched[0]) else None
            out = _chunked_vmap(
                lambda l, c: _selected_vjp(engine, keep, perturbed, l, c), axis_size, in_batched, lv, cs, chunk=chunk
            )
        return out, jax.tree_util.tree_map(lambda _: True, out)

    return (f(list(leaves), cts),)


_reverse.defvjp(_reverse_fwd, _reverse_bwd, symbolic_zeros=True)


def _keep(x):
    return x


def _exportable(program, engine: BatchedSolve):
    """`program(engine, ...)` as a function of `engine.unnamed()`: a cache of programs
    (`run_program`'s runner) keys a call by its arguments' structure, in which a function
    has no stable name; the solve's function is in the program's name instead
    (`BatchedSolve.name`)."""
    return lambda unnamed, *args: program(dataclasses.replace(unnamed, fn=engine.fn, rebuild=engine.rebuild), *args)


def _zero_cotangent(x):
    if jnp.issubdtype(jnp.result_type(x), jnp.inexact):
        return jnp.zeros(jnp.shape(x), jnp.result_type(x))
    return np.zeros(jnp.shape(x), jax.dtypes.float0)


def _selected(engine: BatchedSolve, keep, layout: Layout, leaves):
    """The outputs of the solve whose cotangents are kept (`keep`, over its leaves)."""
    out = jax.tree_util.tree_leaves(engine(leaves, layout))
    return [o for k, o in zip(keep, out) if k]


def _with(leaves, perturbed, xs):
    """`leaves` with the perturbed ones (`perturbed`, over `leaves`) replaced by `xs`."""
    it = iter(xs)
    return [next(it) if p else x for x, p in zip(leaves, perturbed)]


def _selected_vjp(engine: BatchedSolve, keep, perturbed, leaves, cts):
    """The cotangents of `leaves` for the cotangents `cts` of the kept outputs (flat layout)."""
    return _vjp(lambda lv: _selected(engine, keep, Layout.FLAT, lv), leaves, perturbed, cts, _zero_cotangent)


def _vjp(fn, leaves, perturbed, cts, missing):
    """The cotangents of `leaves` for the cotangents `cts` of `fn(leaves)`: by the VJP with
    respect to the perturbed leaves (`perturbed`, over `leaves`); `missing(x)` for the others."""
    xs = [x for x, p in zip(leaves, perturbed) if p]
    _, pull = jax.vjp(lambda xs: fn(_with(leaves, perturbed, xs)), xs)
    g = iter(pull(cts)[0])
    return [next(g) if p else missing(x) for x, p in zip(leaves, perturbed)]


@eager_jit
def _flat_primal(engine: BatchedSolve, leaves):
    """One trial's solve in the flat layout, as one compiled program."""
    return engine(leaves, Layout.FLAT)


@eager_jit
def _flat_vjp(engine: BatchedSolve, keep, perturbed, leaves, cts):
    """`_selected_vjp` as one compiled program (forward and backward pass together)."""
    return _selected_vjp(engine, keep, perturbed, leaves, cts)


def _inexact(x) -> bool:
    return jnp.issubdtype(jnp.result_type(x), jnp.inexact)


@eager_jit
def _flat_jacfwd(engine: BatchedSolve, perturbed, leaves):
    """One trial's solve in the flat layout and the Jacobian of its floating-point outputs
    with respect to the perturbed leaves, by forward mode (`diffrax.ForwardMode`: the same
    discretised solve as the checkpointed adjoint differentiates, so the same derivative to
    rounding), one tangent per input scalar under `vmap`. Returns the solve's output and the
    Jacobian as an `(n_inputs, n_outputs)` array, outputs in the order of their leaves."""
    forward = dataclasses.replace(engine, flat=engine.flat[:-1] + (dfx.ForwardMode(),))
    idx = [i for i, p in enumerate(perturbed) if p]
    xs = [leaves[i] for i in idx]
    sizes = [int(np.size(x)) for x in xs]
    splits = np.cumsum(sizes)[:-1].tolist()

    def solve(ys):
        lv = list(leaves)
        for i, y in zip(idx, ys):
            lv[i] = y
        return forward(lv, Layout.FLAT)

    def column(e):
        tangents = [t.reshape(jnp.shape(x)).astype(jnp.result_type(x)) for t, x in zip(jnp.split(e, splits), xs)]
        return jax.jvp(solve, (xs,), (tangents,))

    dtype = jnp.result_type(*xs)
    out, tangents = jax.vmap(column, out_axes=(None, 0))(jnp.eye(sum(sizes), dtype=dtype))
    columns = [
        t.reshape(t.shape[0], -1)
        for o, t in zip(jax.tree_util.tree_leaves(out), jax.tree_util.tree_leaves(tangents))
        if _inexact(o)
    ]
    return out, jnp.concatenate(columns, axis=1)


def _with_jacobian(rebuild):
    """`rebuild` for `_flat_jacfwd`'s leaves: the solve's output, then the Jacobian."""
    return lambda leaves: (rebuild(leaves[:-1]), leaves[-1])


def _jacobian_transpose(values, perturbed, jac, flat_ct):
    """The cotangents of the leaves `values` from the Jacobian of `_flat_jacfwd` and the
    cotangents `flat_ct` of the solve's output leaves, in one compiled program."""
    cts, offsets, offset = [], [], 0
    for c in flat_ct:
        zero = isinstance(c, SymbolicZero)
        size = int(np.prod(c.shape)) if zero else int(np.size(c))
        inexact = jnp.issubdtype(c.dtype if zero else jnp.result_type(c), jnp.inexact)
        if inexact and not zero:
            cts.append(c)
            offsets.append((offset, size))
        offset += size if inexact else 0
    shapes = tuple((np.shape(x), jnp.result_type(x)) for x in values)
    inexact = tuple(jnp.issubdtype(dt, jnp.inexact) for _, dt in shapes)
    out = _contract(jac, cts, tuple(offsets), tuple(perturbed), shapes)
    return [o if i else np.zeros(s, jax.dtypes.float0) for o, i, (s, _) in zip(out, inexact, shapes)]


@eqx.filter_jit
def _contract(jac, cts, offsets, perturbed, shapes):
    total = sum(
        (jac[:, a : a + n] @ jnp.ravel(c).astype(jac.dtype) for c, (a, n) in zip(cts, offsets)),
        start=jnp.zeros(jac.shape[:1], jac.dtype),
    )
    out, start = [], 0
    for p, (shape, dt) in zip(perturbed, shapes):
        if not jnp.issubdtype(dt, jnp.inexact):
            out.append(None)
        elif p:
            size = int(np.prod(shape))
            out.append(total[start : start + size].reshape(shape).astype(dt))
            start += size
        else:
            out.append(jnp.zeros(shape, dt))
    return out


def _loop_vjp(engine: BatchedSolve, keep, perturbed, axis_size, lv_batched, ct_batched, lv, cts):
    """Per-trial cotangents of the leaves `lv` of a batch solved in the batch loop (shared or
    per-trial steps), for the cotangents `cts` of its kept outputs: `jax.vjp` of the batched
    solve (`vmap` inside, so the batching rule of `jsphere.solve.batched.segment.solve` runs
    before differentiation and the loop's discrete adjoint applies), chunk by chunk
    (`batch_chunk()` trials: padding trials get zero cotangents). The cotangents of leaves shared
    by the batch are sums over the batch; they are returned in the first trial's row (zeros
    elsewhere), which sums to the same. Leaves not `perturbed` get zeros: the discrete adjoint
    computes no cotangents for them."""
    chunk = min(axis_size, _layout.batch_chunk())
    layout = engine.layout_for(axis_size)
    n = -(-axis_size // chunk)
    in_axes = [0 if b else None for b in lv_batched]
    # the forward pass's chunks (`_chunked_vmap`): their shared steps are the ones differentiated
    ct_b = [to_chunks(c, n, chunk, zero=True) if b else c for c, b in zip(cts, ct_batched)]
    lv_b = [to_chunks(x, n, chunk) if b else x for x, b in zip(lv, lv_batched)]

    def batched(l):
        return _selected(engine, keep, layout, l)

    def one(ch):
        l_ch, c_ch = ch
        full = [c if b else x for c, x, b in zip(l_ch, lv, lv_batched)]
        # the vmapped solve's outputs are all batched: a cotangent shared by the batch is each trial's
        cc = [c if b else jnp.broadcast_to(x, (chunk,) + jnp.shape(x)) for c, x, b in zip(c_ch, cts, ct_batched)]
        solve = jax.vmap(batched, in_axes=(in_axes,), axis_size=chunk)
        return _vjp(solve, full, perturbed, cc, lambda x: None)  # no float0 through the map

    xs = ([x if b else None for x, b in zip(lv_b, lv_batched)], [c if b else None for c, b in zip(ct_b, ct_batched)])
    grads = (
        jax.lax.map(one, xs)
        if n > 1
        else jax.tree_util.tree_map(lambda g: g[None], one(jax.tree_util.tree_map(lambda x: x[0], xs)))
    )
    result = []
    for g, b, x in zip(grads, lv_batched, lv):
        if g is None:  # leaves not perturbed, integer leaves among them
            result.append(
                _zero_cotangent(jax.ShapeDtypeStruct((axis_size,) + jnp.shape(x)[int(b) :], jnp.result_type(x)))
            )
        elif b:
            result.append(from_chunks(g, axis_size))
        else:  # the batch's sum, in the first trial's row
            total = jnp.sum(g, axis=0)
            result.append(jnp.zeros((axis_size,) + total.shape, total.dtype).at[0].set(total))
    return result
