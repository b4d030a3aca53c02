"""Parameterised gait families for planning: smooth tilt and spin profiles whose
start and end are stationary motions by construction (Proposition of Section 4).

A `TiltGait` prescribes the platform's vertical through a horizontal *tilt vector*
`u(t) = (u_1, u_2)` [rad] instead of the Euler angles `theta, phi` of (4.2):

    gamma(t) = Q_m (sin|u| u_1/|u|, sin|u| u_2/|u|, cos|u|),

i.e. `theta = |u|`, `phi = atan2(u_2, u_1)`, but smooth through `u = 0` (the paper's (4.2)
with a varying `phi` is singular there). The paper's gaits (5.1), (5.3), (5.6) are the special
case `u = theta(t) (cos phi_0, sin phi_0)`.

Profiles (`Smooth`) are `sin^p(pi s) sum_k c_k cos(k pi s)`, `s = t/T`: with `p = 2` value
and rate vanish at both ends (the Proposition's `gamma = gamma_m`, `gamma_dot = 0`,
`omega_gamma = 0`), with `p = 3` also the second derivative, so that `K(t)` starts and ends
at zero instead of jumping (`theta_ddot(0) != 0` makes the paper's torques jump).
`sin^2(2 pi s) = 2 sin^2(pi s) (1 + cos 2 pi s)`: the paper's two-hump profile on `[0, 2]` is
exactly `c = (2 theta_max, 0, 2 theta_max)` with `p = 2`.
"""

from __future__ import annotations

from collections.abc import Callable

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, Float

from .._runtime.checks import finite
from ..model.linalg import matvec
from .gaits import Gait, Profile, _duration, _real, _zero, at, cos, sin, sincos


class Smooth(Profile):
    """`sin^p(pi t/T) sum_k c_k cos(k pi t/T)` on `[0, T]` (zero outside the sum's support is
    not needed: gaits are evaluated on `[0, T]` only).

    `coeffs (..., n)`: one row of `n` Fourier-cosine coefficients per output component [units
    of the profile: rad for a tilt, rad/s for a spin]; `T` [s]; `power` (static): 2 makes the
    value and first derivative vanish at both ends, 3 also the second derivative.
    """

    coeffs: Float[Array, "... n"]
    T: Float[Array, ""] = eqx.field(converter=_real)
    power: int = eqx.field(static=True, default=3)

    def __call__(self, t, *, elementwise: bool = False):
        s = t / self.T
        k = jnp.arange(self.coeffs.shape[-1], dtype=self.coeffs.dtype)
        basis = cos(jnp.pi * k * s, elementwise) * sin(jnp.pi * s, elementwise) ** self.power
        return self.coeffs @ basis


def _sinc_cos(s, elementwise: bool = False):
    """`(sin r / r, cos r)` as smooth functions of `s = r^2` (Taylor series below `s = 1e-3`,
    so that derivatives of every order are finite at `r = 0`; `elementwise`: as `sincos`)."""
    small = s < 1e-3
    ss = jnp.where(small, 1.0, s)
    r = jnp.sqrt(ss)
    sin_r, cos_r = sincos(r, elementwise)
    sinc = jnp.where(small, 1.0 - s / 6 + s**2 / 120 - s**3 / 5040, sin_r / r)
    return sinc, jnp.where(small, 1.0 - s / 2 + s**2 / 24 - s**3 / 720, cos_r)


def tilt_to_gamma(u: Float[Array, " 2"], elementwise: bool = False) -> Float[Array, " 3"]:
    """`gamma` (before the rest-attitude rotation `Q_m`) for the tilt vector `u` [rad]:
    `(sin|u| u/|u|, cos|u|)`, i.e. (4.2) with `theta = |u|`, `phi = atan2(u_2, u_1)`
    (`elementwise`: as `jsphere.gaits.gaits.sincos`)."""
    sinc, cos_u = _sinc_cos(u[0] ** 2 + u[1] ** 2, elementwise)
    return jnp.stack([sinc * u[0], sinc * u[1], cos_u])


class _TiltAngle(Profile):
    tilt: Callable

    def __call__(self, t, *, elementwise: bool = False):
        u = at(self.tilt, t, elementwise)
        sinc, cos_u = _sinc_cos(u[0] ** 2 + u[1] ** 2, elementwise)
        return jnp.arctan2(sinc * jnp.sqrt(u[0] ** 2 + u[1] ** 2), cos_u)


