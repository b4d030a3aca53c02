"""The Fisher information of the free parameters that a set of input programmes gives, and the
D-optimal criterion.

Model of a trial (as the fit's, `jsphere.identify.residuals.trial_model`): the robot starts
from its rest attitude `q_m` turned by a small rotation `rot0`, at `(x0, y0)`, with the shell
rate `Omega(0)` and, with torque inputs, the platform rate `omega(0)`; these are the trial's
nuisance values `nu` (`jsphere.identify.data.nuisance_names`), as in the fit. The poses are
sampled at `rate` [Hz] and whitened as the fit's residuals:

    r = ((x - x*) / sigma_pos, (y - y*) / sigma_pos, Log(q*^-1 q) / sigma_rot)

(`*`: the pose at the design's own parameters, so `r = 0` there). For onboard sensors
(`Noise.mounting`, `jsphere.identify.residuals.onboard_model`) the trial starts at rest
(`State.at_rest` of the parameters) and the outputs are the IMU's and the encoders' readings

    r = ((g - g*) / sigma_gyro, (a - a*) / sigma_acc, (chi - chi(0) - (chi - chi(0))*) / sigma_encoder)

(`g, a = imu_readings(p, mounting, gamma, omega, Omega, K)`), and `nu` are the trial's six IMU
biases and `N` encoder offsets: they add to the readings, so their columns of `J_t` are
constant, `1 / sigma` in their channel's rows. `J_t = d r / d(theta, nu_t)`
(forward mode, `jax.jacfwd`) gives per trial the blocks `H = J_t^T J_t`; the information of
`theta` with every trial's nuisance values eliminated is the Schur complement

    F = sum_t (Hgg_t - Hgn_t Hnn_t^-1 Hng_t)

(`jsphere.numerics.lm.marginal_information`), mapped to the physical values `v` of the free
names, `F_v = A^-T F A^-1`, `A = d v / d theta`. The predicted covariance of `v` is `F_v^-1`
(the fit's, with noise levels that are right: `s^2 = 1`) and the D-optimal criterion is

    Phi = log det(S F_v S),    S = diag(max(|v|, 0.1 scale))

(the information of the relative values: the same units as the fit's scaled covariance; the
scaling adds a constant, so it does not change the optimum).

Inside the optimisation each trial is integrated by classical RK4 on a fixed grid (`substeps`
steps per sample) with the simulator's own vector fields (`jsphere.solve.fields`, (3.4), (3.5),
(2.2)-(2.4)): a fixed amount of work, whose forward-mode Jacobian reverse mode differentiates
again (`jax.grad` of `Phi`). The reported standard errors come from the fit's own Jacobian at the
capture rate (`jsphere.design.prediction.fit_information`).
"""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from ..controls import Torques, WheelSpeeds
from ..identify.data import nuisance_names
from ..identify.free import FreeParams
from ..model.kinematics import relative_rate_from_wheel_speeds
from ..model.params import RobotParams, derive
from ..model.rotations import quat_conj, quat_exp, quat_log, quat_mul, rotmat
from ..model.sensors import Mounting, imu_readings
from ..model.state import Flat, State
from ..solve.field_args import FieldArgs
from ..solve.fixed_grid import Rollout, integrate
from ..solve.internal import torque_field, torque_outputs, wheel_field, wheel_outputs
from .inputs import Programme, Spec, coefficients, programme

#: the onboard channels' noise levels: gyro [rad/s], accelerometer [m/s^2] per axis, and the
#: rounding of a 4096-count encoder [rad], one count / sqrt(12)
ONBOARD_SIGMAS = (0.003, 0.03, 2 * math.pi / 4096 / math.sqrt(12))


class Noise(eqx.Module):
    """The sensors' noise levels: the capture's `sigma_pos` [m] per coordinate, `sigma_rot` [rad]
    per axis; with an IMU `mounting` (onboard sensors) the gyro's, the accelerometer's and the
    encoders' `sigma_onboard` (`ONBOARD_SIGMAS`'s units) instead."""

    sigma_pos: float = 1e-3
    sigma_rot: float = float(np.radians(0.5))
    mounting: Mounting | None = None
    sigma_onboard: tuple[float, float, float] = ONBOARD_SIGMAS


class Grid(eqx.Module):
    """The optimisation's model grid (static): `rate` [Hz] of the sampled poses, RK4 `substeps`
    per sample."""

    rate: float = eqx.field(static=True, default=20.0)
    substeps: int = eqx.field(static=True, default=2)

    def times(self, duration: float) -> np.ndarray:
        n = max(int(round(duration * self.rate)), 1)
        return np.linspace(0.0, duration, n + 1)


