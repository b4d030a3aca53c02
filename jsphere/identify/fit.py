"""System identification: fit `RobotParams` to captured trials, or to the robot's own
sensors (`fit`; onboard-sensor trials: `jsphere.identify.onboard`).

The cost `1/2 sum r^2` of the whitened residuals of all trials (`jsphere.identify.residuals`)
is minimised over the free parameters `theta` (see `FreeParams`) and, per trial, the nuisance
parameters `nu` (`jsphere.identify.data.nuisance_names`):

    wheel speeds: nu = (Omega(0) [3], initial rotation offset [3], x0, y0 offsets [2])
    torques:      nu = (Omega(0) [3], initial rotation offset [3], x0, y0 offsets [2], omega(0) [3])

and, with `fit_time_offset=True`, one more: the offset of the trial's capture clock from its
inputs' clock (the inputs drive the model at `t + offset`, `|offset| < max_time_offset`).

The optimisation runs in stages (the checkpoint's `stage`), every start vmapped in one batch:

- `4 + k`: for long trials, multiple shooting (trials cut into segments with their own initial
  states, their continuity defects closed by a rising weight `MU_LEVELS[k]`:
  `jsphere.identify.shooting`);
- `0`: otherwise a few Adam steps (optax) from the starts (`jsphere.identify.starts`);
- `1`: Levenberg-Marquardt to convergence (`jsphere.numerics.lm`, the block-arrow solve);
- `2`: the noise levels estimated from the residuals, Levenberg-Marquardt again;
- `3`: done: the best start is kept, its covariance and verdict assembled
  (`jsphere.identify.report`, `jsphere.identify.verdict`).

After every step the optimiser's whole state is written to the checkpoint
(`jsphere.identify.checkpoint`), from which a fit resumes bit for bit.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import time
import warnings
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import optax

from .._runtime.arrays import to_jax
from .._runtime.errors import InputError, SolverFailure
from .._runtime.files import remove_stale_temporaries
from .._runtime.precision import warn_if_float32_by_default
from .._runtime.progress import Progress
from ..capture.onboard import OnboardTrial
from ..model.names import parse_name
from ..model.params import RobotParams
from ..numerics.lm import LM_KEYS, LevenbergMarquardt, LMState, iterate
from . import shooting as _shooting
from .checkpoint import (
    _checkpoint_layout,
    _config_fingerprint,
    _flat_evaluation,
    _load_checkpoint,
    _save_checkpoint,
    _unflat_evaluation,
)
from .data import FitData, pack_trials
from .free import FreeParams, _overlaps, _split_names, apply_fixes
from .mixed import MixedData, mixed_data, n_nuisance, n_res, parts_of, stacked, weighted
from .onboard import CHANNELS, START_SIGMA, UNITS, channel_sigmas, nuisance_start, pack_onboard
from .options import FIT_SOLVER, FIT_TOLERANCES, FitOptions, fit_options
from .report import FitResult, fit_result
from .residuals import _Functions, _functions
from .robust import reweigh_with_excess, robust_cost
from .shooting import CONTINUATION_RTOL, DEFECT_CLOSED, MU_LEVELS, Segments
from .starts import _NU_SCALE, nuisance_guess, start_design
from .verdict import robust_sd

__all__ = ["FIT_SOLVER", "FIT_TOLERANCES", "FitOptions", "fit", "outlier_keys"]


def fit(
    trials: Sequence,
    params: RobotParams,
    free: str | Sequence[str],
    *,
    fix: Mapping[str, Any] | None = None,
    bounds: Mapping[str, Sequence] | None = None,
    options: FitOptions | None = None,
    checkpoint: str | Path | None = None,
    restart: bool = False,
    progress: bool | None | Callable[[str], None] = None,
    **deprecated,
) -> FitResult:
    """Fit the free parameters of `params` to captured trials (position and orientation), or to
    onboard-sensor trials (the robot's own IMU and wheel encoders: `jsphere.identify.onboard`,
    docs/onboard.md).

    **Arguments:**
    - `trials`: `Trial`s (same input kind, wheel count of `params`), or `OnboardTrial`s (the
      IMU's mounting and the channels' noise levels are `FitOptions`' `imu_position`,
      `imu_rotation`, `sigma_gyro`, `sigma_acc`, `sigma_encoder`); not both kinds together.
    - `params`: start values of every parameter; `fix` sets some first (`{"m": 2.5}`).
    - `free`: names to fit, `"r_m[2],j,I"` or a list (see `FreeParams`): whole fields free all
      their independent entries (`I`: 6, kept positive definite).
    - `bounds`: `{name: (lo, hi)}` (None for an open end) by reparameterisation.
    - `options`: a `FitOptions`: the starts, shooting, iterations, noise levels, the ODE
      solver's settings, the clock offsets and the loss (each documented there).
    - `checkpoint`: a file (`.npz`) written atomically after every Adam and Levenberg-Marquardt
      step with the optimiser's whole state; a fit with the same data and configuration resumes
      from it to the same result, bit for bit, wherever it was stopped (`restart=True` ignores
      it). A checkpoint that cannot be read or belongs to another fit is ignored with a warning.
    - `progress`: `None` (default): progress bars on stderr when it is a terminal; `True`:
      bars, or one line per iteration where stderr is not a terminal; `False`: none; a
      callable gets every line instead (`jsphere._runtime.progress`).

    The fields of `FitOptions` are also taken as keywords (`fit(..., loss="l2")`), as are
    `rtol`, `atol` and `max_steps` (`FitOptions.solver`), and a `SolverOptions` as `options`:
    each is deprecated with a `DeprecationWarning` naming its spelling in `FitOptions`, and a
    keyword given wins over the same field of `options`.

    Returns a `FitResult`. Raises `InputError` (a `ValueError`) for unknown or overlapping
    names, a name both free and fixed, bounds that exclude the start, trials that do not fit
    `params`, bad options; `SolverFailure` when no start gives a finite cost (the checkpoint
    is then removed), naming where the first start fails.
    """
    t_begin = time.perf_counter()
    prog = Progress(progress)
    onboard = _onboard(trials)
    o = fit_options(options, deprecated).checked(onboard=onboard)
    _check_free_and_fixed(free, fix)
    params = apply_fixes(params, fix)
    fp_ = FreeParams(params, free, bounds, mounting=o.mounting if onboard else None)
    data = _pack(trials, params, o, onboard)
    _check_unknowns(data, fp_)
    warn_if_float32_by_default(params.R0.dtype, "fit")
    run, st = _setup(data, fp_, params, o, checkpoint, prog, t_begin)
    _resume(run, st, restart)
    run.say(
        f"fit: {run.T} trials ({data.kind}), {sum(data.lengths)} samples, {run.P} free parameters + {run.n_nu} nuisance per "
        f"trial, {run.S} start(s)"
    )
    _multiple_shooting(run, st)
    _adam(run, st)
    _single_shooting(run, st)
    keys = outlier_keys(trials)
    if onboard == "mixed":  # (the stack's order: the pose trials first)
        keys = [k for pose in (True, False) for k, t in zip(keys, trials) if isinstance(t, OnboardTrial) != pose]
    return _result(run, st, keys)


def outlier_keys(trials: Sequence) -> list[str]:
    """Each trial's key in `FitResult.outliers`: the name of the file it was read from
    (`Trial.source`), else its name; where two files share a name, their paths."""
    sources = [getattr(t, "source", None) for t in trials]
    names = [Path(s).name if s is not None else t.name for s, t in zip(sources, trials)]
    return [s if s is not None and names.count(n) > 1 else n for s, n in zip(sources, names)]


# ----------------------------------------------------------------------------- checks


def _onboard(trials: Sequence) -> bool | str:
    """Whether the trials are onboard-sensor trials (`OnboardTrial`): True, False, or `"mixed"`
    for trials of both kinds."""
    trials = list(trials)
    n = sum(isinstance(t, OnboardTrial) for t in trials)
    return "mixed" if 0 < n < len(trials) else bool(trials) and n == len(trials)


def _pack(trials: Sequence, params: RobotParams, o: FitOptions, onboard: bool | str):
    """The trials packed: `FitData` (captured poses), `OnboardData` (onboard sensors, which
    need neither a clock offset, their sensors and inputs sharing one clock, nor multiple
    shooting, their trials starting at rest) or, for trials of both kinds, `MixedData`."""
    if not onboard:
        return pack_trials(trials, params, max_offset=o.max_offset)
    if onboard == "mixed":
        pose = [t for t in trials if not isinstance(t, OnboardTrial)]
        onboard_data = _pack([t for t in trials if isinstance(t, OnboardTrial)], params, o, True)
        return mixed_data(pack_trials(pose, params), onboard_data)
    if o.fit_time_offset:
        raise InputError(
            "fit: fit_time_offset (--fit-time-offset) is for motion-capture trials alone; an onboard trial's sensors and "
            "inputs share one clock."
        )
    if o.shooting == "multiple":
        raise InputError(
            "fit: onboard-sensor trials are fitted by single shooting from rest; leave shooting at 'auto'."
        )
    if o.zero_order_hold:
        trials = [t if t.hold else dataclasses.replace(t, hold=True) for t in trials]
    return pack_onboard(trials, params, o.mounting, o.start_at_rest)


def _check_free_and_fixed(free, fix) -> None:
    if fix:
        free_list = _split_names(free) if isinstance(free, str) else list(free)
        for fname in fix:
            parse_name(fname)
            for fr in free_list:
                if _overlaps(fname, fr.strip()):
                    raise InputError(f"{fname!r} is both free ({fr!r}) and fixed; choose one.")


def _check_unknowns(data: FitData, free: FreeParams) -> None:
    P, T, n_nu = free.size, len(data.names), n_nuisance(data)
    n_res = data.n_measured
    if n_res <= P + T * n_nu:
        raise InputError(
            f"fit: the trials hold {n_res} measured values but the fit has {P + T * n_nu} unknowns ({P} free parameters and "
            f"{n_nu} nuisance parameters per trial); give longer trials or fewer free parameters."
        )


def _use_multiple(shooting: str, data: FitData, segment: float) -> bool:
    """`"auto"`: multiple shooting when a trial lasts more than two segments (never for onboard
    trials, which start at rest)."""
    if data.measure != "pose":
        return False
    return shooting == "multiple" or (shooting == "auto" and float(np.max(data.t1)) > 2.0 * segment)


# ----------------------------------------------------------------------------- the run


@dataclasses.dataclass(frozen=True)
class _Shooting:
    """Multiple shooting's fixed inputs: the segments, each segment's position in its trial, the
    segments' arrays and the defect scale."""

    seg: Segments
    segment: float
    position: np.ndarray
    arrays: dict[str, jax.Array]
    seg_arrays: dict[str, jax.Array]
    scale: jax.Array

    @property
    def G(self) -> int:
        return self.seg.n_segments

    @property
    def Gmax(self) -> int:
        return self.seg.slot.shape[1]


