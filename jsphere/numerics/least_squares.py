"""Generic nonlinear least squares for small dense problems (`least_squares`).

The package's Levenberg-Marquardt (`jsphere.numerics.lm`, the `Dense` solve) driven from the
host around the jitted residuals and their Jacobian, the Jacobian evaluated at accepted points
only. It is kept instead of `optimistix.least_squares` with `optimistix.LevenbergMarquardt`,
which compiles the whole iteration, residual function included, into one program: measured
side by side by `benchmarks/least_squares.py`, that compile dominates for residuals that run
simulations (`docs/decisions/least-squares.md`).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import equinox as eqx
import jax
import numpy as np

from .lm import Dense, LevenbergMarquardt, host_propose, host_update

#: `least_squares`' iteration: accepted decreases only, the damping / 5 (down to 1e-15) or x 10
LEAST_SQUARES_LM = LevenbergMarquardt(Dense(floor=1e-300), lam_min=1e-15)


@dataclasses.dataclass
class LeastSquaresResult:
    """`x`: the solution; `cost = 1/2 |r|^2`; `jac`: `dr/dx` at `x`; `covariance`:
    `s2 (J^T J)^-1` with `s2 = 1` (the residuals are taken as whitened) unless `scale_by_residual`."""

    x: np.ndarray
    cost: float
    jac: np.ndarray
    covariance: np.ndarray
    iterations: int
    converged: bool


def least_squares(
    fun: Callable,
    x0,
    *,
    max_iter: int = 50,
    ftol: float = 1e-14,
    xtol: float = 1e-12,
    jac: str = "rev",
    scale_by_residual: bool = False,
) -> LeastSquaresResult:
    """Levenberg-Marquardt on a small dense problem: minimise `1/2 |fun(x)|^2`.

    `fun` is a pure JAX function of `x (P,)` returning whitened residuals `(K,)`; its
    Jacobian is taken by `jax.jacrev` (`jac="rev"`, for few residuals or simulations with the
    default adjoint) or `jax.jacfwd` (`jac="fwd"`, with `adjoint=diffrax.ForwardMode()`).
    It has converged when an accepted step lowers the cost by at most `ftol` (relative) or
    moves `x` by less than `xtol` (relative to `max(|x|, 1)`), the cost is 0, or the damping
    has grown past 1e15. Used by `examples/fit_paper_Rm_j.py` together with `FreeParams`.
    """
    jf = jax.jit(jax.jacrev(fun) if jac == "rev" else jax.jacfwd(fun))
    f = jax.jit(fun)
    lm = LEAST_SQUARES_LM
    x = np.asarray(x0, np.float64)
    r = np.asarray(f(x))
    state = lm.init(0.5 * float(r @ r), (r, np.asarray(jf(x))))
    converged, k = False, 0
    for k in range(1, max_iter + 1):
        x_new, predicted = host_propose(lm, x, state)
        r_new = np.asarray(f(x_new))
        cost = 0.5 * float(r_new @ r_new)
        x_old, old = x, float(state.cost)
        x, state = host_update(
            lm, x, x_new, state, cost if np.isfinite(cost) else np.inf, (r_new, state.current[1]), predicted
        )
        x = np.asarray(x)
        if int(state.rejected) == 0:  # accepted: the Jacobian there
            state = eqx.tree_at(lambda s: s.current, state, (r_new, np.asarray(jf(x))))
            moved = np.max(np.abs(x - x_old) / np.maximum(np.abs(x_old), 1.0))
            small = old - cost <= ftol * max(old, 1e-300) or moved < xtol
            if small or cost == 0.0:
                converged = True
                break
        elif float(state.lam) > 1e15:
            converged = True
            break
    r, Jm = (np.asarray(a) for a in state.current)
    cost = float(state.cost)
    s2 = 2 * cost / max(len(r) - len(x), 1) if scale_by_residual else 1.0
    cov = s2 * np.linalg.pinv(Jm.T @ Jm, rcond=1e-14, hermitian=True)
    return LeastSquaresResult(x=x, cost=cost, jac=Jm, covariance=cov, iterations=k, converged=converged)
