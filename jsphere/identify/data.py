"""The trials as the fit sees them: packed into arrays of a common length, and the per-trial
nuisance parameters (the initial state the capture does not give)."""

from __future__ import annotations

import dataclasses
import hashlib
from collections.abc import Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from .._runtime.arrays import to_jax
from .._runtime.errors import InputError
from ..capture.onboard import refuse_onboard
from ..capture.validation import KINDS
from ..model.params import RobotParams
from ..model.rotations import quat_conj_np, quat_log_np, quat_mul_np

_START = ("Omega0_x", "Omega0_y", "Omega0_z", "rot0_x", "rot0_y", "rot0_z", "x0", "y0")
#: nuisance parameters per trial, in order
NUISANCE = {"wheel_speeds": _START, "torques": _START + ("omega0_x", "omega0_y", "omega0_z")}
#: the nuisance parameter of a trial's clock offset (`fit(..., fit_time_offset=True)`), last in order
TIME_OFFSET = "time_offset"


def nuisance_names(kind: str, time_offset: bool = False) -> tuple[str, ...]:
    """The nuisance parameters of one trial, in order: `NUISANCE[kind]`, then `time_offset`
    when the clock offset is fitted."""
    return NUISANCE[kind] + ((TIME_OFFSET,) if time_offset else ())


def offset_from_nuisance(v, max_offset: float):
    """The clock offset [s] of the nuisance value `v`: `max_offset tanh(v / max_offset)`, so that
    every value keeps within `+- max_offset` (and `v` is the offset itself when it is small)."""
    return max_offset * jnp.tanh(v / max_offset)


def nuisance_from_offset(offset, max_offset: float):
    """The inverse of `offset_from_nuisance` (offsets clipped to 0.999 `max_offset`)."""
    return max_offset * np.arctanh(np.clip(np.asarray(offset, float) / max_offset, -0.999, 0.999))


#: the arrays of a `FitData`, one row per trial
ARRAYS = ("ts", "tc", "u", "t1", "x", "y", "q", "wpos", "wrot", "xy0", "q0")


@dataclasses.dataclass(frozen=True)
class FitData:
    """Trials packed into arrays of a common length `M` (padded samples are masked).

    `ts (T, M)`: capture times from 0 (padded with the last time); `tc (T, M)`: control knot
    times (padded beyond the end, values held); `u (T, M, N)`: inputs; `t1 (T,)`: durations;
    `x, y (T, M)`, `q (T, M, 4)`: measurements (0 / identity at gaps); `wpos, wrot (T, M)`:
    1.0 where the position / orientation was measured; `xy0 (T, 2)`, `q0 (T, 4)`: the first
    measured pose of each trial. `max_offset` [s]: the bound of each trial's clock offset when it
    is fitted (its inputs then drive the model at `t + offset`), 0 when it is not.
    """

    ts: np.ndarray
    tc: np.ndarray
    u: np.ndarray
    t1: np.ndarray
    x: np.ndarray
    y: np.ndarray
    q: np.ndarray
    wpos: np.ndarray
    wrot: np.ndarray
    xy0: np.ndarray
    q0: np.ndarray
    kind: str
    names: tuple[str, ...]
    lengths: tuple[int, ...]
    t_start: tuple[float, ...]
    max_offset: float = 0.0

    #: the model of a trial (`jsphere.identify.residuals._functions`)
    measure = "pose"
    #: the residuals of one frame: position (2) and orientation (3)
    width = 5
    #: the channels, each with its noise level
    channels = ("position", "orientation")

    @property
    def nuisance(self) -> tuple[str, ...]:
        """The names of each trial's nuisance parameters (`nuisance_names`)."""
        return nuisance_names(self.kind, self.max_offset > 0)

    @property
    def n_measured(self) -> int:
        """The measured values of all trials: 2 per measured position, 3 per orientation."""
        return int(2 * self.wpos.sum() + 3 * self.wrot.sum())

    def aux_shapes(self) -> tuple[tuple[int, ...], ...]:
        """The shapes of a trial's simulated poses `(x, y, q)`."""
        M = self.ts.shape[1]
        return (M,), (M,), (M, 4)

    def arrays(self) -> dict[str, jax.Array]:
        return {k: to_jax(getattr(self, k)) for k in ARRAYS}

    @classmethod
    def stacked(cls, rows: Sequence[dict], kind: str, max_offset: float = 0.0) -> FitData:
        """The trials `rows` (each its `ARRAYS`, `name`, `length` and `start`) packed."""
        arrays = {k: np.stack([r[k] for r in rows]) for k in ARRAYS}
        info = {
            k: tuple(r[key] for r in rows)
            for k, key in (("names", "name"), ("lengths", "length"), ("t_start", "start"))
        }
        return cls(**arrays, **info, kind=kind, max_offset=float(max_offset))

    def fingerprint(self) -> str:
        h = hashlib.sha256(self.kind.encode())
        for k in ("ts", "u", "x", "y", "q", "wpos", "wrot"):
            h.update(np.ascontiguousarray(getattr(self, k)).tobytes())
        return h.hexdigest()