@dataclasses.dataclass(frozen=True)
class _Run:
    """What a fit works on, fixed while it runs."""

    data: FitData
    free: FreeParams
    base: RobotParams
    options: FitOptions
    fns: _Functions
    arrays: dict[str, jax.Array]
    shooting: _Shooting | None
    adam_scale: dict[str, jax.Array]  # Adam works in these units: z = scale * w
    adam: optax.GradientTransformation
    adam_shapes: tuple[tuple[int, ...], ...]
    checkpoint: Path | None
    fingerprint: str
    progress: Progress
    t_begin: float

    def say(self, line: str) -> None:
        self.progress.say(line)

    @property
    def S(self) -> int:
        return self.options.n_starts

    @property
    def P(self) -> int:
        return self.free.size

    @property
    def T(self) -> int:
        return len(self.data.names)

    @property
    def n_nu(self) -> int:
        return n_nuisance(self.data)


@dataclasses.dataclass
class _State:
    """What the optimiser carries from one step to the next: the checkpoint's contents.

    `stage` (see the module docstring); `sig`: the noise levels; `theta (S, P)`; `nu (S, T, n)`;
    `nu_ms (S, G, n)`: per segment in multiple shooting; `adam`: Adam's position and optimiser
    state, `adam_k` its steps, `adam_best`: (cost, theta, nu) of each start's best point;
    `lm`: Levenberg-Marquardt's state within a stage, `it`: the steps of the last stage;
    `last`: the poses, solver status and data of the last evaluation (for the failure message,
    not saved)."""

    stage: int
    sig: np.ndarray
    theta: np.ndarray
    nu: np.ndarray
    nu_ms: np.ndarray | None
    adam: tuple
    adam_k: int = 0
    adam_best: tuple | None = None
    total_it: int = 0
    it: int = 0
    stage_converged: bool = False
    max_defect: float = math.nan
    lm: LMState | None = None
    last: dict[str, Any] = dataclasses.field(default_factory=dict)


