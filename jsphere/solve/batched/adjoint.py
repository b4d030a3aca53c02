"""The discrete adjoint of the batch loop (`jsphere.solve.batched.loop`): reverse mode through
its accepted steps, with their sizes held fixed.

The forward pass of a gradient records the accepted steps and checkpoints their states
(`jsphere.solve.batched.method.checkpoints`). `backward` replays each stretch between two
checkpoints (`_Adjoint.stretch`) and runs its steps in reverse (`_Adjoint.step`): the step's
stages are recomputed (`recompute_stages`), the cotangents of the save times it served are
pulled back through its dense output (`save_cotangents`), and its stages are run backwards,
one VJP of the field per stage (`reverse_stages`, `stage_vjp`).

Parameters shared by the batch are broadcast to one copy per trial for the stage VJPs only, so
each gives per-trial cotangents with no reduction over the batch; they are summed once at the
end. Arguments in `elementwise` (the robot's parameter arrays) reach the field's VJPs as
nested tuples of per-trial scalars (`_elements`), so that no slice of them is transposed into a
pad inside the stage VJPs; their cotangents, and those of every other per-trial scalar, leave
each stage VJP packed in one `(elements, batch)` buffer (`_Packed`) and accumulate there.
With per-trial steps (`jsphere.solve.batched.loop.forward`, `per_trial`) the recorded iterations
run backwards with each trial's own step sizes.
"""

from __future__ import annotations

from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp

from .method import Method, checkpoints


class Record(NamedTuple):
    """What the forward pass of a gradient keeps: `Y` the checkpointed states (`C + 1` slots),
    `TK`, `HK` each step's (or iteration's) time and size (`(max_steps,)` for shared steps,
    `(max_steps, batch)` per trial), the checkpoint stride and the slots used."""

    Y: Any
    TK: Any
    HK: Any
    stride: Any
    used: Any


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


class _Packed:
    """The leaves of a pytree as one stacked `(E, batch)` buffer of its per-trial scalars (the
    `(batch,)` leaves) and a list of the others, and back."""

    def __init__(self, tree, B):
        leaves, self.treedef = jax.tree_util.tree_flatten(tree)
        self.n = len(leaves)
        self.cols = [i for i, x in enumerate(leaves) if x.shape == (B,)]
        col_set = set(self.cols)
        self.rest = [i for i in range(self.n) if i not in col_set]
        self.zeros = self.pack([jnp.zeros_like(x) for x in leaves])

    def pack(self, leaves):
        return (jnp.stack([leaves[i] for i in self.cols]) if self.cols else None, [leaves[i] for i in self.rest])

    def unpack(self, packed):
        stacked, others = packed
        leaves = [None] * self.n
        for k, i in enumerate(self.cols):
            leaves[i] = stacked[k]
        for x, i in zip(others, self.rest):
            leaves[i] = x
        return jax.tree_util.tree_unflatten(self.treedef, leaves)


