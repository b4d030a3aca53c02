"""Where the optimisation starts: the free parameters of each start (`start_design`, a Latin
hypercube) and the nuisance parameters guessed from the first frames of each trial
(`nuisance_guess`)."""

from __future__ import annotations

import equinox as eqx
import jax
import numpy as np

from .._runtime.errors import InputError
from ..capture.clock import estimate_time_offset
from ..model.kinematics import relative_rate_from_wheel_speeds
from ..model.params import RobotParams
from ..model.rotations import quat_conj_np, quat_log_np, quat_mul_np, rotmat_np
from .data import NUISANCE, FitData, nuisance_from_offset
from .free import FreeParams

#: typical step of each nuisance parameter (1/s, rad, m): for Adam and the start spread
_NU_SCALE = {
    "Omega0": 0.05,
    "rot0": 0.01,
    "x0": 0.002,
    "y0": 0.002,
    "omega0": 0.05,
    "time": 0.01,
    "gyro": 0.005,
    "acc": 0.05,
    "tilt0": 0.01,
    "chi0": 5e-4,
}
#: `relative_rate_from_wheel_speeds` of a stack of commands, as one compiled program
_relative_rates = eqx.filter_jit(jax.vmap(relative_rate_from_wheel_speeds, in_axes=(None, 0)))


def _line_rate(t, y):
    """Slope of a least-squares line through `(t, y)` (y may be (n, d))."""
    tt = t - t.mean()
    return (tt[:, None] * (y - y.mean(0))).sum(0) / max((tt * tt).sum(), 1e-300)


def nuisance_guess(data: FitData, params: RobotParams, *, window: float = 0.1, time_offset: bool = True) -> np.ndarray:
    """Initial nuisance parameters `(T, n)` from the first `window` seconds of each trial:
    the platform's angular velocity from the orientations, the horizontal shell rate from
    the rolling velocity `v = R0 Omega x gamma` (2.3); offsets 0. A fitted clock offset starts
    at the quick estimate from the whole trial (`jsphere.capture.clock.estimate_time_offset`),
    or 0 where there is none; `time_offset=False` leaves it out."""
    T = data.ts.shape[0]
    offset = time_offset and data.max_offset > 0
    n = len(NUISANCE[data.kind]) + offset
    nu = np.zeros((T, n))
    R0 = float(params.R0)
    if data.kind == "wheel_speeds":  # the start's commanded relative rate, every trial at once
        w0 = np.asarray(_relative_rates(params, data.u[:, 0]))
    for i in range(T):
        m = data.lengths[i]
        t = data.ts[i, :m]
        sel = t <= t[0] + window
        if sel.sum() < 3:
            sel = np.arange(m) < 3
        pr, rr = sel & (data.wpos[i, :m] > 0), sel & (data.wrot[i, :m] > 0)
        q0 = np.asarray(data.q0[i], float)
        R = rotmat_np(q0)  # platform -> fixed
        omega = np.zeros(3)
        if rr.sum() >= 3:
            rv = quat_log_np(quat_mul_np(quat_conj_np(q0), data.q[i, :m][rr]))
            omega = _line_rate(t[rr], rv)
        v = np.zeros(2)
        if pr.sum() >= 3:
            v = _line_rate(t[pr], np.stack([data.x[i, :m][pr], data.y[i, :m][pr]], 1))
        if data.kind == "wheel_speeds":
            nu[i, 0:3] = omega - w0[i]
        else:
            Om_f = np.array([-v[1] / R0, v[0] / R0, (R @ omega)[2]])
            nu[i, 0:3] = R.T @ Om_f
            nu[i, 8:11] = omega
        if offset:
            nu[i, -1] = nuisance_from_offset(_offset_guess(data, i, params), data.max_offset)
    return nu


def _offset_guess(data: FitData, i: int, params: RobotParams) -> float:
    """The quick estimate of trial `i`'s clock offset, 0 where the data give none."""
    m = data.lengths[i]
    wp, wr = data.wpos[i, :m] > 0, data.wrot[i, :m] > 0
    x, y = np.where(wp, data.x[i, :m], np.nan), np.where(wp, data.y[i, :m], np.nan)
    q = np.where(wr[:, None], data.q[i, :m], np.nan)
    try:
        off, corr = estimate_time_offset(
            data.ts[i, :m], x, y, q, data.tc[i, :m], data.u[i, :m], data.kind, params, max_offset=data.max_offset
        )
    except InputError:
        return 0.0
    return off if corr > 0.5 else 0.0


def latin_hypercube(n: int, d: int, rng: np.random.Generator) -> np.ndarray:
    """`(n, d)` points of a Latin hypercube in `[0, 1)^d` (McKay, Beckman and Conover 1979):
    in each dimension one point in each of the `n` strata `[k/n, (k+1)/n)`, uniform within its
    stratum, the strata in a random order per dimension. Drawn, as `scipy.stats.qmc.
    LatinHypercube(d, rng=rng).random(n)` draws its default (scrambled) form, from a child of
    `rng` (`rng.spawn(1)[0]`): the same points, without the half second `scipy.stats` takes to
    import (docs/decisions/hand-written-code-kept.md)."""
    rng = rng.spawn(1)[0]
    jitter = rng.uniform(size=(n, d))
    strata = np.tile(np.arange(1, n + 1), (d, 1))
    for row in strata:
        rng.shuffle(row)
    return (strata.T - jitter) / n


def start_design(free: FreeParams, n_starts: int, spread: float, rng: np.random.Generator) -> np.ndarray:
    """`theta (S, P)` of `n_starts` starts: the first at the start values, the others a
    Latin hypercube (space-filling, `latin_hypercube`) over a box: for a name with bounds on
    both sides uniform in the physical value within them; for the others `+- 2 spread` times
    the coordinate's scale about the start (log-transformed values: factors of `e^(+-2 spread)`)."""
    P = free.size
    theta = np.repeat(free.theta0[None], n_starts, 0)
    if n_starts < 2 or P == 0:
        return theta
    u = latin_hypercube(n_starts - 1, P, rng)
    ts = free.theta_scales()
    box = theta[1:] + 2.0 * spread * ts * (2.0 * u - 1.0)
    k = 0
    for sl in free.slots:
        if sl.kind == "interval":
            v = np.clip(u[:, k], 0.02, 0.98)
            box[:, k] = np.log(v / (1.0 - v))
        k += sl.size
    theta[1:] = box
    return theta
