"""The options of a solve in one place: `SolverOptions`, its defaults and their validation."""

from __future__ import annotations

import dataclasses
import numbers
import warnings
from typing import Any, Literal

import diffrax as dfx
import equinox as eqx
import jax.numpy as jnp

from .._runtime.precision import warn_if_float32_by_default


def default_solver() -> dfx.AbstractSolver:
    """The default Runge-Kutta method: `diffrax.Dopri8()` (8th order). At the tolerances the
    paper's millimetre-level numbers need (rtol 1e-8 and below) it takes several times fewer
    steps than `Tsit5` (measurements: `docs/performance.md`)."""
    return dfx.Dopri8()


#: Tolerances `(rtol, atol)` of `simulate` by the parameters' precision when none are given.
#: float64: positions within 1e-3 mm over the paper's 4 s manoeuvres. float32: about 100
#: machine epsilons.
DEFAULT_TOLERANCES = {"float64": (1e-8, 1e-10), "float32": (1e-5, 1e-7)}

#: Below this `rtol` a float32 solve's error estimates are mostly rounding noise: steps shrink
#: and are rejected at random, worst in batches with shared steps.
FLOAT32_MIN_RTOL = 1e-5

BATCH_STEPS = ("shared", "per_trial", "diffrax")


def tolerances(
    dtype, rtol, atol, defaults=DEFAULT_TOLERANCES, *, where: str = "simulate", stacklevel: int = 3
) -> tuple[Any, Any]:
    """`(rtol, atol)` with `None` replaced by the default for `dtype` (`defaults[dtype name]`),
    and a warning when a float32 solve is asked for an `rtol` its rounding cannot resolve.
    `simulate`, `simulate_gaits` and `monte_carlo` (and so `fit`, the planner's verification
    and `reproduce`) pass here: float32 parameters while JAX's float64 is off warn once per
    process (`jsphere.PrecisionWarning`)."""
    warn_if_float32_by_default(dtype, where)
    name = "float32" if jnp.dtype(dtype).itemsize <= 4 else "float64"
    rtol = defaults[name][0] if rtol is None else rtol
    atol = defaults[name][1] if atol is None else atol
    if name == "float32" and isinstance(rtol, (int, float)) and rtol < FLOAT32_MIN_RTOL:
        warnings.warn(
            f"{where}: rtol={rtol:g} with float32 parameters is below what float32 resolves "
            f"(~{FLOAT32_MIN_RTOL:g}, about 100 machine epsilons): the error estimates are rounding "
            "noise, so the solver takes many more steps (most of all for batches with shared steps) "
            f"or fails. Pass rtol >= {FLOAT32_MIN_RTOL:g} (the float32 default when rtol is not "
            "given) or use float64 parameters.",
            stacklevel=stacklevel,
        )
    return rtol, atol


def _check(where: str, max_steps, batch_steps) -> None:
    if batch_steps not in BATCH_STEPS:
        raise ValueError(f"{where}: batch_steps must be 'shared', 'per_trial' or 'diffrax'; got {batch_steps!r}.")
    if isinstance(max_steps, bool) or not isinstance(max_steps, numbers.Integral) or max_steps < 1:
        raise ValueError(f"{where}: max_steps must be a positive integer; got {max_steps!r}.")


