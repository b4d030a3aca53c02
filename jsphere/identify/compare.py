"""Validation of a model on trials: `compare` (simulated against measured, per trial and overall).

Each trial is simulated with the given parameters from its own initial pose; its nuisance values
(the initial velocities and the small offsets of the initial pose, and the clock offset where it
is asked for: `jsphere.identify.data.nuisance_names`) are estimated as the fit estimates them,
by Levenberg-Marquardt on the trial's whitened residuals with the parameters held. Then:

- the normalised fit `100 (1 - |y - y_hat| / |y - mean(y)|)` [%] of `x`, `y` and the platform's
  orientation (`rot`: `y` the rotation vector from the first measured orientation, `y - y_hat`
  the rotation vector of `q_sim^-1 q_meas`, norms over all samples and components), on every
  measured frame;
- the whiteness of the residuals per channel (`x`, `y`, `rot_x..z`; `jsphere.identify.whiteness`):
  their autocorrelation at lags `1..lags`, the fraction outside the 99 % band `+- 2.576 / sqrt(N)`
  of white noise and the Ljung-Box test, on the frames not set aside;
- their cross-correlation with each input at lags `-lags..lags`, with the same band;
- the verdict (`VERDICTS`): `"consistent"` when every trial's residuals are white and at most
  `REJECTED` of its frames are set aside; `"model error"` when the residuals of some trial and
  channel are correlated in time (the Ljung-Box test at `ALPHA` over all trials and channels
  together) or more than `ABANDONED` of a trial's frames are set aside (a trial the model does
  not follow); `"capture defects"` when they are white but more than `REJECTED` of a trial's
  frames are set aside (ghost frames, marker swaps).

The nuisance values are estimated with the fit's robust loss (`loss`, `jsphere.identify.robust`;
a redescending loss from the point its convex `WARM_LOSS` reaches, as in `fit`): the frames it
sets aside are each trial's `outliers`, counted and listed, and left out of the whiteness test
only. A right model leaves white residuals (about 1 % of the lags outside the band) and a fit near
100 % where the motion is large against the noise; a wrong one scores lower and leaves
correlated residuals.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import diffrax as dfx
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._runtime.checks import real, whole
from .._runtime.errors import SolverFailure
from ..capture.trial import Trial
from ..model.params import RobotParams
from ..model.rotations import quat_conj_np, quat_log_np, quat_mul_np
from ..numerics.lm import Dense, LevenbergMarquardt, iterate
from .data import FitData, nuisance_values, pack_trials, trial_errors
from .options import save_json
from .residuals import trial_model
from .robust import DEFAULT_LOSS, REDESCENDING, REJECT, WARM_LOSS, check_loss, frame_weights, reweigh, robust_cost
from .starts import nuisance_guess
from .verdict import ABANDONED, REJECTED
from .whiteness import ALPHA, Z99, channel, rejects

#: the residual channels, in the order of `series["residuals"]`'s columns
CHANNELS = ("x", "y", "rot_x", "rot_y", "rot_z")
#: what `compare` can conclude (`CompareResult.verdict`)
VERDICTS = ("consistent", "model error", "capture defects")


@dataclasses.dataclass
class CompareResult:
    """What `compare` returns. `trials`: per trial `name`, `fit_percent` (`x`, `y`, `rot`),
    `whiteness` (`acf_outside_99`: the fraction of autocorrelations at lags `1..lags` outside the
    99 % band, over all channels; per channel under `channels`; `band`, `lags`),
    `cross_correlation` (`ccf_outside_99`, `max_abs`, per input under `inputs`), RMS residuals,
    the nuisance values, and under `series` the time series for the figures (not written to JSON);
    `overall`: the same scores over all trials together (fits of the pooled norms, fractions over
    all lags); `predicted`: the simulated trials (`Trial`s with the simulated pose and the
    measured inputs); `params`: the parameters compared."""

    trials: list[dict[str, Any]]
    overall: dict[str, Any]
    predicted: list[Trial]
    params: RobotParams
    verdict: str = "consistent"
    reason: str = ""

    @property
    def consistent(self) -> bool:
        """Whether the model explains the trials (`verdict == "consistent"`)."""
        return self.verdict == "consistent"

    def to_json(self) -> dict[str, Any]:
        """The JSON document: `verdict` (one of `VERDICTS`) and its `reason`, `trials` (each with
        `name`, `fit_percent`, `whiteness`, `outliers`, ...), `overall` and the `params` compared."""
        return {
            "verdict": self.verdict,
            "reason": self.reason,
            "trials": [{k: v for k, v in t.items() if k != "series"} for t in self.trials],
            "overall": self.overall,
            "params": self.params.to_dict(),
        }

    def save(self, path, **deprecated) -> list[Path]:
        """Write the JSON atomically; returns `[path]`. The figures are drawn by
        `jsphere.plots.compare_figure` (one per trial; `jsphere compare` writes them beside the
        JSON). `plots=` is deprecated and draws nothing."""
        return save_json(
            self.to_json(),
            path,
            deprecated,
            "CompareResult.save",
            "jsphere.plots.compare_figure(result.trials[i], path)",
        )

    def table(self) -> str:
        """A plain-text summary: fits [%] and the whiteness per trial, then overall."""
        lines = [
            f"{'trial':<20} {'fit x %':>8} {'fit y %':>8} {'fit rot %':>9} {'acf out 99':>10} {'ccf out 99':>10} "
            f"{'set aside':>9}"
        ]
        for t in [*self.trials, self.overall]:
            f = t["fit_percent"]
            lines.append(
                f"{t['name'][:20]:<20} {f['x']:>8.2f} {f['y']:>8.2f} {f['rot']:>9.2f} "
                f"{t['whiteness']['acf_outside_99']:>10.3f} {t['cross_correlation']['ccf_outside_99']:>10.3f} "
                f"{t['outliers']['count']:>9d}"
            )
        return "\n".join(lines)

    def headline(self) -> str:
        """The verdict in one line: `verdict: <verdict> (<reason>)`."""
        return f"verdict: {self.verdict} ({self.reason})"


def compare(
    params: RobotParams,
    trials: Sequence[Trial],
    *,
    lags: int = 25,
    sigma_pos: float = 1e-3,
    sigma_rot: float = math.radians(0.5),
    fit_time_offset: bool = False,
    max_time_offset: float = 0.5,
    max_iter: int = 30,
    rtol: float = 1e-6,
    atol: float = 1e-8,
    max_steps: int = 16384,
    loss: str = DEFAULT_LOSS,
) -> CompareResult:
    """Simulate each trial with `params` and score it against the measurement (module docstring).

    **Arguments:**
    - `params`: the model (e.g. `FitResult.params`, or `RobotParams.load("fit.json")`).
    - `trials`: `Trial`s of one input kind with the wheel count of `params`.
    - `lags`: the largest lag of the correlations [samples].
    - `sigma_pos` [m], `sigma_rot` [rad]: weights of position and orientation in the estimate
      of the nuisance values (the capture's noise levels).
    - `fit_time_offset`, `max_time_offset`: estimate each trial's clock offset too (as `fit`).
    - `max_iter`: Levenberg-Marquardt iterations of the nuisance estimate.
    - `rtol`, `atol`, `max_steps`: the ODE solver's (`fit`'s defaults).
    - `loss`: the loss of the nuisance estimate, as `fit`'s (`jsphere.identify.robust`); the
      frames it sets aside are each trial's `outliers` (`{"frames": [rows], "count": n}`).

    Returns a `CompareResult`. Raises `InputError` for trials that do not fit `params` or bad
    options, `SolverFailure` when a trial cannot be simulated (named)."""
    lags = whole("compare", "lags", lags, 1)
    for name, v, unit in (
        ("sigma_pos", sigma_pos, "m"),
        ("sigma_rot", sigma_rot, "rad"),
        ("max_time_offset", max_time_offset, "s"),
    ):
        real("compare", name, v, strict=True, unit=unit)
    check_loss(loss, "compare")
    trials = list(trials)
    data = pack_trials(
        trials, params, max_offset=float(max_time_offset) if fit_time_offset else 0.0, where="jsphere compare"
    )
    sig = np.array([float(sigma_pos), float(sigma_rot)])
    est = functools.partial(
        _estimate_nuisance, params, data, sig, int(max_iter), float(rtol), float(atol), int(max_steps)
    )
    if loss in REDESCENDING:  # from the point of the convex loss, as `fit` does
        nu, pose, ok, res = est(WARM_LOSS)
        nu, pose, ok, res = est(loss, nu)
    else:
        nu, pose, ok, res = est(loss)
    aside = (frame_weights(loss, res) < REJECT) & ((data.wpos > 0) | (data.wrot > 0))
    bad = np.flatnonzero(~ok)
    if bad.size:
        raise SolverFailure(
            f"compare: the simulation of trial {data.names[int(bad[0])]!r} with these parameters did not reach its end "
            "(or gave non-finite values); check the parameters and that trial's inputs."
        )
    reports, predicted = [], []
    for i, (tr, e) in enumerate(zip(trials, trial_errors(data, pose))):
        rep = _trial_report(data, i, e, nu[i], np.asarray(tr.inputs, float), lags, aside[i], loss)
        reports.append(rep)
        s = rep["series"]
        q_sim = np.asarray(pose[2][i, : data.lengths[i]])
        name = f"{data.names[i]}_predicted"
        predicted.append(
            Trial(
                np.asarray(tr.t, float),
                s["x_sim"],
                s["y_sim"],
                q_sim,
                np.asarray(tr.inputs, float),
                data.kind,
                name=name,
            )
        )
    verdict, reason = judge(reports)
    return CompareResult(
        trials=reports,
        overall=_overall(reports, lags),
        predicted=predicted,
        params=params,
        verdict=verdict,
        reason=reason,
    )


def judge(reports: Sequence[dict[str, Any]], alpha: float = ALPHA) -> tuple[str, str]:
    """The verdict (one of `VERDICTS`) and its one-sentence reason from the trials' reports
    (module docstring): the Ljung-Box p-values of every trial and channel tested together at
    `alpha`, then the share of each trial's frames set aside against `REJECTED`. Marks each
    report's channels: `whiteness["correlated"]`, the channels whose residuals are not white."""
    p = [r["whiteness"]["ljung_box"][c]["p"] for r in reports for c in CHANNELS]
    bad, cut = rejects(p, alpha)
    bad = bad.reshape(len(reports), len(CHANNELS))
    for r, row in zip(reports, bad):
        r["whiteness"]["correlated"] = [c for c, b in zip(CHANNELS, row) if b]
        r["whiteness"]["p_threshold"] = cut
    correlated = [(r, r["whiteness"]["correlated"]) for r in reports if r["whiteness"]["correlated"]]
    heavy = [r for r in reports if r["outliers"]["count"] > REJECTED * max(r["measured"], 1)]
    left_out = [r for r in heavy if r["outliers"]["count"] > ABANDONED * max(r["measured"], 1)]
    if left_out and not correlated:
        where = ", ".join(f"{r['name']!r} ({r['outliers']['count']} of {r['measured']} frames)" for r in left_out)
        return "model error", (
            f"more than {ABANDONED:.0%} of the frames of {where} were set aside: no capture's glitches, but a trial "
            "the model does not follow; a parameter is off or the model misses an effect (dissipation, a torque "
            "gain, a clock offset): fit again on these trials with those parameters free, or check the robot file"
        )
    if correlated:
        worst = min(correlated, key=lambda rc: min(rc[0]["whiteness"]["ljung_box"][c]["p"] for c in rc[1]))[0]
        where = "; ".join(f"trial {r['name']!r}: {', '.join(cs)}" for r, cs in correlated)
        return "model error", (
            f"the residuals are correlated in time ({where}; worst {worst['name']!r}, "
            f"{worst['whiteness']['acf_outside_99']:.0%} of its autocorrelation lags outside the 99 % band, "
            f"Ljung-Box p < {cut:.1e}): the model does not explain these trials; a parameter is off or the model "
            "misses an effect (dissipation, a torque gain, a clock offset): fit again on these trials with those "
            "parameters free, or check the robot file"
        )
    if heavy:
        where = ", ".join(f"{r['name']!r} ({r['outliers']['count']} of {r['measured']} frames)" for r in heavy)
        return "capture defects", (
            f"the residuals are white, but more than {REJECTED:.0%} of the frames of {where} were set aside as "
            "ghost frames or marker swaps: those trials do not test the model; convert the takes again or use "
            "other trials"
        )
    n = sum(r["outliers"]["count"] for r in reports)
    aside = f"; {n} frame(s) set aside as capture glitches" if n else ""
    return "consistent", (
        f"the residuals of every trial and channel are white (Ljung-Box at {alpha:g} over "
        f"{len(reports) * len(CHANNELS)} series){aside}"
    )


