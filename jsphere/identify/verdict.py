"""The verdict on a fit: is what came back a result?

A fit can end in a wrong valley: the optimiser stops, the covariance is computed, and the
residuals are tens of times the capture noise. The verdict compares the fitted residuals with
the capture's own noise floor, estimated from the data alone, and looks at their whiteness:

- `noise_floor(data)`: the capture's noise levels from its high-frequency content (third
  differences), independent of any model.
- `lag1(errors, valid)`: the lag-1 autocorrelation of residuals (white noise: ~0; a model that
  misses a smooth motion: ~1).
- the whiteness of each trial's residuals per channel (`jsphere.identify.whiteness`: the
  Ljung-Box test at `ALPHA` over every trial and channel together);
- `judge(...)`: `"converged"`, `"not_converged"` or `"misfit"`, a one-sentence reason a user
  can act on, the `diagnosis` (`"model error"`, `"capture defects"`, `"wrong valley"` or None)
  and the numbers behind it.

The rules (thresholds are the module constants below):

1. `not_converged` when the optimiser says it did not converge; the reason also gives the
   residual ratio when the residuals are far above the floor; `misfit` instead when a ratio is
   above `UNREACHABLE` (more iterations do not bring it to the floor).
2. otherwise `misfit` when the residual sigma of a channel (position or orientation), over
   all trials or of the worst trial, is more than `FAR` times the noise floor, or more than
   `MODERATE` times with a lag-1 autocorrelation above `CORRELATED` (far from white);
3. otherwise `misfit` with the diagnosis "model error" when the residuals of some trial and
   channel are not white (a model error leaves a smooth part in them, correlated over many
   frames, even where it is small against the noise: unmodelled dissipation 1.3x the floor
   moves the estimates by tens of standard errors); the reason names the effects the fit could
   be missing (`missing_effects`). Channels whose floor is at `FLOOR_RESOLUTION` (a noise-free
   capture: residuals of the ODE solver's own error) are not tested;
4. otherwise `converged`.

A misfit whose residuals are correlated in time is put down to the model, never to the
capture: its reason advises no cleaning or converting.

Frames a robust loss set aside (`jsphere.identify.robust`: ghost frames, marker swaps) are left
out of the residual sigmas and of the whiteness test, and counted per trial. Where more than
`REJECTED` of a trial's measured frames are set aside and the residuals of the frames kept are
white, the reason names the trial ("trial 'X': 12 % of frames rejected: check the capture"):
a misfit is then put down to the capture, and a fit whose other frames sit at the noise floor
stays `converged` with that warning in its reason.
More than `ABANDONED` of a trial's frames set aside is no capture's glitches but a fit that has
left the trial out (a wrong valley, where the redescending Cauchy loss lets a whole trial go, or a
trial the model does not describe): a `misfit` naming the trial.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from typing import Any

import numpy as np

from ..model.rotations import quat_conj_np, quat_log_np, quat_mul_np
from . import whiteness

#: residual sigma / noise floor above which a fit is a misfit
FAR = 3.0
#: residual sigma / noise floor above which correlated residuals make a fit a misfit
MODERATE = 1.5
#: residual sigma / noise floor above which a fit that ran out of iterations is a misfit: more
#: iterations do not bring residuals this far off to the noise floor (a model that does not
#: describe the trials, under a robust loss, keeps moving frames in and out of the fit)
UNREACHABLE = 3 * FAR
#: lag-1 autocorrelation above which residuals are far from white
CORRELATED = 0.8
#: fewest third differences (per channel, all trials) for a noise floor; fewer give NaN
MIN_DIFFERENCES = 20
#: a run of 4 frames spanning more than this many median frame intervals (a missing row, a
#: jump of the clock) is not used for the noise floor
MAX_SPAN = 3.5
#: the smallest floors the residuals are compared with [m], [rad]: the fit's ODE solver and the
#: capture's number format resolve about a micrometre and a few microradians, so a noise-free
#: capture is compared with these instead of ~0
FLOOR_RESOLUTION = (1e-5, 1e-4)
#: third differences beyond this many robust sd (`1.4826 median |e|`) are outliers
OUTLIER = 5.0
#: the share of a trial's measured frames set aside above which the verdict names the trial
REJECTED = 0.05
#: the share of a trial's measured frames set aside above which the fit has left the trial out
ABANDONED = 0.5
#: scale of the median absolute value to the standard deviation of a normal variable
_MAD = 1.4826

CHANNELS = ("position", "orientation")
#: the residual series tested for whiteness, per trial: position x, y and orientation about 3 axes
SERIES = ("x", "y", "rot_x", "rot_y", "rot_z")
#: what the verdict can put a misfit down to
DIAGNOSES = ("model error", "capture defects", "wrong valley")


def missing_effects(free: Sequence[str], kind: str, time_offset: bool, known: Sequence[str] = ()) -> list[str]:
    """What a fit of the free names `free` on trials of input `kind` could be missing, in words
    and the options that add it: dissipation (unless `c_roll` and `c_axle` are free), a torque
    gain (torque trials, unless `k_tau` is free; only where the model has one: `known` holds the
    parameter names), a clock offset (unless fitted), and a parameter held at a wrong value."""
    out = []
    if not {"c_roll", "c_axle"} <= set(free):
        out.append("dissipation (--free c_roll,c_axle)")
    if kind == "torques" and "k_tau" in known and "k_tau" not in free:
        out.append("a torque gain (--free k_tau, with one mass fixed at its known value)")
    if not time_offset:
        out.append("a clock offset between the capture and the inputs (--fit-time-offset)")
    out.append("a parameter held at a wrong value (--free it, or check the robot file)")
    return out


# ----------------------------------------------------------------------------- the noise floor


def _runs(t: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """First indices `k` of the runs `k..k+3` of 4 consecutive measured frames whose span is at
    most `MAX_SPAN` median frame intervals."""
    m = len(t)
    if m < 4:
        return np.zeros(0, int)
    k = np.arange(m - 3)
    ok = valid[k] & valid[k + 1] & valid[k + 2] & valid[k + 3]
    dt = float(np.median(np.diff(t)))
    ok &= t[k + 3] - t[k] <= MAX_SPAN * dt
    return k[ok]


def _coefficients(t: np.ndarray) -> np.ndarray:
    """Third divided-difference weights of the runs `t (n, 4)`, scaled to unit norm: `(n, 4)`.

    `c_j = 1 / prod_{i != j} (t_j - t_i)` annihilates every quadratic in `t`; scaled to
    `sum c_j^2 = 1`, white noise of sd `s` gives differences of sd `s`. For evenly spaced
    frames they are `(-1, 3, -3, 1) / sqrt(20)`."""
    c = np.ones_like(t)
    for j in range(4):
        for i in range(4):
            if i != j:
                c[:, j] /= t[:, j] - t[:, i]
    return c / np.linalg.norm(c, axis=1, keepdims=True)


def third_differences(data) -> tuple[np.ndarray, np.ndarray]:
    """The normalised third differences of a capture: positions `(n_pos,)` [m] (x and y) and
    orientations `(n_rot,)` [rad] (3 axes), pooled over trials; each has the sd of the noise.

    Positions: `sum_j c_j x_{k+j}` over runs of 4 consecutive measured frames (`_coefficients`).
    Orientations: `v_j = Log(q_k^-1 q_{k+j})` (rotation vectors, platform frame; `v_0 = 0`),
    then `sum_j c_j v_j` per axis: with `q = q_true Exp(n)` and small `n`,
    `v_j = w_j + n_{k+j} - n_k` (to first order), `w_j` the smooth relative rotation, so the
    noise enters as in the positions. A smooth motion contributes `x''' dt^3 / sqrt(20)`:
    about 1e-6 m at 100 Hz for the robot's motions, far below capture noise."""
    pos, rot = [], []
    for i in range(data.ts.shape[0]):
        m = data.lengths[i]
        t = data.ts[i, :m]
        k = _runs(t, data.wpos[i, :m] > 0)
        if k.size:
            c = _coefficients(t[k[:, None] + np.arange(4)])
            pos += [(c * a[k[:, None] + np.arange(4)]).sum(1) for a in (data.x[i, :m], data.y[i, :m])]
        k = _runs(t, data.wrot[i, :m] > 0)
        if k.size:
            c = _coefficients(t[k[:, None] + np.arange(4)])
            q = data.q[i, :m]
            q0_inv = quat_conj_np(q[k])
            v = np.stack([quat_log_np(quat_mul_np(q0_inv, q[k + j])) for j in range(1, 4)], 1)  # (n, 3 steps, 3 axes)
            rot.append(np.einsum("nj,nja->na", c[:, 1:], v).reshape(-1))
    cat = lambda parts: np.concatenate(parts) if parts else np.zeros(0)
    return cat(pos), cat(rot)


