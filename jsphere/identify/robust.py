"""Robust losses of the fit: frames that a capture got wrong (ghost frames, marker swaps) set aside.

The residuals of one frame, position and orientation together (`r_f`: 2 position and 3
orientation values, whitened by the noise levels `sigma_pos`, `sigma_rot`:
`jsphere.identify.residuals`), enter the cost through a robust function of their squared norm
`s_f = |r_f|^2`, so that a frame swapped or ghosted counts once, whatever channel it spoils:

    cost = 1/2 sum_f c^2 rho(s_f / c^2)

with `c = SCALE` noise levels and, for `z = s / c^2` (the forms of `scipy.optimize.least_squares`
and Ceres, `rho(z) = z + O(z^2)` near 0):

    l2       rho(z) = z                                  (the plain least squares)
    huber    rho(z) = z                  (z <= 1),  2 sqrt(z) - 1   (z > 1)
    soft_l1  rho(z) = 2 (sqrt(1 + z) - 1)
    cauchy   rho(z) = log(1 + z)                         (the default)

The fit minimises it by iteratively reweighted least squares inside its Levenberg-Marquardt
(`jsphere.numerics.lm`): at every point it evaluates, each frame's residuals and their Jacobian
are multiplied by `sqrt(w_f)`, `w_f = rho'(z_f)`, the weights held fixed in the derivatives.
The gradient of the weighted sum of squares is then the gradient of the robust cost, and its
Gauss-Newton matrix `sum_f w_f J_f^T J_f` the robust cost's without the term in `rho''`
(which can make it indefinite). Steps are accepted on the robust cost itself.

`SCALE^2 = 20.5` is the 99.9 % point of chi^2 with 5 degrees of freedom: under Cauchy a frame of
Gaussian noise has weight below one half (`REJECT`, the frames reported as set aside) once in a
thousand (under Huber and soft-L1, whose weights fall more slowly, almost never).
Cauchy is the default: its influence `w s` falls back to `c^2` for a frame far off (a swap of
60 degrees at 0.5 degree noise keeps `1e-3` of its least-squares influence), where Huber's and
soft-L1's grow as `|r_f|` without bound, and a burst of a dozen such frames moves the fit by
standard errors. On Gaussian noise its efficiency is 98.6 % (5 values per frame: standard errors
0.7 % larger than those of least squares), Huber's at this scale 97.5 %, soft-L1's 99.7 %.

Standard errors (`variance_factor`): the covariance of an M-estimator, in the weighted
Gauss-Newton form `s2 (sum_f w_f J_f^T J_f)^-1` with Huber's factor

    s2 = [sum_f w_f^2 s_f / (n - n_par)] mean_f(w_f) / mean_f(w_f + 2 z_f rho''(z_f) / p_f)^2

(`p_f` the values a frame holds, `n` all of them), which is `2 cost / (n - n_par)` for `l2`.
"""

from __future__ import annotations

import math

import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from .._runtime.arrays import to_jax
from .._runtime.quick_compile import eager_jit

#: the losses by name; `l2` is plain least squares
LOSSES = ("l2", "huber", "cauchy", "soft_l1")
#: the loss of `fit` and `compare` unless one is given
DEFAULT_LOSS = "cauchy"
#: the scale `c` of the robust function, in noise levels of a frame's whitened residual norm:
#: `c^2` is the 99.9 % point of chi^2 with 5 degrees of freedom
SCALE = math.sqrt(20.5)
#: a frame whose weight is below this is reported as set aside
REJECT = 0.5
#: losses whose influence falls back to a constant for a frame far off: from a point far from the
#: answer they can let whole stretches of a trial go, so a fit's warm-up stages (multiple
#: shooting, the Adam steps) run with `WARM_LOSS` instead
REDESCENDING = ("cauchy",)
#: the loss of a fit's warm-up stages where its loss is redescending: convex in the residuals,
#: every frame keeps a pull of at least `c` noise levels, so no trial can be left out
WARM_LOSS = "huber"


def check_loss(loss, where: str) -> str:
    """`loss` if it is one of `LOSSES`, else a `ValueError` naming them."""
    from .._runtime.errors import InputError

    if loss not in LOSSES:
        raise InputError(f"{where}: loss must be one of {', '.join(LOSSES)}; got {loss!r}.")
    return loss


def rho(loss: str, z):
    """The robust function `rho(z)` of `z = s / c^2` (module docstring)."""
    if loss == "l2":
        return z
    if loss == "huber":
        return jnp.where(z <= 1.0, z, 2.0 * jnp.sqrt(jnp.maximum(z, 1.0)) - 1.0)
    if loss == "soft_l1":
        return 2.0 * (jnp.sqrt(1.0 + z) - 1.0)
    return jnp.log1p(z)


