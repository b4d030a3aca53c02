"""Control by gaits (Section 4): prescribed `gamma(t)`, `omega_gamma(t)`; `Omega(t)` from the
control-free equation; torques `K(t)` and wheel rates `chi_dot(t)` as outputs.
"""

from __future__ import annotations

import inspect
import math
from typing import Callable, Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from .._runtime.arrays import as_array, under_jit
from .._runtime.checks import finite
from .._runtime.errors import InputError
from .._runtime.quick_compile import eager_jit
from ..controls import Constant
from ..model.dynamics import free_Omega_dot, required_torques
from ..model.kinematics import rest_attitude
from ..model.linalg import cross, matvec
from ..model.params import RobotParams, derive
from ..model.rotations import rotation_between, rotmat
from ..model.state import Flat, State
from ..numerics import trig
from ..solve.batched.components import gait_field_components, unit
from ..solve.batched.layout import Layout
from ..solve.field_args import FieldArgs
from ..solve.internal import rates as _rates
from ..solve.options import DEFAULT_TOLERANCES, SolverOptions, solver_options
from ..solve.segments import solve_segments
from ..solve.simulate import batch_engine_applies, output_times, run_solve
from ..solve.trajectory import Trajectory


def sincos(x, elementwise: bool = False):
    """`(sin x, cos x)` for the gaits: with `elementwise`, `jsphere.numerics.trig`'s
    elementwise polynomials (a batched solve's kinematics, where each trial evaluates its own);
    XLA's own functions otherwise (a single solve evaluates one of each per stage, and the
    polynomials cost it compile time: docs/decisions/sine-and-cosine-in-elementwise-arithmetic.md)."""
    return trig.sincos(x) if elementwise else (jnp.sin(x), jnp.cos(x))


def sin(x, elementwise: bool = False):
    """`sin x` as `sincos` chooses it."""
    return trig.sin(x) if elementwise else jnp.sin(x)


def cos(x, elementwise: bool = False):
    """`cos x` as `sincos` chooses it."""
    return trig.cos(x) if elementwise else jnp.cos(x)


class Profile(eqx.Module):
    """A function of time of jsphere's (`SinSquared`, `Smooth`, ...) whose sines and cosines
    may be evaluated elementwise: `profile(t, elementwise=True)` (`sincos`)."""

    def __call__(self, t, *, elementwise: bool = False):
        raise NotImplementedError


def at(f: Callable, t, elementwise: bool = False):
    """`f(t)`, with `elementwise` passed on where `f` is a `Profile` (a function of one's own
    evaluates its sines and cosines its own way)."""
    return f(t, elementwise=elementwise) if isinstance(f, Profile) else f(t)


def _real(x):
    """A float array of the default float dtype (strongly typed), so that Python floats and
    NumPy/JAX scalars give the same compiled function. Inside a `jit` a Python or NumPy value
    stays a NumPy array, a constant known while tracing (a gait built inside a `jit` keeps a
    known duration)."""
    dtype = x.dtype if hasattr(x, "dtype") and jnp.issubdtype(x.dtype, jnp.floating) else jnp.result_type(float)
    if not isinstance(x, (jax.Array, jax.core.Tracer)) and under_jit():
        return np.asarray(x, dtype)
    return as_array(x, dtype)


class SinSquared(Profile):
    """`amplitude * sin^2(pi t / period)`: the paper's tilt profile of (5.1), (5.3), (5.6).

    Starts and ends (at whole multiples of `period`) with zero value and zero rate, as the
    Proposition of Section 4 requires.
    """

    amplitude: Float[Array, ""] = eqx.field(converter=_real)
    period: Float[Array, ""] = eqx.field(converter=_real, default=1.0)

    def __call__(self, t, *, elementwise: bool = False):
        return self.amplitude * sin(jnp.pi * t / self.period, elementwise) ** 2


def _zero(t):
    return jnp.zeros_like(t)


def _duration(T, name: str):
    """A gait's duration `T` [s] (`_real`), checked positive and finite when concrete."""
    T = _real(T)
    if not isinstance(T, jax.core.Tracer) and not 0 < float(T) < math.inf:
        raise InputError(f"{name}.T must be a positive duration in seconds; got {float(T)}.")
    return T


