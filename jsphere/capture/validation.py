"""Checks of a trial's arrays: the input kinds, validation with messages naming the row of the
first problem, and the plausibility findings (`CaptureWarning`) shared by every reader."""

from __future__ import annotations

import math
import warnings
from collections.abc import Sequence

import numpy as np

from .._runtime.errors import InputError

KINDS = ("wheel_speeds", "torques")
#: column prefix of the inputs for each kind
INPUT_PREFIX = {"wheel_speeds": "chi_dot_", "torques": "K_"}
POSE_COLUMNS = ("t", "x", "y", "qw", "qx", "qy", "qz")
#: a trial needs at least this many valid (non-gap) frames ...
MIN_VALID_FRAMES = 10
#: ... and at least this duration [s]
MIN_DURATION = 0.2
#: quaternions whose norm is off by more than this are an error; smaller deviations are normalised
QUAT_NORM_TOL = 1e-3
#: a shell centre faster than this [m/s] is beyond any rolling robot of this kind (a 0.15 m ball at
#: 5 m/s turns at 33 rad/s): the positions are in the wrong unit, or the times are
MAX_PLAUSIBLE_SPEED = 5.0
#: a platform turning faster than this [rad/s] (8 turns a second) is implausible likewise
MAX_PLAUSIBLE_RATE = 50.0
#: a time step at least this long [s] (below 1 Hz) means times in milliseconds or frame numbers
MAX_PLAUSIBLE_STEP = 1.0


class CaptureWarning(UserWarning):
    """A capture file that reads without error but looks wrong: positions or times in the wrong
    unit, quaternions in `x, y, z, w` order, a file cut short (read with `allow_truncated`), or
    body markers given in millimetres. The message names the file and the likely cause."""


def warn(message: str, stacklevel: int = 3) -> None:
    """Issue `message` as a `CaptureWarning`; `stacklevel` as `warnings.warn`'s, counted from
    the function that calls this one."""
    warnings.warn(message, CaptureWarning, stacklevel=stacklevel + 1)


def sign_continuous(q: np.ndarray) -> np.ndarray:
    """Flip quaternion signs so that consecutive valid rows have a non-negative dot product
    (`q` and `-q` are the same rotation); the first valid row gets `w >= 0`. NaN rows are kept."""
    q = np.array(q, float)
    prev = None
    for k in range(q.shape[0]):
        if not np.all(np.isfinite(q[k])):
            continue
        if prev is None:
            if q[k, 0] < 0:
                q[k] = -q[k]
        elif q[k] @ prev < 0:
            q[k] = -q[k]
        prev = q[k]
    return q


def _where(source: str, lines: np.ndarray | None, k: int) -> str:
    """`"file.csv, line 17"` (1-based line of the file) or `"trial 'x', sample 17"` (1-based)."""
    if lines is None:
        return f"{source}, sample {k + 1}"
    return f"{source}, line {int(lines[k])}"


def wheel_columns(kind: str, n: int) -> list[str]:
    """`["chi_dot_1", ...]` or `["K_1", ...]`: the names of `n` input columns of `kind`."""
    return [f"{INPUT_PREFIX[kind]}{i + 1}" for i in range(n)]


def _check_times(
    t: np.ndarray,
    source: str,
    lines: np.ndarray | None,
    blank: str = "the time is blank or not finite; every row needs one",
    hint: str = "",
) -> None:
    """Raise an `InputError` naming the first row whose time is blank or not finite (`blank`
    says so), duplicated or going back (`hint` ends that message)."""
    bad = np.nonzero(~np.isfinite(t))[0]
    if bad.size:
        raise InputError(f"{_where(source, lines, int(bad[0]))}: {blank}.")
    dt = np.diff(t)
    if np.any(dt <= 0):
        k = int(np.nonzero(dt <= 0)[0][0])
        what = "duplicated" if dt[k] == 0 else "not increasing"
        raise InputError(
            f"{_where(source, lines, k + 1)}: time stamps are {what}: t = {t[k + 1]:.9g} s follows t = {t[k]:.9g} s "
            f"({_where(source, lines, k).split(', ')[-1]}); times must be strictly increasing{hint}."
        )


def _check_inputs(t: np.ndarray, inputs: np.ndarray, names: Sequence[str], source: str, lines) -> None:
    """Raise a `ValueError` naming the row and the column of the first blank or non-finite input."""
    bad = np.argwhere(~np.isfinite(inputs))
    if bad.size:
        k, c = int(bad[0, 0]), int(bad[0, 1])
        raise ValueError(
            f"{_where(source, lines, k)}: input column {names[c]} is blank or not finite (t = {t[k]:g} s); "
            "inputs may not have gaps: fill them in (e.g. interpolate the commands) or cut the trial."
        )