def robust_sd(e: np.ndarray) -> float:
    """The sd of normal noise from values `e` that may hold a few outliers (a marker swap, a
    glitch): `s0 = 1.4826 median |e|`, then the RMS of the values within `OUTLIER s0` of 0 (the
    RMS is ~2.7x as efficient as the median, which matters for a few hundred differences;
    cutting at 5 sd changes the sd of normal noise by 2e-5). NaN for fewer than
    `MIN_DIFFERENCES` values."""
    if e.size < MIN_DIFFERENCES:
        return math.nan
    s0 = float(_MAD * np.median(np.abs(e)))
    kept = e[np.abs(e) <= OUTLIER * s0]
    return float(np.sqrt(np.mean(kept * kept))) if kept.size else s0


def noise_floor(data) -> tuple[float, float]:
    """The capture's noise levels `(sigma_pos [m] per coordinate, sigma_rot [rad] per axis)`,
    estimated from its high-frequency content, independent of any model.

    `data` is a `jsphere.identify.fit.FitData`. Third differences over runs of 4 consecutive measured
    frames (`third_differences`) remove every motion up to a quadratic; white noise of sd `s`
    gives differences of sd `s` after normalisation (`sqrt(20) s` for evenly spaced frames
    before it), estimated by their RMS after removing outliers (`robust_sd`). Overlapping
    differences are correlated (-0.75 at lag 1), so `n` differences estimate `s` to a relative
    sd of about `sqrt(2.3 / (2 n))`: 3 % for the ~1200 position differences of two trials of
    3 s at 100 Hz, 6.5 % for two trials of 1.5 s at 50 Hz (over 200 noise draws: 3.3 % and
    6.1 %, means within 1.2 % of the truth). Gaps are skipped; a channel with fewer than
    `MIN_DIFFERENCES` differences gives NaN. Capture noise that is not white (a capture system
    that smooths its output) has less high-frequency content, so its floor comes out low."""
    pos, rot = third_differences(data)
    return robust_sd(pos), robust_sd(rot)