def pack_trials(trials: Sequence, params: RobotParams, *, max_offset: float = 0.0, where: str = "fit") -> FitData:
    """Check the trials against `params` and pack them (see `FitData`; `max_offset` > 0: each
    trial's clock offset is fitted within `+- max_offset` seconds).

    A trial needs `t (M,)`, `x, y (M,)` [m] (NaN at gaps), `q (M, 4)` (platform -> fixed,
    NaN rows at gaps), `inputs (M, N)`, `kind` and `name` (the `Trial` of `jsphere.capture.trial`);
    an onboard-sensor trial is an `InputError` naming the command `where`.
    """
    trials = list(trials)
    if not trials:
        raise InputError("fit: no trials given.")
    refuse_onboard(trials, where)
    kinds = {getattr(t, "kind", None) for t in trials}
    if len(kinds) != 1 or next(iter(kinds)) not in KINDS:
        raise InputError(
            f"fit: all trials must have the same input kind, one of {KINDS}; got {sorted(map(str, kinds))}."
        )
    kind = next(iter(kinds))
    N = params.n_wheels
    M = max(len(np.asarray(t.t)) for t in trials)
    rows = []
    for k, tr in enumerate(trials):
        name, t, u, x, y, q, vp, vr = _checked_arrays(tr, k, N)
        m = len(t)
        qn = np.where(vr[:, None], q, [1.0, 0.0, 0.0, 0.0])
        qn = qn / np.linalg.norm(qn, axis=1, keepdims=True)
        t0 = t[0]
        dt = (t[-1] - t[0]) / (m - 1)

        def pad(a, v, m=m):
            return np.concatenate([a, np.broadcast_to(v, (M - m,) + a.shape[1:])])

        rows.append(
            {
                "ts": np.concatenate([t - t0, np.full(M - m, t[-1] - t0)]),
                "tc": np.concatenate([t - t0, t[-1] - t0 + dt * np.arange(1, M - m + 1)]),
                "u": pad(u, u[-1]),
                "t1": t[-1] - t0,
                "x": pad(np.where(vp, x, 0.0), 0.0),
                "y": pad(np.where(vp, y, 0.0), 0.0),
                "q": pad(qn, np.array([1.0, 0.0, 0.0, 0.0])),
                "wpos": pad(vp.astype(np.float64), 0.0),
                "wrot": pad(vr.astype(np.float64), 0.0),
                "xy0": np.array([x[vp][0], y[vp][0]]),
                "q0": qn[vr][0],
                "name": name,
                "length": m,
                "start": float(t0),
            }
        )
    return FitData.stacked(rows, kind, max_offset)


def _checked_arrays(tr, k: int, N: int):
    """The name and float64 arrays `t, inputs, x, y, q` of trial number `k`, and where its
    position and orientation were measured; `InputError` for a trial the fit cannot use."""
    name = str(getattr(tr, "name", f"trial{k}"))
    t = np.asarray(tr.t, np.float64)
    u = np.asarray(tr.inputs, np.float64)
    x, y = np.asarray(tr.x, np.float64), np.asarray(tr.y, np.float64)
    q = np.asarray(tr.q, np.float64)
    if u.ndim != 2 or u.shape[1] != N:
        raise InputError(
            f"fit: trial {name!r} has inputs for {u.shape[-1] if u.ndim == 2 else '?'} wheels (shape {u.shape}) but the robot has {N}; use parameters with the same wheel count."
        )
    m = len(t)
    if m < 4 or u.shape[0] != m or x.shape != (m,) or y.shape != (m,) or q.shape != (m, 4):
        raise InputError(
            f"fit: trial {name!r}: t, x, y, q, inputs must have the same number of samples (>= 4); got {m}, {x.shape}, {y.shape}, {q.shape}, {u.shape}."
        )
    if not np.all(np.diff(t) > 0):
        raise InputError(f"fit: trial {name!r}: times must be strictly increasing.")
    if not np.all(np.isfinite(u)):
        raise InputError(f"fit: trial {name!r}: the inputs contain NaN or inf.")
    vp = np.isfinite(x) & np.isfinite(y)
    vr = np.all(np.isfinite(q), axis=1)
    if vp.sum() < 2 or vr.sum() < 2:
        raise InputError(f"fit: trial {name!r} has fewer than 2 measured frames.")
    return name, t, u, x, y, q, vp, vr


def nuisance_values(data: FitData, nu_i) -> dict[str, float]:
    """A trial's nuisance values by name, its clock offset in seconds (`offset_from_nuisance`)."""
    m = data.max_offset
    return {k: float(offset_from_nuisance(v, m)) if k == TIME_OFFSET else float(v) for k, v in zip(data.nuisance, nu_i)}


def trial_errors(data: FitData, pose) -> list[dict[str, Any]]:
    """Per trial, from the simulated poses `pose = (x, y, q)` `(T, M, ...)`: where its position and
    orientation were measured (`wp`, `wr`), the position errors `ep (m, 2)` [m] and orientation
    errors `er (m, 3)` [rad] (rotation vectors of `q_sim^-1 q_meas`), and the `series` of its
    figures (`t`, the measured `x`, `y`, NaN at gaps, and the simulated `x_sim`, `y_sim`)."""
    xs, ys, qs = (np.asarray(a) for a in pose)
    with np.errstate(divide="ignore", invalid="ignore"):  # (padding: zero quaternions)
        rot_err = quat_log_np(quat_mul_np(quat_conj_np(qs), data.q))
    out = []
    for i, m in enumerate(data.lengths):
        wp, wr = data.wpos[i, :m] > 0, data.wrot[i, :m] > 0
        series = {
            "t": data.ts[i, :m] + data.t_start[i],
            "x": np.where(wp, data.x[i, :m], np.nan),
            "y": np.where(wp, data.y[i, :m], np.nan),
            "x_sim": xs[i, :m],
            "y_sim": ys[i, :m],
        }
        ep = np.stack([xs[i, :m] - data.x[i, :m], ys[i, :m] - data.y[i, :m]], 1)
        out.append({"wp": wp, "wr": wr, "ep": ep, "er": rot_err[i, :m], "series": series})
    return out
