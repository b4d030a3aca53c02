"""Onboard-sensor trials: what the robot's own IMU and wheel encoders record, with the inputs
that drove it (`OnboardTrial`, its CSV format, and synthetic ones for rehearsal).

The CSV holds `t` [s]; `gyro_x, gyro_y, gyro_z` [rad/s], the platform's angular velocity in the
IMU's axes; `acc_x, acc_y, acc_z` [m/s^2], the specific force at the IMU (a level IMU at rest
reads +9.81 on its up axis), each plus a constant bias; `chi_1..chi_N` [rad], the wheels'
cumulative (unwrapped) angles relative to the platform, with the sign of jsphere's wheel speeds,
starting at 0; and `K_1..K_N` [N m] or `chi_dot_1..chi_dot_N` [rad/s], the inputs. No position
columns. A `# hold: zero-order` comment says the inputs are held between samples (a digital
controller's); otherwise they are samples of a smooth programme. The measurement model is
`jsphere.imu_readings` (`docs/model.md`, "Onboard sensors").
"""

from __future__ import annotations

import math
import re
from pathlib import Path

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from .._runtime.errors import InputError
from .._runtime.files import atomic_write_text
from ..controls import Torques, WheelSpeeds, eval_controls
from ..model.params import RobotParams
from ..model.sensors import Mounting, imu_readings
from ..model.state import State
from .text import _input_columns, _numbers, cells, check_unique_columns, headed_rows
from .validation import KINDS, _check_times, _where, wheel_columns

#: the sensor columns of an onboard-sensor trial, before `chi_1..N` and the inputs
SENSOR_COLUMNS = ("t", "gyro_x", "gyro_y", "gyro_z", "acc_x", "acc_y", "acc_z")
#: the values of the `# hold:` comment: inputs held between samples, or samples of a smooth programme
HOLDS = ("zero-order", "none")


def _array(x) -> np.ndarray:
    return np.asarray(x, dtype=float)


class OnboardTrial(eqx.Module):
    """One onboard-sensor trial, as numpy arrays (module docstring for the columns).

    **Fields:** `t` `(M,)` [s], strictly increasing; `gyro`, `acc` `(M, 3)` in the IMU's axes;
    `chi` `(M, N)` wheel angles [rad] from 0; `inputs` `(M, N)`: torques `K_i` or wheel speeds
    `chi_dot_i`; `kind`: `"torques"` or `"wheel_speeds"`; `hold`: True where the torques are
    held between samples (zero-order); `name`, `source` as for `Trial`.

    Construction checks what the file reader checks (`InputError` naming the sample): finite
    values, strictly increasing times, encoder angles from 0 and unwrapped (no step of more
    than half a turn between samples).
    """

    t: np.ndarray = eqx.field(converter=_array)
    gyro: np.ndarray = eqx.field(converter=_array)
    acc: np.ndarray = eqx.field(converter=_array)
    chi: np.ndarray = eqx.field(converter=_array)
    inputs: np.ndarray = eqx.field(converter=_array)
    kind: str = eqx.field(static=True)
    hold: bool = eqx.field(static=True, default=False)
    name: str = eqx.field(static=True, default="trial")
    source: str | None = eqx.field(static=True, default=None)

    def __check_init__(self):
        where = self.source or f"trial {self.name!r}"
        if self.kind not in KINDS:
            raise InputError(f"{where}: kind must be one of {KINDS}; got {self.kind!r}.")
        if self.hold and self.kind == "wheel_speeds":
            raise InputError(
                f"{where}: held wheel-speed commands would make every sample a jump of the servo; '# hold: "
                "zero-order' is for torques."
            )
        M = self.t.shape[0]
        for name, a, cols in (("gyro", self.gyro, 3), ("acc", self.acc, 3), ("inputs", self.inputs, None)):
            if a.ndim != 2 or a.shape[0] != M or (cols is not None and a.shape[1] != cols):
                raise InputError(f"{where}: {name} must have shape ({M}, {cols or 'N'}); got {a.shape}.")
        if self.chi.shape != self.inputs.shape:
            raise InputError(f"{where}: chi must have the inputs' shape {self.inputs.shape}; got {self.chi.shape}.")
        _check_values(self.t, np.concatenate([self.gyro, self.acc, self.chi, self.inputs], axis=1), self.kind, where)

    @property
    def n_wheels(self) -> int:
        return int(self.inputs.shape[1])

    @property
    def input_names(self) -> list[str]:
        """`["K_1", ...]` or `["chi_dot_1", ...]`."""
        return wheel_columns(self.kind, self.n_wheels)

    def controls(self) -> WheelSpeeds | Torques:
        """The recorded inputs as a control: held torques (`kind="zoh"`) or cubic Hermite samples."""
        cls = WheelSpeeds if self.kind == "wheel_speeds" else Torques
        return cls.from_samples(jnp.asarray(self.t), jnp.asarray(self.inputs), kind="zoh" if self.hold else "cubic")