# ----------------------------------------------------------------------------- whiteness


def lag1(errors: np.ndarray, valid: np.ndarray | None = None) -> tuple[float, float]:
    """The sums behind the lag-1 autocorrelation of residuals `errors (m, c)` (NaN or
    `valid = False` at gaps): `(sum e_k . e_{k+1}, sqrt(sum |e_k|^2 sum |e_{k+1}|^2))` over the
    pairs of consecutive measured frames (a gap breaks the series). The autocorrelation is
    their ratio; pooled over trials, the sums are added. It is taken about zero, not about the
    mean: residuals with an offset are not white either."""
    e = np.asarray(errors, float).reshape(len(errors), -1)
    ok = np.all(np.isfinite(e), 1)
    if valid is not None:
        ok &= np.asarray(valid, bool)
    pair = ok[:-1] & ok[1:]
    a, b = e[:-1][pair], e[1:][pair]
    return float((a * b).sum()), float(np.sqrt((a * a).sum() * (b * b).sum()))


def _ratio(num: float, den: float) -> float:
    return num / den if den > 0 else math.nan


def _x(r: float) -> str:
    return f"{r:.2f}x" if math.isfinite(r) else "n/a"


# ----------------------------------------------------------------------------- the verdict


def _sigma(errors: Sequence[np.ndarray], frac: float) -> float:
    """Residual sigma per coordinate / axis of the finite rows of `errors`, dof-corrected by
    `frac = 1 - n_params / n_residuals` as the fit's noise estimate."""
    e = np.concatenate([np.asarray(x, float).reshape(len(x), -1) for x in errors])
    e = e[np.all(np.isfinite(e), 1)]
    return math.sqrt((e * e).sum() / (e.size * frac)) if e.size else math.nan