# ----------------------------------------------------------------------------- the nuisance values


@functools.partial(jax.jit, static_argnames=("kind", "rtol", "atol", "max_steps", "max_offset"))
def _model(params, nu, arrays, sig, *, kind: str, rtol: float, atol: float, max_steps: int, max_offset: float):
    """The residuals and their Jacobian with respect to each trial's nuisance values, vmapped
    over trials: `(params, nu (T, n), data, sig) -> (res, ok, J, pose)`."""

    def one(p, nu, d, sig):
        def f(z):
            res, ok, pose, _ = trial_model(
                p, kind, rtol, atol, max_steps, dfx.ForwardMode(), z, d, sig, None, max_offset
            )
            return res, (res, ok, pose)

        J, (res, ok, pose) = jax.jacfwd(f, has_aux=True)(nu)
        return res, ok, J, pose

    return jax.vmap(one, in_axes=(None, 0, 0, None))(params, nu, arrays, sig)


#: the nuisance estimate's iteration: one dense problem per trial, damped as the fit's
NUISANCE_LM = LevenbergMarquardt(
    eqx.filter_vmap(Dense(shift=1e-12)), rel_done=1e-10, gtol=1e-8, max_stalled=3, max_rejected=8
)
#: its linear solve as one compiled program
_nuisance_step = eqx.filter_jit(NUISANCE_LM.solve)


