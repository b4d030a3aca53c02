"""The standard errors a fit would report for input programmes: the fit's own Jacobian
(`jsphere.identify.residuals`, the adaptive solver in forward mode: `trial_model` of captured
poses, or `onboard_model` of the onboard sensors' readings at `ONBOARD_TOLERANCES`) on
noise-free trials of the programmes at the capture rate, and its covariance
(`jsphere.identify.report`, with `s^2 = 1`: noise levels that are right)."""

from __future__ import annotations

import math

import jax.numpy as jnp
import numpy as np

from .._runtime.errors import SolverFailure
from ..capture.onboard import OnboardTrial
from ..capture.trial import Trial
from ..controls import Sampled, Torques, WheelSpeeds
from ..identify.data import pack_trials
from ..identify.free import FreeParams
from ..identify.internal import covariance, fit_functions
from ..identify.onboard import pack_onboard
from ..identify.options import ONBOARD_TOLERANCES
from ..model.params import RobotParams
from ..model.sensors import Mounting, imu_readings
from ..model.state import State
from ..solve.simulate import simulate
from .information import Noise

#: the fit's default ODE tolerances and step limit (`jsphere.fit`)
RTOL, ATOL, MAX_STEPS = 1e-6, 1e-8, 16384


def noise_free_trial(params, kind: str, t: np.ndarray, u: np.ndarray, name: str, mounting: Mounting | None = None):
    """The trial a capture at the times `t` would record without noise (with an IMU `mounting`:
    the `OnboardTrial` its IMU and encoders would, without noise, biases or rounding): the robot
    at rest at the origin driven by the table `(t, u)` (cubic, as the fit interpolates it); and
    the largest wheel rate [rad/s] and platform tilt from its rest attitude [rad] at those
    times, as the accurate solver (rtol 1e-10) integrates them."""
    table = Sampled(jnp.asarray(t), jnp.asarray(u), "cubic")
    controls = Torques(table) if kind == "torques" else WheelSpeeds(table)
    tr = simulate(params, State.at_rest(params), controls, float(t[-1]), ts=t, rtol=1e-10, atol=1e-12)
    if mounting is None:
        trial = Trial(t, np.asarray(tr.x), np.asarray(tr.y), np.asarray(tr.q), u, kind, None, name=name)
    else:
        gyro, acc = imu_readings(params, mounting, tr.gamma, tr.omega, tr.Omega, tr.K)
        chi = np.asarray(tr.chi - tr.chi[:1])
        trial = OnboardTrial(t, np.asarray(gyro), np.asarray(acc), chi, u, kind, name=name)
    r_m = np.asarray(params.r_m, np.float64)
    cos_tilt = np.asarray(tr.gamma, np.float64) @ (-r_m / np.linalg.norm(r_m))
    tilt = float(np.max(np.arccos(np.clip(cos_tilt, -1.0, 1.0))))
    return trial, (float(np.max(np.abs(np.asarray(tr.chi_dot)))), tilt)


def fit_information(params: RobotParams, free: FreeParams, kind: str, t, tables, noise: Noise):
    """`(values, F_v, cov, stderr, extremes)`: the physical values of the free names, their
    information with the nuisance values eliminated, the covariance and the standard errors a
    fit of noise-free trials of `tables` (captured at the times `t`) reports with the sensors
    and noise levels of `noise` (`jsphere.design.information.Noise`); `extremes`: the largest
    wheel rate and tilt over the trials (`noise_free_trial`)."""
    m = noise.mounting
    runs = [noise_free_trial(params, kind, t, u, f"design_{k + 1}", m) for k, u in enumerate(tables)]
    trials = [r for r, _ in runs]
    extremes = tuple(max(e[i] for _, e in runs) for i in range(2))
    if m is None:
        data, sig = pack_trials(trials, params), [noise.sigma_pos, noise.sigma_rot]
        fns = fit_functions(free, kind, RTOL, ATOL, MAX_STEPS, None, 0.0)
    else:
        data, sig = pack_onboard(trials, params, m), list(noise.sigma_onboard)
        tol = ONBOARD_TOLERANCES
        fns = fit_functions(free, kind, tol["rtol"], tol["atol"], MAX_STEPS, None, 0.0, measure=data.measure)
    theta = jnp.asarray(free.theta0)[None]
    nu = jnp.zeros((1, len(trials), len(data.nuisance)))
    sig = jnp.asarray(sig)
    res, ok, J, _ = fns.jacobian(params, theta, nu, data.arrays(), sig)
    if not bool(np.all(np.asarray(ok))):
        raise SolverFailure(
            "design: the fit's model of a design trial did not reach its end (max_steps); try smaller limits."
        )
    values, F_v, cov, se, _ = covariance(free, free.theta0, np.asarray(res[0]), J[0], 1.0)
    return values, F_v, cov, se, extremes


def d_criterion(free: FreeParams, values: np.ndarray, F_v: np.ndarray) -> float:
    """`log det(S F_v S)`, `S = diag(max(|v|, 0.1 scale))` (`jsphere.design.information`)."""
    S = np.maximum(np.abs(values), 0.1 * free.scales())
    sign, ld = np.linalg.slogdet(S[:, None] * F_v * S[None, :])
    return float(ld) if sign > 0 else -math.inf