def judge(
    pos_err: Sequence[np.ndarray],
    rot_err: Sequence[np.ndarray],
    floor: tuple[float, float],
    *,
    names: Sequence[str] | None = None,
    converged: bool = True,
    why_not: str = "",
    n_params: int = 0,
    set_aside: Sequence[int] | None = None,
    measured: Sequence[int] | None = None,
    missing: Sequence[str] = (),
    lags: int = whiteness.LAGS,
    unphysical: str = "",
) -> dict[str, Any]:
    """The verdict on a fit from its residuals.

    **Arguments:**
    - `pos_err`: per trial the position residuals `(m, 2)` [m], NaN at gaps.
    - `rot_err`: per trial the orientation residuals `(m, 3)` [rad] (rotation vectors), NaN at gaps.
    - `floor`: the capture's noise levels `(sigma_pos [m], sigma_rot [rad])` (`noise_floor`);
      NaN for a channel that cannot be judged. Floors below `FLOOR_RESOLUTION` are raised to it.
    - `names`: the trials' names; `converged`, `why_not`: the optimiser's flag and, when it did
      not converge, why (e.g. "Levenberg-Marquardt stopped at max_iter").
    - `n_params`: the number of fitted values (free and nuisance), for the residual sigmas'
      dof correction `sqrt(sum e^2 / (n (1 - n_params / n_total)))`.
    - `set_aside`, `measured`: per trial the frames a robust loss set aside (already NaN in
      `pos_err`, `rot_err`) and the frames measured; more than `REJECTED` of them names the
      trial in the reason (module docstring).
    - `missing`: what the fit could be missing, in words (`missing_effects`), named by a model
      error's reason; `lags`: the largest lag of the whiteness test.
    - `unphysical`: why the fitted values are no physical robot (a broken rule of
      `RobotParams`), or "": such a fit is a `misfit` (a wrong valley), whatever its residuals.

    Returns a dict: `status` (`"converged"`, `"not_converged"` or `"misfit"`, see the module's
    rules), `reason` (one sentence), and the numbers in JSON units: `noise_floor_pos_m`,
    `noise_floor_rot_deg`, `sigma_pos_m`, `sigma_rot_deg` (residual sigmas over all trials),
    `ratio_pos`, `ratio_rot` (sigma / floor), `autocorr_pos`, `autocorr_rot` (lag-1),
    `worst_trial` (the name of the trial with the highest ratio), `trials` (per trial
    `name`, `sigma_pos_m`, `sigma_rot_deg`, `ratio_pos`, `ratio_rot`, `autocorr_pos`,
    `autocorr_rot`, `set_aside`, `whiteness`: per series (`SERIES`) the Ljung-Box `p`),
    `optimiser_converged`, `set_aside` (all trials), `diagnosis` (one of `DIAGNOSES` or None),
    `correlated` (per trial name, the series that are not white) and `thresholds`.
    """
    T = len(pos_err)
    names = list(names) if names is not None else [f"trial{i}" for i in range(T)]
    aside = list(set_aside) if set_aside is not None else [0] * T
    held = list(measured) if measured is not None else [0] * T
    sc = _scores(pos_err, rot_err, floor, n_params, names)
    rejected = [
        f"trial {names[i]!r}: {100.0 * aside[i] / held[i]:.0f} % of frames rejected: check the capture"
        for i in range(T)
        if held[i] and aside[i] > REJECTED * held[i]
    ]
    left_out = [names[i] for i in range(T) if held[i] and aside[i] > ABANDONED * held[i]]
    white = _whiteness(pos_err, rot_err, floor, lags)
    bad, cut = whiteness.rejects([w["p"] for ws in white for w in ws])
    bad = bad.reshape(T, len(SERIES)) if T else bad
    correlated = {names[i]: [c for c, b in zip(SERIES, bad[i]) if b] for i in range(T) if bad[i].any()}
    if unphysical:
        status, diagnosis = "misfit", "wrong valley"
        reason = (
            f"the fitted values are no physical robot ({unphysical}): the fit is in a wrong valley, or a value held "
            "fixed is wrong; try more starts (--n-starts), other start values (--params, --fix) or bounds (--bound)."
        )
    elif left_out and converged:
        status, diagnosis = "misfit", "wrong valley"
        reason = (
            f"the fit has set aside more than {ABANDONED:.0%} of the frames of {', '.join(map(repr, left_out))}: it "
            "has left the trial out (a wrong valley, or a trial the model does not describe), not a capture's "
            "glitches; try more starts (--n-starts) or other start values (--params, --fix), and check that "
            "trial's inputs and capture."
        )
    elif correlated and converged:
        status, diagnosis = "misfit", "model error"
        reason = _model_error(correlated, white, sc, cut, missing, lags)
    else:
        status, reason = _status(sc, converged, why_not, rejected)
        diagnosis = ("capture defects" if rejected else "wrong valley") if status == "misfit" else None
    out = _numbers(status, reason, converged, floor, sc)
    for t, n, ws in zip(out["trials"], aside, white):
        t["set_aside"] = int(n)
        t["whiteness"] = {c: w["p"] for c, w in zip(SERIES, ws)}
    out |= {"set_aside": int(sum(aside)), "diagnosis": diagnosis, "correlated": correlated}
    out["thresholds"] |= {"rejected": REJECTED, "whiteness_alpha": whiteness.ALPHA, "whiteness_lags": lags}
    return out