class SolverOptions(eqx.Module):
    """How `simulate` and `simulate_gaits` integrate:

    - `rtol`, `atol`: tolerances of the adaptive step-size controller; `None`: the default for
      the parameters' precision (`DEFAULT_TOLERANCES`, `jsphere.gaits.gaits.GAIT_TOLERANCES`;
      a float32 `rtol` below `FLOAT32_MIN_RTOL` warns: its error estimates would be rounding
      noise);
    - `solver`: a diffrax solver; `None`: `default_solver()` (`Dopri8`);
    - `max_steps`: the most steps a segment may take;
    - `throw`: raise on solver failure (max steps, NaN), or report it in `Trajectory.ok` and
      `Trajectory.status` (per trial under `vmap`): a trial that fails fails alone, and the
      others get the results they get in a batch without it (a batch with shared steps that
      fail is solved again with per-trial steps);
    - `adjoint`: a diffrax adjoint; `None`: `diffrax.RecursiveCheckpointAdjoint()`
      (`diffrax.ForwardMode()` for `jax.jacfwd`);
    - `batch_steps`: under `vmap` (from 32 trials, `SHARED_MIN_BATCH`) of torques or gaits,
      with the default adjoint, `"shared"` (default) integrates the batch with shared steps:
      one step sequence, accepted only when every trial meets its tolerance (results depend
      on the batch within the tolerance; `max_steps` and `num_steps` count the shared steps;
      `jsphere.solve.batched.segment`); its gradient is the discrete adjoint of the shared
      steps (within the tolerance of the per-trial gradient). `"per_trial"` gives each trial
      its own step-size control: with `Dopri8`, `Dopri5`, `Tsit5` or a method of one's own
      (`jsphere.solve.batched.method.tableau`) the batch runs in the same vectorised loop,
      every trial with its own times, steps, failures and `num_steps` (in lockstep), so a
      trial's result is bitwise the same in any batch; its gradient is the discrete adjoint
      of those per-trial steps. `"diffrax"` is diffrax's own `vmap` of the flat state
      (per-trial steps; the reference the others are measured against). It changes nothing
      for unbatched calls, nor when `t0`, `t1`, `ts` or `jump_ts` are batched. (Speed:
      `docs/performance.md`.)

    Each field is also a keyword argument of `simulate` and `simulate_gaits` (a shortcut): a
    keyword given wins over the same field of `options` (`given`).

    `fit`, `plan`, `plan_route`, `plan_many`, `replay_errors` and `monte_carlo` take `options`
    too: each uses the fields it can (its docstring says which), with its own defaults for the
    fields left at `SolverOptions`' defaults (`or_defaults`), and refuses a field it cannot use
    set away from its default (`unused`).
    """

    rtol: Any = None
    atol: Any = None
    solver: dfx.AbstractSolver | None = None
    max_steps: int = eqx.field(static=True, default=16384)
    throw: bool = eqx.field(static=True, default=True)
    adjoint: dfx.AbstractAdjoint | None = None
    batch_steps: Literal["shared", "per_trial", "diffrax"] = eqx.field(static=True, default="shared")

    def __check_init__(self):
        _check("SolverOptions", self.max_steps, self.batch_steps)

    def given(self, **shortcuts) -> "SolverOptions":
        """These options with each keyword shortcut that was given (not `None`) in its field."""
        return dataclasses.replace(self, **{k: v for k, v in shortcuts.items() if v is not None})

    def or_defaults(self, **defaults) -> "SolverOptions":
        """These options with a function's own `defaults` for the fields at `SolverOptions`'
        defaults (an option set to exactly that default cannot be told from one not set)."""
        return dataclasses.replace(self, **{k: v for k, v in defaults.items() if _at_default(self, k)})

    def tolerances(self, dtype, defaults=DEFAULT_TOLERANCES, *, where: str = "simulate") -> tuple[Any, Any]:
        """`(rtol, atol)` for parameters of `dtype` (`tolerances`)."""
        return tolerances(dtype, self.rtol, self.atol, defaults, where=where, stacklevel=4)

    def solver_or_default(self) -> dfx.AbstractSolver:
        return default_solver() if self.solver is None else self.solver

    def adjoint_or_default(self) -> dfx.AbstractAdjoint:
        return dfx.RecursiveCheckpointAdjoint() if self.adjoint is None else self.adjoint


def _at_default(options: SolverOptions, name: str) -> bool:
    """Whether a field of `options` is at `SolverOptions`' default (`None` or a plain value)."""
    value, default = getattr(options, name), getattr(SolverOptions(), name)
    return value is default or (default is not None and isinstance(value, (bool, int, str)) and value == default)


def solver_options(options: SolverOptions | None, *, where: str, **shortcuts) -> SolverOptions:
    """`options` (default `SolverOptions()`) with the keyword shortcuts given (`given`); a
    keyword that is no field of `SolverOptions` is a `TypeError` naming it."""
    if options is not None and not isinstance(options, SolverOptions):
        raise TypeError(f"{where}: options must be a jsphere.SolverOptions; got {type(options).__name__}.")
    unknown = sorted(set(shortcuts) - {f.name for f in dataclasses.fields(SolverOptions)})
    if unknown:
        raise TypeError(f"{where}() got an unexpected keyword argument {unknown[0]!r}.")
    return (SolverOptions() if options is None else options).given(**shortcuts)


def unused(options: SolverOptions | None, *, where: str, **why: str) -> None:
    """Refuse fields of `options` that a function does not use: for each `field=reason`, a
    field set away from `SolverOptions`' default is an error naming it and `reason`
    (`TypeError` if `options` is not a `SolverOptions`)."""
    if options is None:
        return
    if not isinstance(options, SolverOptions):
        raise TypeError(f"{where}: options must be a jsphere.SolverOptions; got {type(options).__name__}.")
    for name, reason in why.items():
        value = getattr(options, name)
        if not _at_default(options, name):
            raise ValueError(f"{where}: options.{name}={value!r} is not used: {reason}.")
