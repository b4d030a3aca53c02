"""What a fit returns: `FitResult` (values, standard errors, covariance, identifiability, per-trial
residuals, the verdict) and its JSON document.

Covariance: `s^2 F^-1` with `F` the Gauss-Newton information of `theta` after eliminating the
nuisance parameters (`jsphere.numerics.lm.marginal_information`), mapped to physical units. For a
robust loss `F` is that of the reweighted residuals and `s^2` the M-estimator's variance factor
(`jsphere.identify.robust.variance_factor`).
"""

from __future__ import annotations

import dataclasses
import json
import math
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from .._runtime.arrays import to_jax
from .._runtime.errors import InputError
from .._runtime.files import dumps_json
from ..model.internal import FIELDS
from ..model.names import MOUNTING, parse_name
from ..model.params import RobotParams
from ..numerics.lm import blocks, marginal_information
from .data import FitData, nuisance_values, offset_from_nuisance, trial_errors
from .free import FreeParams
from .identifiability import identifiability, scaled_information, units_note
from .mixed import MixedData, parts_of, weighted
from .onboard import CHANNELS, UNITS, OnboardData
from .onboard_verdict import channel_floors, combined_verdict, judge_onboard
from .options import save_json
from .robust import REJECT, frame_weights, variance_factor
from .shooting import DEFECT_CLOSED
from .verdict import judge, missing_effects, noise_floor


