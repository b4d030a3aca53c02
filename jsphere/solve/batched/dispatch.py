"""What a solve becomes under `vmap`: the batching rule that picks its layout.

Under `vmap`, torque- and gait-mode solves carry the state as a tuple of scalar components
(`jsphere.solve.batched.components`): each component is then one contiguous `(batch,)` vector
and XLA on CPU vectorises the right-hand side (3.4) over the batch, while the flat
`(16+N,)` layout is faster for a single trial. A solve cannot see a `vmap` from inside, so the
choice is made by `jax.custom_batching.custom_vmap` (`_dispatched`): the unbatched call runs
`Layout.FLAT`, the batching rule the layout of `BatchedSolve.layout_for` (the batch loop's
layouts from `SHARED_MIN_BATCH` trials, components from `COMPONENT_MIN_BATCH`), in chunks of
`BATCH_CHUNK` trials.

As `custom_vmap` has no reverse mode, the default adjoint wraps it in a custom VJP
(`_reverse`) whose differentiated pass is the flat layout with diffrax's own VJP. Its forward
pass is again a `custom_vmap`: small batches keep the pullback's residuals; batches in the
batch loop run it and their backward pass is its discrete adjoint (`_loop_vjp`,
`jsphere.solve.batched.adjoint`); other large batches run the component layout and recompute
the flat VJP in the backward pass, in chunks of `GRAD_CHUNK` trials. `diffrax.ForwardMode`
uses the `custom_vmap` directly (its `jvp` is supported).

Only traced calls come here (`jsphere.solve.simulate`): a call with concrete inputs cannot be
under `vmap`, and takes diffrax's path directly.
"""

from __future__ import annotations

import functools
from typing import Any, Callable

import diffrax as dfx
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ...model.params import Derived, derive
from . import layout as _layout
from .layout import Layout
from .method import tableau


def has_tracer(tree) -> bool:
    return any(isinstance(x, jax.core.Tracer) for x in jax.tree_util.tree_leaves(tree))


class BatchedSolve(eqx.Module):
    """One solve as the batch engine runs it: `fn(*args, *flat, layout=, derived=)` of the
    traced leaves `leaves` of `args` (its other parts, `static`, are constants), for a layout.

    - `flat`: `(solver, rtol, atol, max_steps, adjoint)`;
    - `derived`: the `Derived` constants when the parameters are concrete (folded by XLA);
    - `steps`: the layout a batch of at least `SHARED_MIN_BATCH` trials asks for
      (`jsphere.solve.batched.layout.steps_layout`);
    - `loop`: whether the batch loop (`jsphere.solve.batched.loop`) integrates this solver in
      reverse mode, so that batches take it and their gradient is its discrete adjoint.
    """

    fn: Callable
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


def solve(fn, args, flat, steps: Layout):
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
            derived = derive(args[0])
    forward_mode = isinstance(adjoint, dfx.ForwardMode)
    engine = BatchedSolve(fn, treedef, static, flat, derived, steps, tableau(flat[0]) is not None and not forward_mode)
    if forward_mode:
        return _dispatched(engine)(leaves)
    return _reverse(engine, leaves)


def _dispatched(engine: BatchedSolve):
    """`engine(leaves, layout)` as a `custom_vmap` over a flat list of arrays: the flat layout
    unbatched, the batch's layout batched. (A flat list: `custom_vmap`'s JVP rule does not
    accept `None` nodes in its inputs.)"""

    @jax.custom_batching.custom_vmap
    def f(leaves):
        return engine(leaves, Layout.FLAT)

    @f.def_vmap
    def _rule(axis_size, in_batched, leaves):
        if not any(jax.tree_util.tree_leaves(in_batched)):  # e.g. the primal part of a batched jvp
            out = engine(leaves, Layout.FLAT)
            return out, jax.tree_util.tree_map(lambda _: False, out)
        layout = engine.layout_for(axis_size)
        out = _chunked_vmap(lambda lv: engine(lv, layout), axis_size, in_batched, leaves)
        return out, jax.tree_util.tree_map(lambda _: True, out)

    return f