class Gait(eqx.Module):
    """A manoeuvre of Section 4 on `[0, T]`, given by the Euler angles of (4.2) and the spin
    of the platform about the vertical:

        gamma(t) = Q_m (sin theta cos phi, sin theta sin phi, cos theta),   omega_gamma(t),

    with `Q_m` the rest attitude (the identity for the paper's robot). The platform's angular
    velocity follows as `omega = gamma omega_gamma + gamma_dot x gamma` (Proposition).

    `theta`, `phi`, `omega_gamma` are JAX-traceable functions of the gait's local time
    `t in [0, T]`; they may be equinox Modules holding arrays (as `SinSquared` does), so that
    gradients and vmap over gait parameters work. For the robot to start and end on
    stationary motions, `theta`, `theta_dot` and `omega_gamma` should vanish at 0 and T.
    """

    theta: Callable
    phi: Callable
    omega_gamma: Callable
    T: Float[Array, ""]

    def __init__(
        self, theta: Callable, phi: Callable | float = 0.0, omega_gamma: Callable | None = None, T: float = 2.0
    ):
        finite("Gait", "phi", phi, unit="rad")
        self.theta = theta
        self.phi = phi if callable(phi) else Constant(_real(phi))
        self.omega_gamma = omega_gamma if omega_gamma is not None else _zero
        self.T = _duration(T, "Gait")

    def gamma(self, Qm, t, *, elementwise: bool = False):
        """`gamma(t)` of (4.2), rotated to the robot's rest attitude by `Q_m` (`elementwise`:
        as `sincos`; a subclass's `gamma` need not take it)."""
        e = elementwise
        (st, ct), (sp, cp) = sincos(at(self.theta, t, e), e), sincos(at(self.phi, t, e), e)
        return matvec(Qm, jnp.stack([st * cp, st * sp, ct]))

    def kinematics(self, Qm, t):
        """`(gamma, omega, omega_dot)` at local time `t` (derivatives by forward-mode autodiff)."""

        def omega_fn(s):
            g, g_dot = jax.jvp(lambda u: self.gamma(Qm, u), (s,), (jnp.ones_like(s),))
            return g * self.omega_gamma(s) + cross(g_dot, g), g

        (omega, gamma), (omega_dot, _) = jax.jvp(omega_fn, (t,), (jnp.ones_like(t),))
        return gamma, omega, omega_dot

    def kinematics_components(self, Qm, t) -> tuple:
        """`kinematics` as a 9-tuple of scalars `(gamma, omega, omega_dot)`, for batched solves:
        under `vmap` every component is one contiguous vector (faster than the stacked
        3-vectors, `docs/performance.md`). A subclass that overrides
        `gamma` is differentiated through its own `gamma`. Its sines and cosines, and those of
        its `Profile`s, are `jsphere.numerics.trig`'s (`sincos(..., elementwise=True)`)."""
        if type(self).gamma is Gait.gamma:

            def gamma(u):
                (st, ct), (sp, cp) = sincos(at(self.theta, u, True), True), sincos(at(self.phi, u, True), True)
                v = (st * cp, st * sp, ct)
                return tuple(Qm[i, 0] * v[0] + Qm[i, 1] * v[1] + Qm[i, 2] * v[2] for i in range(3))
        else:
            takes = "elementwise" in inspect.signature(type(self).gamma).parameters

            def gamma(u):
                g = self.gamma(Qm, u, elementwise=True) if takes else self.gamma(Qm, u)
                return (g[0], g[1], g[2])

        def omega_fn(s):
            g, g_dot = jax.jvp(gamma, (s,), (jnp.ones_like(s),))
            og = at(self.omega_gamma, s, True)
            c = (
                g_dot[1] * g[2] - g_dot[2] * g[1],
                g_dot[2] * g[0] - g_dot[0] * g[2],
                g_dot[0] * g[1] - g_dot[1] * g[0],
            )
            return tuple(g[i] * og + c[i] for i in range(3)), g

        (omega, g), (omega_dot, _) = jax.jvp(omega_fn, (t,), (jnp.ones_like(t),))
        return g + omega + omega_dot


