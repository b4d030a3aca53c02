"""Capture data in: the trial format (one CSV per trial), and synthetic capture-like trials.

A *trial* is what a motion-capture session records about the robot plus the inputs that drove
it: times `t` [s], the shell-centre position `x, y` (optionally `z`) [m] in the fixed frame
(Z up), the platform orientation as a unit quaternion `(w, x, y, z)` rotating platform
components into fixed ones (the convention of `jsphere.State.q`; its rotation matrix has rows
`alpha, beta, gamma`), and per wheel either the commanded/encoder wheel speeds `chi_dot_i`
[rad/s] or the axle torques `K_i` [N m]. `docs/capture.md` describes the file format.

Frames where the pose is missing (a blank cell, `nan`) are *gaps*: their `x, y, q` (and `z`)
are NaN and `Trial.valid` is False there. Times and inputs are never missing.
"""

from __future__ import annotations

import codecs
import csv
import io
import math
import re
import warnings
from collections.abc import Iterable, Sequence
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from ..controls import Torques, WheelSpeeds
from .._runtime.errors import InputError
from .._runtime.files import atomic_write_text
from ..model.params import RobotParams
from ..model.state import State

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


def read_text(path) -> str:
    """The text of a CSV file, for the readers of trials, inputs tables, body markers and raw
    exports.

    UTF-8 is read with or without a byte-order mark (spreadsheets save "CSV UTF-8" with one),
    and UTF-16 with its byte-order mark (a spreadsheet's "Unicode text"). Any other encoding is
    an `InputError` naming the file, the line and the byte (Latin-1 / Windows-1252 text cannot
    be told from other code pages, so it is not guessed), and so is a binary file (a NUL byte:
    a C3D or a spreadsheet's own format given as CSV).
    """
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"{path} does not exist.")
    raw = path.read_bytes()
    if raw.startswith((codecs.BOM_UTF16_LE, codecs.BOM_UTF16_BE)):
        try:
            return raw.decode("utf-16")
        except UnicodeDecodeError as e:
            raise InputError(f"{path}: starts like UTF-16 text but does not decode as UTF-16 ({e.reason}); save it as UTF-8 CSV.") from None
    if b"\x00" in raw:
        line = raw.count(b"\n", 0, raw.index(b"\x00")) + 1
        c3d = len(raw) >= 512 and raw[1] == 0x50
        raise InputError(
            f"{path}, line {line}: a binary file, not CSV text (it holds a NUL byte)"
            + ("; it looks like a C3D file: read it with jsphere convert --format c3d (read_c3d)." if c3d else "; give the CSV export of the data.")
        )
    try:
        return raw.decode("utf-8-sig")
    except UnicodeDecodeError as e:
        line = raw.count(b"\n", 0, e.start) + 1
        raise InputError(
            f"{path}, line {line}: not UTF-8 text (byte 0x{raw[e.start]:02x} at byte {e.start}: {e.reason}); the file "
            "is in another encoding, e.g. Latin-1 or Windows-1252: save it as UTF-8 (in a spreadsheet: 'CSV UTF-8')."
        ) from None


def separator_hint(header: Sequence[str]) -> str:
    """`"; ..."` advice when a header row read as CSV is one cell holding `;` or a tab (a
    spreadsheet that saved with another separator), else `""`."""
    cells = [c for c in header if c.strip()]
    for sep, name in ((";", "semicolons"), ("\t", "tabs")):
        if len(cells) == 1 and sep in cells[0]:
            return (
                f"; the columns are separated by {name}, not commas (a spreadsheet's regional setting): save it as CSV "
                "with commas between the columns and points as decimal marks"
            )
    return ""


def check_unique_columns(header: Sequence[str], source: str, wanted: Iterable[str]) -> None:
    """Raise `InputError` if one of the `wanted` columns appears twice in `header` (which one
    would be read is a guess)."""
    for name in wanted:
        where = [j + 1 for j, h in enumerate(header) if h == name]
        if len(where) > 1:
            raise InputError(f"{source}: column {name!r} appears {len(where)} times (columns {where}); keep one.")


def csv_rows(text: str, source: str) -> list[list[str]]:
    """`text` split into CSV rows (`csv.reader`); a malformed file is an `InputError` naming it."""
    try:
        return list(csv.reader(io.StringIO(text, newline="")))
    except csv.Error as e:
        raise InputError(f"{source}: not a readable CSV file ({e}).") from None


# --------------------------------------------------------------------------- numpy quaternions