def _estimate_nuisance(params, data: FitData, sig, max_iter: int, rtol, atol, max_steps, loss: str = "l2", nu=None):
    """Each trial's nuisance values by Levenberg-Marquardt (`NUISANCE_LM`) with `params` held
    (trials are then independent: one small damped Gauss-Newton step per trial, all in one
    vmapped call), on the cost of `loss` (`jsphere.identify.robust`: the reweighted residuals
    and Jacobian are the linearisation), from `nu (T, n)` (default: `nuisance_guess`). Returns the values `(T, n)`, the simulated poses there,
    whether each trial's solve succeeded and the whitened residuals `(T, K)`."""
    config = {"kind": data.kind, "rtol": rtol, "atol": atol, "max_steps": max_steps, "max_offset": data.max_offset}
    arrays, sig_j = data.arrays(), jnp.asarray(sig)

    def evaluate(nu):
        res, ok, J, pose = _model(params, jnp.asarray(nu), arrays, sig_j, **config)
        if loss == "l2":
            cost, linear = 0.5 * (res * res).sum(1), (res, J)
        else:
            cost = robust_cost(loss, res[:, None])
            rw, Jw = reweigh(loss, res[:, None], J[:, None])
            linear = (rw[:, 0], Jw[:, 0])
        return jnp.where(ok, cost, jnp.inf), (linear, pose, res)

    nu = jnp.asarray(nuisance_guess(data, params) if nu is None else nu)
    state = NUISANCE_LM.init(*evaluate(nu))
    state = eqx.tree_at(lambda s: s.converged, state, ~jnp.isfinite(state.cost))
    solve = lambda current, lam: _nuisance_step(current[0], lam)
    for nu, state, _ in iterate(NUISANCE_LM, evaluate, solve, nu, state, max_iter, every=True):
        pass
    return (
        np.asarray(nu),
        tuple(np.asarray(a) for a in state.current[1]),
        np.isfinite(np.asarray(state.cost)),
        np.asarray(state.current[2]),
    )