@dataclasses.dataclass
class FitResult:
    """What `fit` returns. `params`: the fitted `RobotParams` (fixed values included);
    `free`: the expanded free names; `values`, `stderr`: per free name (physical units), and
    for a whole field given as free (`"I"`, `"r_m"`) nested lists of the field's shape;
    `covariance`, `correlation`: of the expanded names (stderr is `inf` along directions the
    data do not determine); `identifiability`: condition number, poorly determined directions,
    warnings; `sigma_pos` [m], `sigma_rot` [rad]: noise levels (estimated unless given);
    `trials`: per trial its RMS residuals, nuisance values and, under `"series"`, the measured
    and simulated paths (for the plots; not written to JSON); `status`, `status_reason`: the
    verdict on the fit (`"converged"`, `"not_converged"` or `"misfit"`, and one sentence: see
    `jsphere.identify.verdict`), `verdict`: the numbers behind it (the capture's noise floor, the
    residual sigmas and their ratios to it, their lag-1 autocorrelations, per trial, the worst
    trial's name); `time_offset`, `time_offset_stderr` [s]: per trial, in trial order, the
    fitted clock offsets and their standard errors (`fit(..., fit_time_offset=True)`; None
    otherwise); `solve_options`: the fit's ODE tolerances (`rtol`, `atol`, `max_steps`), which
    `predict` uses; `loss`: the fit's loss (`jsphere.identify.robust`); `outliers`: per trial
    (by the name of the file it was read from, `Trial.source`, else by its name; in trial
    order) the frames the loss set aside (weight below one half), as
    `{"frames": [0-based row numbers of the trial's data rows], "count": n}`; `units_note`: what
    the fitted masses and inertias are relative to (the torque constant when torque trials are
    fitted with `k_tau` fixed; `jsphere.identify.identifiability.units_note`); `options`: the
    `FitOptions` of the fit (in `fit.json` as `FitOptions.to_json` writes them).

    Onboard-sensor trials (`kind` ends in `"onboard"`): `sigma_pos`, `sigma_rot` are NaN and
    `sigmas` holds the noise level of each channel (`gyro` [rad/s], `acc` [m/s^2], `encoders`
    [rad]); each trial's report its RMS residual per channel and its biases (`nuisance`);
    `channel_share`: per free name, the share of its information (the diagonal of the
    information with the biases eliminated) that each channel gives; `verdict` is per channel
    (`jsphere.identify.onboard_verdict`); `mounting`: the IMU's `position` [m] and `rotation`
    (quaternion), as given or, where `imu_position`/`imu_rotation` are free, as fitted."""

    params: RobotParams
    free: list[str]
    given: list[tuple[str, list[str]]]
    values: dict[str, Any]
    stderr: dict[str, Any]
    covariance: np.ndarray
    correlation: np.ndarray
    cost: float
    iterations: int
    converged: bool
    sigma_pos: float
    sigma_rot: float
    n_residuals: int
    identifiability: dict[str, Any]
    trials: list[dict[str, Any]]
    starts: list[float]
    kind: str
    elapsed_s: float
    status: str = ""
    status_reason: str = ""
    verdict: dict[str, Any] = dataclasses.field(default_factory=dict)
    shooting: dict[str, Any] = dataclasses.field(default_factory=dict)
    time_offset: list[float] | None = None
    time_offset_stderr: list[float] | None = None
    solve_options: dict[str, Any] = dataclasses.field(default_factory=dict, repr=False)
    loss: str = "l2"
    outliers: dict[str, dict[str, Any]] = dataclasses.field(default_factory=dict)
    units_note: str = ""
    options: Any = dataclasses.field(default=None, repr=False)
    sigmas: dict[str, float] = dataclasses.field(default_factory=dict)
    channel_share: dict[str, dict[str, float]] = dataclasses.field(default_factory=dict)
    mounting: dict[str, list[float]] = dataclasses.field(default_factory=dict)

    def predict(self, trials, **kwargs):
        """The fitted model on `trials` (held out from the fit, or the fit's own): each trial
        simulated from its own initial pose with the fitted parameters, its initial velocities
        estimated as the fit estimates them (`jsphere.compare`, which takes the same keywords;
        the fit's solver tolerances by default). Returns a `CompareResult`: its `predicted` holds
        the simulated trials, its `trials` the scores."""
        from .compare import compare

        return compare(self.params, trials, **(self.solve_options | kwargs))

    def to_json(self) -> dict[str, Any]:
        """The JSON document (`RobotParams.load` reads its `params`; non-finite numbers as None)."""
        same = ("free", "values", "stderr", "correlation", "cost", "iterations", "converged", "status")
        same += ("status_reason", "n_residuals", "kind", "identifiability", "verdict")
        doc = {"params": self.params.to_dict()} | {k: getattr(self, k) for k in same}
        doc |= {
            "trials": [{k: v for k, v in t.items() if k != "series"} for t in self.trials],
            "starts_cost": self.starts,
        }
        if self.sigmas:
            doc |= {"sigmas": self.sigmas, "channel_share": self.channel_share, "mounting": self.mounting}
        if math.isfinite(self.sigma_pos):  # pose trials: theirs only
            doc |= {
                "sigma_pos_m": self.sigma_pos,
                "sigma_rot_deg": math.degrees(self.sigma_rot),
                "rms_pos_m": [t["rms_pos_m"] for t in self.trials if "rms_pos_m" in t],
                "rms_rot_deg": [t["rms_rot_deg"] for t in self.trials if "rms_rot_deg" in t],
            }
        doc |= {k: getattr(self, k) for k in ("elapsed_s", "shooting", "loss", "outliers", "units_note")}
        if self.time_offset is not None:
            doc |= {"time_offset": self.time_offset, "time_offset_stderr": self.time_offset_stderr}
        if self.options is not None:
            doc["options"] = self.options.to_json()
        return json.loads(dumps_json(doc))

    def save(self, path, **deprecated) -> list[Path]:
        """Write the JSON atomically; returns `[path]`. The figures are drawn by
        `jsphere.plots.fit_figures(result, folder, stem=...)` (`jsphere fit` writes
        `<stem>_overlay.png` and `<stem>_residuals.png` beside the JSON). `plots=` is deprecated
        and draws nothing."""
        return save_json(
            self.to_json(), path, deprecated, "FitResult.save", "jsphere.plots.fit_figures(result, folder, stem=...)"
        )

    def table(self) -> str:
        """A plain-text summary: value +- stderr per free name, noise levels, warnings, and last
        the status with its reason."""
        w = max([10] + [len(n) for n in self.free])
        lines = [f"{'name':<{w}} {'value':>14} {'stderr':>12} {'rel':>9}"]
        for n in self.free:
            v, s = self.values[n], self.stderr[n]
            rel = abs(s / v) if v else float("inf")
            lines.append(f"{n:<{w}} {v:>14.6g} {s:>12.3g} {rel:>9.2%}")
        levels = []
        if math.isfinite(self.sigma_pos):
            levels.append(f"sigma_pos {self.sigma_pos * 1e3:.3f} mm, sigma_rot {math.degrees(self.sigma_rot):.3f} deg")
        if self.sigmas:
            levels.append(", ".join(f"sigma_{c} {v:.4g} {u}" for (c, v), u in zip(self.sigmas.items(), UNITS)))
        levels = ", ".join(levels)
        lines.append(
            f"cost {self.cost:.6g} over {self.n_residuals} residuals, {self.iterations} iterations, "
            f"converged: {self.converged}; {levels}"
        )
        if any(n.startswith("imu_") for n in self.free):
            pos, rot = (" ".join(f"{x:.6g}" for x in self.mounting[k]) for k in ("position", "rotation"))
            lines.append(f"IMU mounting as fitted: position {pos} m, rotation {rot}")
        for c, share in self.channel_share.items():
            lines.append(f"information from the {c}: " + ", ".join(f"{n} {v:.0%}" for n, v in share.items()))
        if self.units_note:
            lines.append(f"units: {self.units_note}")
        for w in self.identifiability.get("warnings", []):
            lines.append(f"warning: {w}")
        if self.time_offset is not None:
            for t, v, s in zip(self.trials, self.time_offset, self.time_offset_stderr):
                lines.append(f"time offset of {t['name']}: {v * 1e3:.2f} +- {s * 1e3:.2f} ms")
        if self.status:
            lines.append(f"status: {self.status}: {self.status_reason}")
        return "\n".join(lines)