def _negative(x):
    """`-x`, by NumPy for a Python or NumPy value (no compiled program)."""
    return -x if isinstance(x, (jax.Array, jax.core.Tracer)) else -np.asarray(x)


def _check_sin2_gait(name, theta_max, phi, T, period):
    """The arguments of a sin^2 gait: finite numbers, `T` a whole multiple of `period`."""
    finite(name, "theta_max", theta_max, unit="rad")
    finite(name, "phi", phi, unit="rad")
    finite(name, "T", T, unit="s")
    finite(name, "period", period, positive=True, unit="s")
    if isinstance(T, jax.core.Tracer) or isinstance(period, jax.core.Tracer):
        return
    n = float(T) / float(period)
    if abs(n - round(n)) > 1e-9 or round(n) < 1:
        raise ValueError(
            f"{name}: T = {float(T)} s must be a whole multiple of the sin^2 period {float(period)} s, "
            "or gamma(T) != gamma(0) and the robot does not end on a stationary motion."
        )


def acceleration(theta_max: float = 0.1, phi: float = 0.0, T: float = 2.0, *, period: float = 1.0) -> Gait:
    """Acceleration (5.1): `theta = theta_max sin^2(pi t)`, `phi = phi_0`, `omega_gamma = 0`.

    For the paper's robot and `phi = 0`, accelerates from rest to `Omega = (0, 0.864, 0)` 1/s,
    i.e. rolling along the fixed `+X` axis at 0.1296 m/s.
    """
    _check_sin2_gait("acceleration", theta_max, phi, T, period)
    return Gait(theta=SinSquared(theta_max, period), phi=phi, T=T)


def braking(theta_max: float = 0.1, phi: float = 0.0, T: float = 2.0, *, period: float = 1.0) -> Gait:
    """Braking (5.3): `theta = -theta_max sin^2(pi t)`, `phi = phi_0`, `omega_gamma = 0`."""
    _check_sin2_gait("braking", theta_max, phi, T, period)
    return Gait(theta=SinSquared(_negative(theta_max), period), phi=phi, T=T)


def turn(theta_max: float = 0.1, phi: float = math.pi / 2, T: float = 2.0, *, period: float = 1.0) -> Gait:
    """Turn (5.6): `theta = theta_max sin^2(pi t)`, `phi = pi/2`, `omega_gamma = 0`: adds a
    velocity at right angles to the motion after (5.1)."""
    _check_sin2_gait("turn", theta_max, phi, T, period)
    return Gait(theta=SinSquared(theta_max, period), phi=phi, T=T)


# ----------------------------------------------------------------------- integration


def _gait_field(t, z, args: FieldArgs):
    """The flat state's rates under a gait (`args.control = (gait, Q_m)`): `gamma`, `omega`
    prescribed, `Omega` from the control-free sum of (3.4)."""
    p, d = args.params, args.derived
    gamma, omega, omega_dot = _gait_kinematics(t, args)
    Omega = z[Flat.Omega]
    Omega_dot = free_Omega_dot(p, d, gamma, omega, Omega, omega_dot)
    # positions use the prescribed gamma(t); q is integrated with the same omega(t)
    return _rates(p, d, z, rotmat(z[Flat.q]), gamma, omega, Omega, omega_dot, Omega_dot, omega - Omega)


def _gait_kinematics(t, args: FieldArgs):
    """`(gamma, omega, omega_dot)` the segment's gait prescribes at time `t`."""
    gait, Qm = args.control
    return gait.kinematics(Qm, t - args.t_start)


def _gait_inputs(t, args: FieldArgs):
    """`(gamma, omega, omega_dot)` the gait prescribes at time `t`, as a 9-tuple of scalars
    (the inputs of `_gait_field_soa`)."""
    gait, Qm = args.control
    return gait.kinematics_components(Qm, t - args.t_start)


def _gait_field_soa(t, y, args: FieldArgs, kin=None, adjoint=False):
    """`_gait_field` on a tuple of scalar components (`jsphere.solve.batched.components`), for
    batched solves; `kin`: the gait's `(gamma, omega, omega_dot)` as a 9-tuple, if the caller
    has evaluated it. (`adjoint`: the same field for the discrete adjoint.)"""
    kin = _gait_inputs(t, args) if kin is None else kin
    return gait_field_components(args.params, args.derived, kin, y, unit(t))


