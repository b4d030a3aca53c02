"""The verdict on a fit of onboard-sensor trials, per channel (gyro, accelerometer, encoders).

The rules are those of `jsphere.identify.verdict` for a capture, with the sensors' channels in
place of position and orientation:

- each channel's noise floor comes from the readings alone (`channel_floors`: third
  differences, as `jsphere.identify.verdict.third_differences` takes them of a capture); the
  encoders' floor is at least their quantisation `q / sqrt(12)`, `q` one count;
- `misfit` when a channel's residual sigma (all trials, or the worst trial) is more than `FAR`
  times its floor, or `MODERATE` times with a lag-1 autocorrelation above `CORRELATED`;
- `misfit` with the diagnosis "model error" when a trial's residual series are not white
  (Ljung-Box over every trial and series together, `jsphere.identify.whiteness`); the reason
  names what could be missing, the IMU's mounting first where the gyro's or the
  accelerometer's residuals are correlated, roller slip where only the encoders' are;
- `not_converged` when the optimiser did not converge; otherwise `converged`.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np

from . import whiteness
from .onboard import CHANNELS, UNITS, OnboardData, encoder_quantum
from .verdict import CORRELATED, FAR, MODERATE, _coefficients, _runs, _sigma, _x, lag1, robust_sd

#: the smallest floors the residuals are compared with (gyro [rad/s], accelerometer [m/s^2],
#: encoders [rad]): what the fit's ODE solver and the file's number format resolve
RESOLUTION = (1e-6, 1e-5, 1e-7)


def channel_floors(data: OnboardData) -> tuple[float, float, float]:
    """Each channel's noise level from its readings' third differences (every axis and trial
    pooled; `robust_sd`); the encoders' at least their quantisation (`encoder_quantum`)."""
    parts: list[list[np.ndarray]] = [[], [], []]
    for i, m in enumerate(data.lengths):
        t = data.ts[i, :m]
        k = _runs(t, np.ones(m, bool))
        if not k.size:
            continue
        idx = k[:, None] + np.arange(4)
        c = _coefficients(t[idx])
        for ch, a in enumerate((data.gyro[i, :m], data.acc[i, :m], data.chi[i, :m])):
            parts[ch].append(np.einsum("nj,njc->nc", c, a[idx]).reshape(-1))
    floors = [robust_sd(np.concatenate(p)) if p else math.nan for p in parts]
    floors[2] = max(floors[2], encoder_quantum(data) / math.sqrt(12.0))
    return tuple(floors)


def series_names(n_wheels: int) -> list[list[str]]:
    """The residual series of each channel: `gyro_x..z`, `acc_x..z`, `chi_1..N`."""
    return [[f"gyro_{a}" for a in "xyz"], [f"acc_{a}" for a in "xyz"], [f"chi_{i + 1}" for i in range(n_wheels)]]


def missing_effects(channels: set[str], free: Sequence[str], kind: str) -> list[str]:
    """What a fit whose residuals are correlated in `channels` could be missing, in words."""
    out = []
    if channels & {"gyro", "acc"}:
        out.append("the IMU's mounting (--imu-position, --imu-rotation: check them against the robot)")
    if "encoders" in channels:
        out.append(
            "roller slip of the omniwheels on the shell (down-weight the encoders with --sigma-encoder, docs/onboard.md)"
        )
    if not {"c_roll", "c_axle"} <= set(free):
        out.append("dissipation (--free c_roll,c_axle)")
    if kind == "torques" and "k_tau" not in free:
        out.append("a torque gain (--free k_tau, with one mass fixed at its known value)")
    out.append("a parameter held at a wrong value (--free it, or check the robot file)")
    return out


def _scope(trials, frac: float, fl) -> list[tuple[float, float, float]]:
    """Per channel `(ratio to the floor, lag-1 autocorrelation, sigma)` of the residuals of `trials`."""
    out = []
    for c in range(len(CHANNELS)):
        es = [tr[c] for tr in trials]
        s = _sigma(es, frac)
        sums = [lag1(e) for e in es]
        ac = sum(a for a, _ in sums) / max(sum(b for _, b in sums), 1e-300)
        out.append((s / fl[c] if fl[c] > 0 else math.nan, ac, s))
    return out