def _assemble_named(free: FreeParams, per_name: dict[str, float], params: RobotParams, fill: float) -> dict[str, Any]:
    """Add an entry for each whole field given as free (`"I"`: 3x3 nested list), and one per
    name as given where it differs from its canonical spelling (`"I[1,0]"` is `"I[0,1]"`)."""
    out = dict(per_name)
    for given, comps in free.given:
        field, index = parse_name(given)
        if index or len(comps) == 1:
            if given not in out:  # spelled differently from the canonical name (`I[1,0]`, `I[0, 0]`)
                out[given] = per_name[comps[0]]
            continue
        arr = np.full((3,) if field in MOUNTING else np.shape(getattr(params, field)), fill)
        for c in comps:
            ix = parse_name(c)[1]
            arr[ix] = per_name[c]
            if field == "I":
                arr[ix[::-1]] = per_name[c]
        out[given] = arr.tolist()
    return out


def fit_result(run, st, cost, out, keys: Sequence[str]) -> FitResult:
    """The `FitResult` of the best start (the lowest `cost`) of a fit that has ended: `run` and
    `st` are `jsphere.identify.fit`'s run and state, `out` the evaluation at the final points
    (`pose`: simulated `x, y, q`; `res`, `J` unweighted, as `jsphere.identify.residuals` gives
    them); `keys`: each trial's key in `outliers`."""
    free, data, o = run.free, run.data, run.options
    b, loss, P = int(np.argmin(cost)), o.loss, free.size
    parts = parts_of(data)
    n_res = data.n_measured
    res_b, J_b = np.asarray(out["res"])[b], np.asarray(out["J"])[b]
    own = _parts(data, res_b, np.asarray(st.nu[b]), out["pose"])  # each part's residuals, nuisance values, readings
    pose = next((k for k, d in enumerate(parts) if d.measure == "pose"), None)
    counts = 2 * parts[pose].wpos + 3 * parts[pose].wrot if pose is not None else None
    set_aside = None
    if pose is not None:
        set_aside = np.zeros(counts.shape, bool)
        if loss != "l2":
            set_aside = (frame_weights(loss, own[pose][0]) < REJECT) & (counts > 0)
    s2 = _variance_factor(parts, loss, 2.0 * cost[b], own, counts, P, n_res)
    if loss != "l2":
        res_b, J_b = weighted(data, loss, res_b[None], to_jax(J_b[None]))
        res_b, J_b = np.asarray(res_b[0]), J_b[0]
    params = free.compiled()[1](to_jax(st.theta[b]), run.base)
    unphysical = ""
    try:  # validated: a fit may end at values no body has (a wrong valley); the verdict says so
        params = RobotParams(**{f: getattr(params, f) for f in FIELDS}, dtype=run.base.R0.dtype)
    except InputError as e:
        unphysical = str(e)
    values, F_phys, cov, se, corr = _covariance(free, st.theta[b], res_b, J_b, s2, params=params, kind=data.kind)
    ident = identifiability(free, values, F_phys, s2, params, kind=data.kind)
    ident["sigma_note"] = "relative sd of each direction; warnings list directions with relative sd > 10%"
    trials, verdict = _reports(run, st, parts, own, b, set_aside, counts, unphysical)
    offsets = _time_offsets(data, np.asarray(st.nu[b]), res_b, J_b, P, s2) if pose == 0 and len(parts) == 1 else None
    offsets = offsets or (None, None)
    onboard = parts[-1] if parts[-1].measure != "pose" else None
    sig = dict(zip([c for d in parts for c in (CHANNELS if d.measure != "pose" else d.channels)], map(float, st.sig)))
    shooting = {"method": "single"}
    if run.shooting is not None:
        ms, closed = run.shooting, st.max_defect <= DEFECT_CLOSED
        shooting = {"method": "multiple", "segment_s": ms.segment, "segments": ms.G, "largest_defect": st.max_defect}
        shooting["closed"] = closed
    return FitResult(
        params=params,
        free=list(free.names),
        given=free.given,
        values=_assemble_named(free, dict(zip(free.names, map(float, values))), params, np.nan),
        stderr=_assemble_named(free, dict(zip(free.names, map(float, se))), params, 0.0),
        covariance=cov,
        correlation=corr,
        cost=float(cost[b]),
        iterations=int(st.total_it),
        converged=bool(st.stage_converged),
        sigma_pos=sig.get("position", math.nan),
        sigma_rot=sig.get("orientation", math.nan),
        n_residuals=n_res,
        identifiability=ident,
        trials=trials,
        starts=[float(c) for c in cost],
        kind=data.kind,
        elapsed_s=time.perf_counter() - run.t_begin,
        status=verdict.pop("status"),
        status_reason=verdict.pop("reason"),
        verdict=verdict,
        shooting=shooting,
        time_offset=offsets[0],
        time_offset_stderr=offsets[1],
        solve_options={"rtol": o.rtol, "atol": o.atol, "max_steps": o.max_steps},
        loss=loss,
        outliers={
            k: {"frames": np.flatnonzero(t["series"]["set_aside"]).tolist(), "count": t["set_aside"]}
            for k, t in zip(keys, trials)
        },
        units_note=units_note(free.names, params, data.kind),
        options=o,
        sigmas={c: sig[c] for c in CHANNELS} if onboard else {},
        channel_share=_channel_share(data, free, res_b, J_b) if onboard else {},
        mounting=_mounting(onboard, free, st.theta[b]) if onboard else {},
    )