def quat_mul_np(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Hamilton product `p (x) q` of `(..., 4)` scalar-first quaternions (numpy)."""
    pw, px, py, pz = np.moveaxis(p, -1, 0)
    qw, qx, qy, qz = np.moveaxis(q, -1, 0)
    return np.stack(
        [
            pw * qw - px * qx - py * qy - pz * qz,
            pw * qx + px * qw + py * qz - pz * qy,
            pw * qy - px * qz + py * qw + pz * qx,
            pw * qz + px * qy - py * qx + pz * qw,
        ],
        axis=-1,
    )


def quat_from_rotvec_np(r: np.ndarray) -> np.ndarray:
    """Unit quaternion of the rotation by `|r|` [rad] about `r/|r|` (`(..., 3)` -> `(..., 4)`)."""
    r = np.asarray(r, float)
    a = np.linalg.norm(r, axis=-1, keepdims=True)
    half = 0.5 * a
    # sin(a/2)/a -> 1/2 as a -> 0
    k = np.where(a > 1e-12, np.sin(half) / np.where(a > 1e-12, a, 1.0), 0.5 - a * a / 48.0)
    return np.concatenate([np.cos(half), k * r], axis=-1)


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


# --------------------------------------------------------------------------- validation


def _where(source: str, lines: np.ndarray | None, k: int) -> str:
    """`"file.csv, line 17"` (1-based line of the file) or `"trial 'x', sample 17"` (1-based)."""
    if lines is None:
        return f"{source}, sample {k + 1}"
    return f"{source}, line {int(lines[k])}"


def _check_increasing(t: np.ndarray, source: str, lines: np.ndarray | None, hint: str = "") -> None:
    """Raise a `ValueError` naming the first row whose time stamp is duplicated or goes back."""
    dt = np.diff(t)
    if np.any(dt <= 0):
        k = int(np.nonzero(dt <= 0)[0][0])
        what = "duplicated" if dt[k] == 0 else "not increasing"
        raise ValueError(
            f"{_where(source, lines, k + 1)}: time stamps are {what}: t = {t[k + 1]:.9g} s follows t = {t[k]:.9g} s "
            f"({_where(source, lines, k).split(', ')[-1]}); times must be strictly increasing{hint}."
        )


def _checked(
    t, x, y, q, inputs, kind: str, z, *, source: str, lines: np.ndarray | None = None,
    input_names: Sequence[str] | None = None, check_length: bool = True, max_gap_fraction: float = 1.0,
):  # fmt: skip
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
    for nm, arr, shape in (("x", x, (M,)), ("y", y, (M,)), ("q", q, (M, 4))) + ((("z", z, (M,)),) if z is not None else ()):
        if arr.shape != shape:
            raise ValueError(f"{source}: {nm} must have shape {shape} (one row per time); got {arr.shape}.")
    if inputs.ndim != 2 or inputs.shape[0] != M or inputs.shape[1] < 1:
        raise ValueError(f"{source}: inputs must have shape ({M}, N) with N >= 1 wheels; got {inputs.shape}.")
    names = list(input_names) if input_names is not None else [f"{INPUT_PREFIX[kind]}{i + 1}" for i in range(inputs.shape[1])]

    bad_t = np.nonzero(~np.isfinite(t))[0]
    if bad_t.size:
        k = int(bad_t[0])
        raise ValueError(
            f"{_where(source, lines, k)}: the time t is blank or not finite; every row needs a time (delete the row or fill it in)."
        )
    bad_u = np.argwhere(~np.isfinite(inputs))
    if bad_u.size:
        k, c = int(bad_u[0, 0]), int(bad_u[0, 1])
        raise ValueError(
            f"{_where(source, lines, k)}: input column {names[c]} is blank or not finite (t = {t[k]:g} s); "
            "inputs may not have gaps: fill them in (e.g. interpolate the commands) or cut the trial."
        )
    _check_increasing(t, source, lines, " (remove duplicated frames, sort by time)")

    gap = ~np.isfinite(x) | ~np.isfinite(y) | ~np.all(np.isfinite(q), axis=1)
    if z is not None:
        gap |= ~np.isfinite(z)
    x[gap], y[gap], q[gap] = np.nan, np.nan, np.nan
    if z is not None:
        z[gap] = np.nan
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
                f"{source}: too many gaps: {frac:.0%} of the {M} frames have no pose (limit {max_gap_fraction:.0%}); "
                "check the marker set / rigid-body definition, or raise max_gap_fraction."
            )
    return t, x, y, q, inputs, z


# --------------------------------------------------------------------------- plausibility


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
    pairs; `kind` is `"step"`, `"speed"`, `"rate"`, `"height"`, `"lying"` or `"xyzw"`. Used by
    `warn_implausible`. `from_markers`: the poses were computed from markers (`convert_raw`),
    so their quaternions cannot be in the wrong order, but the up axis can be wrong.

    - `"step"`: the median time step is `MAX_PLAUSIBLE_STEP` (1 s) or longer: times in
      milliseconds or frame numbers.
    - `"speed"`: the shell centre's speed over windows of 0.1 s exceeds `MAX_PLAUSIBLE_SPEED`
      (5 m/s) in more than 5% of them (a window, not a frame: noise of 1 mm at 1 kHz alone
      makes 1.4 m/s from frame to frame; a single swapped marker does not count).
    - `"rate"`: the platform's rotation over windows of 0.02 s exceeds `MAX_PLAUSIBLE_RATE`
      (50 rad/s) in more than 5% of them.
    - `"height"`: the shell centre's height `z` (if given) spans more than 3 cm (5th to 95th
      percentile) and more than a quarter of its horizontal excursion: a ball rolling on a
      floor keeps it within millimetres, so the up axis is probably wrong.
    - `"lying"` (`from_markers`): the platform tilts beyond 80 deg (95th percentile; random
      inputs tilt the paper's robot up to 66 deg): the up axis is wrong, or the body markers are
      not in the platform frame.
    - `"xyzw"` (not `from_markers`): the quaternion columns look like `x, y, z, w` order. Read in the wrong order,
      the platform's tilt is its heading instead (the angle between its axis 1 and the fixed X),
      and its lean no longer follows the ball's acceleration. Reported when, read as
      `x, y, z, w`, the platform leans with the acceleration (`_lean_fit`: R^2 >= 0.5) and read
      as `w, x, y, z` much less (R^2 lower by 0.3); or when it is upside down (tilted beyond
      90 deg, 95th percentile) read as `w, x, y, z` and 30 deg less read as `x, y, z, w`; or when
      the first pose read as `w, x, y, z` is a half turn about the vertical that read as
      `x, y, z, w` is the identity (the rest pose of a rigid body defined where the trial
      starts) and the lean does not follow the acceleration better as `w, x, y, z`.
    """
    t, x, y, q = (np.asarray(a, float) for a in (t, x, y, q))
    out = []
    step = float(np.median(np.diff(t))) if t.size >= 2 else math.inf
    if t.size >= 2:
        if step >= MAX_PLAUSIBLE_STEP:
            out.append(("step", f"the median time step is {step:.6g} s ({1.0 / step:.3g} Hz)"))
            return out  # the rates below would only repeat it
    v = np.isfinite(x) & np.isfinite(y) & np.all(np.isfinite(q), axis=1)
    tv, xv, yv, qv = t[v], x[v], y[v], q[v]
    if tv.size < 3 or not np.all(np.isfinite(t)):
        return out
    i, j = _windowed(tv, 0.1)
    if i.size >= 3:
        speed = np.hypot(xv[j] - xv[i], yv[j] - yv[i]) / (tv[j] - tv[i])
        s95 = float(np.percentile(speed, 95))
        if s95 > MAX_PLAUSIBLE_SPEED:
            out.append(("speed", f"the shell centre moves at {s95:.3g} m/s (95th percentile over 0.1 s; {float(speed.max()):.3g} m/s at most)"))
    i, j = _windowed(tv, 0.02)
    if i.size >= 3:
        dot = np.clip(np.abs(np.sum(qv[i] * qv[j], axis=1)), 0.0, 1.0)
        rate = 2.0 * np.arccos(dot) / (tv[j] - tv[i])
        r95 = float(np.percentile(rate, 95))
        if r95 > MAX_PLAUSIBLE_RATE:
            out.append(("rate", f"the platform turns at {r95:.3g} rad/s (95th percentile over 0.02 s)"))
    if z is not None:
        zv = np.asarray(z, float)[v]
        zv = zv[np.isfinite(zv)]
        if zv.size >= 3:
            dz = float(np.ptp(np.percentile(zv, [5, 95])))
            dh = max(float(np.ptp(xv)), float(np.ptp(yv)))
            if dz > 0.03 and dz > 0.25 * dh:
                out.append(("height", f"the shell centre's height z varies by {100 * dz:.3g} cm while it moves "
                                      f"{100 * dh:.3g} cm horizontally"))  # fmt: skip
    tilt = float(np.percentile(_tilt_deg(qv[:, 1], qv[:, 2]), 95))
    if from_markers:
        if tilt > 80.0:
            out.append(("lying", f"the platform tilts {tilt:.0f} deg from upright (95th percentile)"))
        return out
    tilt_swapped = float(np.percentile(_tilt_deg(qv[:, 0], qv[:, 1]), 95))  # columns (qw, qx, qy, qz) = (x, y, z, w)
    fit = fit_swapped = math.nan
    if step < 0.05 and t[-1] - t[0] >= 1.0:  # enough frames over enough time to see accelerations
        fit = _lean_fit(t, x, y, q, v)
        fit_swapped = _lean_fit(t, x, y, q[:, [3, 0, 1, 2]], v)
    half_turn = abs(qv[0, 3]) > math.cos(math.radians(5.0))  # the first pose: a half turn about Z, or x, y, z, w of q = 1
    if fit_swapped >= 0.5 and fit <= fit_swapped - 0.3:
        out.append(("xyzw", f"read as x, y, z, w the platform leans with the ball's acceleration (R^2 {fit_swapped:.2f}); "
                            f"read as w, x, y, z it does not (R^2 {fit:.2f})"))  # fmt: skip
    elif tilt > 90.0 and tilt_swapped < tilt - 30.0:  # upside down, inside a ball
        out.append(("xyzw", f"read as w, x, y, z the platform tilts up to {tilt:.0f} deg from upright; read as x, y, z, w it "
                            f"stays within {tilt_swapped:.0f} deg"))  # fmt: skip
    elif half_turn and not fit > fit_swapped:  # (NaN fits: too little acceleration to tell)
        out.append(("xyzw", "the first pose read as w, x, y, z is a half turn about the vertical (qz = "
                            f"{qv[0, 3]:+.3f}); read as x, y, z, w it is the identity, the rest pose of a rigid body defined "
                            "where the trial starts"))  # fmt: skip
    return out


_CAUSES = {
    "step": "the times look like milliseconds or frame numbers; give t in seconds",
    "speed": "beyond any rolling robot of this size (< {speed:g} m/s): positions in millimetres or centimetres read as "
    "metres ({units}), or times in the wrong unit",
    "rate": "beyond any rolling robot (< {rate:g} rad/s): times in the wrong unit or a wrong frame rate, or frames out "
    "of order",
    "xyzw": "the quaternion columns look like x, y, z, w order; reorder them to qw, qx, qy, qz (scalar first)",
    "height": "a ball rolling on a floor keeps it within millimetres: {up}",
    "lying": "a platform hanging in a ball stays near upright: {up}, or the body markers are not in the platform frame "
    "(give alignment)",
}


def warn_implausible(
    t, x, y, q, source: str, z=None, *, from_markers: bool = False, units_hint: str = "convert them to metres",
    up_hint: str = "is z the height, with the Z axis up?",
) -> list[str]:  # fmt: skip
    """Issue a `CaptureWarning` for each finding of `implausible`, naming `source` and the likely
    cause (`units_hint`: how to say that positions are in millimetres; `up_hint`: what to check
    when the up axis looks wrong). Returns the messages."""
    msgs = []
    for kind, detail in implausible(t, x, y, q, z, from_markers=from_markers):
        cause = _CAUSES[kind].format(speed=MAX_PLAUSIBLE_SPEED, rate=MAX_PLAUSIBLE_RATE, units=units_hint, up=up_hint)
        msgs.append(f"{source}: {detail}: {cause}.")
        warnings.warn(msgs[-1], CaptureWarning, stacklevel=3)
    return msgs


# --------------------------------------------------------------------------- Trial


class Trial(eqx.Module):
    """One captured (or synthetic) trial: poses, inputs and times, as numpy arrays.

    **Fields:**
    - `t`: `(M,)` times [s], strictly increasing.
    - `x`, `y`: `(M,)` shell-centre position in the fixed frame (Z up) [m]; NaN in gap frames.
    - `q`: `(M, 4)` unit quaternion `(w, x, y, z)` of the platform, rotating platform components
      into fixed ones (as `jsphere.State.q`), sign-continuous; NaN rows are gaps.
    - `inputs`: `(M, N)` wheel speeds `chi_dot_i` [rad/s] or axle torques `K_i` [N m]; never NaN.
    - `kind`: `"wheel_speeds"` or `"torques"` (static).
    - `z`: `(M,)` shell-centre height [m] or `None`.
    - `name`: a label (the file stem for trials read from files) (static).

    A frame is a gap if any of its pose values is missing; then all its pose values are NaN.
    Construction validates (strictly increasing finite times, finite inputs, unit quaternions:
    a norm off by more than 1e-3 is an error, smaller deviations are normalised) but does not
    require a minimum length; the file readers do (`MIN_VALID_FRAMES`, `MIN_DURATION`).
    """

    t: np.ndarray
    x: np.ndarray
    y: np.ndarray
    q: np.ndarray
    inputs: np.ndarray
    kind: str = eqx.field(static=True)
    z: np.ndarray | None = None
    name: str = eqx.field(static=True, default="trial")

    def __init__(self, t, x, y, q, inputs, kind: str, z=None, name: str = "trial"):
        t, x, y, q, inputs, z = _checked(t, x, y, q, inputs, kind, z, source=f"trial {name!r}", check_length=False)
        self.t, self.x, self.y, self.q, self.inputs, self.kind, self.z, self.name = t, x, y, q, inputs, kind, z, name

    # -------------------------------------------------------------- views
    @property
    def n_wheels(self) -> int:
        return int(self.inputs.shape[1])

    @property
    def n_frames(self) -> int:
        return int(self.t.shape[0])

    @property
    def duration(self) -> float:
        """`t[-1] - t[0]` [s]."""
        return float(self.t[-1] - self.t[0])

    @property
    def valid(self) -> np.ndarray:
        """`(M,)` bool: True where the frame has a pose (not a gap)."""
        ok = np.isfinite(self.x) & np.isfinite(self.y) & np.all(np.isfinite(self.q), axis=1)
        if self.z is not None:
            ok &= np.isfinite(self.z)
        return ok

    @property
    def input_names(self) -> list[str]:
        """`["chi_dot_1", ...]` or `["K_1", ...]`."""
        return [f"{INPUT_PREFIX[self.kind]}{i + 1}" for i in range(self.n_wheels)]

    def controls(self, kind: str = "cubic") -> WheelSpeeds | Torques:
        """The recorded inputs as a control: `WheelSpeeds` or `Torques`, `.from_samples(t,
        inputs, kind=kind)` (cubic Hermite by default; held constant outside `[t0, t1]`)."""
        cls = WheelSpeeds if self.kind == "wheel_speeds" else Torques
        return cls.from_samples(jnp.asarray(self.t), jnp.asarray(self.inputs), kind=kind)

    def state0_guess(self, params: RobotParams) -> State:
        """A `State` for `t[0]`: orientation and position of the first valid frame (even if it is
        later than `t[0]`), shell frame aligned with the fixed frame, velocities and wheel angles
        zero. Good for trials that start at rest."""
        k = np.nonzero(self.valid)[0]
        if k.size == 0:
            raise ValueError(f"trial {self.name!r}: no valid frame, so no initial pose.")
        k = int(k[0])
        dt = params.R0.dtype
        z3 = jnp.zeros(3, dt)
        return State(
            q=jnp.asarray(self.q[k], dt), q_shell=jnp.array([1.0, 0.0, 0.0, 0.0], dt), omega=z3, Omega=z3,
            x=jnp.asarray(self.x[k], dt), y=jnp.asarray(self.y[k], dt), chi=jnp.zeros(params.n_wheels, dt),
        )  # fmt: skip

    def replace(self, **changes) -> Trial:
        """A copy with some fields changed (validated again)."""
        d = {"t": self.t, "x": self.x, "y": self.y, "q": self.q, "inputs": self.inputs, "kind": self.kind}
        d.update({"z": self.z, "name": self.name})
        d.update(changes)
        return Trial(**d)

    def __repr__(self) -> str:
        return (
            f"Trial(name={self.name!r}, kind={self.kind!r}, frames={self.n_frames}, valid={int(self.valid.sum())}, "
            f"wheels={self.n_wheels}, duration={self.duration:.3f} s)"
        )


# --------------------------------------------------------------------------- CSV format

_UNITS_SCALE = {"m": 1.0, "mm": 1e-3}
_META = re.compile(r"^#\s*(\w+)\s*[:=]\s*(.*?)\s*$")


def detect_position_units(values: np.ndarray, z: np.ndarray | None = None) -> str | None:
    """Guess whether positions are in metres or millimetres: `"m"`, `"mm"` or `None` (cannot tell).

    A height `z` of the shell centre (its radius, 0.03-1 m) decides if given; otherwise any
    coordinate beyond 20 (a 20 m lab is implausible) means millimetres. Small numbers alone do
    not prove metres (a robot that moved a few mm), so they give `None`.
    """
    if z is not None:
        zz = np.abs(z[np.isfinite(z)])
        if zz.size:
            med = float(np.median(zz))
            if 0.03 <= med <= 1.0:
                return "m"
            if 30.0 <= med <= 1000.0:
                return "mm"
    v = np.abs(np.asarray(values, float))
    v = v[np.isfinite(v)]
    if v.size and float(v.max()) > 20.0:
        return "mm"
    return None


def _resolve_units(declared: str, detected: str | None, source: str, evidence: str) -> float:
    """Scale factor to metres from the declared units (`"auto"`, `"m"`, `"mm"`) and the detected ones."""
    if declared not in ("auto", "m", "mm"):
        raise ValueError(f"{source}: units must be 'auto', 'm' or 'mm'; got {declared!r}.")
    if declared == "auto":
        return _UNITS_SCALE[detected or "m"]
    if detected is not None and detected != declared:
        raise ValueError(
            f"{source}: units={declared!r} was declared but the data look like {'millimetres' if detected == 'mm' else 'metres'} "
            f"({evidence}); pass units={detected!r} (or units='auto') if that is right, or fix the file."
        )
    return _UNITS_SCALE[declared]


def _input_columns(header: list[str], source: str) -> tuple[str, list[int]]:
    """The kind and the column indices of `chi_dot_1..N` or `K_1..N`, in wheel order."""
    found = {}
    for kind, prefix in INPUT_PREFIX.items():
        pat = re.compile(rf"^{re.escape(prefix)}(\d+)$")
        cols = {int(m.group(1)): j for j, h in enumerate(header) if (m := pat.match(h))}
        if cols:
            found[kind] = cols
    if len(found) == 2:
        raise ValueError(
            f"{source}: both chi_dot_* and K_* columns are present; a trial holds one kind of input "
            "(wheel speeds or torques): keep one set of columns."
        )
    if not found:
        raise ValueError(
            f"{source}: no input columns; add chi_dot_1..chi_dot_N (wheel speeds, rad/s) or K_1..K_N (torques, N m). "
            f"Header: {header}"
        )
    kind, cols = next(iter(found.items()))
    n = max(cols)
    missing = [i for i in range(1, n + 1) if i not in cols]
    if missing:
        prefix = INPUT_PREFIX[kind]
        raise ValueError(
            f"{source}: wheel columns must be numbered 1..N without gaps; missing {', '.join(f'{prefix}{i}' for i in missing)} "
            f"(found {', '.join(f'{prefix}{i}' for i in sorted(cols))})."
        )
    return kind, [cols[i] for i in range(1, n + 1)]


def _parse_cell(cell: str, source: str, line: int, column: str) -> float:
    s = cell.strip()
    if s == "":
        return math.nan
    try:
        return float(s)
    except ValueError:
        raise ValueError(f"{source}, line {line}, column {column}: {s!r} is not a number.") from None


def read_trial(path, *, units: str = "auto", max_gap_fraction: float = 0.5) -> Trial:
    """Read one trial CSV (format: `docs/capture.md`).

    Lines starting with `#` before the header are comments; `# units: mm` declares the
    position units (`x, y, z`; default metres). Columns `t, x, y, qw, qx, qy, qz` are required,
    then `chi_dot_1..chi_dot_N` or `K_1..K_N`, optionally `z`; other columns are ignored.
    Blank or `nan` pose cells make the frame a gap.

    **Arguments:**
    - `units`: `"auto"` (the file's `# units:` line, else detected, else metres), `"m"` or
      `"mm"`. A declared unit that contradicts the file's `# units:` line or the detected one
      is an error.
    - `max_gap_fraction`: the largest fraction of gap frames accepted.

    Raises `ValueError` naming the file, the line (1-based, as an editor counts) and the column
    of the first problem: missing columns, mixed or misnumbered input columns, blank/NaN times
    or inputs, non-increasing or duplicated times, non-unit quaternions, too-short trials (fewer
    than 10 valid frames or under 0.2 s), too many gaps, wrong units.
    """
    path = Path(path)
    source = str(path)
    if not path.exists():
        raise FileNotFoundError(f"trial file {path} does not exist.")
    meta: dict[str, str] = {}
    lines_iter = read_text(path).splitlines()
    k = 0
    while k < len(lines_iter) and (lines_iter[k].lstrip().startswith("#") or not lines_iter[k].strip()):
        m = _META.match(lines_iter[k].strip())
        if m:
            meta[m.group(1).lower()] = m.group(2)
        k += 1
    if k == len(lines_iter):
        raise ValueError(
            f"{source}: no header line; the first non-comment line must name the columns t, x, y, qw, qx, qy, qz, ..."
        )
    header_line = k + 1
    rows = csv_rows("\n".join(lines_iter[k:]), source)
    header = [h.strip() for h in rows[0]]
    missing = [c for c in POSE_COLUMNS if c not in header]
    if missing:
        raise ValueError(
            f"{source}, line {header_line}: missing required column(s) {', '.join(missing)}; a trial CSV needs "
            f"{', '.join(POSE_COLUMNS)} and chi_dot_1..N or K_1..N (see docs/capture.md){separator_hint(rows[0])}."
        )
    kind, in_cols = _input_columns(header, f"{source}, line {header_line}")
    check_unique_columns(header, f"{source}, line {header_line}", [*POSE_COLUMNS, "z", *(header[j] for j in in_cols)])
    col = {h: j for j, h in enumerate(header)}
    has_z = "z" in col
    use = [col[c] for c in POSE_COLUMNS] + ([col["z"]] if has_z else []) + in_cols
    names = list(POSE_COLUMNS) + (["z"] if has_z else []) + [header[j] for j in in_cols]
    # drop trailing empty lines
    body = rows[1:]
    while body and not any(c.strip() for c in body[-1]):
        body.pop()
    data = np.empty((len(body), len(use)))
    line_no = np.arange(len(body)) + header_line + 1
    for i, row in enumerate(body):
        if len(row) != len(header):
            cut = " (the file looks cut off: copy or export it again)" if i == len(body) - 1 and len(row) < len(header) else ""
            raise ValueError(f"{source}, line {line_no[i]}: {len(row)} cells but the header has {len(header)} columns{cut}.")
        for jj, j in enumerate(use):
            data[i, jj] = _parse_cell(row[j], source, int(line_no[i]), names[jj])
    if data.shape[0] == 0:
        raise ValueError(f"{source}: the trial is too short: no data rows after the header.")

    file_units = meta.get("units")
    if file_units is not None and file_units not in ("m", "mm"):
        raise ValueError(f"{source}: the '# units:' line says {file_units!r}; it must be 'm' or 'mm'.")
    zcol = data[:, 7] if has_z else None
    detected = detect_position_units(data[:, 1:3], zcol)
    if file_units is not None:
        if units != "auto" and units != file_units:
            raise ValueError(
                f"{source}: units={units!r} was declared but the file's '# units:' line says {file_units!r}; "
                "drop the argument or fix the file."
            )
        scale = _resolve_units(file_units, detected, source, "positions/height")
    else:
        scale = _resolve_units(units, detected, source, "magnitude of the positions/height")
    x, y = data[:, 1] * scale, data[:, 2] * scale
    z = zcol * scale if has_z else None
    t, x, y, q, inputs, z = _checked(
        data[:, 0], x, y, data[:, 3:7], data[:, 8 if has_z else 7 :], kind, z, source=source, lines=line_no,
        input_names=[header[j] for j in in_cols], max_gap_fraction=max_gap_fraction,
    )  # fmt: skip
    name = meta.get("name", path.stem)
    warn_implausible(t, x, y, q, source, z, units_hint="declare '# units: mm' in the file (or pass units='mm')")
    return Trial(t, x, y, q, inputs, kind, z, name=name)


def read_trials(paths: Iterable, **kwargs) -> list[Trial]:
    """`read_trial` on each path (a directory stands for its `*.csv` files, sorted; hidden
    files, such as a temporary file a killed writer left, are skipped). A directory without
    such files is an `InputError` naming it."""
    out = []
    for p in paths:
        p = Path(p)
        if p.is_dir():
            files = [f for f in sorted(p.glob("*.csv")) if not f.name.startswith(".")]
            if not files:
                raise InputError(f"{p} holds no trial CSV files (*.csv); give the folder of the trials or the files themselves.")
            out += [read_trial(f, **kwargs) for f in files]
        else:
            out.append(read_trial(p, **kwargs))
    return out


def _fmt(v: float, spec: str) -> str:
    return "" if not np.isfinite(v) else format(v + 0.0, spec)  # + 0.0: no "-0"


def trial_to_csv(trial: Trial) -> str:
    """The text of `write_trial`: times to 1 µs, positions to 1 µm, quaternions to 1e-9,
    inputs to 10 significant digits; gaps as blank cells."""
    cols = list(POSE_COLUMNS) + (["z"] if trial.z is not None else []) + trial.input_names
    out = [
        "# jsphere trial v1",
        f"# name: {trial.name}",
        f"# kind: {trial.kind}",
        "# units: m",
        ",".join(cols),
    ]
    for k in range(trial.n_frames):
        cells = [_fmt(trial.t[k], ".6f"), _fmt(trial.x[k], ".6f"), _fmt(trial.y[k], ".6f")]
        cells += [_fmt(v, ".9f") for v in trial.q[k]]
        if trial.z is not None:
            cells.append(_fmt(trial.z[k], ".6f"))
        cells += [_fmt(v, ".10g") for v in trial.inputs[k]]
        out.append(",".join(cells))
    return "\n".join(out) + "\n"


def write_trial(path, trial: Trial) -> None:
    """Write `trial` to `path` in the trial CSV format (atomically; see `trial_to_csv`)."""
    if not isinstance(trial, Trial):
        raise TypeError(f"write_trial: expected a jsphere.Trial; got {type(trial).__name__}.")
    atomic_write_text(path, trial_to_csv(trial))


# --------------------------------------------------------------------------- synthetic trials


def _smoothstep(u):
    """`0` for `u <= 0`, `1` for `u >= 1`, `u^3 (10 - 15 u + 6 u^2)` between (C2)."""
    u = jnp.clip(u, 0.0, 1.0)
    return u * u * u * (10.0 + u * (-15.0 + 6.0 * u))


class RandomSines(eqx.Module):
    """`f_i(t) = ramp(t) sum_k amp[i, k] sin(2 pi freq[i, k] t + phase[i, k])` per wheel i, with a
    C2 ramp from 0 at `t = 0` to 1 at `t = ramp_time` (so the robot starts from rest smoothly)."""

    amp: Float[Array, "N K"]
    freq: Float[Array, "N K"]
    phase: Float[Array, "N K"]
    ramp_time: Float[Array, ""]

    def __call__(self, t):
        s = _smoothstep(t / self.ramp_time)
        return s * jnp.sum(self.amp * jnp.sin(2 * jnp.pi * self.freq * t + self.phase), axis=-1)


def default_amplitude(params: RobotParams, kind: str) -> float:
    """A moderate input amplitude: for wheel speeds the largest wheel rate of the kinematic
    model (2.9) rolling at 0.3 m/s (over 8 headings) [rad/s]; for torques `0.05 m g R_m` [N m]
    (5% of the platform's largest gravity torque)."""
    if kind == "wheel_speeds":
        from ..model.kinematics import kinematic_wheel_speeds

        h = np.linspace(0.0, 2 * np.pi, 8, endpoint=False)
        v = jnp.asarray(0.3 * np.stack([np.cos(h), np.sin(h)], axis=1), params.R0.dtype)
        return float(jnp.max(jnp.abs(jax.vmap(lambda r: kinematic_wheel_speeds(params, r))(v))))
    return float(0.05 * params.m * params.g * params.R_m)


def random_inputs(
    params: RobotParams,
    t1: float,
    *,
    kind: str = "wheel_speeds",
    amplitude: float | None = None,
    n_sines: int = 3,
    f_min: float = 0.2,
    f_max: float = 1.5,
    ramp_time: float = 0.5,
    seed: int = 0,
) -> WheelSpeeds | Torques:
    """A smooth, exciting input program: per wheel, `n_sines` sines of random frequencies in
    `[f_min, f_max]` [Hz], phases and weights, bounded by `amplitude` (rad/s for wheel speeds, N m
    for torques; default `default_amplitude`), ramped in from 0 over `ramp_time` [s].

    Returns `WheelSpeeds(RandomSines(...))` or `Torques(RandomSines(...))`: a Module whose
    coefficients are array leaves, so programs from other seeds reuse one compilation. `t1` is
    accepted for symmetry with `synthetic_trial` and checked, but the program is defined for all t.
    """
    if kind not in KINDS:
        raise ValueError(f"random_inputs: kind must be one of {KINDS}; got {kind!r}.")
    if not t1 > 0:
        raise ValueError(f"random_inputs: t1 must be positive; got {t1}.")
    if not (0 < f_min <= f_max):
        raise ValueError(f"random_inputs: need 0 < f_min <= f_max; got {f_min}, {f_max}.")
    if not ramp_time > 0:
        raise ValueError(f"random_inputs: ramp_time must be positive; got {ramp_time}.")
    a = default_amplitude(params, kind) if amplitude is None else float(amplitude)
    rng = np.random.default_rng(seed)
    N = params.n_wheels
    w = rng.uniform(0.5, 1.0, (N, n_sines))
    amp = a * w / n_sines
    freq = rng.uniform(f_min, f_max, (N, n_sines))
    phase = rng.uniform(0, 2 * np.pi, (N, n_sines))
    dt = params.R0.dtype
    fn = RandomSines(jnp.asarray(amp, dt), jnp.asarray(freq, dt), jnp.asarray(phase, dt), jnp.asarray(ramp_time, dt))
    return WheelSpeeds(fn) if kind == "wheel_speeds" else Torques(fn)


@eqx.filter_jit
def eval_controls(controls, ts: Float[Array, " T"]) -> Float[Array, "T N"]:
    """`controls(t)` at each of `ts` (compiled once per control structure)."""
    return jax.vmap(controls)(ts)


def _dropout_mask(rng: np.random.Generator, M: int, dropout: float, max_burst: int = 5) -> np.ndarray:
    """`(M,)` bool, True where a frame is dropped: bursts of 1..`max_burst` frames (uniform,
    mean 3) start with probability `dropout / 3`, so that about a fraction `dropout` is lost.
    Frame 0 is always kept (the initial pose)."""
    drop = np.zeros(M, bool)
    if dropout <= 0:
        return drop
    starts = np.nonzero(rng.random(M) < dropout / ((1 + max_burst) / 2))[0]
    lengths = rng.integers(1, max_burst + 1, starts.size)
    for s, n in zip(starts, lengths):
        drop[s : s + n] = True
    drop[0] = False
    return drop


def synthetic_trial(
    params: RobotParams,
    controls: WheelSpeeds | Torques,
    t1: float,
    *,
    state0: State | None = None,
    rate: float = 100.0,
    pos_sd: float = 1e-3,
    rot_sd_deg: float = 0.5,
    dropout: float = 0.0,
    seed: int = 0,
    name: str = "synthetic",
    rtol: float = 1e-10,
    atol: float = 1e-12,
) -> Trial:
    """A capture-like trial from a simulation.

    Simulates `controls` from `state0` (default `State.at_rest(params)`) with `jsphere.simulate`
    (tolerances `rtol, atol`; errors raised), samples at `rate` [Hz] from 0 to `t1` [s], and
    records:
    - positions `x, y` plus Gaussian noise of `pos_sd` [m] per coordinate;
    - the platform quaternion times a random small rotation (platform frame) with a rotation
      vector of `rot_sd_deg` [deg] standard deviation per axis;
    - gaps (NaN poses) in bursts of 1-5 frames covering about a fraction `dropout` of the
      frames (the first frame is kept);
    - the *commanded* inputs: `controls(t)` at the sample times (for wheel speeds the commanded
      `chi_dot`, for torques `K`), without noise.

    Deterministic for a given `seed` (`numpy.random.default_rng`).
    """
    from ..solve.simulate import simulate

    if not rate > 0 or not t1 > 0:
        raise ValueError(f"synthetic_trial: rate and t1 must be positive; got rate={rate}, t1={t1}.")
    if not 0.0 <= dropout < 1.0:
        raise ValueError(f"synthetic_trial: dropout must be in [0, 1); got {dropout}.")
    ts = np.arange(math.floor(t1 * rate + 1e-9) + 1) / rate
    state0 = State.at_rest(params) if state0 is None else state0
    traj = simulate(params, state0, controls, float(ts[-1]), ts=ts, rtol=rtol, atol=atol, throw=True)
    rng = np.random.default_rng(seed)
    M = ts.shape[0]
    x = np.asarray(traj.x) + rng.normal(0.0, pos_sd, M)
    y = np.asarray(traj.y) + rng.normal(0.0, pos_sd, M)
    noise = quat_from_rotvec_np(rng.normal(0.0, np.deg2rad(rot_sd_deg), (M, 3)))
    q = quat_mul_np(np.asarray(traj.q), noise)
    u = np.asarray(eval_controls(controls, jnp.asarray(ts, params.R0.dtype)))
    drop = _dropout_mask(rng, M, dropout)
    x[drop], y[drop], q[drop] = np.nan, np.nan, np.nan
    kind = "wheel_speeds" if isinstance(controls, WheelSpeeds) else "torques"
    return Trial(ts, x, y, q, u, kind, None, name=name)