def initial_state(p: RobotParams, kind: str, nu, q_rest, u0) -> State:
    """The initial state of nuisance values `nu` (`trial_model`'s): the rest attitude `q_rest`
    turned by `rot0 = nu[3:6]`, `Omega(0) = nu[0:3]`, `(x0, y0) = nu[6:8]`, and `omega(0) =
    nu[8:11]` (torques) or `Omega(0) + w(u0)` (wheel speeds, from the command by (2.4))."""
    dt = p.R0.dtype
    Omega = nu[0:3]
    omega = Omega + relative_rate_from_wheel_speeds(p, u0) if kind == "wheel_speeds" else nu[8:11]
    return State(
        q=quat_mul(q_rest, quat_exp(nu[3:6])),
        q_shell=jnp.array([1.0, 0.0, 0.0, 0.0], dt),
        omega=omega,
        Omega=Omega,
        x=nu[6],
        y=nu[7],
        chi=jnp.zeros(p.n_wheels, dt),
    )


def rk4_rollout(p: RobotParams, kind: str, prog: Programme, nu, q_rest, grid: Grid) -> Rollout:
    """Integrate one trial by classical RK4 (`jsphere.solve.fixed_grid`, `grid.substeps` steps per
    sample interval, the attitude quaternion normalised after each) with the
    simulator's vector field of `kind` (pure JAX: jit, vmap, jacfwd and grad work)."""
    dt = p.R0.dtype
    d = derive(p)
    T = prog.duration
    ts = jnp.asarray(grid.times(T), dt)
    control = Torques(prog) if kind == "torques" else WheelSpeeds(prog)
    field = torque_field if kind == "torques" else wheel_field
    args = FieldArgs(params=p, derived=d, control=control)
    z0 = initial_state(p, kind, nu, q_rest, prog(jnp.zeros((), dt))).flatten().astype(dt)
    gm = -p.r_m / jnp.linalg.norm(p.r_m)

    def unit_q(z):
        return z.at[Flat.q].set(z[Flat.q] / jnp.linalg.norm(z[Flat.q]))

    zs = integrate(lambda t, z: field(t, z, args), z0, ts, substeps=grid.substeps, project=unit_q)

    def tilt(z):
        c = jnp.clip(jnp.dot(rotmat(z[Flat.q])[2], gm), -1.0, 1.0 - 1e-15)
        return jnp.arccos(c)

    outputs = torque_outputs if kind == "torques" else wheel_outputs
    omega, chi_dot, K = jax.vmap(lambda t, z: outputs(t, z, args))(ts, zs)
    # the platform's rate of the mode's outputs (wheel speeds: of the command, (2.4)), as `simulate`'s
    zs = zs.at[:, Flat.omega].set(omega)
    return Rollout(ts=ts, zs=zs, chi_dot=chi_dot, K=K, tilt=jax.vmap(tilt)(zs))


def whitened(p: RobotParams, ro: Rollout, noise: Noise) -> Float[Array, " R"]:
    """The whitened residuals of a rollout against itself at the design point (value 0, the fit's
    Jacobian): positions / `sigma_pos`, `Log(q*^-1 q)` / `sigma_rot`; with onboard sensors the
    gyro's, the accelerometer's and the encoders' readings (module docstring) / their sigmas."""
    sg = jax.lax.stop_gradient
    if noise.mounting is not None:
        R = rotmat(ro.q)
        gyro, acc = imu_readings(p, noise.mounting, R[:, 2], ro.zs[:, Flat.omega], ro.Omega, ro.K)
        chi = ro.zs[:, Flat.chi] - ro.zs[:1, Flat.chi]
        return jnp.concatenate([((y - sg(y)) / s).reshape(-1) for y, s in zip((gyro, acc, chi), noise.sigma_onboard)])
    ex = (ro.x - sg(ro.x)) / noise.sigma_pos
    ey = (ro.y - sg(ro.y)) / noise.sigma_pos
    er = quat_log(quat_mul(quat_conj(sg(ro.q)), ro.q)) / noise.sigma_rot
    return jnp.concatenate([ex, ey, er.reshape(-1)])


