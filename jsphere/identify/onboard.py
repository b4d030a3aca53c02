"""Onboard-sensor trials as the fit sees them: packed into arrays (`OnboardData`), the start of
their nuisance parameters and the channels' noise levels; the model of one trial is
`jsphere.identify.residuals.onboard_model`.

A trial starts at rest (`State.at_rest` of the parameters being fitted: upright for a robot whose
mass centre lies on the platform's axis) and runs under its recorded inputs; the residuals are
the simulated minus the recorded readings (`jsphere.imu_readings` at the IMU's mounting, plus the
trial's constant biases, and the encoders' angles from 0), whitened by each channel's noise level:

    r_gyro = (R^T omega + b_gyro - gyro) / sigma_gyro
    r_acc  = (R^T (a_r + g gamma) + b_acc - acc) / sigma_acc
    r_enc  = (chi - chi(0) + chi0 - chi_meas) / sigma_encoder

The nuisance parameters of a trial are its six biases (IMU axes) and its encoders' offsets at
the first sample (each encoder's first count is a rounded angle). Heading and position do not
enter the readings, nor do `m` and `m0` separately beyond `m + m0` and `m r_m`: one of them is
held fixed (`docs/onboard.md`).
"""

from __future__ import annotations

import dataclasses
import hashlib
import math
from collections.abc import Sequence

import jax
import numpy as np

from .._runtime.arrays import to_jax
from .._runtime.errors import InputError
from ..model.params import RobotParams
from ..model.rotations import rotmat
from ..model.sensors import Mounting, imu_readings
from ..model.state import State

#: the channels of an onboard trial, in the order of the residuals and of the noise levels
CHANNELS = ("gyro", "acc", "encoders")
#: each channel's unit
UNITS = ("rad/s", "m/s^2", "rad")
#: the noise levels a fit starts from where none is given (then estimated from the residuals)
START_SIGMA = (0.01, 0.1, 1e-3)
#: nuisance parameters per trial, in order: the gyro's and the accelerometer's constant biases
NUISANCE = ("gyro_bias_x", "gyro_bias_y", "gyro_bias_z", "acc_bias_x", "acc_bias_y", "acc_bias_z")
#: then each wheel's encoder offset `chi0_i` [rad]: the wheel's true angle at the first sample less
#: the encoder's, within a count either way (the count at the start is a rounded angle too);
#: then, for trials that do not start at rest (`FitOptions.start_at_rest=False`): the shell's
#: angular velocity, the platform's tilt from the rest attitude (a rotation about its x and y
#: axes) and, with torques, its angular velocity at the first sample
MOTION = {
    "wheel_speeds": ("Omega0_x", "Omega0_y", "Omega0_z", "tilt0_x", "tilt0_y"),
    "torques": ("Omega0_x", "Omega0_y", "Omega0_z", "tilt0_x", "tilt0_y", "omega0_x", "omega0_y", "omega0_z"),
}


def measure_name(hold: bool, at_rest: bool) -> str:
    """The model of an onboard trial as `jsphere.identify.residuals` names it (`onboard_options`
    reads it back)."""
    return "onboard" + ("-held" if hold else "") + ("" if at_rest else "-moving")


def onboard_options(measure: str) -> dict[str, bool]:
    """`onboard_model`'s `hold` and `at_rest` of a `measure_name`."""
    return {"hold": "-held" in measure, "at_rest": "-moving" not in measure}


ARRAYS = ("ts", "tc", "u", "t1", "gyro", "acc", "chi", "w", "imu_pos", "imu_rot")