def _chunked_vmap(fn, axis_size, in_batched, *args, chunk=None):
    """`vmap(fn)` over the batched leaves of `args`, in chunks of at most `chunk` trials
    (default `BATCH_CHUNK`)."""
    chunk = chunk or _layout.BATCH_CHUNK
    in_axes = tuple(jax.tree_util.tree_map(lambda b: 0 if b else None, b) for b in in_batched)
    if axis_size <= chunk:
        return jax.vmap(fn, in_axes=in_axes, axis_size=axis_size)(*args)
    n = -(-axis_size // chunk)
    pad = n * chunk - axis_size

    def split(x):  # pad with copies of the last trial (valid inputs), then (n, chunk, ...)
        x = jnp.concatenate([x, jnp.repeat(x[-1:], pad, axis=0)]) if pad else x
        return x.reshape((n, chunk) + x.shape[1:])

    batched = [eqx.partition(a, b) for a, b in zip(args, in_batched)]
    chunks = tuple(jax.tree_util.tree_map(split, bt) for bt, _ in batched)

    def one(ch):
        full = tuple(eqx.combine(c, un) for c, (_, un) in zip(ch, batched))
        return jax.vmap(fn, in_axes=in_axes, axis_size=chunk)(*full)

    out = jax.lax.map(one, chunks)
    return jax.tree_util.tree_map(lambda x: x.reshape((n * chunk,) + x.shape[2:])[:axis_size], out)


def _large(axis_size, in_batched) -> bool:
    return axis_size >= _layout.COMPONENT_MIN_BATCH and any(jax.tree_util.tree_leaves(in_batched))


class _Residuals(eqx.Module):
    """The residuals of `_reverse`: its inputs, the leaves of the flat layout's pullback
    (placeholders where the backward pass recomputes), and the pullback's tree structure."""

    leaves: list
    saved: list
    saved_def: Any = eqx.field(static=True)


@functools.partial(jax.custom_vjp, nondiff_argnums=(0,))
def _reverse(engine: BatchedSolve, leaves):
    return _dispatched(engine)(leaves)


def _reverse_fwd(engine: BatchedSolve, leaves):
    """The primal with the layout chosen by batching, and residuals for `_reverse_bwd`.

    Unbatched or in small batches: the flat layout's VJP (diffrax's checkpointed adjoint), its
    residuals kept as arrays (the leaves of the pullback). In batches in the batch loop
    (`BatchedSolve.loop_grad`) or large ones: the batch's layout, and no residuals
    (placeholders of the same structure; the backward pass recomputes). `custom_vmap` needs
    one output structure for both, hence the placeholders.
    """
    pullback_def = []  # the pullback's tree structure, known once `flat_vjp` is traced

    def flat_vjp(lv):
        out, pull = jax.vjp(lambda l: engine(l, Layout.FLAT), lv)
        res, treedef = jax.tree_util.tree_flatten(pull)
        pullback_def[:] = [treedef]
        return out, res

    @jax.custom_batching.custom_vmap
    def f(lv):
        return flat_vjp(lv)

    @f.def_vmap
    def _rule(axis_size, in_batched, lv):
        (batched,) = in_batched
        if engine.loop_grad(axis_size, batched) or _large(axis_size, batched):
            layout = engine.layout_for(axis_size)
            out = _chunked_vmap(lambda l: engine(l, layout), axis_size, in_batched, lv)
            # unbatched placeholders (one trial's worth) for the residuals the backward pass won't read
            one = [jax.ShapeDtypeStruct(jnp.shape(x)[int(b) :], jnp.result_type(x)) for x, b in zip(lv, batched)]
            res = [jnp.zeros(r.shape, r.dtype) for r in jax.eval_shape(lambda l: flat_vjp(l)[1], one)]
            return (out, res), (jax.tree_util.tree_map(lambda _: True, out), [False] * len(res))
        out, res = jax.vmap(flat_vjp, in_axes=([0 if b else None for b in batched],), axis_size=axis_size)(lv)
        return (out, res), jax.tree_util.tree_map(lambda _: True, (out, res))

    out, res = f(list(leaves))
    return out, _Residuals(list(leaves), res, pullback_def[0])


def _reverse_bwd(engine: BatchedSolve, residuals: _Residuals, ct):
    """Apply the pullback saved by `_reverse_fwd`. In batches in the batch loop
    (`BatchedSolve.loop_grad`): the VJP of the batched solve, whose steps have a discrete
    adjoint, in chunks of `BATCH_CHUNK` trials (`_loop_vjp`). In other large batches: the flat
    layout's VJP recomputed per trial, in chunks of `GRAD_CHUNK` trials."""
    leaves, res = residuals.leaves, residuals.saved
    flat_ct, ct_def = jax.tree_util.tree_flatten(ct)
    keep = [jnp.result_type(c) != jax.dtypes.float0 for c in flat_ct]

    def full_ct(cts, like):
        it = iter(cts)
        return jax.tree_util.tree_unflatten(
            ct_def, [next(it) if k else np.zeros(jnp.shape(o), jax.dtypes.float0) for k, o in zip(keep, like)]
        )

    def saved(lv, rs, cts):
        pull = jax.tree_util.tree_unflatten(residuals.saved_def, rs)
        return pull(full_ct(cts, flat_ct))[0]

    def recompute(lv, cts):
        out, pull = jax.vjp(lambda l: engine(l, Layout.FLAT), lv)
        return pull(full_ct(cts, jax.tree_util.tree_leaves(out)))[0]

    @jax.custom_batching.custom_vmap
    def f(lv, rs, cts):
        return saved(lv, rs, cts)

    @f.def_vmap
    def _rule(axis_size, in_batched, lv, rs, cts):
        if engine.loop_grad(axis_size, in_batched[0]):
            out = _loop_vjp(engine, axis_size, in_batched[0], in_batched[2], lv, cts, full_ct)
        elif _large(axis_size, in_batched[0]):
            out = _chunked_vmap(recompute, axis_size, in_batched[::2], lv, cts, chunk=_layout.GRAD_CHUNK)
        else:
            in_axes = tuple(jax.tree_util.tree_map(lambda b: 0 if b else None, b) for b in in_batched)
            out = jax.vmap(saved, in_axes=in_axes, axis_size=axis_size)(lv, rs, cts)
        return out, jax.tree_util.tree_map(lambda _: True, out)

    return (f(leaves, res, [c for k, c in zip(keep, flat_ct) if k]),)


_reverse.defvjp(_reverse_fwd, _reverse_bwd)


def _loop_vjp(engine: BatchedSolve, axis_size, lv_batched, ct_batched, lv, cts, full_ct):
    """Per-trial cotangents of the leaves `lv` of a batch solved in the batch loop (shared or
    per-trial steps), for the cotangents `cts` of its outputs: `jax.vjp` of the batched solve
    (`vmap` inside, so the batching rule of `jsphere.solve.batched.segment.solve` runs before
    differentiation and the loop's discrete adjoint applies), chunk by chunk (`BATCH_CHUNK`
    trials: padding trials get zero cotangents). The cotangents of leaves shared by the batch
    are sums over the batch; they are returned in the first trial's row (zeros elsewhere),
    which sums to the same."""
    chunk = min(axis_size, _layout.BATCH_CHUNK)
    layout = engine.layout_for(axis_size)
    n = -(-axis_size // chunk)
    pad = n * chunk - axis_size
    in_axes = [0 if b else None for b in lv_batched]

    def split(x, zero):  # (axis_size, ...) -> (n, chunk, ...); pad with the last trial (or zeros)
        if pad:
            x = jnp.concatenate([x, jnp.zeros_like(x[-pad:]) if zero else jnp.repeat(x[-1:], pad, axis=0)])
        return x.reshape((n, chunk) + x.shape[1:])

    ct_b = [split(c, True) if b else c for c, b in zip(cts, ct_batched)]
    lv_b = [split(x, False) if b else x for x, b in zip(lv, lv_batched)]
    inexact = [jnp.issubdtype(jnp.result_type(x), jnp.inexact) for x in lv]

    def one(ch):
        l_ch, c_ch = ch
        full = [c if b else x for c, x, b in zip(l_ch, lv, lv_batched)]
        # the vmapped solve's outputs are all batched: a cotangent shared by the batch is each trial's
        cc = [c if b else jnp.broadcast_to(x, (chunk,) + jnp.shape(x)) for c, x, b in zip(c_ch, cts, ct_batched)]
        out, pull = jax.vjp(
            lambda l: jax.vmap(lambda x: engine(x, layout), in_axes=(in_axes,), axis_size=chunk)(l), full
        )
        g = pull(full_ct(cc, jax.tree_util.tree_leaves(out)))[0]
        return [x if k else None for x, k in zip(g, inexact)]  # no float0 through the map

    xs = ([x if b else None for x, b in zip(lv_b, lv_batched)], [c if b else None for c, b in zip(ct_b, ct_batched)])
    grads = (
        jax.lax.map(one, xs)
        if n > 1
        else jax.tree_util.tree_map(lambda g: g[None], one(jax.tree_util.tree_map(lambda x: x[0], xs)))
    )
    result = []
    for g, b, x in zip(grads, lv_batched, lv):
        if g is None:  # integer leaves
            result.append(np.zeros((axis_size,) + jnp.shape(x)[int(b) :], jax.dtypes.float0))
        elif b:
            result.append(g.reshape((n * chunk,) + g.shape[2:])[:axis_size])
        else:  # the batch's sum, in the first trial's row
            total = jnp.sum(g, axis=0)
            result.append(jnp.zeros((axis_size,) + total.shape, total.dtype).at[0].set(total))
    return result
