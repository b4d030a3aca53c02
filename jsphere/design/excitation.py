"""`design_excitation`: input programmes that make a fit's free parameters as well determined as
possible (D-optimal), with their predicted standard errors and those of a random baseline."""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable, Sequence

import jax.numpy as jnp
import numpy as np

from .._runtime.checks import real, whole
from .._runtime.errors import InputError, SolverFailure
from .._runtime.moved_keywords import moved_into, no_other_keywords
from .._runtime.progress import Progress
from ..identify.free import FreeParams
from ..model.limits import Limits
from ..model.params import RobotParams
from .information import Grid, Noise, problem
from .inputs import KINDS, Spec, match_rms, programmes, random_multisine, random_start, rms, sample_times, table
from .optimise import evaluate, limit_values, limits_report, maximise
from .prediction import d_criterion, fit_information
from .result import CRITERION, DesignResult

#: the RMS of the starts' `s_i(t)` in units of the limit: well inside the limits the penalty watches
START_SCALE = 0.03


@dataclasses.dataclass(frozen=True)
class DesignOptions:
    """The options of `design_excitation` (`jsphere design`'s flags).

    - `trials`: identification trials, one programme each.
    - `sigma_pos` [m], `sigma_rot` [rad]: the capture's noise levels.
    - `restarts`, `steps`, `seed`, `learning_rate`: random starts, all vmapped, and Adam steps;
      the result is deterministic for a given `seed`.
    - `n_freqs`, `f_max` [Hz], `ramp` [s]: the programmes' frequencies `j f_max / n_freqs` and
      ramp time (`jsphere.design.inputs`).
    - `model_rate` [Hz], `substeps`: the optimisation's model grid (RK4 steps per sample).
    - `rate`: rows per second of the tables; `capture_rate` [Hz]: the capture rate of the
      predicted standard errors.

    The values are checked by `design_excitation`, before any work.
    """

    trials: int = 1
    sigma_pos: float = 1e-3
    sigma_rot: float = math.radians(0.5)
    restarts: int = 4
    steps: int = 60
    seed: int = 0
    n_freqs: int = 6
    f_max: float = 1.5
    ramp: float = 0.5
    learning_rate: float = 0.02
    model_rate: float = 20.0
    substeps: int = 2
    rate: float = 100.0
    capture_rate: float = 100.0