def adam_start(opt: optax.GradientTransformation, w):
    """`opt.init(w)` for the fit's Adam (`scale_by_adam`, then a scale), made on the host: its
    state at the start is zeros (the step count and both moments), and `opt.init` would compile
    one small program per shape for them."""
    return jax.tree_util.tree_map(lambda s: to_jax(np.zeros(s.shape, s.dtype)), jax.eval_shape(opt.init, w))


def _setup(
    data: FitData,
    free: FreeParams,
    params: RobotParams,
    o: FitOptions,
    checkpoint,
    progress: Progress,
    t_begin,
) -> tuple[_Run, _State]:
    """The run and its first state: the starts (the only random numbers of a fit, drawn from
    `seed`, part of the fingerprint), the segments of multiple shooting, Adam."""
    kind, S, P, T = data.kind, o.n_starts, free.size, len(data.names)
    multiple = _use_multiple(o.shooting, data, o.segment)
    seg = _shooting.segment_trials(data, o.segment) if multiple else None
    fns = _functions(
        free, kind, o.rtol, o.atol, o.max_steps, o.ode_solver, o.max_offset, split=True, measure=data.measure
    )
    rng = np.random.default_rng(o.seed)
    theta = start_design(free, S, o.spread, rng)
    sig, nu = _starts(data, params, o)
    nu = np.repeat(nu[None], S, 0)
    ms, nu_ms = None, None
    if multiple:
        position = np.concatenate([np.arange(len(c) - 1) for c in seg.boundaries])
        offset = o.max_offset > 0
        dscale = to_jax(_shooting.defect_scale(kind, sig, float(params.R0), o.segment, offset))
        ms = _Shooting(seg, o.segment, position, seg.data.arrays(), seg.arrays(), dscale)
        nu_ms = nuisance_guess(seg.data, params, time_offset=False)
        if offset:  # every segment starts at its trial's estimate
            nu_ms = np.concatenate([nu_ms, nu[0, seg.trial, -1:]], axis=1)
        nu_ms = np.repeat(nu_ms[None], S, 0)
    nu_scale = stacked(
        data,
        lambda d: np.broadcast_to([_NU_SCALE[n.split("_")[0]] for n in d.nuisance], (len(d.names), len(d.nuisance))),
        1.0,
    )
    n_nu = nu_scale.shape[-1]
    scale_np = {"theta": np.broadcast_to(free.theta_scales(), (S, P)), "nu": np.broadcast_to(nu_scale, (S, T, n_nu))}
    scale = jax.tree_util.tree_map(lambda s: to_jax(s.copy()), scale_np)
    opt = optax.chain(optax.scale_by_adam(), optax.scale(-o.adam_lr))
    w = jax.tree_util.tree_map(lambda a, s: to_jax(a / s), {"theta": theta, "nu": nu}, scale_np)
    adam = (w, adam_start(opt, w))
    run = _Run(
        data=data,
        free=free,
        base=params,
        options=o,
        fns=fns,
        arrays=data.arrays(),
        shooting=ms,
        adam_scale=scale,
        adam=opt,
        adam_shapes=tuple(np.shape(a) for a in jax.tree_util.tree_leaves(adam)),
        checkpoint=Path(checkpoint) if checkpoint is not None else None,
        fingerprint=_config_fingerprint(data, free, o.config(sig, multiple)),
        progress=progress,
        t_begin=t_begin,
    )
    stage = 4 if multiple else (0 if o.adam_steps > 0 else 1)
    return run, _State(stage=stage, sig=sig, theta=theta, nu=nu, nu_ms=nu_ms, adam=adam)


