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
from ..identify.identifiability import exact_symmetries
from ..model.limits import Limits
from ..model.params import RobotParams
from ..model.sensors import Mounting
from .information import ONBOARD_SIGMAS, Grid, Noise, problem
from .inputs import (
    KINDS,
    Spec,
    match_rms,
    programmes,
    random_multisine,
    random_start,
    rms,
    sample_times,
    table,
    values_at,
)
from .optimise import evaluate, limit_values, limits_report, maximise
from .prediction import d_criterion, fit_information
from .result import CRITERION, DesignResult

#: the RMS of the starts' `s_i(t)` in units of the limit: well inside the limits the penalty watches
START_SCALE = 0.03


@dataclasses.dataclass(frozen=True)
class DesignOptions:
    """The options of `design_excitation` (`jsphere design`'s flags).

    - `trials`: identification trials, one programme each.
    - `sensors`: `"capture"` (motion capture: poses) or `"onboard"` (the robot's IMU and wheel
      encoders, trials from rest: `docs/onboard.md`).
    - `sigma_pos` [m], `sigma_rot` [rad]: the capture's noise levels.
    - `sigma_gyro` [rad/s], `sigma_acc` [m/s^2], `sigma_encoder` [rad]: the onboard sensors'
      (defaults: a MEMS IMU, and one count of a 4096-count encoder / sqrt(12)).
    - `imu_position` [m], `imu_rotation`: the IMU's mounting (`jsphere.Mounting`), as the fit's
      (`FitOptions`).
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
    sensors: str = "capture"
    sigma_pos: float = 1e-3
    sigma_rot: float = math.radians(0.5)
    sigma_gyro: float = ONBOARD_SIGMAS[0]
    sigma_acc: float = ONBOARD_SIGMAS[1]
    sigma_encoder: float = ONBOARD_SIGMAS[2]
    imu_position: tuple[float, float, float] = (0.0, 0.0, 0.0)
    imu_rotation: tuple[float, float, float, float] = (1.0, 0.0, 0.0, 0.0)
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
    spec, lim, o = _checked(params, duration, kind, limits, o)
    fp = _free(params, free, spec.trial_kind)
    pr = problem(params, fp, spec, _noise(o), Grid(o.model_rate, o.substeps))
    prog.say(
        f"design: {o.trials} trial(s) of {duration:g} s ({spec.trial_kind}, {o.sensors}), {fp.size} free parameters, "
        f"{spec.size} coefficients, {o.restarts} restart(s) x {o.steps} Adam steps"
    )
    start_obj, zb, obj, phi, pen = _optimise(prog, pr, lim, fp, o)
    b = int(np.nanargmax(np.where(np.isfinite(obj), obj, -np.inf)))
    # the model criterion of the search's best point, as the search computed it
    design = dataclasses.replace(_candidate(pr, lim, zb[b], o.rate), phi=float(phi[b]))
    prog.say("design: the baseline (random multisines of the same RMS amplitude within the same limits) ...")
    base, equal = _baseline(pr, lim, design, o.rate, o.seed)
    prog.say("design: standard errors of the design and the baseline (the fit's Jacobian) ...")
    result = _result(pr, o, design, base, equal, (start_obj, obj, phi, pen))
    result.elapsed_s = time.perf_counter() - t_begin
    return result


def _result(pr, o: DesignOptions, design: _Candidate, base: _Candidate, equal, search) -> DesignResult:
    """The `DesignResult` of the best start's `design` and the `base`line (`equal`: see
    `_baseline`): their predicted standard errors from the fit's Jacobian at the capture rate
    (`fit_information`), criteria and limits; `search`: the starts' objectives at the start and
    the end, their model criteria and penalties (`maximise`)."""
    fp, spec = pr.free, pr.spec
    start_obj, obj, phi, pen = search
    t_cap = sample_times(spec.duration, o.capture_rate)

    def info(z):
        tables = [values_at(p, t_cap) for p in programmes(jnp.asarray(z), spec)]
        return fit_information(pr.base, fp, spec.trial_kind, t_cap, tables, pr.noise)

    named = lambda v: {n: float(x) for n, x in zip(fp.names, v)}
    values, F_d, _, se_d, ext_d = info(design.z)
    _, F_b, _, se_b, ext_b = info(base.z)
    return DesignResult(
        kind=spec.kind,
        free=list(fp.names),
        values=named(values),
        duration=float(spec.duration),
        rate=float(o.rate),
        tables=design.tables,
        baseline_tables=base.tables,
        criterion={"design": d_criterion(fp, values, F_d), "baseline": d_criterion(fp, values, F_b)},
        criterion_model={"design": design.phi, "baseline": base.phi},
        stderr_predicted=named(se_d),
        stderr_predicted_baseline=named(se_b),
        rms={"design": design.rms, "baseline": base.rms},
        limits=limits_report(_accurate(spec.kind, design.limits, ext_d)),
        limits_baseline=limits_report(_accurate(spec.kind, base.limits, ext_b)),
        limits_model=limits_report(design.limits),
        baseline_equal_rms=None if equal is None else _equal_rms(fp, values, info, equal, design.rms),
        restarts=[
            {"start": float(s), "final": float(f), "penalty": float(p), "criterion": float(c)}
            for s, f, p, c in zip(start_obj, obj, pen, phi)
        ],
        settings=_settings(o, spec),
        elapsed_s=0.0,
    )


def _settings(o: DesignOptions, spec: Spec) -> dict:
    """The `settings` of a `DesignResult` (its JSON names): the sensors' noise levels those of
    `o.sensors`."""
    if o.sensors == "capture":
        noise = {"sigma_pos_m": o.sigma_pos, "sigma_rot_deg": math.degrees(o.sigma_rot)}
    else:
        noise = {"sigma_gyro_rad_s": o.sigma_gyro, "sigma_acc_m_s2": o.sigma_acc, "sigma_encoder_rad": o.sigma_encoder}
        noise |= {"imu_position_m": list(o.imu_position), "imu_rotation": list(o.imu_rotation)}
    return {
        "trials": o.trials,
        "n_freqs": o.n_freqs,
        "f_max_hz": o.f_max,
        "ramp_s": o.ramp,
        "limit": spec.limit,
        "sensors": o.sensors,
        **noise,
        "restarts": o.restarts,
        "steps": o.steps,
        "seed": o.seed,
        "learning_rate": o.learning_rate,
        "model_rate_hz": o.model_rate,
        "substeps": o.substeps,
        "capture_rate_hz": o.capture_rate,
    }


@dataclasses.dataclass(frozen=True)
class _Candidate:
    """Coefficients `z`, their tables at the row rate, RMS amplitude, `limit_values` and model
    criterion `phi`."""

    z: np.ndarray
    tables: list
    rms: float
    limits: list
    phi: float


def _candidate(pr, lim: Limits, z, rate: float) -> _Candidate:
    """The `_Candidate` of the coefficients `z`."""
    tables = [table(p, rate) for p in programmes(jnp.asarray(z), pr.spec)]
    _, (phi, _, ext) = evaluate(jnp.asarray(z), pr, lim)
    u = rms(np.concatenate([u for _, u in tables]))
    return _Candidate(z, tables, u, limit_values(pr, ext, tables, lim), float(phi))


def _optimise(prog: Progress, pr, lim: Limits, fp: FreeParams, o: DesignOptions):
    """Adam on the criterion from `o.restarts` random starts (vmapped; `o.seed`), with a progress
    bar on `prog`. Returns the starts' objectives and each start's final coefficients, objective,
    model criterion and penalty; raises `SolverFailure` where the model of every start fails."""
    spec, grid, steps = pr.spec, pr.grid, o.steps
    rng = np.random.default_rng(o.seed)
    z0s = np.stack([random_start(spec, rng, START_SCALE) for _ in range(o.restarts)])
    key = repr((spec, fp.names, grid.rate, grid.substeps, o.restarts, o.sensors))
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
        zb, obj, phi, pen = maximise(zb, pr, lim, steps=steps, learning_rate=o.learning_rate, on_step=on_step)
    if not np.isfinite(obj).any():
        raise SolverFailure("design: the model of every restart failed (non-finite criterion); try smaller limits.")
    return start_obj, zb, obj, phi, pen


def _equal_rms(fp: FreeParams, values, info: Callable, equal: _Candidate, design_rms: float) -> dict:
    """The report of the multisine at the design's RMS amplitude, which breaks a limit (`equal`;
    `info`: `fit_information` of coefficients): for reference."""
    _, F_e, _, se_e, _ = info(equal.z)
    return {
        "rms": design_rms,
        "criterion": d_criterion(fp, values, F_e),
        "criterion_model": equal.phi,
        "stderr_predicted": {n: float(s) for n, s in zip(fp.names, se_e)},
        "limits": limits_report(equal.limits),
    }


def _baseline(pr, lim: Limits, design: _Candidate, rate: float, seed: int):
    """A random multisine (`random_multisine`, seed `(seed, 1)`) of the design's RMS amplitude,
    scaled down where that breaks a limit further than the design does (each limit's allowance:
    the larger of the limit and the design's own largest value), to the largest scale that keeps
    them (bisection). Returns its `_Candidate`, and that of the multisine at the design's RMS
    amplitude where that was scaled down (else None)."""
    unit = random_multisine(pr.spec, np.random.default_rng([seed, 1]))
    z_rms, _ = match_rms(unit, pr.spec, design.rms, rate)
    allowance = [None if limit is None else max(limit, v) for _, v, limit in design.limits]

    def keeps(c: _Candidate) -> bool:
        return all(a is None or v <= a * (1 + 1e-9) for (_, v, _), a in zip(c.limits, allowance))

    full = _candidate(pr, lim, z_rms, rate)
    if keeps(full):
        return full, None
    lo, hi = 0.0, 1.0
    for _ in range(20):
        mid = 0.5 * (lo + hi)
        if keeps(_candidate(pr, lim, mid * z_rms, rate)):
            lo = mid
        else:
            hi = mid
    return _candidate(pr, lim, lo * z_rms, rate), full


def _accurate(kind: str, entries, extremes):
    """`limit_values`' entries with the wheel rate (of torque inputs) and the tilt replaced by
    the accurate solver's (`extremes`: largest wheel rate, largest tilt)."""
    chi, tilt = extremes
    swap = {"tilt_rad": tilt, **({"wheel_speed_rad_s": chi} if kind == "K" else {})}
    return [(name, swap.get(name, v), limit) for name, v, limit in entries]


def _free(params, free, kind: str) -> FreeParams:
    """The `FreeParams` of `free`; `InputError` for a bad name, or for names that only `m + m0`
    and `m r_m` tell apart (`exact_symmetries`' `"mass_split"`: no trial determines them)."""
    try:
        fp = FreeParams(params, free)
    except ValueError as e:
        raise InputError(f"--free {free}: {e}") from None
    if "mass_split" in exact_symmetries(fp.names, params, kind):
        raise InputError(
            f"--free {free}: only m + m0 and m r_m enter the model, so m, m0 and the platform's centre of mass cannot "
            "all be free: leave m out of --free (the design holds it at its value in --params)."
        )
    return fp


def _noise(o: DesignOptions) -> Noise:
    """The `Noise` of the sensors of `o`."""
    if o.sensors == "capture":
        return Noise(o.sigma_pos, o.sigma_rot)
    sigmas = (o.sigma_gyro, o.sigma_acc, o.sigma_encoder)
    return Noise(o.sigma_pos, o.sigma_rot, Mounting(o.imu_position, o.imu_rotation), sigmas)


#: the fields of `DesignOptions` checked as positive numbers, with their units
_POSITIVE = (
    ("sigma_pos", "m"),
    ("sigma_rot", "rad"),
    ("sigma_gyro", "rad/s"),
    ("sigma_acc", "m/s^2"),
    ("sigma_encoder", "rad"),
    ("f_max", "Hz"),
    ("ramp", "s"),
    ("model_rate", "Hz"),
    ("learning_rate", ""),
    ("rate", "Hz"),
    ("capture_rate", "Hz"),
)
#: the whole-number fields of `DesignOptions` and their least values
_WHOLE = (("trials", 1), ("n_freqs", 1), ("substeps", 1), ("restarts", 1), ("steps", 0), ("seed", 0))


def _checked(params, duration, kind, limits, o: DesignOptions):
    """The `Spec`, `Limits` and checked `DesignOptions` of a request; `InputError` naming a bad
    value."""
    where = "design_excitation"
    if not isinstance(params, RobotParams):
        raise InputError(f"{where}: params must be a jsphere.RobotParams; got {type(params).__name__}.")
    if kind not in KINDS:
        raise InputError(f"{where}: kind must be 'K' (torques) or 'chi_dot' (wheel speeds); got {kind!r}.")
    duration = real(where, "duration", duration, strict=True, unit="s")
    if limits is not None and not isinstance(limits, Limits):
        raise InputError(f"{where}: limits must be a jsphere.Limits; got {type(limits).__name__}.")
    lim = limits or Limits()
    limit = lim.max_torque if kind == "K" else lim.max_wheel_speed
    if limit is None:
        which = "max_torque (--max-torque)" if kind == "K" else "max_wheel_speed (--max-wheel-speed)"
        raise InputError(f"{where}: the programmes need a finite {which}: they are scaled to it.")
    o = dataclasses.replace(
        o,
        **{n: whole(where, n, getattr(o, n), low) for n, low in _WHOLE},
        **{n: real(where, n, getattr(o, n), strict=True, unit=u) for n, u in _POSITIVE},
    )
    if o.sensors not in ("capture", "onboard"):
        raise InputError(f"{where}: sensors must be 'capture' or 'onboard'; got {o.sensors!r}.")
    for name, n in (("imu_position", 3), ("imu_rotation", 4)):
        v = np.asarray(getattr(o, name), float).reshape(-1)
        if v.size != n or not np.all(np.isfinite(v)) or (n == 4 and np.linalg.norm(v) < 1e-6):
            raise InputError(
                f"{where}: {name} must be {n} finite numbers (a rotation not 0); got {getattr(o, name)!r}."
            )
    if 2 * o.ramp > duration:
        raise InputError(
            f"{where}: ramp = {o.ramp:g} s needs a duration of at least {2 * o.ramp:g} s; got {duration:g} s."
        )
    if o.model_rate < 2 * o.f_max:
        raise InputError(f"{where}: model_rate = {o.model_rate:g} Hz must be at least 2 f_max = {2 * o.f_max:g} Hz.")
    if o.capture_rate * duration < 4:
        raise InputError(
            f"{where}: capture_rate x duration must give at least 4 samples; got {o.capture_rate * duration:g}."
        )
    spec = Spec(
        kind=kind,
        trials=o.trials,
        wheels=params.n_wheels,
        n_freqs=o.n_freqs,
        duration=duration,
        f_max=o.f_max,
        ramp=o.ramp,
        limit=float(limit),
    )
    return spec, lim, o
