"""Generic nonlinear least squares for small dense problems (`least_squares`), by optimistix's
Levenberg-Marquardt.

The fit's own iteration (`jsphere.identify.lm`) is separate: it eliminates each trial's
nuisance block from block-arrow normal equations, which a dense solver would factor whole.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx


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
    Jacobian is taken by reverse mode (`jac="rev"`, for few residuals or simulations with the
    default adjoint) or forward mode (`jac="fwd"`, with `adjoint=diffrax.ForwardMode()`).
    The solver is `optimistix.LevenbergMarquardt`, compiled with `fun` into one program; it
    stops when both the step and the change of the cost are below `xtol` relative to their size
    plus `ftol`, or after `max_iter` steps (then `converged` is False).
    Used by `examples/fit_paper_Rm_j.py` together with `FreeParams`.
    """
    if jac not in ("rev", "fwd"):
        raise ValueError(f"least_squares: jac must be 'rev' or 'fwd'; got {jac!r}.")
    x0 = jnp.asarray(x0, jnp.float64)
    solver = optx.LevenbergMarquardt(rtol=xtol, atol=ftol)
    sol = optx.least_squares(
        lambda x, _: fun(x), solver, x0, options={"jac": "bwd" if jac == "rev" else "fwd"}, max_steps=max_iter, throw=False
    )
    x = np.asarray(sol.value)
    r = np.asarray(jax.jit(fun)(x))
    Jm = np.asarray(jax.jit(jax.jacrev(fun) if jac == "rev" else jax.jacfwd(fun))(x))
    cost = 0.5 * float(r @ r)
    s2 = 2 * cost / max(len(r) - len(x), 1) if scale_by_residual else 1.0
    cov = s2 * np.linalg.pinv(Jm.T @ Jm, rcond=1e-14, hermitian=True)
    converged = bool(sol.result == optx.RESULTS.successful)
    return LeastSquaresResult(x=x, cost=cost, jac=Jm, covariance=cov, iterations=int(sol.stats["num_steps"]), converged=converged)
