"""Generic nonlinear least squares for small dense problems (`least_squares`).

A Levenberg-Marquardt loop in NumPy around the jitted residuals and their Jacobian. It is kept
instead of `optimistix.least_squares` with `optimistix.LevenbergMarquardt`, which compiles the
whole iteration, residual function included, into one program: measured side by side by
`benchmarks/least_squares.py`, that compile dominates for residuals that run simulations
(`docs/performance.md`). The fit's own iteration (`jsphere.identify.lm`) is separate: it
eliminates each trial's nuisance block from block-arrow normal equations.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import jax
import numpy as np


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
    Used by `examples/fit_paper_Rm_j.py` together with `FreeParams`.
    """
    jf = jax.jit(jax.jacrev(fun) if jac == "rev" else jax.jacfwd(fun))
    f = jax.jit(fun)
    x = np.asarray(x0, np.float64)
    r = np.asarray(f(x))
    Jm = np.asarray(jf(x))
    cost = 0.5 * float(r @ r)
    lam, converged, k = 1e-3, False, 0
    for k in range(1, max_iter + 1):
        H = Jm.T @ Jm
        g = Jm.T @ r
        D = np.diag(np.diag(H)) + 1e-300 * np.eye(len(x))
        dx = -np.linalg.solve(H + lam * D, g)
        xn = x + dx
        rn = np.asarray(f(xn))
        cn = 0.5 * float(rn @ rn)
        if np.isfinite(cn) and cn < cost:
            small = (cost - cn) <= ftol * max(cost, 1e-300) or np.max(np.abs(dx) / np.maximum(np.abs(x), 1.0)) < xtol
            x, r, cost = xn, rn, cn
            Jm = np.asarray(jf(x))
            lam = max(lam / 5.0, 1e-15)
            if small or cost == 0.0:
                converged = True
                break
        else:
            lam *= 10.0
            if lam > 1e15:
                converged = True
                break
    s2 = 2 * cost / max(len(r) - len(x), 1) if scale_by_residual else 1.0
    cov = s2 * np.linalg.pinv(Jm.T @ Jm, rcond=1e-14, hermitian=True)
    return LeastSquaresResult(x=x, cost=cost, jac=Jm, covariance=cov, iterations=k, converged=converged)