def _checked(
    t,
    x,
    y,
    q,
    inputs,
    kind: str,
    z,
    *,
    source: str,
    lines: np.ndarray | None = None,
    input_names: Sequence[str] | None = None,
    check_length: bool = True,
    max_gap_fraction: float = 1.0,
):
    """Validate and normalise the arrays of a trial; raise `ValueError` naming `source` and the
    row (`lines[k]`: the 1-based line in the file) of the first problem.

    Returns `(t, x, y, q, inputs, z)` as float64 numpy arrays: quaternions normalised and made
    sign-continuous, a frame with any missing pose value turned into a full gap (NaN pose).
    """
    if kind not in KINDS:
        raise ValueError(f"{source}: kind must be one of {KINDS}; got {kind!r}.")
    t = np.asarray(t, float)
    if t.ndim != 1:
        raise ValueError(f"{source}: t must be 1-D; got shape {t.shape}.")
    M = t.shape[0]
    x, y = np.array(x, float), np.array(y, float)
    q = np.array(q, float)
    inputs = np.asarray(inputs, float)
    if inputs.ndim == 1:
        inputs = inputs[:, None]
    z = None if z is None else np.array(z, float)
    for nm, arr, shape in (("x", x, (M,)), ("y", y, (M,)), ("q", q, (M, 4)), ("z", z, (M,))):
        if arr is not None and arr.shape != shape:
            raise ValueError(f"{source}: {nm} must have shape {shape} (one row per time); got {arr.shape}.")
    if inputs.ndim != 2 or inputs.shape[0] != M or inputs.shape[1] < 1:
        raise ValueError(f"{source}: inputs must have shape ({M}, N) with N >= 1 wheels; got {inputs.shape}.")
    blank = "the time t is blank or not finite; every row needs a time (delete the row or fill it in)"
    _check_times(t, source, lines, blank, " (remove duplicated frames, sort by time)")
    _check_inputs(t, inputs, input_names or wheel_columns(kind, inputs.shape[1]), source, lines)

    gap = ~np.isfinite(x) | ~np.isfinite(y) | ~np.all(np.isfinite(q), axis=1) | ~np.isfinite(1.0 if z is None else z)
    for a in (x, y, q) if z is None else (x, y, q, z):
        a[gap] = np.nan
    norms = np.linalg.norm(q, axis=1)
    off = np.nonzero(~gap & (np.abs(norms - 1.0) > QUAT_NORM_TOL))[0]
    if off.size:
        k = int(off[0])
        raise ValueError(
            f"{_where(source, lines, k)}: the quaternion (qw, qx, qy, qz) = {tuple(float(v) for v in q[k])} has norm "
            f"{norms[k]:.6g}, not 1 (tolerance {QUAT_NORM_TOL:g}); the columns must hold a unit quaternion, scalar first "
            "(check that the four columns are the quaternion's, e.g. not Euler angles or a position, and are not rounded)."
        )
    q[~gap] /= norms[~gap, None]
    q = sign_continuous(q)

    if check_length:
        n_valid = int(np.sum(~gap))
        duration = float(t[-1] - t[0]) if M else 0.0
        if n_valid < MIN_VALID_FRAMES or duration < MIN_DURATION:
            raise ValueError(
                f"{source}: the trial is too short: {M} rows, {n_valid} valid (non-gap) frames over {duration:.3g} s; "
                f"a trial needs at least {MIN_VALID_FRAMES} valid frames and {MIN_DURATION:g} s."
            )
        frac = 1.0 - n_valid / M
        if frac > max_gap_fraction:
            raise ValueError(
                f"{source}: too many gaps: {frac:.0%} of the {M} frames have no pose (limit {max_gap_fraction:.0%}): "
                "the rigid body is lost in most frames, or the markers do not move as one rigid body; "
                "check the robot's marker set and its rigid-body definition in the capture software."
            )
    return t, x, y, q, inputs, z