@dataclasses.dataclass(frozen=True)
class OnboardData:
    """Onboard trials packed into arrays of a common length `M` (padded samples are masked).

    `ts (T, M)`: sample times from 0 (padded with the last); `tc (T, M)`: the inputs' knots
    (padded beyond the end, values held); `u (T, M, N)`: inputs; `t1 (T,)`: durations; `gyro`,
    `acc (T, M, 3)`, `chi (T, M, N)`: the readings; `w (T, M)`: 1.0 at a sample, 0.0 at padding;
    `imu_pos (T, 3)`, `imu_rot (T, 4)`: the IMU's mounting (`Mounting`), the same for every trial.
    """

    ts: np.ndarray
    tc: np.ndarray
    u: np.ndarray
    t1: np.ndarray
    gyro: np.ndarray
    acc: np.ndarray
    chi: np.ndarray
    w: np.ndarray
    imu_pos: np.ndarray
    imu_rot: np.ndarray
    kind: str
    hold: bool
    names: tuple[str, ...]
    lengths: tuple[int, ...]
    t_start: tuple[float, ...]
    at_rest: bool = True
    max_offset: float = 0.0

    channels = CHANNELS

    @property
    def measure(self) -> str:
        return measure_name(self.hold, self.at_rest)

    @property
    def nuisance(self) -> tuple[str, ...]:
        """The biases, the encoders' offsets and the initial motion where the trials do not start
        at rest (`MOTION`)."""
        offsets = tuple(f"chi0_{i + 1}" for i in range(self.widths[2]))
        return NUISANCE + offsets + (() if self.at_rest else MOTION[self.kind])

    @property
    def widths(self) -> tuple[int, int, int]:
        """The columns of each channel: 3, 3 and one per wheel."""
        return (3, 3, self.chi.shape[2])

    @property
    def width(self) -> int:
        """The residuals of one sample."""
        return sum(self.widths)

    @property
    def n_measured(self) -> int:
        """The measured values of all trials."""
        return int(self.w.sum()) * self.width

    def aux_shapes(self) -> tuple[tuple[int, ...], ...]:
        """The shapes of a trial's simulated readings `(gyro, acc, chi)`."""
        M = self.ts.shape[1]
        return (M, 3), (M, 3), (M, self.widths[2])

    def arrays(self) -> dict[str, jax.Array]:
        return {k: to_jax(getattr(self, k)) for k in ARRAYS}

    def fingerprint(self) -> str:
        h = hashlib.sha256(f"onboard:{self.kind}:{self.hold}:{self.at_rest}".encode())
        for k in ("ts", "u", "gyro", "acc", "chi", "imu_pos", "imu_rot"):
            h.update(np.ascontiguousarray(getattr(self, k)).tobytes())
        return h.hexdigest()

    def blocks(self, res: np.ndarray) -> list[np.ndarray]:
        """The residuals `res (..., M * width)` of a trial (the layout of `onboard_model`) cut
        into its channels: `(..., M, 3)`, `(..., M, 3)`, `(..., M, N)`."""
        M, out, at = self.ts.shape[1], [], 0
        for c in self.widths:
            out.append(res[..., at : at + M * c].reshape(res.shape[:-1] + (M, c)))
            at += M * c
        return out