def refuse_onboard(trials, where: str) -> None:
    """An `InputError` naming the first onboard-sensor trial of `trials`, for a command (`where`)
    that needs captured poses."""
    for t in trials:
        if isinstance(t, OnboardTrial):
            raise InputError(
                f"{t.source or repr(t.name)}: an onboard-sensor trial (IMU and encoders, no poses); {where} needs "
                "motion-capture trials: fit onboard trials with jsphere fit, whose verdict judges them (docs/onboard.md)."
            )


def _check_values(t, values, kind: str, where: str, lines: np.ndarray | None = None) -> None:
    """Check the times and the columns `gyro_x..acc_z, chi_1..N, inputs` of `values` `(M, 6 +
    2N)`; errors name the file's `lines` where given, else the samples."""
    n = (values.shape[1] - 6) // 2
    _check_times(t, where, lines)

    def row(k):
        return _where(where, lines, int(k))

    columns = [*SENSOR_COLUMNS[1:], *(f"chi_{i + 1}" for i in range(n)), *wheel_columns(kind, n)]
    bad = np.argwhere(~np.isfinite(values))
    if bad.size:
        k, j = bad[0]
        raise InputError(f"{row(k)}, column {columns[j]}: blank or not finite; onboard trials have no gaps.")
    chi = values[:, 6 : 6 + n]
    if np.any(np.abs(chi[0]) > 1e-9):
        i = int(np.argmax(np.abs(chi[0]) > 1e-9))
        raise InputError(
            f"{row(0)}, column chi_{i + 1}: the encoder angle starts at {chi[0, i]:.6g} rad; encoder angles start "
            "at 0: subtract each wheel's first angle."
        )
    jumps = np.argwhere(np.abs(np.diff(chi, axis=0)) > math.pi)
    if jumps.size:
        k, i = jumps[0]
        raise InputError(
            f"{row(k + 1)}, column chi_{i + 1}: the encoder angle jumps by more than half a turn in one sample; "
            "give cumulative (unwrapped) angles, e.g. numpy.unwrap of a wrapped encoder."
        )


def read_onboard_trial(path) -> OnboardTrial:
    """Read an onboard-sensor trial CSV (module docstring). Lines starting with `#` before the
    header are comments (`# name:`, `# hold: zero-order`). Raises `InputError` (a
    `ValueError`) naming the file, the line and the column of the first problem."""
    path = Path(path)
    needs = f"the first non-comment line must name the columns {', '.join(SENSOR_COLUMNS)}, chi_1, ..."
    source, meta, rows, k = headed_rows(path, needs)
    header, at = [h.strip() for h in rows[k]], f"{source}, line {k + 1}"
    missing = [c for c in SENSOR_COLUMNS if c not in header]
    if missing:
        raise InputError(
            f"{at}: missing column(s) {', '.join(missing)}; an onboard-sensor trial needs {', '.join(SENSOR_COLUMNS)}, "
            "chi_1..N and K_1..N or chi_dot_1..N (see docs/capture.md)."
        )
    kind, in_cols = _input_columns(header, at)
    chi = {int(m.group(1)): j for j, h in enumerate(header) if (m := re.fullmatch(r"chi_(\d+)", h))}
    n = len(in_cols)
    if sorted(chi) != list(range(1, n + 1)):
        raise InputError(
            f"{at}: the encoder columns must be chi_1..chi_{n}, one per input column; found {sorted(chi)}."
        )
    hold = meta.get("hold", "none").strip().lower()
    if hold not in HOLDS:
        raise InputError(f"{source}: '# hold: {hold}' is not one of {', '.join(HOLDS)}.")
    names = [*SENSOR_COLUMNS, *(f"chi_{i}" for i in range(1, n + 1)), *(header[j] for j in in_cols)]
    check_unique_columns(header, at, names)
    cols = [header.index(c) for c in SENSOR_COLUMNS] + [chi[i] for i in range(1, n + 1)] + in_cols
    data, lines = _numbers(rows, k + 1, cols, source, names, width=len(header))
    if data.shape[0] < 2:
        raise InputError(f"{source}: the trial is too short: fewer than two data rows after the header.")
    _check_values(data[:, 0], data[:, 1:], kind, source, lines)
    return OnboardTrial(
        data[:, 0], data[:, 1:4], data[:, 4:7], data[:, 7 : 7 + n], data[:, 7 + n :], kind,
        hold == "zero-order", meta.get("name", path.stem), source,
    )  # fmt: skip