# ----------------------------------------------------------------------------- the scores


def _norms(err: np.ndarray, y: np.ndarray) -> tuple[float, float]:
    """`(|err|^2, |y - mean(y)|^2)`, sums over all entries (`y (n, ...)`)."""
    return float((err**2).sum()), float(((y - y.mean(0)) ** 2).sum())


def _fit_percent(norms: tuple[float, float]) -> float:
    """`100 (1 - |err| / |y - mean(y)|)` from `_norms`."""
    num, den = norms
    return 100.0 * (1.0 - math.sqrt(num / den)) if den > 0 else -math.inf


def _ccf(e: np.ndarray, w: np.ndarray, u: np.ndarray, lags: int) -> np.ndarray:
    """Cross-correlation `(2 lags + 1,)` of a residual series `e` (measured where `w`) with an
    input `u`, at lags `-lags..lags` (`e(t)` against `u(t - k)`)."""
    e = np.where(w, e - e[w].mean(), 0.0)
    u = u - u.mean()
    se, su = math.sqrt((e * e).sum() / max(w.sum(), 1)), math.sqrt((u * u).mean())
    out = np.zeros(2 * lags + 1)
    if se == 0 or su == 0:
        return out
    n = len(e)
    for j, k in enumerate(range(-lags, lags + 1)):
        a, b = (e[k:], u[: n - k]) if k >= 0 else (e[: n + k], u[-k:])
        ww = w[k:] if k >= 0 else w[: n + k]
        out[j] = (a * b).sum() / max(ww.sum(), 1) / (se * su)
    return out