def _reports(run, st, parts, own, b: int, set_aside, counts, unphysical: str) -> tuple[list[dict], dict[str, Any]]:
    """Every trial's report (`_trial_reports`, `_onboard_reports`) and the verdict (of both
    parts, `combined_verdict`, where there are two)."""
    trials, verdicts = [], []
    for d, (_, nu_d, aux) in zip(parts, own):
        if d.measure == "pose":
            part = _trial_reports(d, aux, nu_d, b, set_aside)
            verdicts.append(_verdict(run, st, d, part, counts, unphysical))
        else:
            part = _onboard_reports(d, aux, nu_d, b)
            verdicts.append(_onboard_verdict(run, st, d, part, unphysical))
        trials += part
    return trials, verdicts[0] if len(verdicts) == 1 else combined_verdict(*verdicts)


def _parts(data, res_b: np.ndarray, nu_b: np.ndarray, aux) -> list[tuple[np.ndarray, np.ndarray, Any]]:
    """Per part of the fit (`MixedData.parts`, or the data itself): its trials' residuals and
    nuisance values without padding, and their simulated poses or readings (every start)."""
    if not isinstance(data, MixedData):
        return [(res_b, nu_b, aux)]
    return [
        (data.unpad(r, k), data.unpad(n, k, "nu"), a)
        for k, (r, n, a) in enumerate(zip(data.split(res_b), data.split(nu_b), aux))
    ]