def _gait_outputs(t, z, args: FieldArgs):
    """`(omega, chi_dot, K)` at a saved state under a gait: `K` the torques it requires."""
    p, d = args.params, args.derived
    gamma, omega, omega_dot = _gait_kinematics(t, args)
    Omega = z[Flat.Omega]
    Omega_dot = free_Omega_dot(p, d, gamma, omega, Omega, omega_dot)
    K = required_torques(p, d, gamma, omega, Omega, omega_dot, Omega_dot)
    return omega, -matvec(d.Sk, omega - Omega), K


def _rolling_direction(gait: Gait, Qm):
    """Horizontal direction of the shell's angular velocity a gait produces: `Q_m (-sin phi,
    cos phi, 0)` at the gait's midpoint."""
    sp, cp = sincos(gait.phi(0.5 * gait.T))
    return matvec(Qm, jnp.stack([-sp, cp, jnp.zeros_like(sp)]))


#: Tolerances `(rtol, atol)` of `simulate_gaits` by the parameters' precision when none are
#: given (`jsphere.solve.simulate.tolerances`).
GAIT_TOLERANCES = {**DEFAULT_TOLERANCES, "float64": (1e-10, 1e-12)}


def simulate_gaits(
    params: RobotParams,
    gaits: Sequence[Gait],
    *,
    Omega0: Float[ArrayLike, "3"] = (0.0, 0.0, 0.0),
    alpha0: Float[ArrayLike, "3"] = (1.0, 0.0, 0.0),
    beta0: Float[ArrayLike, "3"] = (0.0, 1.0, 0.0),
    x0: float = 0.0,
    y0: float = 0.0,
    ts: Float[ArrayLike, " T"] | None = None,
    reset: bool | Sequence = False,
    rate: float = 100.0,
    options: SolverOptions | None = None,
    **shortcuts,
) -> Trajectory:
    """Execute a sequence of gaits (Section 4) and return the motion, torques and wheel rates.

    Within each gait, `gamma(t)` and `omega(t)` are prescribed; `Omega(t)` is integrated from
    the control-free sum of the two equations of (3.4); `K(t)` follows from the second
    equation (least-norm for `N > 3` wheels); `chi_dot(t)` from (2.4); `x, y` from (2.2),
    (2.3); `alpha, beta` from the Poisson equations.

    **Arguments:**
    - `gaits`: a list of `Gait`s, executed one after the other.
    - `Omega0, alpha0, beta0, x0, y0`: the initial stationary motion ((5.2) by default: at rest,
      platform axes = fixed axes). `alpha0 x beta0` must equal the first gait's `gamma(0)`.
    - `ts`: global output times. Default: each gait sampled at `rate` Hz on its own
      `[start, end]`, so a boundary time appears twice (left and right limits of `K`).
    - `reset`: `False` (default): each gait starts from the previous gait's end state.
      `True`: the paper's (5.4)/(5.7) convention before every gait after the first: `alpha,
      beta` are reset to `alpha0, beta0`, and `Omega` is replaced by its projection onto the
      span of the rolling directions of the gaits executed so far (dropping the spin about
      the vertical and the sideways drift caused by the wheels' inertia). A sequence (one
      entry per boundary) mixes `None`/`False` (continue), `True` (as above), or an explicit
      `Omega` 3-vector (with `alpha, beta` reset too), e.g. `(-0.868, 0.852, 0)` of (5.7).
    - `options`: a `SolverOptions`, its fields also keywords, as in `simulate`; default
      tolerances 1e-10, 1e-12 (tight enough for 1e-8 agreement of `Omega, K`), with float32
      parameters 1e-5, 1e-7 (`GAIT_TOLERANCES`).

    Returns a `Trajectory`; `segment` tells which gait each sample belongs to.
    """
    gaits = list(gaits)
    if not gaits or not all(isinstance(g, Gait) for g in gaits):
        raise TypeError(
            "simulate_gaits: gaits must be a non-empty list of jsphere.Gait (e.g. [acceleration(), braking()])."
        )
    resets = _reset_data(reset, len(gaits) - 1, params.R0.dtype)
    opts = solver_options(options, where="simulate_gaits", **shortcuts)
    dt = params.R0.dtype
    tol = opts.tolerances(dt, GAIT_TOLERANCES, where="simulate_gaits")
    initial = tuple(as_array(v, dt) for v in (alpha0, beta0, Omega0, x0, y0))
    _check_start(params, gaits[0], initial[0], initial[1])

    ts_out = output_times(ts, dt, "simulate_gaits") if ts is not None else _default_times(gaits, rate, dt)
    # gait coefficients in the parameters' precision (float32 robots stay float32)
    gaits = jax.tree_util.tree_map(
        lambda x: x.astype(dt) if eqx.is_array(x) and jnp.issubdtype(x.dtype, jnp.floating) and x.dtype != dt else x,
        gaits,
    )
    args = (params, gaits, initial, ts_out, resets)
    return run_solve("simulate_gaits", _simulate_gaits, args, opts, tol, batch_engine_applies(opts))


