"""The standard errors a fit would report for input programmes: the fit's own Jacobian
(`jsphere.identify.residuals`, the adaptive solver in forward mode) on noise-free trials of the
programmes at the capture rate, and its covariance (`jsphere.identify.report`, with `s^2 = 1`:
noise levels that are right)."""

from __future__ import annotations

import math

import jax.numpy as jnp
import numpy as np

from .._runtime.errors import SolverFailure
from ..capture.trial import Trial
from ..controls import Sampled, Torques, WheelSpeeds
from ..identify.data import pack_trials
from ..identify.free import FreeParams
from ..identify.internal import covariance, fit_functions
from ..model.params import RobotParams
from ..model.state import State
from ..solve.simulate import simulate

#: the fit's default ODE tolerances and step limit (`jsphere.fit`)
RTOL, ATOL, MAX_STEPS = 1e-6, 1e-8, 16384


def noise_free_trial(params: RobotParams, kind: str, t: np.ndarray, u: np.ndarray, name: str):
    """The trial a capture at the times `t` would record without noise: the robot at rest at
    the origin driven by the table `(t, u)` (cubic, as the fit interpolates it); and the
    largest wheel rate [rad/s] and platform tilt from its rest attitude [rad] at those times,
    as the accurate solver (rtol 1e-10) integrates them."""
    table = Sampled(jnp.asarray(t), jnp.asarray(u), "cubic")
    controls = Torques(table) if kind == "torques" else WheelSpeeds(table)
    tr = simulate(params, State.at_rest(params), controls, float(t[-1]), ts=t, rtol=1e-10, atol=1e-12)
    trial = Trial(t, np.asarray(tr.x), np.asarray(tr.y), np.asarray(tr.q), u, kind, None, name=name)
    r_m = np.asarray(params.r_m, np.float64)
    cos_tilt = np.asarray(tr.gamma, np.float64) @ (-r_m / np.linalg.norm(r_m))
    tilt = float(np.max(np.arccos(np.clip(cos_tilt, -1.0, 1.0))))
    return trial, (float(np.max(np.abs(np.asarray(tr.chi_dot)))), tilt)


def fit_information(params: RobotParams, free: FreeParams, kind: str, t, tables, sigma_pos: float, sigma_rot: float):
    """`(values, F_v, cov, stderr, extremes)`: the physical values of the free names, their
    information with the nuisance values eliminated, the covariance and the standard errors a
    fit of noise-free trials of `tables` (captured at the times `t`) reports with noise levels
    `sigma_pos` [m], `sigma_rot` [rad]; `extremes`: the largest wheel rate and tilt over the
    trials (`noise_free_trial`)."""
    runs = [noise_free_trial(params, kind, t, u, f"design_{k + 1}") for k, u in enumerate(tables)]
    trials = [r for r, _ in runs]
    extremes = tuple(max(e[i] for _, e in runs) for i in range(2))
    data = pack_trials(trials, params)
    fns = fit_functions(free, kind, RTOL, ATOL, MAX_STEPS, None, 0.0)
    theta = jnp.asarray(free.theta0)[None]
    nu = jnp.zeros((1, len(trials), len(data.nuisance)))
    sig = jnp.asarray([sigma_pos, sigma_rot])
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