def _white(errors, floors, lags: int) -> list[list[dict[str, Any]]]:
    """Per trial, the whiteness of each series (`whiteness.channel`); a channel whose floor is
    at `RESOLUTION` (noise-free readings) gets `p = NaN`, not tested."""
    judged = [math.isfinite(f) and f > r for f, r in zip(floors, RESOLUTION)]
    out = []
    for tr in errors:
        row = []
        for c, e in enumerate(tr):
            for k in range(e.shape[1]):
                w = whiteness.channel(e[:, k], np.isfinite(e[:, k]), lags)
                row.append(w if judged[c] else w | {"p": math.nan})
        out.append(row)
    return out


def _status(overall, hits, correlated, cut, converged, why_not, unphysical, names, worst, series, free, kind):
    """`(status, diagnosis, reason)` by the module's rules."""
    ratios = ", ".join(f"{_x(r)} ({c})" for c, (r, _, _) in zip(CHANNELS, overall))
    if unphysical:
        return (
            "misfit",
            "wrong valley",
            (
                f"the fitted values are no physical robot ({unphysical}): the fit is in a wrong valley, or a value held "
                "fixed is wrong; try more starts (--n-starts), other start values (--params, --fix) or bounds (--bound)."
            ),
        )
    if correlated and converged:
        channels = {c for ss in correlated.values() for s in ss for c, names_c in zip(CHANNELS, series) if s in names_c}
        where = "; ".join(f"trial {n!r}: {', '.join(ss)}" for n, ss in correlated.items())
        return (
            "misfit",
            "model error",
            (
                f"model error: the residuals are correlated in time ({where}; Ljung-Box p < {cut:.1e}), at {ratios} the "
                "sensors' noise floors: the model does not describe these trials, and the values and standard errors are "
                f"biased. What it could be missing: {'; '.join(missing_effects(channels, free, kind))}."
            ),
        )
    if not converged:
        return (
            "not_converged",
            None,
            (
                f"the optimiser did not converge ({why_not or 'it stopped before its convergence test was met'}); the "
                f"residual sigmas are {ratios} the sensors' noise floors: the values and standard errors are not final; "
                "rerun with more iterations (--max-iter) or more starts (--n-starts)."
            ),
        )
    if hits:
        return (
            "misfit",
            "wrong valley",
            (
                f"the residual sigmas are {ratios} the sensors' noise floors (worst trial {names[worst]!r}): the fit is in a "
                "wrong valley or the model does not describe the trials; try more starts (--n-starts), other start values "
                "(--params, --fix), and check the IMU's mounting (--imu-position, --imu-rotation) and the inputs."
            ),
        )
    acs = ", ".join(f"{a:.2f}" for _, a, _ in overall)
    return (
        "converged",
        None,
        (
            f"the optimiser converged and the residual sigmas are {ratios} the sensors' noise floors, lag-1 "
            f"autocorrelations {acs}."
        ),
    )