def _variance_factor(parts, loss: str, ssq: float, own, counts, P: int, n_measured: int) -> float:
    """`s^2`, the scale of the covariance: the sum of squares per degree of freedom, or for a
    robust loss `variance_factor` of the pose trials' residuals, pooled by degrees of freedom
    with the other part's sum of squares (its unknowns: its nuisance values and its share of
    the free parameters, by measured values)."""
    n_unknown = P + sum(len(d.names) * len(d.nuisance) for d in parts)
    if loss == "l2":
        return float(ssq / max(n_measured - n_unknown, 1))
    num = den = 0.0
    for d, (r, _, _) in zip(parts, own):
        n_par = P * d.n_measured / n_measured + len(d.names) * len(d.nuisance)
        dof = max(d.n_measured - n_par, 1.0)
        num += variance_factor(loss, r, counts, n_par) * dof if d.measure == "pose" else float((r * r).sum())
        den += dof
    return num / den


def _mounting(data: OnboardData, free: FreeParams, theta: np.ndarray) -> dict[str, list[float]]:
    """The IMU's mounting of an onboard fit: as given, with the free names' fitted values."""
    pos, rot = free.mounting_at(to_jax(theta), to_jax(data.imu_pos[0]), to_jax(data.imu_rot[0]))
    rot = np.asarray(rot) / np.linalg.norm(np.asarray(rot))
    return {"position": np.asarray(pos).tolist(), "rotation": rot.tolist()}


def _onboard_reports(data: OnboardData, readings, nu_b: np.ndarray, b: int) -> list[dict[str, Any]]:
    """Per onboard trial: the RMS residual of each channel, the biases and the series (`t`, the
    readings `gyro`, `acc`, `chi` and the residuals `gyro_err`, `acc_err`, `chi_err`) of start `b`."""
    sim = [np.asarray(a)[b] for a in readings]
    out = []
    for i, m in enumerate(data.lengths):
        errs = [s[i, :m] - meas[i, :m] for s, meas in zip(sim, (data.gyro, data.acc, data.chi))]
        series = {"t": data.ts[i, :m] + data.t_start[i], "set_aside": np.zeros(m, bool)}
        series |= {f"{k}_err": e for k, e in zip(("gyro", "acc", "chi"), errs)}
        series |= {k: meas[i, :m] for k, meas in zip(("gyro", "acc", "chi"), (data.gyro, data.acc, data.chi))}
        rms = {f"rms_{c}": _rms(e) for c, e in zip(CHANNELS, errs)}
        nuisance = dict(zip(data.nuisance, map(float, nu_b[i])))
        out.append({"name": data.names[i], "samples": m, **rms, "set_aside": 0, "nuisance": nuisance, "series": series})
    return out