def _starts(data, params: RobotParams, o: FitOptions) -> tuple[np.ndarray, np.ndarray]:
    """The noise levels a fit starts from (`sigma_pos, sigma_rot` and/or each onboard
    channel's) and its nuisance values `(T, n)` (`nuisance_guess`, `nuisance_start`)."""
    if isinstance(data, MixedData):
        parts = [_starts(d, params, o) for d in data.parts]
        return np.concatenate([s for s, _ in parts]), stacked(data, lambda d: parts[data.parts.index(d)][1], 0.0)
    if data.measure == "pose":
        return np.array([o.sigma_pos or 1e-3, o.sigma_rot or math.radians(0.5)]), nuisance_guess(data, params)
    return np.array([s or s0 for s, s0 in zip(o.sigmas_onboard, START_SIGMA)]), nuisance_start(data, params)


# ----------------------------------------------------------------------------- the checkpoint


def _layout(run: _Run, stage: int) -> dict[str, tuple]:
    """The arrays of a checkpoint at `stage` and their shapes (`_checkpoint_layout`)."""
    S, P, T, n_nu = run.S, run.P, run.T, run.n_nu
    if run.shooting is not None and stage >= 4:
        G, N = run.shooting.G, run.shooting.Gmax * n_nu
        ev = {
            "Hgg": (S, P, P),
            "Hgn": (S, T, P, N),
            "Hnn": (S, T, N, N),
            "gg": (S, P),
            "gn": (S, T, N),
            "defect": (S, G, n_nu),
        }
        nu_shape = (G, n_nu)
    else:
        ev = {"res": (S, T, n_res(run.data)), "J": (S, T, n_res(run.data), P + n_nu)}
        parts = parts_of(run.data)
        for part, key in zip(parts, ("pose", "onboard")):
            ev |= {f"{key}_{c}": (S, len(part.names), *shape) for c, shape in zip("xyq", part.aux_shapes())}
        nu_shape = (T, n_nu)
    return _checkpoint_layout(stage, S, P, nu_shape, run.adam_shapes, ev, len(run.data.channels))