def design_excitation(
    params: RobotParams,
    free: str | Sequence[str],
    duration: float,
    kind: str = "K",
    *,
    limits: Limits | None = None,
    options: DesignOptions | None = None,
    progress: bool | None | Callable[[str], None] = None,
    **kwargs,
) -> DesignResult:
    """Input programmes for `options.trials` identification trials of `duration` [s] that
    maximise the D-optimal criterion of the free parameters (`jsphere.design.information`).

    **Arguments:**
    - `params`: the robot (the parameters at which the information is evaluated).
    - `free`: the names to identify, as for `jsphere.fit` (`"r_m[2],j,I[2,2]"`).
    - `kind`: `"K"` (axle torques, within `limits.max_torque`) or `"chi_dot"` (wheel speeds,
      within `limits.max_wheel_speed`). Wheel-speed inputs fix the rolling kinematics whatever
      the inertias, so inertias are identifiable through torque inputs only.
    - `limits`: a `jsphere.Limits` (defaults as for `plan`): the programmes keep the input
      limit by construction; torque rate, wheel rate (torques) and platform tilt are kept by a
      penalty on the optimisation's model (`jsphere.design.optimise`).
    - `options`: a `DesignOptions` (trials, noise levels, the search, the programmes' band,
      the rates); its fields given as keywords (`trials=2`) still work, with a
      `DeprecationWarning`.
    - `progress`: as for `jsphere.fit`.

    The baseline is random multisines (equal amplitudes, random phases, the same frequencies,
    window and saturation) of the same RMS amplitude as the design, scaled down where that breaks
    a limit the design keeps (`docs/design.md`). Returns a `DesignResult`; raises `InputError`
    for a bad value, `SolverFailure` where the model of every start fails.

    Example:

        res = jsphere.design_excitation(p, "j", 4.0, "K", options=jsphere.DesignOptions(trials=2))
    """
    o = moved_into("design_excitation", kwargs, options, DesignOptions, "options")
    no_other_keywords("design_excitation", kwargs)
    t_begin = time.perf_counter()
    prog = Progress(progress)
    spec, lim, noise, grid = _checked(params, duration, kind, limits, o)
    fp, restarts, steps, seed = _checked_run(params, free, duration, o)
    rate, capture_rate = o.rate, o.capture_rate
    pr = problem(params, fp, spec, noise, grid)
    prog.say(
        f"design: {o.trials} trial(s) of {duration:g} s ({spec.trial_kind}), {fp.size} free parameters, "
        f"{spec.size} coefficients, {restarts} restart(s) x {steps} Adam steps"
    )
    start_obj, zb, obj, phi, pen = _optimise(prog, pr, lim, fp, restarts, steps, seed, o.learning_rate)
    b = int(np.nanargmax(np.where(np.isfinite(obj), obj, -np.inf)))
    z = zb[b]
    tables = _tables(z, spec, rate)
    design_rms = rms(np.concatenate([u for _, u in tables]))
    _, _, _, ext = evaluate(jnp.asarray(z), pr, lim)
    design_limits = limit_values(pr, ext, tables, lim)
    prog.say("design: the baseline (random multisines of the same RMS amplitude within the same limits) ...")
    z_base, base_limits, phi_base, equal = _baseline(pr, lim, design_rms, design_limits, rate, seed)
    base_tables = _tables(z_base, spec, rate)
    prog.say("design: standard errors of the design and the baseline (the fit's Jacobian) ...")
    t_cap = sample_times(duration, capture_rate)
    cap = lambda zz: [table_at(p, t_cap) for p in programmes(jnp.asarray(zz), spec)]
    info = lambda zz: fit_information(params, fp, spec.trial_kind, t_cap, cap(zz), o.sigma_pos, o.sigma_rot)
    named = lambda v: {n: float(x) for n, x in zip(fp.names, v)}
    values, F_d, _, se_d, ext_d = info(z)
    _, F_b, _, se_b, ext_b = info(z_base)
    return DesignResult(
        kind=kind,
        free=list(fp.names),
        values=named(values),
        duration=float(duration),
        rate=float(rate),
        tables=tables,
        baseline_tables=base_tables,
        criterion={"design": d_criterion(fp, values, F_d), "baseline": d_criterion(fp, values, F_b)},
        criterion_model={"design": float(phi[b]), "baseline": phi_base},
        stderr_predicted=named(se_d),
        stderr_predicted_baseline=named(se_b),
        rms={"design": design_rms, "baseline": rms(np.concatenate([u for _, u in base_tables]))},
        limits=limits_report(_accurate(kind, design_limits, ext_d)),
        limits_baseline=limits_report(_accurate(kind, base_limits, ext_b)),
        limits_model=limits_report(design_limits),
        baseline_equal_rms=None if equal is None else _equal_rms(fp, values, info, equal, design_rms),
        restarts=[
            {"start": float(s), "final": float(f), "penalty": float(p), "criterion": float(c)}
            for s, f, p, c in zip(start_obj, obj, pen, phi)
        ],
        settings={
            "trials": o.trials,
            "n_freqs": o.n_freqs,
            "f_max_hz": o.f_max,
            "ramp_s": o.ramp,
            "limit": spec.limit,
            "sigma_pos_m": o.sigma_pos,
            "sigma_rot_deg": math.degrees(o.sigma_rot),
            "restarts": restarts,
            "steps": steps,
            "seed": seed,
            "learning_rate": o.learning_rate,
            "model_rate_hz": grid.rate,
            "substeps": grid.substeps,
            "capture_rate_hz": capture_rate,
        },
        elapsed_s=time.perf_counter() - t_begin,
    )