def weight(loss: str, z):
    """The weight `rho'(z)` of a frame (1 for `l2` and near `z = 0`)."""
    if loss == "l2":
        return jnp.ones_like(z)
    if loss == "huber":
        return jnp.where(z <= 1.0, 1.0, 1.0 / jnp.sqrt(jnp.maximum(z, 1.0)))
    if loss == "soft_l1":
        return 1.0 / jnp.sqrt(1.0 + z)
    return 1.0 / (1.0 + z)


def curvature(loss: str, z):
    """`rho''(z)` (for the standard errors)."""
    if loss == "l2":
        return jnp.zeros_like(z)
    if loss == "huber":
        return jnp.where(z <= 1.0, 0.0, -0.5 * jnp.maximum(z, 1.0) ** -1.5)
    if loss == "soft_l1":
        return -0.5 * (1.0 + z) ** -1.5
    return -1.0 / (1.0 + z) ** 2


def frame_norms(res: Float[Array, "... K"]) -> Float[Array, "... M"]:
    """Squared norms `s_f` of each frame's whitened residuals, `res` laid out as
    `jsphere.identify.residuals` gives them: `(x (M), y (M), rotation (M, 3))`, `K = 5 M`."""
    M = res.shape[-1] // 5
    rot = res[..., 2 * M :].reshape(res.shape[:-1] + (M, 3))
    return res[..., :M] ** 2 + res[..., M : 2 * M] ** 2 + jnp.sum(rot * rot, axis=-1)


def per_value(w: Float[Array, "... M"]) -> Float[Array, "... K"]:
    """Frame values `(..., M)` spread over the residual layout `(..., 5 M)` of `frame_norms`."""
    return jnp.concatenate([w, w, jnp.repeat(w, 3, axis=-1)], axis=-1)


@eager_jit
def robust_cost(loss: str, res: Float[Array, "S T K"]) -> Float[Array, " S"]:
    """The robust cost `1/2 sum_f c^2 rho(s_f / c^2)` of every start (module docstring)."""
    return 0.5 * SCALE**2 * jnp.sum(rho(loss, frame_norms(res) / SCALE**2), axis=(1, 2))


@eager_jit
def reweigh(loss: str, res: Float[Array, "S T K"], J: Float[Array, "S T K Z"]):
    """The residuals and Jacobian of every start's trials (or segments) reweighted for `loss`:
    `(sqrt(w) res, sqrt(w) J)`, the weights per frame from the residuals themselves and held
    fixed in the Jacobian (module docstring)."""
    sw = per_value(jnp.sqrt(weight(loss, frame_norms(res) / SCALE**2)))
    return res * sw, J * sw[..., None]


@eager_jit
def reweigh_with_excess(loss: str, res: Float[Array, "S T K"], J: Float[Array, "S T K Z"]):
    """`reweigh(loss, res, J)` and, per start, the robust cost less the half sum of squares of
    the reweighted residuals `(S,)`: added to a cost computed from the reweighted residuals
    (multiple shooting's `assemble`), it gives the robust cost. One program for the three."""
    res_w, J_w = reweigh(loss, res, J)
    return res_w, J_w, robust_cost(loss, res) - 0.5 * jnp.sum(res_w * res_w, axis=(1, 2))


@eager_jit
def _frame_terms(loss: str, res: Float[Array, "... K"]):
    """Per frame of `res`: `s_f`, `z_f = s_f / c^2`, `rho'(z_f)` and `rho''(z_f)`."""
    s = frame_norms(res)
    z = s / SCALE**2
    return s, z, weight(loss, z), curvature(loss, z)


def frame_weights(loss: str, res) -> np.ndarray:
    """The weights `rho'(z_f)` `(..., M)` of the frames of whitened residuals `res (..., 5 M)`."""
    return np.asarray(_frame_terms(loss, to_jax(res))[2])


def variance_factor(loss: str, res: np.ndarray, counts: np.ndarray, n_par: int) -> float:
    """The variance factor `s2` of the weighted Gauss-Newton covariance (module docstring) from
    the unweighted whitened residuals `res (T, 5 M)` of the best start and the number of values
    each frame holds, `counts (T, M)` (0 for a frame not captured)."""
    s, z, w, d2 = (np.asarray(a) for a in _frame_terms(loss, to_jax(res)))
    held = counts > 0
    n = float(counts.sum())
    dof = max(n - n_par, 1.0)
    spread = float((w * w * s)[held].sum()) / dof
    psi = w + 2.0 * z * d2 / np.where(held, counts, 1.0)
    return spread * float(w[held].mean()) / float(psi[held].mean()) ** 2