def judge_onboard(
    errors: Sequence[Sequence[np.ndarray]],
    floors: Sequence[float],
    *,
    names: Sequence[str],
    converged: bool,
    why_not: str = "",
    n_params: int = 0,
    free: Sequence[str] = (),
    kind: str = "torques",
    unphysical: str = "",
    lags: int = whiteness.LAGS,
) -> dict[str, Any]:
    """The verdict from the residuals `errors[trial][channel] (m, c)` (channels `CHANNELS`, in
    their units) and the channels' noise `floors`. Returns `status`, `reason`, `diagnosis`, the
    numbers per channel (`channels`: `noise_floor`, `sigma`, `ratio`, `autocorr`, `unit`), per
    trial (`trials`: the same per channel and `whiteness`: the Ljung-Box `p` per series), the
    `worst_trial`, `correlated` (per trial name, the series that are not white) and `thresholds`."""
    T = len(errors)
    n_total = sum(np.asarray(e).size for tr in errors for e in tr)
    frac = max(1.0 - n_params / n_total, 1e-3) if n_total else 1.0
    fl = [max(f, r) if math.isfinite(f) else math.nan for f, r in zip(floors, RESOLUTION)]
    overall = _scope(errors, frac, fl)
    per_trial = [_scope([errors[i]], frac, fl) for i in range(T)]
    worst = max(range(T), key=lambda i: max((r for r, _, _ in per_trial[i] if math.isfinite(r)), default=-1.0))
    series = series_names(errors[0][2].shape[1]) if T else [[], [], []]
    white = _white(errors, floors, lags)
    flat = [s for ss in series for s in ss]
    bad, cut = whiteness.rejects([w["p"] for row in white for w in row])
    bad = bad.reshape(T, len(flat)) if T else bad
    correlated = {names[i]: [s for s, b in zip(flat, bad[i]) if b] for i in range(T) if bad[i].any()}
    hits = [
        (label, CHANNELS[c], r, a)
        for label, sc in (("", overall), (names[worst], per_trial[worst]))
        for c, (r, a, _) in enumerate(sc)
        if r > FAR or (r > MODERATE and a > CORRELATED)
    ]
    status, diagnosis, reason = _status(
        overall, hits, correlated, cut, converged, why_not, unphysical, names, worst, series, free, kind
    )

    def row(sc) -> dict[str, Any]:
        return {c: {"sigma": s, "ratio": r, "autocorr": a, "unit": u} for c, (r, a, s), u in zip(CHANNELS, sc, UNITS)}

    channels_out = row(overall)
    for c, f in zip(CHANNELS, floors):
        channels_out[c]["noise_floor"] = float(f)
    return {
        "status": status,
        "reason": reason,
        "optimiser_converged": bool(converged),
        "diagnosis": diagnosis,
        "channels": channels_out,
        "worst_trial": names[worst] if T else None,
        "trials": [
            {"name": n, **row(sc), "whiteness": {s: w["p"] for s, w in zip(flat, wr)}}
            for n, sc, wr in zip(names, per_trial, white)
        ],
        "correlated": correlated,
        "set_aside": 0,
        "thresholds": {
            "far": FAR,
            "moderate": MODERATE,
            "correlated": CORRELATED,
            "whiteness_alpha": whiteness.ALPHA,
            "whiteness_lags": lags,
        },
    }


#: statuses from the best to the worst
_ORDER = ("converged", "not_converged", "misfit")
_PARTS = {"capture": "motion capture", "onboard": "onboard sensors"}


def combined_verdict(capture: dict[str, Any], onboard: dict[str, Any]) -> dict[str, Any]:
    """The verdict of a fit of trials of both kinds from each part's (`jsphere.identify.verdict.judge`
    on the pose trials, `judge_onboard` on the onboard trials): the worse status, with the reason
    of each part at that status, named by part; the worse part's `diagnosis` and `worst_trial`,
    every part's `correlated` series, and each part's own verdict under `parts`."""
    parts = {"capture": capture, "onboard": onboard}
    status = max((v["status"] for v in parts.values()), key=_ORDER.index)
    worst = next(k for k, v in parts.items() if v["status"] == status)
    reason = "; ".join(f"{_PARTS[k]}: {v['reason'].rstrip('.')}" for k, v in parts.items() if v["status"] == status)
    return {
        "status": status,
        "reason": reason,
        "optimiser_converged": all(v["optimiser_converged"] for v in parts.values()),
        "diagnosis": parts[worst].get("diagnosis"),
        "worst_trial": parts[worst]["worst_trial"],
        "correlated": {**capture.get("correlated", {}), **onboard.get("correlated", {})},
        "set_aside": capture.get("set_aside", 0),
        "parts": {k: dict(v) for k, v in parts.items()},
    }
