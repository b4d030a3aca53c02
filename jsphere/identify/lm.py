"""Levenberg-Marquardt for the fit: block-arrow normal equations and the damped iteration.

The fit's unknowns are the free parameters `theta (P,)` shared by all trials and, per trial,
nuisance parameters `nu_t (n,)` (or, in multiple shooting, one dense block of a trial's
segments). The Gauss-Newton matrix is then a block arrow:

    [ Hgg    Hgn_1 ... Hgn_T ] [ d_theta ]     [ gg   ]
    [ Hng_1  Hnn_1           ] [ d_nu_1  ]  = -[ gn_1 ]
    [  ...          ...      ] [  ...    ]     [ ...  ]
    [ Hng_T          Hnn_T   ] [ d_nu_T  ]     [ gn_T ]

`_solve_arrow` eliminates each trial's dense nuisance block (Schur complement
`S = Hgg - sum_t Hgn_t Hnn_t^-1 Hng_t`), so a step costs `T` small solves and one `P x P`
solve, linear in the number of trials, and runs vmapped over the starts in one compiled call.
A generic dense solver (`optimistix.LevenbergMarquardt`, used by `jsphere.least_squares`)
would factor the whole `(P + T n)` matrix instead; the fit's iteration also needs what a
generic solver does not give: steps accepted within the ODE solver's noise floor (`noise`),
per-start convergence flags in one vmapped batch, a cap on the step length (`STEP_MAX`) and
its whole state after every step for the checkpoint. So the fit keeps its own iteration here
(choices and measurements: `docs/performance.md`).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Iterator
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

#: the longest Levenberg-Marquardt step, in the free parameters' scaled units (`theta_scales`:
#: a factor e^2 for a log-transformed value)
STEP_MAX = 2.0
#: per-start state of Levenberg-Marquardt: damping, converged, accepted steps without progress,
#: rejections in a row, best cost, cost
LM_KEYS = ("lam", "converged", "stalled", "rejected", "best_cost", "cost")


# ----------------------------------------------------------------------------- the linear algebra


def _blocks(res, J, P):
    """Gauss-Newton blocks of the block-arrow normal equations: `Hgg (P,P)`, `Hgn (T,P,n)`,
    `Hnn (T,n,n)`, gradients `gg (P,)`, `gn (T,n)`."""
    Jg, Jn = J[..., :P], J[..., P:]
    Hgg = jnp.einsum("tkp,tkq->pq", Jg, Jg)
    Hgn = jnp.einsum("tkp,tkn->tpn", Jg, Jn)
    Hnn = jnp.einsum("tkn,tkm->tnm", Jn, Jn)
    return Hgg, Hgn, Hnn, jnp.einsum("tkp,tk->p", Jg, res), jnp.einsum("tkn,tk->tn", Jn, res)


def _damp(H, lam):
    d = jnp.diagonal(H, axis1=-2, axis2=-1)
    floor = 1e-12 * jnp.max(d, axis=-1, keepdims=True) + 1e-300
    return H + (lam * d + floor)[..., None] * jnp.eye(H.shape[-1], dtype=H.dtype)


def _solve_arrow(blocks, lam):
    """Levenberg-Marquardt step `(H + lam diag H) delta = -g` of block-arrow normal equations
    (`_blocks`), the nuisance blocks eliminated (Schur complement). Returns
    `(d_theta (P,), d_nu (T,n), predicted cost decrease -(g.delta + delta^T H delta / 2))`."""
    Hgg, Hgn, Hnn, gg, gn = blocks
    Hnn_d = _damp(Hnn, lam)
    Hnn_inv = jnp.linalg.inv(Hnn_d)
    X = jnp.einsum("tpn,tnm->tpm", Hgn, Hnn_inv)
    S = _damp(Hgg, lam) - jnp.einsum("tpm,tqm->pq", X, Hgn)
    rhs = gg - jnp.einsum("tpm,tm->p", X, gn)
    dg = -jnp.linalg.solve(S, rhs)
    dn = -jnp.einsum("tnm,tm->tn", Hnn_inv, gn + jnp.einsum("tpn,p->tn", Hgn, dg))
    g_dot = gg @ dg + jnp.sum(gn * dn)
    quad = dg @ Hgg @ dg + 2.0 * jnp.einsum("p,tpn,tn->", dg, Hgn, dn) + jnp.einsum("tn,tnm,tm->", dn, Hnn, dn)
    return dg, dn, -(g_dot + 0.5 * quad)


def _lm_step(res, J, lam, P: int):
    """The Levenberg-Marquardt step of single shooting (`_solve_arrow` of `_blocks`)."""
    return _solve_arrow(_blocks(res, J, P), lam)


def marginal_information(res, J, P: int) -> np.ndarray:
    """Gauss-Newton information of `theta` with the nuisance parameters eliminated:
    `F = Hgg - sum_t Hgn_t Hnn_t^-1 Hng_t` (numpy, float64)."""
    Hgg, Hgn, Hnn, _, _ = (np.asarray(a) for a in _blocks(res, J, P))
    F = Hgg.copy()
    for t in range(Hnn.shape[0]):
        F -= Hgn[t] @ np.linalg.pinv(Hnn[t], rcond=1e-13, hermitian=True) @ Hgn[t].T
    return 0.5 * (F + F.T)


# ----------------------------------------------------------------------------- the iteration


@dataclasses.dataclass
class LMState:
    """Levenberg-Marquardt's state, per start (arrays `(S,)`, named as `LM_KEYS`): the damping
    `lam`, `converged`, accepted steps without progress (`stalled`), rejections in a row
    (`rejected`), the best and the current cost; `it`: the steps taken; `current`: the
    evaluation (residuals and Jacobian, or normal-equation blocks) at the current points."""

    lam: np.ndarray
    converged: np.ndarray
    stalled: np.ndarray
    rejected: np.ndarray
    best_cost: np.ndarray
    cost: np.ndarray
    it: int
    current: dict[str, Any]

    @classmethod
    def start(cls, cost: np.ndarray, current: dict[str, Any]) -> LMState:
        S = cost.shape[0]
        return cls(
            np.full(S, 1e-3), np.zeros(S, bool), np.zeros(S, int), np.zeros(S, int), cost.copy(), cost, 0, current
        )

    def arrays(self) -> dict[str, np.ndarray]:
        """The per-start arrays by name (`LM_KEYS`)."""
        return {k: getattr(self, k) for k in LM_KEYS}

    @property
    def best_converged(self) -> bool:
        """Whether the start of the lowest cost has converged."""
        return bool(self.converged[int(np.argmin(self.cost))])


@dataclasses.dataclass(frozen=True)
class LMOptions:
    """`max_iter` steps at most; `rel_done`: the relative change of the cost of an accepted step
    that ends a start; `gtol`: the predicted decrease below which a start is done, and the
    progress that counts against stalling; `noise`: steps predicted to gain less than this are
    accepted unless the cost rises by more (the ODE solver's noise floor); `max_rejected`:
    rejections in a row that end a start; `step_scale (P,)`: the scaled units of `STEP_MAX`."""

    max_iter: int
    rel_done: float
    gtol: float
    noise: float
    step_scale: np.ndarray
    max_rejected: int = 8


@dataclasses.dataclass(frozen=True)
class Step:
    """What one iteration did: `accepted (S,)`, and the longest step in scaled units."""

    accepted: np.ndarray
    length: float


def levenberg_marquardt(
    evaluate: Callable, solve: Callable, th: np.ndarray, n: np.ndarray, lm: LMState, options: LMOptions
) -> Iterator[tuple[np.ndarray, np.ndarray, LMState, Step]]:
    """Levenberg-Marquardt on every start from `(th (S, P), n (S, ...))` and the state `lm`,
    until the start of the lowest cost has converged or `max_iter` steps.

    `evaluate(th, n) -> (cost (S,), evaluation)` (an infinite cost for a failed start);
    `solve(evaluation, lam) -> (d_theta, d_nu, predicted decrease)`. Yields after every step the
    points, the new state and the `Step`, so that the caller can save and report."""
    while lm.it < options.max_iter and not lm.best_converged:
        th, n, lm, step = _iterate(evaluate, solve, th, n, lm, options)
        yield th, n, lm, step


def _iterate(evaluate, solve, th, n, lm: LMState, o: LMOptions) -> tuple[np.ndarray, np.ndarray, LMState, Step]:
    """One step of every start: solve, shorten to `STEP_MAX`, evaluate, accept or reject."""
    S, P = th.shape
    out, cost, lam = lm.current, lm.cost, lm.lam
    dg, dn, pred_n = solve(out, lam)
    # a step longer than `STEP_MAX` (in the free parameters' scaled units) is shortened:
    # a start far off can otherwise jump to parameters whose motion takes the ODE solver
    # `max_steps` steps, and the whole vmapped batch waits for it
    length = np.max(np.abs(dg) / o.step_scale, axis=1) if P else np.zeros(S)
    shrink = np.minimum(1.0, STEP_MAX / np.maximum(length, 1e-300))
    dg, dn = dg * shrink[:, None], dn * shrink.reshape((S,) + (1,) * (dn.ndim - 1))
    pred_n = np.where(shrink < 1.0, np.inf, pred_n)  # (the quadratic model's prediction is of the full step)
    th_new, n_new = th + dg, n + dn
    bad = ~np.all(np.isfinite(th_new), 1) | ~np.all(np.isfinite(n_new.reshape(S, -1)), 1)
    th_new = np.where(bad[:, None], th, th_new)
    n_new = np.where(bad[:, None, None], n, n_new)
    cost_n, out_n = evaluate(th_new, n_new)
    # accept a decrease; near the optimum (predicted decrease below `noise`), accept the
    # Gauss-Newton step unless the cost rises by more than the solver's noise floor: its
    # Jacobian is accurate where cost differences are not
    with np.errstate(invalid="ignore"):  # (inf - inf for a start that has failed)
        near = (pred_n < o.noise) & (cost_n < cost + o.noise)
        acc = np.isfinite(cost_n) & ((cost_n < cost) | near) & ~lm.converged & ~bad
        rel = (cost - cost_n) / np.maximum(cost, 1e-300)
    # accepted steps that do not lower the best cost by gtol (the solver's noise floor)
    stalled = np.where(acc, np.where(cost_n < lm.best_cost - o.gtol, 0, lm.stalled + 1), lm.stalled)
    rejected = np.where(acc, 0, lm.rejected + 1)
    best_cost = np.where(acc, np.minimum(lm.best_cost, cost_n), lm.best_cost)
    # done: a negligible predicted or relative decrease, 3 accepted steps without
    # progress, or `max_rejected` rejections in a row (lambda grown by 10^max_rejected)
    newly = (
        (acc & (np.abs(rel) < o.rel_done))
        | ((pred_n < o.gtol) & (lam <= 1.0))
        | (stalled >= 3)
        | (rejected >= o.max_rejected)
    )
    th = np.where(acc[:, None], th_new, th)
    n = np.where(acc[:, None, None], n_new, n)
    lm = LMState(
        lam=np.where(acc, np.maximum(lam / 5.0, 1e-12), lam * 10.0),
        converged=lm.converged | newly,
        stalled=stalled,
        rejected=rejected,
        best_cost=best_cost,
        cost=np.where(acc, cost_n, cost),
        it=lm.it + 1,
        current=_select(acc, out_n, out),
    )
    return th, n, lm, Step(acc, float(np.max(np.abs(dg) / o.step_scale)) if P else 0.0)


def _select(acc, new, old):
    """Per start: `new` where accepted, else `old` (pytrees with a leading start axis)."""
    a = jnp.asarray(acc)
    return jax.tree_util.tree_map(lambda x, y: jnp.where(a.reshape((-1,) + (1,) * (x.ndim - 1)), x, y), new, old)