def _default_times(gaits, rate, dt):
    """Each gait sampled at `rate` Hz on its own `[start, end]`."""
    if any(isinstance(g.T, jax.core.Tracer) for g in gaits):
        raise ValueError("simulate_gaits: pass `ts` when gait durations are traced (under jit/grad).")
    starts = np.cumsum([0.0] + [float(g.T) for g in gaits])[:-1]
    grids = [a + np.linspace(0.0, float(g.T), max(2, int(round(float(g.T) * rate)) + 1)) for g, a in zip(gaits, starts)]
    return as_array(np.concatenate(grids), dt)


def _reset_data(reset, nb: int, dt):
    """`simulate_gaits`' `reset` at its `nb` gait boundaries as data `(modes, values)`, so that
    there is one compiled function per number of gaits: mode 0 continue, 1 project `Omega`
    (`reset=True`), 2 the explicit `Omega` of `values`."""
    resets = [bool(reset)] * nb if isinstance(reset, (bool, np.bool_)) else list(reset)
    if len(resets) != nb:
        raise ValueError(f"simulate_gaits: reset needs one entry per gait boundary ({nb}); got {len(resets)}.")
    for i, r in enumerate(resets):
        if not (r is None or isinstance(r, bool)) and np.shape(r) != (3,):
            raise ValueError(
                f"simulate_gaits: reset[{i}] must be None, True/False or an Omega 3-vector; got shape {np.shape(r)}."
            )
    modes = as_array([0 if (r is None or r is False) else 1 if r is True else 2 for r in resets], np.int32)
    values = as_array(
        [np.zeros(3) if (r is None or isinstance(r, bool)) else r for r in resets] if nb else np.zeros((0, 3)), dt
    )
    if values.shape != (nb, 3):
        raise ValueError(f"simulate_gaits: an explicit reset must be an Omega 3-vector; got shapes {values.shape}.")
    return modes, values


@eqx.filter_jit  # one compiled program per kind of gait, not one per operation
def _start_gamma(r_m, gait: Gait):
    """The gait's `gamma(0)` for a robot whose rest attitude is `gamma_m = -r_m/|r_m|` (2.5)."""
    Qm = rotation_between(jnp.array([0.0, 0.0, 1.0], r_m.dtype), -r_m / jnp.linalg.norm(r_m))
    return gait.gamma(Qm, jnp.zeros((), r_m.dtype))