def _resume(run: _Run, st: _State, restart: bool) -> None:
    """Continue from the checkpoint where there is one of this fit (unless `restart`)."""
    path = run.checkpoint
    if path is None:
        return
    remove_stale_temporaries(path)
    saved, why = (None, None) if restart else _load_checkpoint(path, run.fingerprint, functools.partial(_layout, run))
    if why is not None:
        warnings.warn(f"fit: the checkpoint {path} {why}; it is ignored and the fit starts afresh.", stacklevel=3)
    if saved is None:
        return
    st.stage, st.total_it = int(saved["stage"]), int(saved["total_it"])
    st.sig, st.theta, st.max_defect = saved["sig"], saved["theta"], float(saved["max_defect"])
    if st.stage >= 4:
        st.nu_ms = saved["nu"]
    else:
        st.nu = saved["nu"]
    if st.stage == 0:
        st.adam_k = int(saved["adam_k"])
        leaves, treedef = jax.tree_util.tree_flatten(st.adam)
        st.adam = jax.tree_util.tree_unflatten(
            treedef, [jnp.asarray(saved[f"adam_{i}"], a.dtype) for i, a in enumerate(leaves)]
        )
        st.adam_best = (saved["adam_best_cost"], saved["adam_best_theta"], saved["adam_best_nu"])
        run.say(f"fit: resuming from {path} (Adam step {st.adam_k})")
    elif st.stage == 3:
        st.it, st.stage_converged = int(saved["it"]), bool(saved["stage_converged"])
        run.say(f"fit: resuming from {path} (stage 3: finished)")
    else:
        current = _unflat_evaluation({k[4:]: v for k, v in saved.items() if k.startswith("out_")})
        arrays = {k: saved[k] for k in LM_KEYS} | {"converged": saved["converged"].astype(bool)}
        st.lm = LMState(**arrays, it=int(saved["it"]), current=current)
        run.say(f"fit: resuming from {path} (stage {st.stage}, iteration {st.lm.it})")


def _save(run: _Run, st: _State) -> None:
    if run.checkpoint is None:
        return
    out = {
        "stage": st.stage,
        "total_it": st.total_it,
        "sig": st.sig,
        "theta": st.theta,
        "nu": st.nu_ms if st.stage >= 4 else st.nu,
    }
    out["max_defect"] = st.max_defect
    if st.stage == 0:
        out |= {
            "adam_k": st.adam_k,
            "adam_best_cost": st.adam_best[0],
            "adam_best_theta": st.adam_best[1],
            "adam_best_nu": st.adam_best[2],
        }
        out |= {f"adam_{i}": a for i, a in enumerate(jax.tree_util.tree_leaves(st.adam))}
    elif st.stage == 3:
        out |= {"it": st.it, "stage_converged": st.stage_converged}
    else:
        out |= {"it": st.lm.it, **st.lm.arrays(), **{f"out_{k}": v for k, v in _flat_evaluation(st.lm.current).items()}}
    _save_checkpoint(run.checkpoint, run.fingerprint, {k: np.asarray(v) for k, v in out.items()})


# ----------------------------------------------------------------------------- evaluations and steps


def _program(run: _Run, shooting: str) -> str:
    """What identifies the compiled residuals of a fit (for `Progress.compiling`)."""
    o, d = run.options, run.data
    segments = () if run.shooting is None or shooting == "single" else run.shooting.seg.slot.shape
    shapes = [p.ts.shape for p in d.parts] if isinstance(d, MixedData) else d.ts.shape
    return repr((shooting, d.kind, shapes, run.free.names, o.n_starts, o.rtol, o.atol, o.max_steps, segments))


def _evaluate_single(run: _Run, st: _State, th, n):
    """Cost `(S,)` (inf for a failed start), residuals, Jacobian and poses of single shooting."""
    with run.progress.compiling("fit", _program(run, "single"), "fit: single shooting"):
        res, ok, J, pose = run.fns.run("jacobian", run.base, to_jax(th), to_jax(n), run.arrays, to_jax(st.sig))
        res, ok = np.asarray(res), np.asarray(ok)
    cost = np.where(ok.all(1), _cost(run.data, run.options.stage_loss(st.stage), res), np.inf)
    st.last.update(pose=pose, ok=ok, data=run.data)
    return cost, {"res": res, "J": J, "pose": pose}


def _cost(data, loss: str, res: np.ndarray) -> np.ndarray:
    """The cost of every start `(S,)`: half the sum of squares, or the robust cost of the pose
    trials' residuals (an onboard trial's are always least squares)."""
    if loss == "l2" or data.measure != "pose" and not isinstance(data, MixedData):
        return 0.5 * (res * res).sum((1, 2))
    if isinstance(data, MixedData):
        Tp, Kp = data.n_pose, data.sizes[0]
        rest = 0.5 * (res[:, Tp:] ** 2).sum((1, 2))
        return np.asarray(robust_cost(loss, to_jax(res[:, :Tp, :Kp]))) + rest
    return np.asarray(robust_cost(loss, to_jax(res)))


def _weighted(run: _Run, loss: str, res, J):
    """The residuals and Jacobian as Levenberg-Marquardt sees them: reweighted for a robust
    `loss` (`jsphere.identify.robust.reweigh`; the pose trials' only), as they are for `l2`. An
    evaluation holds them unweighted, so that the checkpoint does too and the weights follow
    from what it holds."""
    return weighted(run.data, loss, res, J)


def _solve_single(run: _Run, st: _State, out, lam):
    res, J = _weighted(run, run.options.stage_loss(st.stage), out["res"], out["J"])
    dg, dn, pred = run.fns.run("step", to_jax(res), J, to_jax(lam))
    return (np.asarray(dg), np.asarray(dn)), np.asarray(pred)