def _trial_report(
    data: FitData, i: int, errors: dict[str, Any], nu_i, inputs: np.ndarray, lags: int, aside, loss: str
) -> dict[str, Any]:
    """One trial's scores from its errors (`trial_errors`): fits on every measured frame,
    whiteness and cross-correlations on those not set aside (`aside (M,)`)."""
    m, wp, wr, ep, rot_err = data.lengths[i], errors["wp"], errors["wr"], errors["ep"], errors["er"]
    out = np.asarray(aside[:m], bool)
    rot_meas = quat_log_np(quat_mul_np(quat_conj_np(data.q0[i]), data.q[i, :m]))
    ex, ey = ep[:, 0], ep[:, 1]
    norms = {
        "x": _norms(ex[wp], data.x[i, :m][wp]),
        "y": _norms(ey[wp], data.y[i, :m][wp]),
        "rot": _norms(rot_err[wr], rot_meas[wr]),
    }
    fit = {k: _fit_percent(v) for k, v in norms.items()}
    resid = np.stack([ex, ey, *rot_err.T], 1)
    masks = [wp & ~out, wp & ~out, wr & ~out, wr & ~out, wr & ~out]
    white = [channel(resid[:, c], masks[c], lags) for c in range(len(CHANNELS))]
    band = Z99 / math.sqrt(max(int(masks[0].sum()), 1))
    acfs = np.stack([w["acf"] for w in white])
    outside = np.abs(acfs[:, 1:]) > band
    u = np.asarray(inputs, float)[:m]
    # (channel, input, lag)
    ccfs = np.array([[_ccf(resid[:, c], masks[c], u[:, j], lags) for j in range(u.shape[1])] for c in range(5)])
    c_out = np.abs(ccfs) > band
    return {
        "name": data.names[i],
        "samples": m,
        "fit_percent": fit,
        "whiteness": {
            "acf_outside_99": float(outside.mean()),
            "band": band,
            "lags": lags,
            "channels": {c: float(outside[k].mean()) for k, c in enumerate(CHANNELS)},
            "ljung_box": {c: {"q": w["q"], "p": w["p"], "frames": w["frames"]} for c, w in zip(CHANNELS, white)},
        },
        "cross_correlation": {
            "ccf_outside_99": float(c_out.mean()),
            "max_abs": float(np.abs(ccfs).max()),
            "band": band,
            "lags": lags,
            "inputs": {f"input_{j + 1}": float(c_out[:, j].mean()) for j in range(u.shape[1])},
        },
        "outliers": {"frames": np.flatnonzero(out).tolist(), "count": int(out.sum()), "loss": loss},
        "measured": int((wp | wr).sum()),
        "rms_pos_m": float(np.sqrt((ex[wp] ** 2 + ey[wp] ** 2).mean())),
        "rms_rot_deg": float(np.degrees(np.sqrt((rot_err[wr] ** 2).sum(1).mean()))),
        "nuisance": nuisance_values(data, nu_i),
        "series": errors["series"]
        | {
            "residuals": np.where(np.stack([wp, wp, wr, wr, wr], 1), resid, np.nan),
            "set_aside": out,
            "acf": acfs,
            "channels": CHANNELS,
            "band": band,
            "fit_percent": fit,
            "norms": norms,
        },
    }


def _overall(reports: list[dict[str, Any]], lags: int) -> dict[str, Any]:
    """The scores of all trials together: fits from the pooled norms (each trial about its own
    mean), fractions over all trials' lags (weighted by their counts), RMS over all samples."""
    pooled = lambda key: [sum(r["series"]["norms"][key][j] for r in reports) for j in (0, 1)]
    fit = {key: _fit_percent(pooled(key)) for key in ("x", "y", "rot")}
    n = np.array([r["samples"] for r in reports], float)
    wavg = lambda vals: float((np.asarray(vals) * n).sum() / n.sum())
    return {
        "name": "overall",
        "trials": len(reports),
        "samples": int(n.sum()),
        "fit_percent": fit,
        "whiteness": {
            "acf_outside_99": wavg([r["whiteness"]["acf_outside_99"] for r in reports]),
            "lags": lags,
        },
        "cross_correlation": {
            "ccf_outside_99": wavg([r["cross_correlation"]["ccf_outside_99"] for r in reports]),
            "max_abs": max(r["cross_correlation"]["max_abs"] for r in reports),
            "lags": lags,
        },
        "rms_pos_m": math.sqrt(wavg([r["rms_pos_m"] ** 2 for r in reports])),
        "rms_rot_deg": math.sqrt(wavg([r["rms_rot_deg"] ** 2 for r in reports])),
        "outliers": {"count": sum(r["outliers"]["count"] for r in reports)},
        "measured": sum(r["measured"] for r in reports),
    }
