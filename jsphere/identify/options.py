"""The options of a fit in one place: `FitOptions`, its defaults and their validation."""

from __future__ import annotations

import dataclasses
import warnings
from pathlib import Path
from typing import Any

import diffrax as dfx
import equinox as eqx
import numpy as np

from .._runtime.checks import real, whole
from .._runtime.errors import InputError
from .._runtime.files import atomic_write_json
from .._runtime.moved_keywords import moved_into, no_other_keywords
from ..solve.options import SolverOptions, default_solver, solver_options, unused
from .checkpoint import _CHECKPOINT_FORMAT
from .robust import DEFAULT_LOSS, REDESCENDING, WARM_LOSS, check_loss
from .shooting import MU_LEVELS

#: fit's solver settings where `FitOptions.solver` sets none: positions within ~2 um of a 1e-11
#: solution over a few seconds of exciting input
FIT_TOLERANCES = {"rtol": 1e-6, "atol": 1e-8}
#: fit's Runge-Kutta method where `FitOptions.solver` sets none: at `FIT_TOLERANCES` a compiled
#: fit with `Tsit5` takes 0.28x the time of one with `simulate`'s `Dopri8`, with the same
#: answers (docs/decisions/the-fit-integrates-with-tsit5.md)
FIT_SOLVER = dfx.Tsit5()
#: fit's solver settings for onboard-sensor trials where `FitOptions.solver` sets none: their
#: encoders resolve the wheels to ~1e-4 rad, and at `FIT_TOLERANCES` the solver's error moves
#: the estimates by standard errors; `simulate`'s `Dopri8` at these keeps it well under them
#: (`docs/onboard.md`, "Tolerance")
ONBOARD_TOLERANCES = {"rtol": 1e-8, "atol": 1e-10}