class _Adjoint:
    """The backward pass of one recorded solve (see `backward`); trace-time context only."""

    def __init__(self, m: Method, args, batched, diff, ts, y0, at, rec: Record, ct, *, elementwise, f_adjoint):
        self.m, self.args, self.batched, self.diff = m, args, batched, diff
        self.ts, self.at, self.rec, self.ct = ts, at, rec, ct
        self.f_adjoint = f_adjoint or m.f
        self.dtype = y0.dtype
        _, B = y0.shape
        self.T = ts.shape[0]
        self.lockstep = rec.TK.ndim == 2  # each trial's own steps, in lockstep (`forward`, `per_trial`)
        self.trials = jnp.arange(B)
        self.per_trial = [  # the differentiated shared arguments, one copy per trial
            x if b or i not in diff else jnp.broadcast_to(x, (B,) + jnp.shape(x))
            for i, (x, b) in enumerate(zip(args, batched))
        ]
        self.pt_batched = tuple(b or i in diff for i, b in enumerate(batched))
        self.dargs0 = [_elements(self.per_trial[i]) if i in elementwise else self.per_trial[i] for i in diff]
        self.packed = _Packed(self.dargs0, B)
        self.a, self.c = jnp.asarray(m.tab.a, self.dtype), jnp.asarray(m.tab.c, self.dtype)

    def with_diff(self, dargs):
        full = list(self.per_trial)
        for i, x in zip(self.diff, dargs):
            full[i] = x
        return full

    def stage_vjp(self, ti, yi, g, needed):
        """`(d yi, d args)` of `<g, f(ti, yi)>`, forward and backward in a branch of their own
        (zeros unless `needed`)."""
        f, dtype = self.f_adjoint, self.dtype

        def one(ti, yg):  # with respect to the state's rows: no transposed slices (pads)
            yi, g = yg
            rows = tuple(yi[r] for r in range(yi.shape[0]))

            def rates(y, da):
                return f(ti, y, self.with_diff(da), self.pt_batched).astype(dtype)

            _, pull = jax.vjp(rates, rows, self.dargs0)
            dy, da = pull(g)  # rows stay separate buffers: stacked outside the branch
            return dy, self.packed.pack(jax.tree_util.tree_leaves(da))

        def none(ti, yg):
            return tuple(jnp.zeros_like(yi[0]) for _ in range(yi.shape[0])), self.packed.zeros

        dy, da = jax.lax.cond(needed & jnp.all(jnp.isfinite(ti)), one, none, ti, (yi, g))
        return jnp.stack(dy), da

    def saved_here(self, j, k):
        """Whether save `j` (one per trial with per-trial steps) is step `k`'s."""
        if self.lockstep:
            return (j >= 0) & (self.at[jnp.maximum(j, 0), self.trials] == k)
        return (j >= 0) & (self.at[jnp.maximum(j, 0)] == k)

    def recompute_stages(self, t, h, y, has):
        """Step `(t, h)`'s stage increments from `y`, the last one only if the step's dense output
        is saved (`has`), and its end state `y1`."""
        m, s = self.m, self.m.s
        K = jnp.zeros((s,) + y.shape, self.dtype).at[0].set(h * m.rates(t, y, self.args, self.batched))

        def fwd_stage(i, K):
            return K.at[i].set(h * m.rates(t + self.c[i] * h, m.stage_arg(i, y, K), self.args, self.batched))

        K = jax.lax.fori_loop(1, jnp.where(has, s, s - 1), fwd_stage, K)
        return K, m.stage_arg(s - 1, y, K)

    def save_cotangents(self, k, t, h, y, y1, K, jp, ts_bar, times):
        """The cotangents of `(y, y1, K)` from the saves step `k` served (the VJP of its dense
        output, latest save first), the next save still to be served, and with `times` those of
        the save times."""
        m, ts, ct = self.m, self.ts, self.ct

        def more(cc):
            return jnp.any(self.saved_here(cc[0], k))

        def one(cc):
            j, gy, gy1, gK, ts_bar = cc
            if self.lockstep:  # each trial's next save, if it is this step's
                here = self.saved_here(j, k)
                jq = jnp.maximum(j, 0)
                ctj = jnp.where(here, ct[jq, :, self.trials].T, 0.0)
                tj = ts[jq]
            else:
                jq, ctj, tj = j, ct[j], ts[j]
            yj, ipull = jax.vjp(lambda y, y1, K: m.dense(t, h, y, y1, K, tj), y, y1, K)
            dy, dy1, dK = ipull(ctj)
            if times:
                rate = ctj * m.rates(tj, yj, self.args, self.batched)
                if self.lockstep:
                    ts_bar = ts_bar.at[jq].add(jnp.sum(rate, axis=0))
                else:
                    ts_bar = ts_bar.at[j].set(jnp.sum(rate))
            return (jnp.where(here, j - 1, j) if self.lockstep else j - 1), gy + dy, gy1 + dy1, gK + dK, ts_bar

        zero = jnp.zeros_like(y)
        if self.T:
            return jax.lax.while_loop(more, one, (jp, zero, zero, jnp.zeros_like(K), ts_bar))
        return jp, zero, zero, jnp.zeros_like(K), ts_bar

    def reverse_stages(self, t, h, y, K, G, gy, last_bar, has, acc):
        """Run the step's stages backwards from the last: `y`'s cotangent and the arguments'
        accumulated ones, for the stage cotangents `G` and that of `y1`, `last_bar`."""
        m, s, a, c = self.m, self.m.s, self.a, self.c

        def rev(r, cc):
            G, ybar, acc = cc
            i = s - 1 - r
            yi = m.stage_arg(i, y, K)
            dyi, da = self.stage_vjp(t + c[i] * h, yi, h * G[i], (i < s - 1) | has)
            dyi = dyi + jnp.where(i == s - 1, last_bar, 0.0)
            G = G + a[i][:, None, None] * dyi[None]  # y_i = y + sum_j a_ij K_j
            return G, ybar + dyi, jax.tree_util.tree_map(jnp.add, acc, da)

        _, ybar, acc = jax.lax.fori_loop(0, s, rev, (G, gy, acc))
        return ybar, acc

    def step(self, k, y, carry, times):
        """Step `k` from `y` in reverse: its stages are recomputed, then run backwards stage by
        stage (each stage's VJP on its own, so nothing is stacked across stages)."""
        lam, acc, ts_bar, jp = carry
        t, h = self.rec.TK[k], self.rec.HK[k]
        has = jnp.any(self.saved_here(jp, k)) if self.T else jnp.bool_(False)
        K, y1 = self.recompute_stages(t, h, y, has)
        jp, gy, gy1, G, ts_bar = self.save_cotangents(k, t, h, y, y1, K, jp, ts_bar, times)
        ybar, acc = self.reverse_stages(t, h, y, K, G, gy, lam + gy1, has, acc)  # lam + gy1: y1's cotangent
        return ybar, acc, ts_bar, jp

    def stretch(self, r, c, accepted, times):
        """The checkpoint stretch `g = used - 1 - r`: replay its steps from the stored state,
        then run them in reverse."""
        m, rec = self.m, self.rec
        carry, Z = c
        g = rec.used - 1 - r
        k0 = g * rec.stride
        L = jnp.minimum(rec.stride, accepted - k0)
        Z = Z.at[0].set(rec.Y[g])

        def replay(i, Z):
            k = k0 + i - 1
            return Z.at[i].set(m.step(rec.TK[k], rec.HK[k], Z[i - 1], self.args, self.batched, last=False)[0])

        Z = jax.lax.fori_loop(1, L, replay, Z)
        carry = jax.lax.fori_loop(0, L, lambda i, cc: self.step(k0 + L - 1 - i, Z[L - 1 - i], cc, times), carry)
        return carry, Z


