"""The package's one Levenberg-Marquardt: an `init` / `propose` / `update` triple over an explicit
state (`LMState`), in the style of optax, with the linear solve pluggable and the acceptance rule
set by options.

One iteration from the point `x` (any pytree of arrays) and the state:

    x_new, predicted = lm.propose(x, state)          # solve, shorten, check finite
    cost_new, evaluation_new = evaluate(x_new)        # the caller's model
    x, state = lm.update(x, x_new, state, cost_new, evaluation_new, predicted)

`evaluation` is whatever the linear solve needs at a point (for `Dense`, the residuals and
their Jacobian); the state keeps the one of the current point, so a model is evaluated once per
iteration, residuals and Jacobian together. Every function is pure JAX: the whole iteration
runs under `jit`, `vmap` and `lax.scan` (the planner), or is driven from the host one step at a
time with the state saved after each (`iterate`, the fit's checkpoints). Its arrays may carry
leading batch axes (one problem per start, as the cost): the rule is elementwise.

The linear solves: `Dense` (the damped normal equations of one dense Jacobian), and the
block-arrow elimination `solve_arrow` of a problem whose unknowns are shared parameters `theta`
and, per group `t`, parameters `nu_t` of their own:

    [ Hgg    Hgn_1 ... Hgn_T ] [ d_theta ]     [ gg   ]
    [ Hng_1  Hnn_1           ] [ d_nu_1  ]  = -[ gn_1 ]
    [  ...          ...      ] [  ...    ]     [ ...  ]
    [ Hng_T          Hnn_T   ] [ d_nu_T  ]     [ gn_T ]

Each group's block is eliminated (Schur complement `S = Hgg - sum_t Hgn_t Hnn_t^-1 Hng_t`), so
a step costs `T` small solves and one `P x P` solve, linear in the number of groups.

The acceptance rule (`LevenbergMarquardt`'s fields): a step is accepted if it lowers the cost,
or, with a noise floor `noise > 0`, if its predicted decrease is below `noise` and the cost
rises by less (an evaluation whose Jacobian is accurate where cost differences are not: an
ODE solver's tolerance). The damping `lam` is divided by `decrease` on acceptance and multiplied
by `increase` on rejection. With "delayed acceptance" (the planner), each evaluation serves
both as the test of the previous step and as the Jacobian of the next. Choices and
measurements: `docs/decisions/least-squares.md`.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from .._runtime.arrays import to_jax
from .._runtime.quick_compile import eager_jit

#: the per-problem arrays of `LMState` (what a checkpoint saves besides `it` and `current`)
LM_KEYS = ("lam", "converged", "stalled", "rejected", "best_cost", "cost")


# ----------------------------------------------------------------------------- the linear solves


def damp(H, lam, floor: float = 0.0, shift: float = 0.0):
    """`H + diag(lam (diag H + floor) + shift max(diag H) + 1e-300)` (batched over leading axes):
    Marquardt's damping, `floor` a damping of directions of zero curvature, `shift` an undamped
    regulariser relative to the largest curvature."""
    d = jnp.diagonal(H, axis1=-2, axis2=-1)
    extra = shift * jnp.max(d, axis=-1, keepdims=True) + 1e-300
    return H + (lam * (d + floor) + extra)[..., None] * jnp.eye(H.shape[-1], dtype=H.dtype)


class Dense(eqx.Module):
    """The linear solve of one dense problem: `evaluation = (r (K,), J (K, P))`, the step
    `(J^T J + damping) dx = -J^T r` (`damp`) and its predicted decrease of `|r|^2 / 2`."""

    floor: float = 0.0
    shift: float = 0.0

    def __call__(self, evaluation, lam):
        r, J = evaluation
        H = J.T @ J
        g = J.T @ r
        dx = -jnp.linalg.solve(damp(H, lam, self.floor, self.shift), g)
        return dx, -(g @ dx + 0.5 * dx @ H @ dx)


def blocks(res: Float[Array, "T K"], J: Float[Array, "T K Q"], P: int):
    """Gauss-Newton blocks of the block-arrow normal equations of the residuals `res` of `T`
    groups, `J`'s first `P` columns the shared parameters: `Hgg (P,P)`, `Hgn (T,P,n)`,
    `Hnn (T,n,n)`, gradients `gg (P,)`, `gn (T,n)`."""
    Jg, Jn = J[..., :P], J[..., P:]
    Hgg = jnp.einsum("tkp,tkq->pq", Jg, Jg)
    Hgn = jnp.einsum("tkp,tkn->tpn", Jg, Jn)
    Hnn = jnp.einsum("tkn,tkm->tnm", Jn, Jn)
    return Hgg, Hgn, Hnn, jnp.einsum("tkp,tk->p", Jg, res), jnp.einsum("tkn,tk->tn", Jn, res)


def solve_arrow(arrow, lam):
    """The damped step `(H + damping) delta = -g` of block-arrow normal equations (`blocks`),
    the groups' blocks eliminated (module docstring). Returns `(d_theta (P,), d_nu (T,n),
    predicted decrease -(g.delta + delta^T H delta / 2))`."""
    Hgg, Hgn, Hnn, gg, gn = arrow
    Hnn_inv = jnp.linalg.inv(damp(Hnn, lam, shift=1e-12))
    X = jnp.einsum("tpn,tnm->tpm", Hgn, Hnn_inv)
    S = damp(Hgg, lam, shift=1e-12) - jnp.einsum("tpm,tqm->pq", X, Hgn)
    rhs = gg - jnp.einsum("tpm,tm->p", X, gn)
    dg = -jnp.linalg.solve(S, rhs)
    dn = -jnp.einsum("tnm,tm->tn", Hnn_inv, gn + jnp.einsum("tpn,p->tn", Hgn, dg))
    g_dot = gg @ dg + jnp.sum(gn * dn)
    quad = dg @ Hgg @ dg + 2.0 * jnp.einsum("p,tpn,tn->", dg, Hgn, dn) + jnp.einsum("tn,tnm,tm->", dn, Hnn, dn)
    return dg, dn, -(g_dot + 0.5 * quad)


def arrow_step(res, J, lam, P: int):
    """The damped step of residuals `res (T, K)` with Jacobian `J (T, K, P + n)`
    (`solve_arrow` of `blocks`)."""
    return solve_arrow(blocks(res, J, P), lam)


#: `blocks` as one compiled program, for arrays on the host
_blocks = jax.jit(blocks, static_argnums=2)


def marginal_information(res, J, P: int) -> np.ndarray:
    """Gauss-Newton information of `theta` with the groups' parameters eliminated:
    `F = Hgg - sum_t Hgn_t Hnn_t^-1 Hng_t` (numpy, float64)."""
    Hgg, Hgn, Hnn, _, _ = (np.asarray(a) for a in _blocks(res, J, P))
    F = Hgg.copy()
    for t in range(Hnn.shape[0]):
        F -= Hgn[t] @ np.linalg.pinv(Hnn[t], rcond=1e-13, hermitian=True) @ Hgn[t].T
    return 0.5 * (F + F.T)


# ----------------------------------------------------------------------------- the iteration


class LMState(eqx.Module):
    """Levenberg-Marquardt's state (arrays of the cost's shape, named as `LM_KEYS`): the damping
    `lam`, `converged`, accepted steps without progress (`stalled`), rejections in a row
    (`rejected`), the best and the current cost; `it`: the steps taken; `current`: the
    evaluation at the current point."""

    lam: Any
    converged: Any
    stalled: Any
    rejected: Any
    best_cost: Any
    cost: Any
    it: Any
    current: Any

    def arrays(self) -> dict[str, np.ndarray]:
        """The per-problem arrays by name (`LM_KEYS`)."""
        return {k: np.asarray(getattr(self, k)) for k in LM_KEYS}

    @property
    def best_converged(self) -> bool:
        """Whether the problem of the lowest cost has converged."""
        return bool(np.asarray(self.converged).reshape(-1)[int(np.argmin(np.asarray(self.cost)))])


def _pick(mask, new, old):
    """`new` where `mask`, else `old` (pytrees whose leaves have `mask`'s shape as leading axes)."""
    m = jnp.asarray(mask)
    return jax.tree_util.tree_map(
        lambda a, b: jnp.where(m.reshape(m.shape + (1,) * (jnp.ndim(a) - m.ndim)), a, b), new, old
    )


def _rows(tree, batch: tuple[int, ...]):
    """Each leaf of `tree` as `(*batch, -1)`: one row per problem."""
    return [jnp.reshape(a, batch + (math.prod(jnp.shape(a)[len(batch) :]),)) for a in jax.tree_util.tree_leaves(tree)]


class LevenbergMarquardt(eqx.Module):
    """Levenberg-Marquardt's options (module docstring).

    - `solve(evaluation, lam) -> (step, predicted decrease)`: the linear solve (`Dense`, or a
      caller's, e.g. the block-arrow `solve_arrow`); a caller that solves outside may call
      `candidate` with its step instead of `propose`.
    - `decrease`, `increase`, `lam_min`, `lam_max`, `lam0`: the damping's factors, bounds and start.
    - `noise`: the noise floor of the acceptance (0: accept decreases only).
    - `rel_done`: a relative decrease of an accepted step below this ends a problem; `gtol`: a
      predicted decrease below this (at `lam <= 1`) ends it, and an accepted step that does not
      lower the best cost by `gtol` counts as stalled; `max_stalled` such steps, or
      `max_rejected` rejections in a row, end it. A problem that has ended takes no step.
    - `max_step`: the longest step, measured as `max |dx| / step_scale` (`step_scale`: a pytree
      of `x`'s structure, or None for 1); a longer one is shortened (`inf`: never).
    """

    solve: Callable = Dense()
    decrease: float = 5.0
    increase: float = 10.0
    lam_min: float = 1e-12
    lam_max: float = math.inf
    lam0: float = 1e-3
    noise: float = 0.0
    rel_done: float = 0.0
    gtol: float = -math.inf
    max_stalled: int = 2**30
    max_rejected: int = 2**30
    max_step: float = math.inf
    step_scale: Any = None

    def init(self, cost, evaluation) -> LMState:
        """The state at the start point, its cost (`inf`: failed) and its evaluation."""
        cost = to_jax(cost)  # (host values: device arrays, not one small program each)
        zeros = to_jax(np.zeros(cost.shape, int))
        lam = to_jax(np.full(cost.shape, self.lam0, cost.dtype))
        return LMState(lam, to_jax(np.zeros(cost.shape, bool)), zeros, zeros, cost, cost, 0, evaluation)

    def propose(self, x, state: LMState):
        """The next point from `x` (`candidate` of `solve`'s step) and the predicted decrease."""
        step, predicted = self.solve(state.current, state.lam)
        return self.candidate(x, step, predicted)

    def candidate(self, x, step, predicted):
        """`x + step`, the step shortened to `max_step`; `x` itself where the result is not
        finite. Returns it and the predicted decrease (`inf`: a shortened step, NaN: none)."""
        x, step, predicted = jax.tree_util.tree_map(jnp.asarray, (x, step, predicted))
        batch = predicted.shape
        if self.max_step < math.inf:
            scale = jax.tree_util.tree_map(lambda _: 1.0, x) if self.step_scale is None else self.step_scale
            ratios = _rows(jax.tree_util.tree_map(lambda d, s: jnp.abs(d) / s, step, scale), batch)
            length = jnp.max(jnp.stack([jnp.max(a, axis=-1, initial=0.0) for a in ratios]), axis=0)
            shrink = jnp.minimum(1.0, self.max_step / jnp.maximum(length, 1e-300))
            step = jax.tree_util.tree_map(lambda d: d * shrink.reshape(batch + (1,) * (d.ndim - len(batch))), step)
            # (the quadratic model's prediction is of the full step)
            predicted = jnp.where(shrink < 1.0, jnp.inf, predicted)
        x_new = jax.tree_util.tree_map(lambda a, d: a + d, x, step)
        bad = jnp.stack([~jnp.all(jnp.isfinite(a), axis=-1) for a in _rows(x_new, batch)]).any(axis=0)
        return _pick(bad, x, x_new), jnp.where(bad, jnp.nan, predicted)

    def update(self, x, x_new, state: LMState, cost, evaluation, predicted):
        """Accept or reject `x_new` (its `cost`, `inf` for a failed evaluation, its evaluation
        and `predicted` decrease from `candidate`; `inf`: no prediction). Returns the point and
        the state."""
        # (every operation in XLA, whether the state was saved and loaded as NumPy arrays or not)
        state = eqx.tree_at(
            lambda s: [getattr(s, k) for k in LM_KEYS], state, [jnp.asarray(getattr(state, k)) for k in LM_KEYS]
        )
        cost_n, predicted = jnp.asarray(cost), jnp.asarray(predicted)
        old, lam = state.cost, state.lam
        near = (predicted < self.noise) & (cost_n < old + self.noise)
        acc = jnp.isfinite(cost_n) & ((cost_n < old) | near) & ~state.converged & ~jnp.isnan(predicted)
        rel = (old - cost_n) / jnp.maximum(old, 1e-300)
        progress = cost_n < state.best_cost - self.gtol
        stalled = jnp.where(acc, jnp.where(progress, 0, state.stalled + 1), state.stalled)
        rejected = jnp.where(acc, 0, state.rejected + 1)
        ended = (
            (acc & (jnp.abs(rel) < self.rel_done))
            | ((predicted < self.gtol) & (lam <= 1.0))
            | (stalled >= self.max_stalled)
            | (rejected >= self.max_rejected)
        )
        grown = jnp.minimum(lam * self.increase, self.lam_max)
        new = LMState(
            lam=jnp.where(acc, jnp.maximum(lam / self.decrease, self.lam_min), grown),
            converged=state.converged | ended,
            stalled=stalled,
            rejected=rejected,
            best_cost=jnp.where(acc, jnp.minimum(state.best_cost, cost_n), state.best_cost),
            cost=jnp.where(acc, cost_n, old),
            it=state.it + 1,
            current=_pick(acc, evaluation, state.current),
        )
        return _pick(acc, x_new, x), new


# ----------------------------------------------------------------------------- driven from the host


def _arrays(tree):
    """Every leaf of `tree` as an array (a Python number would be a static argument of
    `filter_jit`, compiled again for each value)."""
    return jax.tree_util.tree_map(to_jax, tree)


#: `propose`, `candidate` and `update` as compiled programs (per `lm` and shapes)
_propose, _candidate, _update = (
    eager_jit(f) for f in (LevenbergMarquardt.propose, LevenbergMarquardt.candidate, LevenbergMarquardt.update)
)


def _counted(state: LMState) -> LMState:
    """`state` with its step count out of the compiled programs (counted on the host)."""
    return eqx.tree_at(lambda s: s.it, state, replace=0)


def host_propose(lm: LevenbergMarquardt, x, state: LMState):
    """`lm.propose` as one compiled program (per `lm` and shapes), for a loop driven from the
    host: eager, each operation would compile a program of its own on its first call."""
    return _propose(lm, _arrays(x), _arrays(_counted(state)))


def host_candidate(lm: LevenbergMarquardt, x, step, predicted):
    """`lm.candidate` as one compiled program (`host_propose`)."""
    return _candidate(lm, *_arrays((x, step, predicted)))


def host_update(lm: LevenbergMarquardt, x, x_new, state: LMState, cost, evaluation, predicted):
    """`lm.update` as one compiled program (`host_propose`); the step count `it` stays a
    Python number."""
    x, new = _update(lm, *_arrays((x, x_new, _counted(state), cost, evaluation, predicted)))
    return x, eqx.tree_at(lambda s: s.it, new, replace=state.it + 1)


def iterate(
    lm: LevenbergMarquardt,
    evaluate: Callable,
    solve: Callable,
    x,
    state: LMState,
    max_iter: int,
    *,
    every: bool = False,
) -> Iterator[tuple[Any, LMState, Any]]:
    """Levenberg-Marquardt driven from the host, one step at a time, until the problem of the
    lowest cost has converged (with `every`: every problem, for a batch of independent ones) or
    `max_iter` steps: `evaluate(x) -> (cost, evaluation)` (a batch of problems, `inf` for a
    failed one), `solve(evaluation, lam) -> (step, predicted)`. Yields after every step the
    point, the state and the candidate evaluated, so that the caller can save and report (a
    problem's step was accepted where `state.rejected == 0`)."""
    done = (lambda s: bool(np.all(np.asarray(s.converged)))) if every else (lambda s: s.best_converged)
    while state.it < max_iter and not done(state):
        x_new, predicted = host_candidate(lm, x, *solve(state.current, state.lam))
        cost, evaluation = evaluate(x_new)
        x, state = host_update(lm, x, x_new, state, cost, evaluation, predicted)
        yield x, state, x_new