def _evaluate_multiple(run: _Run, st: _State, mu: float, th, n):
    """Cost `(S,)` (inf for a failed start), normal-equation blocks and defects of multiple
    shooting at defect weight `mu`."""
    ms = run.shooting
    with run.progress.compiling("fit", _program(run, "multiple"), "fit: multiple shooting"):
        args = (run.base, to_jax(th), to_jax(n), ms.arrays, to_jax(st.sig))
        res, ok, J, pose, e, Je = run.fns.run("segments", *args)
        excess, loss = 0.0, run.options.stage_loss(st.stage)
        if loss != "l2":  # the weighted squares replaced by the robust cost
            res, J, excess = reweigh_with_excess(loss, res, J)
            excess = np.asarray(excess)
        # (`mu` an array: one program for every level)
        blocks, cost, dfc = run.fns.run("assemble", res, J, e, Je, to_jax(n), to_jax(mu), ms.seg_arrays, ms.scale)
        ok = np.asarray(ok)
    cost = np.where(ok.all(1), np.asarray(cost) + excess, np.inf)
    st.last.update(pose=pose, ok=ok, data=ms.seg.data)
    return cost, {"blocks": blocks, "defect": np.asarray(dfc)}


def _solve_multiple(run: _Run, out, lam):
    ms = run.shooting
    dg, dn, pred = run.fns.run("solve", out["blocks"], to_jax(lam))
    dn = np.asarray(dn).reshape(run.S, run.T, ms.Gmax, run.n_nu)[:, ms.seg.trial, ms.position]
    return (np.asarray(dg), dn), np.asarray(pred)


def _first_failure(data, pose, ok) -> str:
    """Where the first start fails: its first non-finite residual (trial, time, channel), or
    the first trial whose solve did not finish."""
    if isinstance(data, MixedData):
        ok = np.asarray(ok)
        for part, aux, okk in zip(data.parts, pose, data.split(ok, axis=1)):
            where = _first_failure(part, aux, okk)
            if not where.startswith("the first start failed"):
                return where
        return "the first start failed, but no trial shows where"
    channels = ("x", "y", "orientation") if data.measure == "pose" else CHANNELS
    arrays = [np.asarray(a[0]) for a in pose]
    for i in range(data.ts.shape[0]):
        m = data.lengths[i]
        bad = np.stack([~np.isfinite(a[i, :m]).reshape(m, -1).all(-1) for a in arrays])
        hit = np.flatnonzero(bad.any(0))
        if hit.size:
            k = int(hit[0])
            channel = channels[int(np.argmax(bad[:, k]))]
            t = data.ts[i, k] + data.t_start[i]
            return f"the first non-finite residual is in trial {data.names[i]!r} at t = {t:.6g} s (sample {k}), channel {channel}"
    failed = np.flatnonzero(~np.asarray(ok)[0])
    if failed.size:
        return f"the ODE solve of trial {data.names[int(failed[0])]!r} did not reach its end (max_steps)"
    return "the first start failed, but no trial shows where"


def _fail(run: _Run, st: _State, where: str):
    """Every start has failed: nothing later can recover, so stop here and say where."""
    if run.checkpoint is not None:
        run.checkpoint.unlink(missing_ok=True)
    raise SolverFailure(
        f"fit: every start failed in {where} (no start gives a finite cost); {_first_failure(st.last['data'], st.last['pose'], st.last['ok'])}, "
        "for the first start. Try: check that trial's inputs and capture near that time, start values "
        "nearer the robot (--params, --fix), bounds on the free parameters (--bound), or, in Python, a larger max_steps or a "
        "looser rtol."
    )


# ----------------------------------------------------------------------------- the stages


#: the longest Levenberg-Marquardt step, in the free parameters' scaled units (`theta_scales`:
#: a factor e^2 for a log-transformed value)
STEP_MAX = 2.0