def _onboard_verdict(run, st, data: OnboardData, trials: list[dict[str, Any]], unphysical: str) -> dict[str, Any]:
    """`judge_onboard` on the residuals of an onboard fit's trials (`data`)."""
    free = run.free
    return judge_onboard(
        [[t["series"][f"{k}_err"] for k in ("gyro", "acc", "chi")] for t in trials],
        channel_floors(data),
        names=data.names,
        converged=bool(st.stage_converged),
        why_not=f"Levenberg-Marquardt reached max_iter in its last stage, {int(st.total_it)} iterations in all",
        n_params=free.size + data.ts.shape[0] * len(data.nuisance),
        free=free.names,
        kind=data.kind,
        unphysical=unphysical,
    )


def _channel_share(data, free: FreeParams, res_b: np.ndarray, J_b) -> dict[str, dict[str, float]]:
    """Per channel, the share of each free name's information it gives: the diagonal of the
    channel's information over the whole's, the biases eliminated (each bias enters one
    channel only, so the channels' informations add up to the whole's). With pose trials too
    (`MixedData`), theirs is the `"capture"` channel's."""
    P, J_b = free.size, np.asarray(J_b)
    F = np.diag(marginal_information(to_jax(res_b), to_jax(J_b), P))
    onboard, trials, groups = data, slice(None), []
    if isinstance(data, MixedData):
        onboard, trials = data.onboard, slice(data.n_pose, None)
        groups.append(("capture", slice(None, data.n_pose), slice(None)))
    M, at = onboard.ts.shape[1], 0
    for c, width in zip(CHANNELS, onboard.widths):
        groups.append((c, trials, slice(at, at + M * width)))
        at += M * width
    out = {}
    for c, ts, rows in groups:
        Fc = np.diag(marginal_information(to_jax(res_b[ts, rows]), to_jax(J_b[ts, rows]), P))
        with np.errstate(invalid="ignore", divide="ignore"):
            share = np.where(F > 0, Fc / F, np.nan)
        out[c] = {n: float(v) for n, v in zip(free.names, share)}
    return out


def _verdict(run, st, data: FitData, trials: list[dict[str, Any]], counts: np.ndarray, unphysical: str) -> dict:
    """`judge` on the residuals of the frames a fit kept of its pose trials `data` (`trials`:
    `_trial_reports`)."""
    free = run.free
    kept = [~t["series"]["set_aside"][:, None] for t in trials]
    return judge(
        [np.where(k, t["series"]["pos_err"], np.nan) for t, k in zip(trials, kept)],
        [np.where(k, np.radians(t["series"]["rot_err_deg"]), np.nan) for t, k in zip(trials, kept)],
        noise_floor(data),
        names=data.names,
        set_aside=[int(t["set_aside"]) for t in trials],
        measured=[int((counts[i, :m] > 0).sum()) for i, m in enumerate(data.lengths)],
        converged=bool(st.stage_converged),
        n_params=free.size + data.ts.shape[0] * len(data.nuisance),
        why_not=f"Levenberg-Marquardt reached max_iter in its last stage, {int(st.total_it)} iterations in all",
        missing=missing_effects(free.names, data.kind, data.max_offset > 0, known=FIELDS),
        unphysical=unphysical,
    )


def _time_offsets(data: FitData, nu_b: np.ndarray, res_b: np.ndarray, J_b, P: int, s2: float):
    """The fitted clock offsets [s] and their standard errors per trial, or None where they are
    not fitted. The covariance of a trial's nuisance block of the block-arrow normal equations
    (`jsphere.numerics.lm`) is `s2 (A + A Hng F^-1 Hgn A)`, `A = Hnn^-1` and `F` the marginal
    information of the free parameters; the offset's is mapped through `offset_from_nuisance`."""
    if data.max_offset <= 0:
        return None
    m = data.max_offset
    Hgg, Hgn, Hnn, _, _ = (np.asarray(a) for a in blocks(to_jax(res_b), to_jax(J_b), P))
    F = marginal_information(to_jax(res_b), to_jax(J_b), P)
    Finv = np.linalg.pinv(F, rcond=1e-13, hermitian=True)
    values, errors = [], []
    for t in range(Hnn.shape[0]):
        A = np.linalg.pinv(Hnn[t], rcond=1e-13, hermitian=True)
        cov = A + A @ Hgn[t].T @ Finv @ Hgn[t] @ A
        v = float(nu_b[t, -1])
        slope = 1.0 - math.tanh(v / m) ** 2
        values.append(float(offset_from_nuisance(v, m)))
        errors.append(float(math.sqrt(max(s2 * cov[-1, -1], 0.0)) * slope))
    return values, errors