def backward(
    m: Method,
    args,
    batched,
    diff,
    t0,
    t1,
    ts,
    y0,
    out,
    at,
    rec: Record,
    ct,
    *,
    max_steps,
    times,
    elementwise=(),
    f_adjoint: Callable | None = None,
):
    """The discrete adjoint of `jsphere.solve.batched.loop.forward` (or with `per_trial`:
    its iterations, with each trial's own step sizes): the cotangents of
    `(y0, args[i] for i in diff)` for the cotangent `ct` of the saved states, with the accepted
    steps' sizes held fixed; if `times`, also those of `(t0, t1, ts)` (the exact solution's:
    `-<lambda(t0), f(t0, y0)>`, `<ct(t1), f(t1, y(t1))>`, `<ct_j, f(ts_j, y(ts_j))>`).

    `out = (ys, failed, n)`, `n` the number of recorded steps (iterations with per-trial
    steps); `at` for each save the step that served it. `f_adjoint`: the field whose VJPs the
    stages take (default the method's own; it may materialise more intermediate values).
    The replayed steps and the recomputed stages (and the rates behind the times' cotangents)
    take the arguments as given (shared ones unbroadcast): only the stage VJPs need per-trial
    copies."""
    ys, _, accepted = out
    _, S = checkpoints(max_steps)
    n, B = y0.shape
    T = ts.shape[0]
    dtype = y0.dtype
    adj = _Adjoint(m, args, batched, diff, ts, y0, at, rec, ct, elementwise=elementwise, f_adjoint=f_adjoint)
    direct = (ts <= t0)[:, None, None]  # rows that are y0 itself
    carry = (ct[T], adj.packed.zeros, jnp.zeros((T,), dtype), jnp.full((B,) if adj.lockstep else (), T - 1, jnp.int32))
    (lam, acc, ts_bar, _), _ = jax.lax.fori_loop(
        0, rec.used, lambda r, c: adj.stretch(r, c, accepted, times), (carry, jnp.zeros((S, n, B), dtype))
    )
    y0_bar = lam + jnp.sum(jnp.where(direct, ct[:T], 0.0), axis=0) if T else lam
    acc = adj.packed.unpack(acc)
    acc = [_assemble(a) if i in elementwise else a for i, a in zip(diff, acc)]
    args_bar = [a.sum(0) if not batched[i] else a for i, a in zip(diff, acc)]
    time_bars = None
    if times:
        f0 = m.rates(t0, y0, args, batched)
        f1 = m.rates(t1, ys[-1], args, batched)
        time_bars = (-jnp.sum(lam * f0), jnp.sum(ct[T] * f1), ts_bar)
    return y0_bar, args_bar, time_bars