@dataclasses.dataclass(frozen=True)
class FitOptions:
    """How `fit` optimises (`fit(trials, params, free, options=FitOptions(loss="l2", n_starts=8))`).

    Each field below is one option, with its default. `fit.json` records them
    (`FitResult.options`, `to_json`/`from_json`), so that a fit can be replayed.
    """

    n_starts: int = 2
    """Starts vmapped together: the first at `params`, the others a Latin hypercube over the
    bounds, or over `+- 2 spread` (relative, for positive values) about `params`
    (`jsphere.identify.starts.start_design`). The best start is kept."""
    spread: float = 0.2
    """The relative spread of the starts about `params` (see `n_starts`)."""
    seed: int = 0
    """The seed of the start design (the only random numbers of a fit)."""
    shooting: str = "auto"
    """`"multiple"` cuts each trial into segments of about `segment` seconds with their own
    initial states, started from the capture, and closes the continuity defects between them by
    raising their weight (`MU_LEVELS`); single shooting then polishes the result. `"single"`
    simulates each trial whole from its start. `"auto"`: multiple shooting when a trial is
    longer than two segments."""
    segment: float = 2.0
    """The segment length of multiple shooting [s] (>= 0.05)."""
    adam_steps: int = 3
    """optax Adam warm-start steps of single shooting (per-coordinate scaled units); multiple
    shooting needs none (its segments start from the capture)."""
    adam_lr: float = 0.1
    """The learning rate of the Adam steps."""
    max_iter: int = 40
    """Levenberg-Marquardt iterations per stage. A stage ends when the predicted decrease of
    the cost is below `gtol`, when an accepted step changes the cost by less than `ftol`
    (relative), after 3 accepted steps that do not lower the best cost by `gtol`, or after 8
    rejected steps in a row."""
    ftol: float = 1e-10
    """The relative change of the cost below which an accepted step ends a stage."""
    gtol: float = 1e-2
    """The predicted decrease of the cost that ends a stage, in units of chi^2/2: 0.01 is a step
    of ~0.14 standard errors along the worst direction."""
    noise: float = 1.0
    """The ODE solver's noise floor in the cost: the adaptive solver makes the cost piecewise
    smooth with jumps (~0.1 at `rtol=1e-6` for a few thousand samples) while its Jacobian stays
    accurate, so steps predicted to gain less than `noise` are accepted unless the cost rises by
    more than `noise`."""
    sigma_pos: float | None = None
    """The position noise level [m]. If not given (nor `sigma_rot`) the levels start at 1 mm and
    0.5 deg, are estimated from the residuals after the first stage, and the fit is finished
    with the estimates."""
    sigma_rot: float | None = None
    """The orientation noise level [rad] (see `sigma_pos`)."""
    solver: SolverOptions | None = None
    """A `SolverOptions`: its `rtol`, `atol`, `max_steps` and `solver` are used, with fit's own
    defaults where it leaves them at `SolverOptions`' defaults (`FIT_TOLERANCES`: 1e-6, 1e-8,
    16384 steps; the solver `diffrax.Tsit5()`, `FIT_SOLVER`). The defaults keep the simulated
    positions within ~2 um of a 1e-11 solution over a few seconds of exciting input, far below
    capture noise (100 Hz tables: the cubic command has a kink in its rate at every sample,
    which makes tighter tolerances costly: `docs/performance.md`). `throw` and `batch_steps`
    are fit's own: a failed solve is a start of infinite cost, and forward-mode derivatives give
    every trial its own steps. `adjoint` set is an error (fit differentiates in forward mode,
    `diffrax.ForwardMode`)."""
    fit_time_offset: bool = False
    """Estimate each trial's clock offset as one more nuisance value: the trial's inputs drive
    the model at `t + offset` (a capture clock that runs 0.15 s behind the inputs' gives +0.15
    s), bounded smoothly to `+- max_time_offset` (`offset = max tanh(v / max)`), started at the
    quick estimate of `jsphere.estimate_time_offset`. Beyond the ends of a trial's table its
    inputs are held. The offsets and their standard errors are `FitResult.time_offset` and
    `time_offset_stderr`."""
    max_time_offset: float = 0.5
    """The largest clock offset, either way [s] (see `fit_time_offset`)."""
    loss: str = DEFAULT_LOSS
    """How a frame's residuals (position and orientation together) enter the cost: `"cauchy"`
    (default), `"huber"`, `"soft_l1"` or `"l2"` (plain least squares), at a scale of `SCALE`
    noise levels (`jsphere.identify.robust`). Frames the loss sets aside (weight below one half:
    ghost frames, marker swaps) are `FitResult.outliers`, by the file name of each trial read
    from a file (`Trial.source`), else by its name; the noise levels are then estimated from the
    residuals without them. Onboard-sensor trials are fitted by least squares whatever is
    given: an IMU and encoders have no ghost frames."""
    imu_position: tuple[float, float, float] = (0.0, 0.0, 0.0)
    """Onboard-sensor trials: the IMU's position [m], platform components from the shell's
    centre (the platform frame's origin; `jsphere.Mounting`)."""
    imu_rotation: tuple[float, float, float, float] = (1.0, 0.0, 0.0, 0.0)
    """Onboard-sensor trials: the IMU's orientation, a scalar-first quaternion whose matrix maps
    IMU components to platform components (`jsphere.Mounting`)."""
    start_at_rest: bool = True
    """Onboard-sensor trials: each starts at rest (upright: `State.at_rest`). `False` fits each
    trial's initial motion too (the shell's angular velocity, the platform's tilt and, with
    torques, its angular velocity: `jsphere.identify.onboard.MOTION`), for trials cut from a
    longer run; the standard errors grow (`docs/onboard.md`)."""
    zero_order_hold: bool = False
    """Onboard-sensor trials: their torques are held between samples (a digital controller's),
    whatever the trial files say (a file says it itself with `# hold: zero-order`)."""
    sigma_gyro: float | None = None
    """Onboard-sensor trials: the gyro's noise level [rad/s]; if not given it starts at 0.01 and
    is estimated from the residuals after the first stage (as `sigma_pos`)."""
    sigma_acc: float | None = None
    """Onboard-sensor trials: the accelerometer's noise level [m/s^2]; estimated if not given
    (start 0.1)."""
    sigma_encoder: float | None = None
    """Onboard-sensor trials: the encoders' noise level [rad]; estimated if not given (start
    1e-3). Giving a larger one down-weights encoders whose rollers slip (`docs/onboard.md`)."""

    # ------------------------------------------------------------------ validation

    def checked(self, onboard: bool | str = False) -> FitOptions:
        """These options validated (`InputError` naming the first bad one), with the counts as
        ints and `solver` filled with fit's defaults (for `onboard` trials, `ONBOARD_TOLERANCES`
        with `simulate`'s solver, and least squares; `"mixed"`: onboard and pose trials, the
        onboard tolerances and the loss for the pose trials)."""
        check_loss(self.loss, "fit")
        mount = {}
        for name, n in (("imu_position", 3), ("imu_rotation", 4)):
            v = np.asarray(getattr(self, name), dtype=float) if np.size(getattr(self, name)) == n else None
            if v is None or not np.all(np.isfinite(v)):
                raise InputError(f"fit: {name} must be {n} finite numbers; got {getattr(self, name)!r}.")
            mount[name] = tuple(float(x) for x in v)
        if np.linalg.norm(mount["imu_rotation"]) < 1e-6:
            raise InputError("fit: imu_rotation is a zero quaternion; give the IMU's orientation, e.g. 1 0 0 0.")
        for name, unit in (("sigma_gyro", "rad/s"), ("sigma_acc", "m/s^2"), ("sigma_encoder", "rad")):
            if getattr(self, name) is not None:
                real("fit", name, getattr(self, name), strict=True, unit=unit)
        for name in ("fit_time_offset", "start_at_rest", "zero_order_hold"):
            if not isinstance(getattr(self, name), (bool, np.bool_)):
                raise InputError(f"fit: {name} must be True or False; got {getattr(self, name)!r}.")
        real("fit", "max_time_offset", self.max_time_offset, strict=True, unit="s")
        counts = {k: whole("fit", k, getattr(self, k), low) for k, low in (("n_starts", 1), ("max_iter", 1))}
        counts |= {k: whole("fit", k, getattr(self, k), 0) for k in ("adam_steps", "seed")}
        for name, unit in (("sigma_pos", "m"), ("sigma_rot", "rad")):
            if getattr(self, name) is not None:
                real("fit", name, getattr(self, name), strict=True, unit=unit)
        if self.shooting not in ("auto", "single", "multiple"):
            raise InputError(f"fit: shooting must be 'auto', 'single' or 'multiple'; got {self.shooting!r}.")
        segment = real("fit", "segment", self.segment, low=0.05, unit="s")
        solver = _fit_solver(self.solver, onboard)
        loss = "l2" if onboard is True else self.loss  # (with pose trials too: their loss)
        return dataclasses.replace(self, **counts, **mount, segment=segment, solver=solver, loss=loss)

    # ------------------------------------------------------------------ what the fit reads

    @property
    def rtol(self) -> float:
        return float(self.solver.rtol)

    @property
    def atol(self) -> float:
        return float(self.solver.atol)

    @property
    def max_steps(self) -> int:
        return int(self.solver.max_steps)

    @property
    def ode_solver(self) -> dfx.AbstractSolver | None:
        """The Runge-Kutta method, `None` where it is `simulate`'s default."""
        return None if eqx.tree_equal(self.solver.solver_or_default(), default_solver()) else self.solver.solver

    @property
    def max_offset(self) -> float:
        """The bound of the fitted clock offsets [s], 0 when they are not fitted."""
        return float(self.max_time_offset) if self.fit_time_offset else 0.0

    @property
    def estimate_sigma(self) -> bool:
        return self.sigma_pos is None or self.sigma_rot is None

    @property
    def mounting(self):
        """The IMU's `jsphere.Mounting` of `imu_position` and `imu_rotation`."""
        from ..model.sensors import Mounting

        return Mounting(self.imu_position, self.imu_rotation)

    @property
    def sigmas_onboard(self) -> tuple[float | None, float | None, float | None]:
        """The noise levels given for the gyro, the accelerometer and the encoders (None: estimated)."""
        return self.sigma_gyro, self.sigma_acc, self.sigma_encoder

    @property
    def estimate_sigma_onboard(self) -> bool:
        return any(s is None for s in self.sigmas_onboard)

    def stage_loss(self, stage: int) -> str:
        """The loss of a stage: in the warm-up stages, far from the answer (multiple shooting,
        `4 + k`, and the Adam steps, 0), the convex `WARM_LOSS` where the fit's loss is
        redescending (`REDESCENDING`); the fit's loss in the Levenberg-Marquardt stages 1 and 2."""
        return WARM_LOSS if self.loss in REDESCENDING and (stage == 0 or stage >= 4) else self.loss

    def config(self, sig: np.ndarray, multiple: bool) -> dict[str, Any]:
        """What the checkpoint's fingerprint holds besides the data and the free parameters (the
        solver only when it is not the default, so that a default fit's fingerprint does not
        depend on whether it was given)."""
        solver = {} if self.ode_solver is None else {"solver": repr(self.ode_solver)}
        if self.max_offset:
            solver = solver | {"max_time_offset": self.max_offset}
        if self.loss != "l2":
            solver = solver | {"loss": self.loss}
        plain = ("n_starts", "spread", "seed", "adam_steps", "adam_lr", "max_iter", "ftol", "gtol", "noise")
        return (
            solver
            | {k: getattr(self, k) for k in plain}
            | {
                "sig": sig.tolist(),
                "estimate_sigma": self.estimate_sigma,
                "rtol": self.rtol,
                "atol": self.atol,
                "max_steps": self.max_steps,
                "format": _CHECKPOINT_FORMAT,
                "multiple": multiple,
                "segment": self.segment,
                "mu": list(MU_LEVELS),
            }
        )

    # ------------------------------------------------------------------ JSON

    def to_json(self) -> dict[str, Any]:
        """The options as `fit.json` records them: every field, the solver's as `rtol`, `atol`,
        `max_steps` and the Runge-Kutta method's class name (`None`: `simulate`'s default)."""
        out = {f.name: getattr(self, f.name) for f in dataclasses.fields(self) if f.name != "solver"}
        s = self.solver or SolverOptions()
        method = None if s.solver is None else type(s.solver).__name__
        return out | {"solver": {"rtol": s.rtol, "atol": s.atol, "max_steps": s.max_steps, "solver": method}}

    @classmethod
    def from_json(cls, d: dict[str, Any]) -> FitOptions:
        """The options `to_json` wrote (the Runge-Kutta method by its diffrax class name)."""
        d = dict(d)
        s = dict(d.pop("solver", None) or {})
        method = s.pop("solver", None)
        solver = SolverOptions(**s, solver=None if method is None else getattr(dfx, method)())
        for k in ("imu_position", "imu_rotation"):
            if k in d:
                d[k] = tuple(float(x) for x in d[k])
        return cls(**d, solver=solver)