def _optimise(prog: Progress, pr, lim: Limits, fp: FreeParams, restarts: int, steps: int, seed: int, learning_rate):
    """Adam on the criterion from `restarts` random starts (vmapped; `seed`), with a progress bar
    on `prog`. Returns the starts' objectives and each start's final coefficients, objective,
    model criterion and penalty; raises `SolverFailure` where the model of every start fails."""
    spec, grid = pr.spec, pr.grid
    rng = np.random.default_rng(seed)
    z0s = np.stack([random_start(spec, rng, START_SCALE) for _ in range(restarts)])
    key = repr((spec, fp.names, grid.rate, grid.substeps, restarts))
    with prog.bar(steps + 1, "design: Adam", "step") as bar:

        def on_step(k, obj, phi, pen):
            if not np.isfinite(obj).any():
                bar.update(1, "no finite criterion yet")
                prog.step(f"design: step {k:3d}/{steps}  the model of every restart failed so far")
                return
            b = int(np.argmax(np.where(np.isfinite(obj), obj, -np.inf)))
            bar.update(1, f"log det {phi[b]:.3f}")
            prog.step(f"design: step {k:3d}/{steps}  best so far: {CRITERION} {phi[b]:.4f}, limit penalty {pen[b]:.3g}")

        with prog.compiling("design", key, "design: the criterion's gradient"):
            zb, obj, phi, pen = maximise(z0s, pr, lim, steps=0)
        start_obj = obj.copy()
        zb, obj, phi, pen = maximise(zb, pr, lim, steps=steps, learning_rate=learning_rate, on_step=on_step)
    if not np.isfinite(obj).any():
        raise SolverFailure("design: the model of every restart failed (non-finite criterion); try smaller limits.")
    return start_obj, zb, obj, phi, pen


def _checked_run(params, free, duration, o: DesignOptions):
    """The `FreeParams` and the checked `restarts`, `steps` and `seed` of a request (its learning
    rate and rates checked too); `InputError` naming a bad value."""
    restarts = whole("design_excitation", "restarts", o.restarts, 1)
    steps = whole("design_excitation", "steps", o.steps, 0)
    seed = whole("design_excitation", "seed", o.seed, 0)
    real("design_excitation", "learning_rate", o.learning_rate, strict=True)
    real("design_excitation", "rate", o.rate, strict=True, unit="Hz")
    real("design_excitation", "capture_rate", o.capture_rate, strict=True, unit="Hz")
    if o.capture_rate * duration < 4:
        raise InputError(
            "design_excitation: capture_rate x duration must give at least 4 samples; "
            f"got {o.capture_rate * duration:g}."
        )
    try:
        return FreeParams(params, free), restarts, steps, seed
    except ValueError as e:
        raise InputError(f"--free {free}: {e}") from None


def _equal_rms(fp: FreeParams, values, info: Callable, equal, design_rms: float) -> dict:
    """The report of the multisine at the design's RMS amplitude, which breaks a limit (`equal`:
    its coefficients, `limit_values` and model criterion; `info`: `fit_information` of
    coefficients): for reference."""
    _, F_e, _, se_e, _ = info(equal[0])
    return {
        "rms": design_rms,
        "criterion": d_criterion(fp, values, F_e),
        "criterion_model": equal[2],
        "stderr_predicted": {n: float(s) for n, s in zip(fp.names, se_e)},
        "limits": limits_report(equal[1]),
    }


def _tables(z, spec: Spec, rate: float) -> list:
    """The tables `(t, u)`, `rate` rows per second, of the programmes of the coefficients `z`."""
    return [table(p, rate) for p in programmes(jnp.asarray(z), spec)]


