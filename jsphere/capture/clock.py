"""The offset between a capture's clock and its inputs' clock, estimated from the data alone
(`estimate_time_offset`): the measured motion against the motion the inputs imply.

A quick estimate, for `jsphere convert --time-offset auto` and as the start of the offset that
`jsphere fit --fit-time-offset` estimates with the model: that one is the accurate value.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np

from .._runtime.errors import InputError
from ..model.kinematics import relative_rate_from_wheel_speeds
from ..model.params import RobotParams
from ..model.rotations import rotmat_np


def estimate_time_offset(
    t,
    x,
    y,
    q,
    t_inputs,
    inputs,
    kind: str,
    params: RobotParams | None = None,
    *,
    max_offset: float = 0.5,
) -> tuple[float, float]:
    """The clock offset `offset` [s] such that the inputs at `t + offset` drove the capture at `t`
    (the `time_offset` of `markers_to_trial`: `t_trial = t_capture + offset`), and the
    correlation of the two signals compared at it.

    `t`, `x`, `y` [m], `q (M, 4)` (platform -> fixed): the capture, NaN at gaps; `t_inputs`,
    `inputs (K, N)`: the inputs table; `params`: the robot (default: the paper's). The capture
    is smoothed by Savitzky-Golay filters over ~0.2 s (`scipy.signal.savgol_filter`).

    The measured velocity of the shell centre is matched with the velocity the wheel speeds
    imply at each lag: rolling (2.3) gives `v = R0 (R Omega) x e3` with `Omega = omega - w`
    (2.4), `omega` the platform's measured angular velocity, `w` the relative rate the wheel
    speeds command, `R` the measured orientation. The lag of the least squared difference wins.
    Torques drive the motion only through the platform's swing, which no quick estimate
    undoes: for them fit the offset (`fit(..., fit_time_offset=True)`).

    Lags within `+- max_offset` on a 1 ms grid, the best refined by a parabola; the inputs are
    held at their end values beyond their table. Raises `InputError` for inputs that are not
    wheel speeds, fewer than 10 measured frames, or a trial without motion."""
    if kind != "wheel_speeds":
        raise InputError(
            f"estimate_time_offset: the quick estimate needs wheel-speed inputs (chi_dot); got {kind!r}. With torques, "
            "fit the offset with the model instead (jsphere fit --fit-time-offset)."
        )
    if isinstance(max_offset, bool) or not (isinstance(max_offset, (int, float)) and 0 < max_offset < math.inf):
        raise InputError(f"estimate_time_offset: max_offset must be a positive number of seconds; got {max_offset!r}.")
    params = RobotParams.paper() if params is None else params
    t, x, y = (np.asarray(a, float) for a in (t, x, y))
    q = np.asarray(q, float).reshape(len(t), 4)
    t_in, u_in = np.asarray(t_inputs, float), np.asarray(inputs, float).reshape(len(t_inputs), -1)
    ok = np.isfinite(x) & np.isfinite(y) & np.all(np.isfinite(q), axis=1)
    if ok.sum() < 10:
        raise InputError("estimate_time_offset: fewer than 10 measured frames; the offset cannot be estimated.")
    dt = float(np.median(np.diff(t)))
    win = min(max(5, int(round(0.2 / dt)) | 1), len(t) if len(t) % 2 else len(t) - 1)
    from scipy.signal import savgol_filter  # (imported here: `import scipy.signal` takes ~0.8 s)

    # (the measured values, at the frames `ok`, smoothed over every frame)
    smooth = lambda a, deriv=0: savgol_filter(np.interp(t, t[ok], a), win, 3, deriv=deriv, delta=dt)
    lags = np.arange(-max_offset, max_offset + 0.5e-3, 1e-3)
    v = np.stack([smooth(x[ok], 1), smooth(y[ok], 1)], 1)
    R = rotmat_np(q[ok])
    Rf = np.stack([[smooth(R[:, i, j]) for j in range(3)] for i in range(3)]).transpose(2, 0, 1)
    Rd = np.stack([[smooth(R[:, i, j], 1) for j in range(3)] for i in range(3)]).transpose(2, 0, 1)
    S = Rd @ np.swapaxes(Rf, 1, 2)  # the hat matrix of omega in the fixed frame (its skew part)
    om = 0.5 * np.stack([S[:, 2, 1] - S[:, 1, 2], S[:, 0, 2] - S[:, 2, 0], S[:, 1, 0] - S[:, 0, 1]], 1)
    w = _relative_rate(params, u_in)  # (K, 3) platform frame
    w_l = np.stack([np.interp(t[None, :] + lags[:, None], t_in, w[:, c]) for c in range(3)], -1)  # (L, M, 3)
    Om = om[None] - np.einsum("mij,lmj->lmi", Rf, w_l)
    v_in = float(params.R0) * np.stack([Om[..., 1], -Om[..., 0]], -1)  # R0 Omega x e3
    score = -((v_in - v[None]) ** 2).sum((1, 2))
    a = v.reshape(-1) - v.mean()
    b = v_in.reshape(len(lags), -1)
    b = b - b.mean(1, keepdims=True)
    den = np.sqrt((a * a).sum() * (b * b).sum(1))
    if not np.all(den > 0):
        raise InputError(
            "estimate_time_offset: the measured or the implied motion does not change; give a trial with motion."
        )
    corr = (b @ a) / den
    k = int(np.argmax(score))
    lag = float(lags[k])
    if 0 < k < len(lags) - 1:
        c0, c1, c2 = score[k - 1], score[k], score[k + 1]
        d = c0 - 2 * c1 + c2
        if d < 0:
            lag += 1e-3 * 0.5 * (c0 - c2) / d
    return float(np.clip(lag, -max_offset, max_offset)), float(corr[k])


def _relative_rate(params: RobotParams, u_in: np.ndarray) -> np.ndarray:
    """The platform's rate relative to the shell, `omega - Omega` (2.4), that each row of wheel
    speeds commands (platform frame)."""
    u = jnp.asarray(u_in, params.R0.dtype)
    return np.asarray(jax.vmap(lambda c: relative_rate_from_wheel_speeds(params, c))(u))