def _fit_solver(options: SolverOptions | None, onboard: bool = False) -> SolverOptions:
    """`options` with fit's defaults where it leaves `SolverOptions`' (`FIT_SOLVER`,
    `FIT_TOLERANCES`; for onboard trials `simulate`'s solver at `ONBOARD_TOLERANCES`); refuses
    an `adjoint`."""
    unused(
        options,
        where="fit",
        adjoint="fit differentiates its solves in forward mode (diffrax.ForwardMode), which it chooses itself",
    )
    options = solver_options(options, where="fit")
    if onboard:
        return options.or_defaults(solver=default_solver(), **ONBOARD_TOLERANCES)
    return options.or_defaults(solver=FIT_SOLVER, **FIT_TOLERANCES)


#: `fit`'s keywords of the solver's settings (`FitOptions.solver`)
_SOLVER_KEYWORDS = ("rtol", "atol", "max_steps")


def fit_options(options: FitOptions | SolverOptions | None, deprecated: dict[str, Any]) -> FitOptions:
    """`fit`'s `options` with the keywords it took before `FitOptions` (`deprecated`: each warns
    with its spelling in `FitOptions`, `jsphere._runtime.moved_keywords`, and wins over the same
    field of `options`); a `SolverOptions` as `options` is `FitOptions(solver=...)`, with a
    warning too."""
    if options is not None and not isinstance(options, FitOptions):
        warnings.warn(
            "fit(options=SolverOptions(...)) is deprecated; write options=FitOptions(solver=SolverOptions(...)).",
            DeprecationWarning,
            stacklevel=3,
        )
        options = FitOptions(solver=solver_options(options, where="fit"))
    shortcuts = {k: deprecated.pop(k) for k in _SOLVER_KEYWORDS if k in deprecated}
    options = moved_into("fit", deprecated, options, FitOptions, "options")
    no_other_keywords("fit", deprecated)
    if not shortcuts:
        return options
    for k in shortcuts:
        warnings.warn(
            f"fit: {k}= is deprecated; pass options=FitOptions(solver=SolverOptions({k}=...))",
            DeprecationWarning,
            stacklevel=3,
        )
    return dataclasses.replace(options, solver=solver_options(options.solver, where="fit", **shortcuts))


def save_json(doc: dict[str, Any], path, deprecated: dict[str, Any], where: str, instead: str) -> list[Path]:
    """A result's `save`: its JSON `doc` written atomically to `path`; returns `[path]`. The
    `plots=` keyword draws nothing: results are data, and `jsphere.plots` draws them (`instead`).
    It warns; any other keyword is a `TypeError`."""
    for k in deprecated:
        if k != "plots":
            raise TypeError(f"{where}() got an unexpected keyword argument {k!r}.")
        warnings.warn(
            f"{where}(plots=...) is deprecated: save writes the JSON only; draw the figures with {instead}.",
            DeprecationWarning,
            stacklevel=3,
        )
    atomic_write_json(Path(path), doc)
    return [Path(path)]