def _covariance(
    free: FreeParams,
    th_b,
    res_b: np.ndarray,
    J_b,
    s2: float,
    *,
    params: RobotParams | None = None,
    kind: str | None = None,
):
    """`(values, F_phys, cov, stderr, corr)` in physical units: the values of the free names, the
    information of theta with the nuisance parameters eliminated, the covariance `s2 F^-1`
    (pseudo-inverse on the scaled names; stderr `inf` along directions the data do not
    determine) and the correlations. Given the fitted `params` and the trials' input `kind`,
    the exact invariances of the free set (`exact_symmetries`) are removed from the information
    before it is inverted: their names get an infinite stderr, not one rounding left finite
    (`F_phys` is returned as computed)."""
    P = free.size
    F = marginal_information(to_jax(res_b), to_jax(J_b), P)  # information of theta (whitened)
    values, A = (np.asarray(a) for a in free.compiled()[0](to_jax(th_b)))
    # (pinv: a transform at the edge of its range, e.g. exp(u) -> 0, has a zero derivative; the
    # name then gets no information, and an infinite standard error)
    Ainv = np.linalg.pinv(A)
    F_phys = Ainv.T @ F @ Ainv
    sc, Fs = scaled_information(free, values, F_phys, params, kind)
    lam, V = np.linalg.eigh(Fs)
    keep = lam > 1e-14 * max(lam[-1], 1e-300)
    cov_s = (V[:, keep] / lam[keep]) @ V[:, keep].T * s2
    cov = sc[:, None] * cov_s * sc[None, :]
    se = np.sqrt(np.maximum(np.diag(cov), 0.0))
    null_w = np.abs(V[:, ~keep]).max(1) if (~keep).any() else np.zeros(P)
    se = np.where(null_w > 1e-6, np.inf, se)
    with np.errstate(invalid="ignore", divide="ignore"):
        corr = cov / np.outer(se, se)
    corr = np.where(np.isfinite(corr), corr, np.nan)
    np.fill_diagonal(corr, 1.0)
    return values, F_phys, cov, se, corr


def _rms(e: np.ndarray) -> float:
    """The RMS norm of the rows of `e`; NaN for none (every frame of a trial set aside)."""
    return float(np.sqrt((e**2).sum(1).mean())) if len(e) else math.nan


def _trial_reports(data: FitData, pose, nu_b: np.ndarray, b: int, set_aside: np.ndarray) -> list[dict[str, Any]]:
    """Per trial: RMS residuals (of the frames not set aside: `set_aside (T, M)`), the number
    set aside, nuisance values and the measured and fitted series (for the plots) of start `b`."""
    trials = []
    for i, e in enumerate(trial_errors(data, [np.asarray(a)[b] for a in pose])):
        m, wp, wr, ep, er = data.lengths[i], e["wp"], e["wr"], e["ep"], e["er"]
        out = set_aside[i, :m]
        series = e["series"] | {
            "pos_err": np.where(wp[:, None], ep, np.nan),
            "rot_err_deg": np.where(wr[:, None], np.degrees(er), np.nan),
            "set_aside": out,
        }
        trials.append(
            {
                "name": data.names[i],
                "samples": m,
                "rms_pos_m": _rms(ep[wp & ~out]),
                "rms_rot_deg": float(np.degrees(_rms(er[wr & ~out]))),
                "set_aside": int(out.sum()),
                "nuisance": nuisance_values(data, nu_b[i]),
                "series": series,
            }
        )
    return trials