def _check_start(params, gait, alpha0, beta0) -> None:
    """With concrete inputs: `alpha0, beta0` orthonormal and `alpha0 x beta0` equal to the first
    gait's `gamma(0)` (NumPy, and one compiled call for the gait's `gamma(0)`: no eager JAX
    operations, each of which would be a small program to compile or load from the cache)."""
    if any(isinstance(v, jax.core.Tracer) for v in (alpha0, beta0, params.r_m)):
        return
    a, b = np.asarray(alpha0, np.float64), np.asarray(beta0, np.float64)
    if abs(np.linalg.norm(a) - 1) > 1e-6 or abs(np.linalg.norm(b) - 1) > 1e-6 or abs(a @ b) > 1e-6:
        raise ValueError(f"simulate_gaits: alpha0 and beta0 must be orthonormal; got {a}, {b}.")
    if any(isinstance(v, jax.core.Tracer) for v in jax.tree_util.tree_leaves(gait)):
        return  # traced gait coefficients (a gradient with respect to the gait): gamma(0) is not known here
    try:
        g0 = np.asarray(_start_gamma(params.r_m, gait), np.float64)
    except (
        TypeError,
        jax.errors.ConcretizationTypeError,
        jax.errors.TracerArrayConversionError,
    ):  # traced gait coefficients
        return
    gamma0 = np.cross(a, b)
    if np.max(np.abs(gamma0 - g0)) > 1e-6:
        raise ValueError(
            f"simulate_gaits: alpha0 x beta0 = {gamma0} but the first gait starts at gamma(0) = {g0}; a gait "
            "must start from the rest attitude gamma = -r_m/|r_m| (Proposition of Section 4)."
        )


@eager_jit
def _simulate_gaits(
    params, gaits, initial, ts_out, resets, solver, rtol, atol, max_steps, adjoint, layout=Layout.FLAT, derived=None
):
    dt = params.R0.dtype
    d = derive(params) if derived is None else derived
    alpha0, beta0, Omega0, x0, y0 = initial
    state0 = State.from_axes(params, alpha0, beta0, Omega=Omega0, x=x0, y=y0)
    Qm = rotation_between(jnp.array([0.0, 0.0, 1.0], dt), rest_attitude(params))
    starts, t = [], jnp.asarray(0.0, dt)
    for g in gaits:
        starts.append(t)
        t = t + jnp.asarray(g.T, dt)
    segments = [((g, Qm), a, a + jnp.asarray(g.T, dt)) for g, a in zip(gaits, starts)]
    q0 = state0.q
    modes, values, projectors = _boundary_resets(gaits, Qm, resets, dt)

    def jump_fn(k, a, z, control):
        gait, _ = control
        _, omega_start, _ = gait.kinematics(Qm, jnp.zeros_like(a))
        z = Flat.replace(z, omega=omega_start)
        mode = modes[k]
        Omega = jnp.where(mode == 1, matvec(projectors[k], z[Flat.Omega]), values[k])
        reset_z = Flat.replace(z, q=q0, Omega=Omega)
        return jnp.where(mode == 0, z, reset_z)

    traj = solve_segments(
        _gait_field,
        _gait_outputs,
        params,
        d,
        segments,
        state0.flatten(),
        ts_out,
        (solver, rtol, atol, max_steps, adjoint),
        jump_fn=jump_fn,
        layout=layout,
        component_field=_gait_field_soa if layout.components else None,
        component_control=_gait_inputs,
    )
    # report the prescribed gamma(t) (the integrated one agrees to the solver tolerance)
    gam = jax.vmap(lambda t, k: _prescribed_gamma(gaits, Qm, starts, t, k))(ts_out, traj.segment)
    return eqx.tree_at(lambda tr: tr.gamma, traj, gam)


def _boundary_resets(gaits, Qm, resets, dt):
    """Per gait (the first one's entries unused): the reset mode and explicit value at its start
    (`_reset_data`), and the projector onto the rolling directions of the gaits before it."""
    P, projectors = jnp.zeros((3, 3), dt), [jnp.zeros((3, 3), dt)]
    for g in gaits[:-1]:
        dvec = _rolling_direction(g, Qm)
        u = dvec - matvec(P, dvec)
        nu = jnp.sum(u * u)
        P = P + jnp.where(nu > 1e-12, 1.0, 0.0) * jnp.outer(u, u) / jnp.where(nu > 1e-12, nu, 1.0)
        projectors.append(P)
    modes = jnp.concatenate([jnp.zeros((1,), jnp.int32), resets[0]])
    values = jnp.concatenate([jnp.zeros((1, 3), dt), resets[1]])
    return modes, values, jnp.stack(projectors)


def _prescribed_gamma(gaits, Qm, starts, t, k):
    branches = [lambda t, g=g, a=a: g.gamma(Qm, t - a) for g, a in zip(gaits, starts)]
    return jax.lax.switch(k, branches, t)