class _TiltDirection(Profile):
    tilt: Callable

    def __call__(self, t, *, elementwise: bool = False):
        u = at(self.tilt, t, elementwise)
        return jnp.arctan2(u[1], u[0])


class TiltGait(Gait):
    """A gait (Section 4) given by the tilt vector `u(t)` [rad] and the spin `omega_gamma(t)`
    [rad/s] of the platform about the vertical, on `[0, T]`:
    `gamma(t) = Q_m tilt_to_gamma(u(t))`, `omega = gamma omega_gamma + gamma_dot x gamma`.

    `theta` and `phi` are kept as views (`|u|`, `atan2(u_2, u_1)`) for plots and for
    `simulate_gaits`' checks; the motion uses `gamma` only. A stationary start and end need
    `u, u_dot, omega_gamma = 0` at 0 and T (true for `Smooth` profiles).
    """

    tilt: Callable

    def __init__(self, tilt: Callable, omega_gamma: Callable | None = None, T: float = 2.0):
        self.tilt = tilt
        self.theta = _TiltAngle(tilt)
        self.phi = _TiltDirection(tilt)
        self.omega_gamma = omega_gamma if omega_gamma is not None else _zero
        self.T = _duration(T, "TiltGait")

    def gamma(self, Qm, t, *, elementwise: bool = False):
        """`gamma(t) = Q_m tilt_to_gamma(u(t))`."""
        return matvec(Qm, tilt_to_gamma(at(self.tilt, t, elementwise), elementwise))


def smooth_gait(
    tilt_coeffs: Float[Array, "2 n"],
    spin_coeffs: Float[Array, " m"] | None = None,
    T: float = 4.0,
    *,
    power: int = 3,
) -> TiltGait:
    """A `TiltGait` with `Smooth` profiles: `u(t) = sin^p(pi s) sum_k a_k cos(k pi s)` (one
    row of `tilt_coeffs` [rad] per horizontal axis of the platform) and
    `omega_gamma(t) = sin^p(pi s) sum_k b_k cos(k pi s)` (`spin_coeffs` [rad/s]), `s = t/T`.

    Traceable in every coefficient and in `T` (pass `ts` to `simulate_gaits` when `T` is traced).
    """
    if power not in (2, 3):
        raise ValueError(f"smooth_gait: power must be 2 (C1 ends) or 3 (C2 ends, torques start at 0); got {power}.")
    finite("smooth_gait", "tilt_coeffs", tilt_coeffs, unit="rad")
    if spin_coeffs is not None:
        finite("smooth_gait", "spin_coeffs", spin_coeffs, unit="rad/s")
    finite("smooth_gait", "T", T, positive=True, unit="s")
    tilt_coeffs = jnp.asarray(tilt_coeffs)
    if tilt_coeffs.ndim != 2 or tilt_coeffs.shape[0] != 2:
        raise ValueError(f"smooth_gait: tilt_coeffs must have shape (2, n); got {tilt_coeffs.shape}.")
    T = _real(T)
    spin = None if spin_coeffs is None else Smooth(jnp.asarray(spin_coeffs), T, power)
    return TiltGait(Smooth(tilt_coeffs, T, power), spin, T)


def paper_gait(theta_max: float, phi: float = 0.0, T: float = 2.0) -> TiltGait:
    """The paper's profile `theta_max sin^2(pi t)` on `[0, T]` (T a whole number of seconds)
    in direction `phi`, as a member of the `Smooth` family (`p = 2`): `sin^2(pi t) =
    sin^2(pi s) * (sum of cosines)` with `s = t/T`. Equal to `acceleration(theta_max, phi, T)`
    (test `test_paper_gaits_are_special_cases`)."""
    finite("paper_gait", "theta_max", theta_max, unit="rad")
    finite("paper_gait", "phi", phi, unit="rad")
    finite("paper_gait", "T", T, positive=True, unit="s")
    n = round(float(T))
    # sin^2(n pi s) / sin^2(pi s) = (sin(n x)/sin x)^2, x = pi s, a cosine polynomial of degree 2(n-1)
    # with coefficients c_0 = n, c_{2j} = 2 (n - j)   (Fejer kernel)
    c = jnp.zeros(2 * n - 1).at[0].set(n)
    for j in range(1, n):
        c = c.at[2 * j].set(2.0 * (n - j))
    sp, cp = sincos(_real(phi))
    direction = jnp.stack([cp, sp])
    coeffs = _real(theta_max) * direction[:, None] * c[None, :]
    return TiltGait(Smooth(coeffs, T, 2), None, T)
