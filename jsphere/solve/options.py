"""The options of a solve in one place: `SolverOptions`, its defaults and their validation."""

from __future__ import annotations

import numbers
import warnings
from collections.abc import Mapping
from typing import Any, Callable, Literal

import diffrax as dfx
import equinox as eqx
import jax
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
    """How `simulate` and `simulate_gaits` integrate (each field as their keyword argument of
    the same name):

    - `rtol`, `atol`: tolerances of the adaptive step-size controller; `None`: the default for
      the parameters' precision (`DEFAULT_TOLERANCES`, `jsphere.gaits.gaits.GAIT_TOLERANCES`);
    - `solver`: a diffrax solver; `None`: `default_solver()` (`Dopri8`);
    - `max_steps`: the most steps a segment may take;
    - `throw`: raise on a failed solve, or report it in `Trajectory.status`;
    - `adjoint`: a diffrax adjoint; `None`: `diffrax.RecursiveCheckpointAdjoint()`
      (`diffrax.ForwardMode()` for `jax.jacfwd`);
    - `batch_steps`: under `vmap`, `"shared"` (one step sequence for a batch), `"per_trial"`
      (each trial its own steps, in the same vectorised loop) or `"diffrax"` (diffrax's own
      `vmap` of the flat state, bypassing the batch engine: the engine's reference);
    - `programs`: how the programs of a call with concrete inputs are compiled and run,
      `programs(name, fn, rebuild, *args)` in place of `fn(*args)`; `None`: `fn(*args)` (jitted
      in this process). `jsphere.FastStart()` compiles them for a short first call and keeps
      them on disk for the next process (what the command line does).

    `simulate(..., options=SolverOptions(rtol=1e-10))` is `simulate(..., rtol=1e-10)`; keyword
    arguments given besides `options` are merged into it (`merge`).

    `fit`, `plan`, `plan_route`, `plan_many`, `replay_errors` and `monte_carlo` take `options`
    too: each uses the fields it can (its docstring says which), with its own defaults where
    they differ from these (`resolve`), and refuses a field it cannot use set away from its
    default.
    """

    rtol: Any = None
    atol: Any = None
    solver: dfx.AbstractSolver | None = None
    max_steps: int = eqx.field(static=True, default=16384)
    throw: bool = eqx.field(static=True, default=True)
    adjoint: dfx.AbstractAdjoint | None = None
    batch_steps: Literal["shared", "per_trial", "diffrax"] = eqx.field(static=True, default="shared")
    programs: Callable | None = eqx.field(static=True, default=None)

    def __check_init__(self):
        _check("SolverOptions", self.max_steps, self.batch_steps)

    def merge(self, *, where: str = "SolverOptions", **keywords) -> "SolverOptions":
        """These options with `keywords` (fields of `SolverOptions`) on top. A keyword at its
        default value leaves the option as it is; one that differs from the default replaces
        an option at its default; a keyword and an option that both differ from the default
        and from each other are an error naming both."""
        unknown = set(keywords) - set(_DEFAULTS)
        if unknown:
            raise TypeError(f"{where}: unknown solver options {sorted(unknown)}; known: {list(_DEFAULTS)}.")
        values = {name: getattr(self, name) for name in _DEFAULTS}
        for name, value in keywords.items():
            default, current = _DEFAULTS[name], values[name]
            if _same(value, default) or _same(value, current):
                continue
            if not _same(current, default):
                raise ValueError(
                    f"{where}: {name}={value!r} conflicts with options.{name}={current!r}; give it in one place."
                )
            values[name] = value
        _check(where, values["max_steps"], values["batch_steps"])
        return SolverOptions(**values)

    def tolerances(self, dtype, defaults=DEFAULT_TOLERANCES, *, where: str = "simulate") -> tuple[Any, Any]:
        """`(rtol, atol)` for parameters of `dtype` (`tolerances`)."""
        return tolerances(dtype, self.rtol, self.atol, defaults, where=where, stacklevel=4)

    def solver_or_default(self) -> dfx.AbstractSolver:
        return default_solver() if self.solver is None else self.solver

    def adjoint_or_default(self) -> dfx.AbstractAdjoint:
        return dfx.RecursiveCheckpointAdjoint() if self.adjoint is None else self.adjoint


_DEFAULTS = {
    "rtol": None,
    "atol": None,
    "solver": None,
    "max_steps": 16384,
    "throw": True,
    "adjoint": None,
    "batch_steps": "shared",
    "programs": None,
}


def _same(a, b) -> bool:
    """Whether two option values are the same (`None` only equals `None`; solvers and adjoints
    by their type and fields; traced values are never the same as anything else)."""
    if a is b:
        return True
    if a is None or b is None:
        return False
    if isinstance(a, jax.core.Tracer) or isinstance(b, jax.core.Tracer):
        return False
    try:
        return bool(eqx.tree_equal(a, b))
    except Exception:  # noqa: BLE001 - values that cannot be compared are different
        return False


def resolve(
    options: SolverOptions | None, *, where: str, defaults: Mapping[str, Any] | None = None, **keywords
) -> SolverOptions:
    """The options of a call that takes `options=` and the same settings as keyword arguments.

    Without `defaults`: `options` (default `SolverOptions()`) merged with `keywords`
    (`SolverOptions.merge`), for functions whose keyword defaults are `SolverOptions`' own.

    `defaults` (`{field: value}`) are the function's own defaults where they differ from
    `SolverOptions`' (e.g. `fit`'s `rtol=1e-6`); a field named there but not in `keywords` is
    taken as a keyword at that default. Per field of `keywords`:

    - a field of `options` at `SolverOptions`' default takes the keyword's value (the
      function's own default when the keyword is not given): an option set to exactly
      `SolverOptions`' default cannot be told from one not set;
    - a keyword at the function's own default, or equal to the option, leaves the option as
      it is;
    - a keyword and an option that are both set and differ are an error naming both.
    """
    if options is not None and not isinstance(options, SolverOptions):
        raise TypeError(f"{where}: options must be a jsphere.SolverOptions; got {type(options).__name__}.")
    options = SolverOptions() if options is None else options
    if defaults is None:
        return options.merge(where=where, **keywords)
    unknown = (set(keywords) | set(defaults)) - set(_DEFAULTS)
    if unknown:
        raise TypeError(f"{where}: unknown solver options {sorted(unknown)}; known: {list(_DEFAULTS)}.")
    values = {name: getattr(options, name) for name in _DEFAULTS}
    for name, value in ({**defaults, **keywords}).items():
        own, current = defaults.get(name, _DEFAULTS[name]), values[name]
        if _same(current, _DEFAULTS[name]):
            values[name] = value
        elif not (_same(value, own) or _same(value, current)):
            raise ValueError(
                f"{where}: {name}={value!r} conflicts with options.{name}={current!r}; give it in one place."
            )
    _check(where, values["max_steps"], values["batch_steps"])
    return SolverOptions(**values)


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
        if not _same(value, _DEFAULTS[name]):
            raise ValueError(f"{where}: options.{name}={value!r} is not used: {reason}.")