def _baseline(pr, lim: Limits, design_rms: float, design_limits, rate: float, seed: int):
    """A random multisine (`random_multisine`, seed `(seed, 1)`) of the design's RMS amplitude,
    scaled down where that breaks a limit further than the design does (each limit's allowance:
    the larger of the limit and the design's own largest value), to the largest scale that keeps
    them (bisection). Returns its coefficients, its `limit_values` and its model criterion, and
    the same of the multisine at the design's RMS amplitude where that was scaled down (else
    None)."""
    spec = pr.spec
    unit = random_multisine(spec, np.random.default_rng([seed, 1]))
    z_rms, _ = match_rms(unit, spec, design_rms, rate)
    allowance = [None if limit is None else max(limit, v) for _, v, limit in design_limits]

    def check(zz):
        tables = _tables(zz, spec, rate)
        _, phi, _, ext = evaluate(jnp.asarray(zz), pr, lim)
        entries = limit_values(pr, ext, tables, lim)
        ok = all(a is None or v <= a * (1 + 1e-9) for (_, v, _), a in zip(entries, allowance))
        return ok, entries, float(phi)

    ok, entries, phi = check(z_rms)
    if ok:
        return z_rms, entries, phi, None
    equal = (z_rms, entries, phi)
    lo, hi = 0.0, 1.0
    for _ in range(20):
        mid = 0.5 * (lo + hi)
        if check(mid * z_rms)[0]:
            lo = mid
        else:
            hi = mid
    z = lo * z_rms
    _, entries, phi = check(z)
    return z, entries, phi, equal


def _accurate(kind: str, entries, extremes):
    """`limit_values`' entries with the wheel rate (of torque inputs) and the tilt replaced by
    the accurate solver's (`extremes`: largest wheel rate, largest tilt)."""
    chi, tilt = extremes
    swap = {"tilt_rad": tilt, **({"wheel_speed_rad_s": chi} if kind == "K" else {})}
    return [(name, swap.get(name, v), limit) for name, v, limit in entries]


def table_at(prog, t: np.ndarray) -> np.ndarray:
    """A programme's values `(R, N)` at the times `t`."""
    from .inputs import _values

    return np.asarray(_values(prog, jnp.asarray(t, prog.coef.dtype)))


def _checked(params, duration, kind, limits, o: DesignOptions):
    """The `Spec`, `Limits`, `Noise` and `Grid` of a request; `InputError` naming a bad value."""
    where = "design_excitation"
    if not isinstance(params, RobotParams):
        raise InputError(f"{where}: params must be a jsphere.RobotParams; got {type(params).__name__}.")
    if kind not in KINDS:
        raise InputError(f"{where}: kind must be 'K' (torques) or 'chi_dot' (wheel speeds); got {kind!r}.")
    duration = real(where, "duration", duration, strict=True, unit="s")
    trials = whole(where, "trials", o.trials, 1)
    if limits is not None and not isinstance(limits, Limits):
        raise InputError(f"{where}: limits must be a jsphere.Limits; got {type(limits).__name__}.")
    lim = limits or Limits()
    limit = lim.max_torque if kind == "K" else lim.max_wheel_speed
    if limit is None:
        which = "max_torque (--max-torque)" if kind == "K" else "max_wheel_speed (--max-wheel-speed)"
        raise InputError(f"{where}: the programmes need a finite {which}: they are scaled to it.")
    sigma_pos = real(where, "sigma_pos", o.sigma_pos, strict=True, unit="m")
    sigma_rot = real(where, "sigma_rot", o.sigma_rot, strict=True, unit="rad")
    n_freqs = whole(where, "n_freqs", o.n_freqs, 1)
    f_max = real(where, "f_max", o.f_max, strict=True, unit="Hz")
    ramp = real(where, "ramp", o.ramp, strict=True, unit="s")
    if 2 * ramp > duration:
        raise InputError(f"{where}: ramp = {ramp:g} s needs a duration of at least {2 * ramp:g} s; got {duration:g} s.")
    model_rate = real(where, "model_rate", o.model_rate, strict=True, unit="Hz")
    substeps = whole(where, "substeps", o.substeps, 1)
    if model_rate < 2 * f_max:
        raise InputError(f"{where}: model_rate = {model_rate:g} Hz must be at least 2 f_max = {2 * f_max:g} Hz.")
    spec = Spec(
        kind=kind,
        trials=trials,
        wheels=params.n_wheels,
        n_freqs=n_freqs,
        duration=duration,
        f_max=f_max,
        ramp=ramp,
        limit=float(limit),
    )
    return spec, lim, Noise(sigma_pos, sigma_rot), Grid(model_rate, substeps)