def _lm_stage(run: _Run, st: _State, evaluate, solve, th, n, label: str, *, rel_done: float, max_rejected: int = 8):
    """Levenberg-Marquardt on every start from `(th, n)`, or from the state loaded, until the
    best start has converged or `max_iter`; saves after every step. Returns the final point,
    its cost and evaluation."""
    if st.lm is None:
        cost, out = evaluate(th, n)
        if not np.isfinite(cost).any():
            _fail(run, st, f"Levenberg-Marquardt {label}")
    o, scales = run.options, run.free.theta_scales()
    # accepted within the ODE solver's noise floor `noise`; a step longer than `STEP_MAX` is
    # shortened: a start far off can otherwise jump to parameters whose motion takes the ODE
    # solver `max_steps` steps, and the whole vmapped batch waits for it
    lm = LevenbergMarquardt(
        rel_done=rel_done,
        gtol=o.gtol,
        noise=o.noise,
        max_stalled=3,
        max_rejected=max_rejected,
        max_step=STEP_MAX,
        step_scale=(scales, np.inf),
    )
    if st.lm is None:
        st.lm = lm.init(cost, out)
        _save(run, st)
    with run.progress.bar(o.max_iter, f"fit: LM {label}", "it", initial=st.lm.it) as bar:
        for (th_next, n), st.lm, (th_new, _) in iterate(lm, lambda x: evaluate(*x), solve, (th, n), st.lm, o.max_iter):
            length = float(np.max(np.abs(np.asarray(th_new) - th) / scales, initial=0.0))
            th, n = np.asarray(th_next), np.asarray(n)
            st.total_it += 1
            st.theta = th
            if st.stage >= 4:
                st.nu_ms = n
            else:
                st.nu = n
            _save(run, st)
            # (NumPy's functions would call the JAX arrays' methods: one small program each)
            costs, lam, rejected = (np.asarray(a) for a in (st.lm.cost, st.lm.lam, st.lm.rejected))
            b = int(np.argmin(costs))
            bar.update(1, f"cost {np.min(costs):.4e}")
            run.progress.step(
                f"fit: LM {label} it {st.lm.it:3d}  cost {np.min(costs):.6e}  lambda {lam[b]:.1e}  "
                f"step {length:.2e}  accepted {int(np.sum(rejected == 0))}/{run.S}  ({time.perf_counter() - run.t_begin:.1f} s)"
            )
        bar.done()
    st.it = st.lm.it
    return th, n, st.lm.cost, st.lm.current


def _multiple_shooting(run: _Run, st: _State) -> None:
    """Stages `4 + k`: the defect weight rises through `MU_LEVELS` until the defects close."""
    ms = run.shooting
    while st.stage >= 4:
        level = st.stage - 4
        mu = MU_LEVELS[level]
        if st.lm is None:
            run.say(f"fit: multiple shooting: {ms.G} segments of about {ms.segment:g} s, defect weight {mu:g}")
        evaluate, solve = functools.partial(_evaluate_multiple, run, st, mu), functools.partial(_solve_multiple, run)
        rel_done = max(run.options.ftol, CONTINUATION_RTOL)
        st.theta, st.nu_ms, cost, out = _lm_stage(
            run, st, evaluate, solve, st.theta, st.nu_ms, f"shooting {mu:g}", rel_done=rel_done, max_rejected=3
        )
        b = int(np.argmin(cost))
        st.max_defect = float(np.max(np.abs(np.asarray(out["defect"])[b]))) if ms.G > run.T else 0.0
        st.lm = None
        if st.max_defect <= DEFECT_CLOSED or level + 1 == len(MU_LEVELS):
            run.say(
                f"fit: multiple shooting: largest defect {st.max_defect:.3g} noise levels; single shooting from here"
            )
            st.nu = st.nu_ms[:, ms.seg.first]  # each trial's first segment's
            st.stage = 1
        else:
            run.say(f"fit: multiple shooting: largest defect {st.max_defect:.3g} noise levels; raising the weight")
            st.stage += 1


def _adam(run: _Run, st: _State) -> None:
    """Stage 0: Adam warm-start steps of single shooting, in per-coordinate scaled units; the
    best point of each start is kept."""
    if st.stage != 0:
        return
    with run.progress.bar(run.options.adam_steps, "fit: Adam", "step", initial=st.adam_k) as bar:
        _adam_steps(run, st, *st.adam, bar)
    if st.adam_best is not None:
        st.theta, st.nu = st.adam_best[1], st.adam_best[2]
    st.stage = 1


def _adam_steps(run: _Run, st: _State, w, ost, bar) -> None:
    """The Adam steps left (from `st.adam_k`), each saved; `bar` counts them."""
    P, scale = run.P, run.adam_scale
    for k in range(st.adam_k, run.options.adam_steps):
        zz = jax.tree_util.tree_map(lambda a, s: a * s, w, scale)
        cost_k, out_k = _evaluate_single(run, st, zz["theta"], zz["nu"])
        res_k, J_k = _weighted(run, run.options.stage_loss(st.stage), out_k["res"], out_k["J"])
        if st.adam_best is None:
            st.adam_best = (cost_k.copy(), np.asarray(zz["theta"]).copy(), np.asarray(zz["nu"]).copy())
        else:
            better = cost_k < st.adam_best[0]
            st.adam_best = (
                np.where(better, cost_k, st.adam_best[0]),
                np.where(better[:, None], zz["theta"], st.adam_best[1]),
                np.where(better[:, None, None], zz["nu"], st.adam_best[2]),
            )
        if not np.isfinite(st.adam_best[0]).any():
            _fail(run, st, "the Adam warm start")
        gg = jnp.einsum("stkp,stk->sp", J_k[..., :P], res_k)
        gn = jnp.einsum("stkn,stk->stn", J_k[..., P:], res_k)
        g = {"theta": gg * scale["theta"], "nu": gn * scale["nu"]}
        g = jax.tree_util.tree_map(lambda a: jnp.nan_to_num(a), g)
        upd, ost = run.adam.update(g, ost)
        w = optax.apply_updates(w, upd)
        st.adam, st.adam_k = (w, ost), k + 1
        _save(run, st)
        bar.update(1, f"cost {np.min(cost_k):.4e}")
        run.progress.step(
            f"fit: adam {k + 1:3d}/{run.options.adam_steps}  cost {np.min(cost_k):.6e}  ({time.perf_counter() - run.t_begin:.1f} s)"
        )