def marginal(J: Float[Array, "T R Q"], P: int) -> Float[Array, "P P"]:
    """`F = sum_t (Hgg_t - Hgn_t Hnn_t^-1 Hng_t)` from the per-trial Jacobians `J (T, R, P+n)`."""
    H = jnp.einsum("tri,trj->tij", J, J)
    Hgg, Hgn, Hnn = H[:, :P, :P], H[:, :P, P:], H[:, P:, P:]
    n = Hnn.shape[-1]
    # a tiny ridge keeps a nuisance block that a programme leaves singular (no motion) solvable
    ridge = 1e-12 * (jnp.trace(Hnn, axis1=1, axis2=2)[:, None, None] / n + 1e-300) * jnp.eye(n, dtype=J.dtype)
    X = jnp.linalg.solve(Hnn + ridge, jnp.swapaxes(Hgn, 1, 2))
    F = jnp.sum(Hgg - Hgn @ X, axis=0)
    return 0.5 * (F + F.T)


class Free:
    """`FreeParams` as a static field: equal (and hashed) by its slots, the names and transforms
    that are all a compiled criterion depends on, so that designs with the same free names share
    one compilation."""

    def __init__(self, free: FreeParams):
        self.params = free

    def __hash__(self) -> int:
        return hash(self.params.slots)

    def __eq__(self, other) -> bool:
        return isinstance(other, Free) and other.params.slots == self.params.slots


class Problem(eqx.Module):
    """What the criterion of a design depends on besides its coefficients: the free parameters
    at the design's values (`theta0`, the map to physical values), the nuisance values at rest,
    the sensors and their noise levels (`noise`) and the model grid."""

    static_free: Free = eqx.field(static=True)
    base: RobotParams
    spec: Spec
    noise: Noise
    grid: Grid
    theta0: Float[Array, " P"]
    q_rest: Float[Array, "4"]

    @property
    def free(self) -> FreeParams:
        return self.static_free.params

    @property
    def kind(self) -> str:
        return self.spec.trial_kind

    @property
    def onboard(self) -> bool:
        return self.noise.mounting is not None

    @property
    def n_nu(self) -> int:
        return 6 + self.base.n_wheels if self.onboard else len(nuisance_names(self.kind))

    def scale(self) -> Float[Array, " P"]:
        """`S`: the scale of each physical value (`|v|`, at least a tenth of its field's size)."""
        v = self.free.physical(self.theta0)
        return jnp.maximum(jnp.abs(v), 0.1 * jnp.asarray(self.free.scales(), v.dtype))

    def trial_jacobian(self, c: Float[Array, "N F2"]) -> tuple[Float[Array, "R Q"], Rollout]:
        """One trial's whitened Jacobian `d r / d(theta, nu)` and its rollout at the design point."""
        P = self.free.size
        prog = programme(c, self.spec)
        dt, n_pose = self.theta0.dtype, len(nuisance_names(self.kind))

        def r(w):
            p = self.free.to_params(w[:P], self.base)
            # onboard: from the rest of `p`, the pose nuisance values at 0
            nu, q0 = (jnp.zeros(n_pose, dt), State.at_rest(p).q) if self.onboard else (w[P:], self.q_rest)
            ro = rk4_rollout(p, self.kind, prog, nu, q0, self.grid)
            return whitened(p, ro, self.noise), ro

        if not self.onboard:
            return jax.jacfwd(r, has_aux=True)(jnp.concatenate([self.theta0, jnp.zeros(self.n_nu, dt)]))
        J, ro = jax.jacfwd(r, has_aux=True)(self.theta0)
        M, widths = ro.ts.shape[0], (3, 3, self.base.n_wheels)
        offsets = [jnp.tile(jnp.eye(c, dtype=dt), (M, 1)) / s for c, s in zip(widths, self.noise.sigma_onboard)]
        return jnp.concatenate([J, jax.scipy.linalg.block_diag(*offsets)], axis=1), ro

    def information(self, z: Float[Array, " V"]) -> tuple[Float[Array, "P P"], Rollout]:
        """`S F_v S` (module docstring) of the programmes `z`, and the trials' rollouts."""
        J, ro = jax.vmap(self.trial_jacobian)(coefficients(z, self.spec))
        F = marginal(J, self.free.size)
        A = jax.jacfwd(self.free.physical)(self.theta0)
        Ainv = jnp.linalg.inv(A)
        S = self.scale()
        Fv = Ainv.T @ F @ Ainv
        return S[:, None] * Fv * S[None, :], ro


def problem(params: RobotParams, free: FreeParams, spec: Spec, noise: Noise, grid: Grid) -> Problem:
    """The `Problem` of a design at `params` (the free names' values and transforms of `free`)."""
    dt = params.R0.dtype
    return Problem(
        static_free=Free(free),
        base=params,
        spec=spec,
        noise=noise,
        grid=grid,
        theta0=jnp.asarray(free.theta0, dt),
        q_rest=State.at_rest(params).q,
    )