def pack_onboard(trials: Sequence, params: RobotParams, mounting: Mounting, at_rest: bool = True) -> OnboardData:
    """Check onboard trials (`jsphere.capture.onboard.OnboardTrial`) against `params` and pack
    them; `at_rest`: they start at rest (otherwise their initial motion is fitted)."""
    trials = list(trials)
    kinds = {t.kind for t in trials}
    holds = {bool(t.hold) for t in trials}
    if len(kinds) != 1 or len(holds) != 1:
        got = ", ".join(f"{t.name!r}: {t.kind}{' held' if t.hold else ''}" for t in trials)
        raise InputError(
            f"fit: onboard trials must share one input kind and hold (torques or wheel speeds, held or smooth); got {got}."
        )
    N = params.n_wheels
    for t in trials:
        if t.n_wheels != N:
            raise InputError(
                f"fit: trial {t.name!r} has {t.n_wheels} wheels' inputs and encoders but the robot has {N}; use "
                "parameters with the same wheel count."
            )
        if len(t.t) < 4:
            raise InputError(f"fit: trial {t.name!r} has {len(t.t)} samples; a fit needs at least 4.")
    M = max(len(t.t) for t in trials)
    rows = []
    for t in trials:
        m = len(t.t)
        t0, dt = t.t[0], (t.t[-1] - t.t[0]) / (m - 1)

        def pad(a, v, m=m):
            return np.concatenate([a, np.broadcast_to(v, (M - m,) + a.shape[1:])])

        rows.append(
            {
                "ts": np.concatenate([t.t - t0, np.full(M - m, t.t[-1] - t0)]),
                "tc": np.concatenate([t.t - t0, t.t[-1] - t0 + dt * np.arange(1, M - m + 1)]),
                "u": pad(t.inputs, t.inputs[-1]),
                "t1": t.t[-1] - t0,
                "gyro": pad(t.gyro, 0.0),
                "acc": pad(t.acc, 0.0),
                "chi": pad(t.chi, 0.0),
                "w": pad(np.ones(m), 0.0),
                "imu_pos": np.asarray(mounting.position, float),
                "imu_rot": np.asarray(mounting.rotation, float),
            }
        )
    return OnboardData(
        **{k: np.stack([r[k] for r in rows]).astype(np.float64) for k in ARRAYS},
        kind=next(iter(kinds)),
        hold=next(iter(holds)),
        names=tuple(t.name for t in trials),
        lengths=tuple(len(t.t) for t in trials),
        t_start=tuple(float(t.t[0]) for t in trials),
        at_rest=bool(at_rest),
    )


def nuisance_start(data: OnboardData, params: RobotParams, *, samples: int = 5) -> np.ndarray:
    """Initial nuisance values `(T, n)`. At rest: the biases are the mean of each trial's first
    `samples` readings minus what the model reads at its start (at rest, under its first input).
    In motion: the gyro's bias starts at 0 and the platform's angular velocity at the mean of
    those readings (in platform axes), the accelerometer's bias as at rest, the rest at 0."""
    mounting = Mounting(data.imu_pos[0], data.imu_rot[0])
    s0 = State.at_rest(params)
    K0 = data.u[:, 0] if data.kind == "torques" else np.zeros_like(data.u[:, 0])
    R = np.asarray(rotmat(mounting.rotation))  # IMU -> platform
    out, N = np.zeros((data.ts.shape[0], len(data.nuisance))), data.widths[2]
    for i in range(data.ts.shape[0]):
        g, a = (np.asarray(x) for x in imu_readings(params, mounting, s0.gamma, s0.omega, s0.Omega, K0[i]))
        k = min(samples, data.lengths[i])
        gyro = data.gyro[i, :k].mean(0)
        out[i, :6] = np.concatenate([gyro - g, data.acc[i, :k].mean(0) - a])
        if not data.at_rest:
            out[i, :3] = 0.0
            if data.kind == "torques":
                out[i, 6 + N + 5 : 6 + N + 8] = R @ gyro
    return out


def channel_sigmas(res_b: np.ndarray, data: OnboardData, sig: np.ndarray, n_par: int) -> np.ndarray:
    """The channels' noise levels from the whitened residuals `res_b (T, K)` of the best start,
    dof-corrected as `jsphere.identify.fit` corrects the capture's."""
    frac = 1.0 - n_par / data.n_measured
    n = data.w.sum()
    return np.array(
        [
            math.sqrt(float((b * b).sum()) * s * s / (n * c * frac))
            for b, s, c in zip(data.blocks(res_b), sig, data.widths)
        ]
    )


def encoder_quantum(data: OnboardData) -> float:
    """The encoders' resolution [rad]: the smallest step between consecutive angles (one count),
    0 where the angles are not quantised (no step repeats to 1e-9 of the largest)."""
    steps = np.abs(np.diff(data.chi, axis=1))[data.w[:, 1:] > 0].reshape(-1)
    steps = steps[steps > 1e-12]
    if not steps.size:
        return 0.0
    q = float(steps.min())
    multiples = steps / q
    return q if np.all(np.abs(multiples - np.round(multiples)) < 1e-5 * np.maximum(multiples, 1.0)) else 0.0