def _tilt_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Tilt [deg] of the platform's axis 3 from the vertical for quaternions whose vector part has
    horizontal components `a, b`: `arccos(1 - 2 (a^2 + b^2))`."""
    return np.degrees(np.arccos(np.clip(1.0 - 2.0 * (a * a + b * b), -1.0, 1.0)))


def _windowed(t: np.ndarray, window: float) -> tuple[np.ndarray, np.ndarray]:
    """Index pairs `(i, j)`: each frame `i` and the first frame `j` at least `window` [s] later."""
    j = np.searchsorted(t, t + window - 1e-12)
    i = np.nonzero(j < t.size)[0]
    return i, j[i]


def _second_derivative(t: np.ndarray, v: np.ndarray, window: float = 0.3) -> np.ndarray:
    """`d2v/dt2` of a uniformly sampled series by a local quadratic least-squares fit over
    `window` [s] (Savitzky-Golay); the ends, where the window does not fit, are NaN."""
    dt = float(np.median(np.diff(t)))
    h = max(2, int(round(0.5 * window / dt)))
    if v.size < 2 * h + 1:
        return np.full(v.shape, np.nan)
    s2 = (np.arange(-h, h + 1) * dt) ** 2
    c = (s2 - s2.mean()) / np.sum((s2 - s2.mean()) ** 2)  # the quadratic coefficient; s and s^2 are orthogonal
    out = np.full(v.shape, np.nan)
    out[h:-h] = 2.0 * np.convolve(v, c[::-1], mode="valid")
    return out


def _lean_fit(t, x, y, q, valid) -> float:
    """How well the platform's lean follows the ball's acceleration: the R^2 of the horizontal
    part of the platform's axis 3 (in the fixed frame) fitted by `k * (x'', y'')` with one
    scalar `k`. A platform hanging in a rolling ball leans with its acceleration (R^2 0.5-0.96
    on `examples/data`); quaternions read in the wrong order do not (R^2 below 0.35)."""
    xi, yi = np.interp(t, t[valid], x[valid]), np.interp(t, t[valid], y[valid])
    a = np.stack([_second_derivative(t, xi), _second_derivative(t, yi)], axis=1)
    w, qx, qy, qz = (q[:, i] for i in range(4))
    lean = np.stack([2 * (qx * qz + w * qy), 2 * (qy * qz - w * qx)], axis=1)  # rows 1, 2 of R e3
    m = valid & np.all(np.isfinite(a), axis=1) & np.all(np.isfinite(lean), axis=1)
    a, lean = a[m], lean[m]
    aa = float(np.sum(a * a))
    spread = float(np.sum((lean - lean.mean(0)) ** 2))
    if m.sum() < 30 or aa == 0.0 or spread == 0.0:
        return math.nan
    k = float(np.sum(lean * a)) / aa
    return 1.0 - float(np.sum((lean - k * a) ** 2)) / spread


def implausible(t, x, y, q, z=None, *, from_markers: bool = False) -> list[tuple[str, str]]:
    """What looks physically wrong in a trial's arrays (gap frames NaN), as `(kind, detail)`
    pairs, `kind` one of `"step"`, `"speed"`, `"rate"`, `"height"`, `"lying"`, `"xyzw"` (tests
    and thresholds: `docs/capture.md`, "Plausibility warnings"; 95th percentiles, so that one
    swapped marker does not count). `from_markers`: poses computed from markers, whose
    quaternions cannot be out of order (no `"xyzw"`) but whose up axis can be wrong (`"lying"`:
    tilted beyond 80 deg; random inputs tilt the paper's robot up to 66 deg).
    """
    t, x, y, q = (np.asarray(a, float) for a in (t, x, y, q))
    out = []
    step = float(np.median(np.diff(t))) if t.size >= 2 else math.inf
    if t.size >= 2 and step >= MAX_PLAUSIBLE_STEP:  # (the rates below would only repeat it)
        return [("step", f"the median time step is {step:.6g} s ({1.0 / step:.3g} Hz)")]
    v = np.isfinite(x) & np.isfinite(y) & np.all(np.isfinite(q), axis=1)
    tv, xv, yv, qv = t[v], x[v], y[v], q[v]
    if tv.size < 3 or not np.all(np.isfinite(t)):
        return out
    out += _speed_and_rate(tv, xv, yv, qv)
    if z is not None:
        out += _height(np.asarray(z, float)[v], xv, yv)
    tilt = float(np.percentile(_tilt_deg(qv[:, 1], qv[:, 2]), 95))
    if from_markers:
        if tilt > 80.0:
            out.append(("lying", f"the platform tilts {tilt:.0f} deg from upright (95th percentile)"))
        return out
    return out + _quaternion_order(t, x, y, q, v, step, tilt)


def _speed_and_rate(tv, xv, yv, qv) -> list[tuple[str, str]]:
    """The `"speed"` and `"rate"` findings of `implausible` (measured frames only)."""
    out = []
    i, j = _windowed(tv, 0.1)
    if i.size >= 3:
        speed = np.hypot(xv[j] - xv[i], yv[j] - yv[i]) / (tv[j] - tv[i])
        s95 = float(np.percentile(speed, 95))
        if s95 > MAX_PLAUSIBLE_SPEED:
            most = f"95th percentile over 0.1 s; {float(speed.max()):.3g} m/s at most"
            out.append(("speed", f"the shell centre moves at {s95:.3g} m/s ({most})"))
    i, j = _windowed(tv, 0.02)
    if i.size >= 3:
        dot = np.clip(np.abs(np.sum(qv[i] * qv[j], axis=1)), 0.0, 1.0)
        rate = 2.0 * np.arccos(dot) / (tv[j] - tv[i])
        r95 = float(np.percentile(rate, 95))
        if r95 > MAX_PLAUSIBLE_RATE:
            out.append(("rate", f"the platform turns at {r95:.3g} rad/s (95th percentile over 0.02 s)"))
    return out


def _height(zv, xv, yv) -> list[tuple[str, str]]:
    """The `"height"` finding of `implausible` (measured frames only)."""
    zv = zv[np.isfinite(zv)]
    if zv.size >= 3:
        dz = float(np.ptp(np.percentile(zv, [5, 95])))
        dh = max(float(np.ptp(xv)), float(np.ptp(yv)))
        if dz > 0.03 and dz > 0.25 * dh:
            return [
                (
                    "height",
                    f"the shell centre's height z varies by {_length(dz)} while it moves {_length(dh)} horizontally",
                )
            ]
    return []


def _length(v: float) -> str:
    """A length [m] for a message: centimetres below a metre, else metres (no exponent)."""
    return f"{100 * v:.3g} cm" if v < 1.0 else f"{v:.2f} m"


def _quaternion_order(t, x, y, q, v, step: float, tilt: float) -> list[tuple[str, str]]:
    """The `"xyzw"` finding of `implausible`: quaternion columns in `x, y, z, w` order."""
    qv = q[v]
    tilt_swapped = float(np.percentile(_tilt_deg(qv[:, 0], qv[:, 1]), 95))  # columns (qw, qx, qy, qz) = (x, y, z, w)
    fit = fit_swapped = math.nan
    if step < 0.05 and t[-1] - t[0] >= 1.0:  # enough frames over enough time to see accelerations
        fit = _lean_fit(t, x, y, q, v)
        fit_swapped = _lean_fit(t, x, y, q[:, [3, 0, 1, 2]], v)
    # the first pose: a half turn about Z, or x, y, z, w of q = 1
    half_turn = abs(qv[0, 3]) > math.cos(math.radians(5.0))
    if fit_swapped >= 0.5 and fit <= fit_swapped - 0.3:
        why = (
            f"read as x, y, z, w the platform leans with the ball's acceleration (R^2 {fit_swapped:.2f}); "
            f"read as w, x, y, z it does not (R^2 {fit:.2f})"
        )
    elif tilt > 90.0 and tilt_swapped < tilt - 30.0:  # upside down, inside a ball
        why = (
            f"read as w, x, y, z the platform tilts up to {tilt:.0f} deg from upright; read as x, y, z, w it "
            f"stays within {tilt_swapped:.0f} deg"
        )
    elif half_turn and not fit > fit_swapped:  # (NaN fits: too little acceleration to tell)
        why = (
            f"the first pose read as w, x, y, z is a half turn about the vertical (qz = {qv[0, 3]:+.3f}); read as "
            "x, y, z, w it is the identity, the rest pose of a rigid body defined where the trial starts"
        )
    else:
        return []
    return [("xyzw", why)]


_CAUSES = {
    "step": "the times look like milliseconds or frame numbers; give t in seconds",
    "speed": "beyond any rolling robot of this size (< {speed:g} m/s): positions in millimetres or centimetres read as "
    "metres ({units}), or times in the wrong unit",
    "rate": "beyond any rolling robot (< {rate:g} rad/s): times in the wrong unit or a wrong frame rate, or frames out "
    "of order",
    "xyzw": "the quaternion columns look like x, y, z, w order; reorder them to qw, qx, qy, qz (scalar first)",
    "height": "a ball rolling on a floor keeps it within millimetres: {up}",
    "lying": "a platform hanging in a ball stays near upright: {up}, or the body frame is not the platform's",
}


def warn_implausible(
    t,
    x,
    y,
    q,
    source: str,
    z=None,
    *,
    from_markers: bool = False,
    units_hint: str = "convert them to metres",
    up_hint: str = "is z the height, with the Z axis up?",
) -> list[str]:
    """Issue a `CaptureWarning` for each finding of `implausible`, naming `source` and the likely
    cause (`units_hint`: how to say that positions are in millimetres; `up_hint`: what to check
    when the up axis looks wrong). Returns the messages."""
    msgs = []
    for kind, detail in implausible(t, x, y, q, z, from_markers=from_markers):
        cause = _CAUSES[kind].format(speed=MAX_PLAUSIBLE_SPEED, rate=MAX_PLAUSIBLE_RATE, units=units_hint, up=up_hint)
        msgs.append(f"{source}: {detail}: {cause}.")
        warn(msgs[-1])
    return msgs