def write_onboard_trial(path, trial: OnboardTrial) -> None:
    """Write `trial` to `path` in the onboard-sensor trial CSV format, atomically: times to 1 µs,
    readings and inputs to 10 significant digits, encoder angles to 1e-9 rad."""
    n = trial.n_wheels
    head = ["# jsphere onboard trial v1", f"# name: {trial.name}", f"# hold: {HOLDS[0] if trial.hold else HOLDS[1]}"]
    header = [*SENSOR_COLUMNS, *(f"chi_{i + 1}" for i in range(n)), *trial.input_names]
    data = np.concatenate([trial.t[:, None], trial.gyro, trial.acc, trial.chi, trial.inputs], axis=1)
    body = cells(data, [".6f"] + [".10g"] * 6 + [".9f"] * n + [".10g"] * n)
    atomic_write_text(path, "\n".join([*head, ",".join(header), *body]) + "\n")


class OnboardNoise(eqx.Module):
    """What a synthetic onboard trial adds to the exact readings: white noise of `gyro_sd`
    [rad/s] and `acc_sd` [m/s^2] per axis, constant biases `gyro_bias`, `acc_bias` (IMU axes),
    and encoders of `counts_per_turn` counts (angles rounded to whole counts; 0: exact)."""

    gyro_sd: float = 0.003
    acc_sd: float = 0.03
    gyro_bias: tuple[float, float, float] = (0.0, 0.0, 0.0)
    acc_bias: tuple[float, float, float] = (0.0, 0.0, 0.0)
    counts_per_turn: int = 4096


def synthetic_onboard_trial(
    params: RobotParams,
    controls: WheelSpeeds | Torques,
    t1: float,
    *,
    mounting: Mounting | None = None,
    noise: OnboardNoise | None = None,
    state0: State | None = None,
    rate: float = 100.0,
    seed: int = 0,
    name: str = "synthetic",
) -> OnboardTrial:
    """An onboard-sensor trial from a simulation: `controls` from `state0` (default at rest),
    solved at rtol 1e-10, atol 1e-12 and sampled at `rate` [Hz] from 0 to `t1`; the readings of
    `jsphere.imu_readings` at `mounting` (default: the centre, level) with `noise` (default
    `OnboardNoise()`), the wheel angles from 0 as the encoders count them (each wheel starting
    at a random angle: the first count is a rounded angle too), and the
    commanded inputs at the sample times. Deterministic for a given `seed`."""
    if not rate > 0 or not t1 > 0:
        raise ValueError(f"synthetic_onboard_trial: rate and t1 must be positive; got rate={rate}, t1={t1}.")
    ts, tr, u, kind = simulated(params, controls, t1, state0, rate, 1e-10, 1e-12)
    mounting = Mounting() if mounting is None else mounting
    noise = OnboardNoise() if noise is None else noise
    gyro, acc = (np.asarray(a) for a in imu_readings(params, mounting, tr.gamma, tr.omega, tr.Omega, tr.K))
    rng = np.random.default_rng(seed)
    gyro = gyro + np.asarray(noise.gyro_bias) + rng.normal(0.0, noise.gyro_sd, gyro.shape)
    acc = acc + np.asarray(noise.acc_bias) + rng.normal(0.0, noise.acc_sd, acc.shape)
    chi = np.asarray(tr.chi) - np.asarray(tr.chi[0])
    if noise.counts_per_turn:  # counts of the wheels' angles from where each happened to stand
        step = 2 * math.pi / noise.counts_per_turn
        start = rng.uniform(0.0, 2 * math.pi, chi.shape[1])
        chi = (np.round((start + chi) / step) - np.round(start / step)) * step
    return OnboardTrial(ts, gyro, acc, chi, u, kind, name=name)


def simulated(params: RobotParams, controls, t1: float, state0, rate: float, rtol: float, atol: float):
    """`(ts, trajectory, inputs, kind)`: `controls` simulated from `state0` (default at rest;
    errors raised) and sampled at `rate` [Hz] from 0 to `t1` [s], the commanded inputs at the
    sample times and their kind."""
    from ..solve.simulate import simulate

    ts = np.arange(math.floor(t1 * rate + 1e-9) + 1) / rate
    state0 = State.at_rest(params) if state0 is None else state0
    traj = simulate(params, state0, controls, float(ts[-1]), ts=ts, rtol=rtol, atol=atol, throw=True)
    u = np.asarray(eval_controls(controls, jnp.asarray(ts, params.R0.dtype)))
    return ts, traj, u, "wheel_speeds" if isinstance(controls, WheelSpeeds) else "torques"