@dataclasses.dataclass(frozen=True)
class _Scores:
    """The residual sigmas of a fit against the noise floor: per channel `(ratio to the floor,
    lag-1 autocorrelation, sigma)` over all trials (`overall`) and per trial, the worst trial,
    the floors compared with (`fl`) and the rules that fire (`hits`, `_hits`)."""

    names: list[str]
    overall: list[tuple[float, float, float]]
    per_trial: list[list[tuple[float, float, float]]]
    worst: int | None
    fl: list[float]
    hits: list[tuple[str, int, float, float, str]]

    @property
    def ratios(self) -> str:
        return (
            f"{_x(self.overall[0][0])} (position) and {_x(self.overall[1][0])} (orientation) the capture's noise floor"
        )


def _scores(pos_err, rot_err, floor, n_params: int, names: list[str]) -> _Scores:
    """The `_Scores` of the residuals, their sigmas dof-corrected for `n_params` fitted values
    and the floors raised to `FLOOR_RESOLUTION`."""
    T = len(pos_err)
    n_total = sum(np.isfinite(np.asarray(e, float)).all(-1).sum() * 2 for e in pos_err)
    n_total += sum(np.isfinite(np.asarray(e, float)).all(-1).sum() * 3 for e in rot_err)
    frac = max(1.0 - n_params / n_total, 1e-3) if n_total else 1.0
    fl = [max(f, r) if math.isfinite(f) else math.nan for f, r in zip(floor, FLOOR_RESOLUTION)]
    overall = _scope((pos_err, rot_err), frac, fl)
    per_trial = [_scope(([pos_err[i]], [rot_err[i]]), frac, fl) for i in range(T)]
    key = lambda i: max((r for r, _, _ in per_trial[i] if math.isfinite(r)), default=-math.inf)
    worst = max(range(T), key=key) if T else None
    scopes = [("", overall)] + ([(names[worst], per_trial[worst])] if worst is not None else [])
    return _Scores(names, overall, per_trial, worst, fl, _hits(scopes))