def _single_shooting(run: _Run, st: _State) -> None:
    """Stages 1 and 2: Levenberg-Marquardt, the noise levels estimated in between (unless given)."""
    while st.stage in (1, 2):
        evaluate, solve = functools.partial(_evaluate_single, run, st), functools.partial(_solve_single, run, st)
        st.theta, st.nu, cost, out = _lm_stage(
            run, st, evaluate, solve, st.theta, st.nu, f"stage {st.stage}", rel_done=run.options.ftol
        )
        cost = np.asarray(cost)
        st.stage_converged = bool(np.asarray(st.lm.converged)[int(np.argmin(cost))])
        st.lm = None
        o = run.options
        parts = parts_of(run.data)
        wanted = [o.estimate_sigma_onboard if d.measure != "pose" else o.estimate_sigma for d in parts]
        if st.stage == 1 and any(wanted):
            res_b = np.asarray(out["res"])[int(np.argmin(cost))]
            est = _estimate_sigmas(run, res_b, st.sig)
            # residuals of exactly 0 (noise-free data) give no estimate: keep the level used
            usable = np.isfinite(est) & (est > 0)
            st.sig = np.where(usable, est, st.sig)
            st.stage = 2
            kept = "" if usable.all() else " (residuals of 0 give no estimate: the level used is kept)"
            levels, at = [], 0
            for d in parts:
                sig = st.sig[at : at + len(d.channels)]
                at += len(d.channels)
                if d.measure != "pose":
                    levels += [f"{c} {s:.4g} {u}" for c, s, u in zip(CHANNELS, sig, UNITS)]
                else:
                    levels += [f"sigma_pos {sig[0] * 1e3:.4f} mm, sigma_rot {math.degrees(sig[1]):.4f} deg"]
            run.say(f"fit: noise estimated: {', '.join(levels)}{kept}; refitting")
        else:
            st.stage = 3
            _save(run, st)


def _estimate_sigmas(run: _Run, res_b: np.ndarray, sig: np.ndarray) -> np.ndarray:
    """Every part's noise levels from the whitened residuals `res_b (T, K)` of the best start
    (the levels given are kept). The unknowns a part's estimate is corrected for: its trials'
    nuisance values and its share of the free parameters (by its measured values)."""
    o, data = run.options, run.data
    parts = parts_of(data)
    chunks = data.split(res_b) if isinstance(data, MixedData) else (res_b,)
    out, at = [], 0
    for k, (d, r) in enumerate(zip(parts, chunks)):
        n_par = run.P * d.n_measured / data.n_measured + len(d.names) * len(d.nuisance)
        s = sig[at : at + len(d.channels)]
        r = data.unpad(r, k) if isinstance(data, MixedData) else r
        if d.measure != "pose":
            est = np.where([v is None for v in o.sigmas_onboard], channel_sigmas(r, d, s, n_par), s)
        else:
            est = _estimate_sigma(r, d, s, n_par, o.loss) if o.estimate_sigma else s
        out.append(est)
        at += len(d.channels)
    return np.concatenate(out)


def _estimate_sigma(res_b, data: FitData, sig, n_par: int, loss: str = "l2") -> np.ndarray:
    """Noise levels from the whitened residuals of the best start (dof-corrected; in numpy, whose
    sums do not depend on where the residuals were computed). For a robust loss, the RMS of the
    values within 5 robust sd of 0 (`jsphere.identify.verdict.robust_sd`, as the capture's noise
    floor): ghost frames and swaps would otherwise inflate the levels, and the loss's scale."""
    res_b = np.asarray(res_b)
    M = data.ts.shape[1]
    pos = res_b[:, : 2 * M] * sig[0]
    rot = res_b[:, 2 * M :] * sig[1]
    n_pos, n_rot = 2 * data.wpos.sum(), 3 * data.wrot.sum()
    frac = 1.0 - n_par / (n_pos + n_rot)
    if loss != "l2":
        held_pos = np.concatenate([data.wpos, data.wpos], axis=1) > 0
        held_rot = np.repeat(data.wrot, 3, axis=1) > 0
        return np.array([robust_sd(pos[held_pos]), robust_sd(rot[held_rot])]) / math.sqrt(frac)
    return np.sqrt(np.array([(pos * pos).sum() / (n_pos * frac), (rot * rot).sum() / (n_rot * frac)]))


def _result(run: _Run, st: _State, keys: Sequence[str]) -> FitResult:
    """The `FitResult` of the best start, evaluated once more at the final points."""
    cost, out = _evaluate_single(run, st, st.theta, st.nu)
    return fit_result(run, st, cost, out, keys)