def _whiteness(pos_err, rot_err, floor, lags: int) -> list[list[dict[str, Any]]]:
    """Per trial and series (`SERIES`) the whiteness of the residuals (`whiteness.channel`); a
    channel whose floor is not above `FLOOR_RESOLUTION` (a noise-free capture) gets `p = NaN`,
    not tested."""
    judged = [math.isfinite(f) and f > r for f, r in zip(floor, FLOOR_RESOLUTION)]
    out = []
    for pe, re in zip(pos_err, rot_err):
        e = np.concatenate([np.asarray(pe, float), np.asarray(re, float)], 1)  # the columns of `SERIES`
        ws = [whiteness.channel(e[:, k], np.isfinite(e[:, k]), lags) for k in range(len(SERIES))]
        out.append([w if judged[k >= 2] else w | {"p": math.nan, "q": math.nan} for k, w in enumerate(ws)])
    return out


def _model_error(correlated, white, sc: _Scores, cut: float, missing: Sequence[str], lags: int) -> str:
    """The reason of a misfit whose residuals are correlated in time."""
    where = "; ".join(f"trial {n!r}: {', '.join(cs)}" for n, cs in correlated.items())
    i = sc.names.index(next(iter(correlated)))
    share = float(np.mean([w["outside_99"] for w in white[i]]))
    effects = "; ".join(missing) if missing else "a parameter held at a wrong value"
    reason = (
        f"model error: the residuals are correlated in time ({where}; in trial {sc.names[i]!r} {share:.0%} of the "
        f"autocorrelation lags 1-{lags} are outside the 99 % band of white noise, Ljung-Box p < {cut:.1e}), at "
        f"{sc.ratios}: the model does not describe these trials, and the values and standard errors are biased. "
        f"What it could be missing: {effects}."
    )
    if any(h[4] == "far" for h in sc.hits):
        reason += (
            " Residuals this far above the floor can also mean a wrong valley: try more starts (--n-starts) or "
            "other start values (--params)."
        )
    return reason


def _scope(errs, frac: float, fl) -> list[tuple[float, float, float]]:
    """Per channel `(ratio to the floor, lag-1 autocorrelation, sigma)` of the residual lists `errs`."""
    out = []
    for c, e in enumerate(errs):
        s = _sigma(e, frac)
        sums = [lag1(x) for x in e]
        out.append((_ratio(s, fl[c]), _ratio(sum(a for a, _ in sums), sum(b for _, b in sums)), s))
    return out


def _hits(scopes) -> list[tuple[str, int, float, float, str]]:
    """The rules that fire, per scope (all trials, the worst trial) and channel: `(scope text,
    channel, ratio, autocorrelation, "far" | "correlated")`."""
    hits = []
    for label, sc in scopes:
        for c, (r, a, _) in enumerate(sc):
            if r > FAR:
                hits.append((label, c, r, a, "far"))
            elif r > MODERATE and a > CORRELATED:
                hits.append((label, c, r, a, "correlated"))
    return hits


def _status(sc: _Scores, converged: bool, why_not: str, rejected=()) -> tuple[str, str]:
    """The status and its one-sentence reason (the module's rules); `rejected`: per trial with
    too many frames set aside, its sentence."""
    hits, overall, per_trial, names, worst, fl = sc.hits, sc.overall, sc.per_trial, sc.names, sc.worst, sc.fl
    T, ratios = len(per_trial), sc.ratios
    worst_text = ""
    if worst is not None and T > 1:
        wr = per_trial[worst]
        worst_text = f" (worst trial {names[worst]!r}: {_x(wr[0][0])} and {_x(wr[1][0])})"
    unjudged = [CHANNELS[c] for c in range(2) if not math.isfinite(fl[c])]
    no_floor = (
        f"; the {' and '.join(unjudged)} noise floor cannot be estimated (fewer than {MIN_DIFFERENCES} runs of 4 "
        "consecutive measured frames), so those residuals are not judged"
        if unjudged
        else ""
    )
    if not converged and any(h[4] == "far" and h[2] > UNREACHABLE for h in hits):
        return "misfit", (
            f"the optimiser did not converge ({why_not or 'it stopped before its convergence test was met'}) and the "
            f"residual sigmas are {ratios}{worst_text}{no_floor}: more iterations will not bring them to the noise "
            "floor; the fit is in a wrong valley or the model does not describe the trials; try more starts "
            "(--n-starts), other start values (--params, --fix) or more free parameters, and check the inputs and capture."
        )
    if not converged:
        far = f"; the residual sigmas are {ratios}{worst_text}" if hits else ""
        return "not_converged", (
            f"the optimiser did not converge ({why_not or 'it stopped before its convergence test was met'}){far}{no_floor}: "
            "the values and standard errors are not final; rerun with more iterations (--max-iter) or more starts (--n-starts)."
        )
    capture = "; ".join(rejected)
    if hits and capture:
        return "misfit", (
            f"{capture}; the residual sigmas of the frames kept are {ratios}{worst_text}{no_floor}: a capture with this "
            "many bad frames (ghost frames, marker swaps) does not determine the fit; clean the capture or convert it "
            "again (jsphere convert leaves frames of suspect markers out)."
        )
    if hits:
        if any(h[4] == "far" for h in hits):
            what = f"the residual sigmas are {ratios}{worst_text}"
        else:
            label, c, r, a, _ = hits[0]
            where = f" of trial {label!r}" if label else ""
            what = f"the {CHANNELS[c]} residuals{where} are {_x(r)} the capture's noise floor and far from white (lag-1 autocorrelation {a:.2f})"
        check = f"trial {names[worst]!r}" if worst is not None and T > 1 else "the trial"
        return "misfit", (
            f"{what}{no_floor}: the fit is in a wrong valley or the model does not describe the trials; try more starts "
            f"(--n-starts), other start values (--params, --fix) or more free parameters, and check the inputs and capture of {check}."
        )
    acs = f"lag-1 autocorrelations {overall[0][1]:.2f} and {overall[1][1]:.2f}"
    capture = f"; {capture}" if capture else ""
    return "converged", f"the optimiser converged and the residual sigmas are {ratios}, {acs}{no_floor}{capture}."


def _row(scope) -> dict[str, float]:
    """The numbers of one scope (`_scope`: all trials, or one) in JSON units."""
    (rp, ap, sp), (rr, ar, sr) = scope
    return {
        "sigma_pos_m": sp,
        "sigma_rot_deg": math.degrees(sr),
        "ratio_pos": rp,
        "ratio_rot": rr,
        "autocorr_pos": ap,
        "autocorr_rot": ar,
    }


def _numbers(status, reason, converged, floor, sc: _Scores) -> dict[str, Any]:
    """The verdict's dict (see `judge`)."""
    return {
        "status": status,
        "reason": reason,
        "optimiser_converged": bool(converged),
        "noise_floor_pos_m": float(floor[0]),
        "noise_floor_rot_deg": math.degrees(floor[1]),
        **_row(sc.overall),
        "worst_trial": sc.names[sc.worst] if sc.worst is not None else None,
        "trials": [{"name": n, **_row(scope)} for n, scope in zip(sc.names, sc.per_trial)],
        "thresholds": {"far": FAR, "moderate": MODERATE, "correlated": CORRELATED},
    }


def headline(status: str, reason: str, verdict: dict[str, Any]) -> str:
    """The verdict in one line (the last line of `jsphere fit`): for a converged fit its
    residual sigmas relative to the noise floor, otherwise the status and the reason."""
    if status == "converged" and "parts" in verdict:  # trials of both kinds
        label = {"capture": "motion capture", "onboard": "onboard sensors"}
        inner = [headline(v["status"], v["reason"], v)[len("converged (") : -1] for v in verdict["parts"].values()]
        return f"converged ({'; '.join(f'{label[k]}: {x}' for k, x in zip(verdict['parts'], inner))})"
    if status == "converged" and "channels" in verdict:
        ch = verdict["channels"]
        ratios = " / ".join(f"{ch[c]['ratio']:.2f}x" for c in ch)
        return f"converged (residual sigma {ratios} the sensors' noise floors, {' / '.join(ch)})"
    if status == "converged":
        rp, rr = verdict.get("ratio_pos", math.nan), verdict.get("ratio_rot", math.nan)
        if rp is None or rr is None or not (math.isfinite(rp) and math.isfinite(rr)):
            return f"converged ({reason})"
        return f"converged (residual sigma {rp:.2f}x / {rr:.2f}x the capture's noise floor, position / orientation)"
    return f"{status}: {reason}"
