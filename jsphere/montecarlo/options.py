"""The options of a Monte-Carlo study (`StudyOptions`, each written once with its documentation,
its check and its form in the study file of `jsphere montecarlo`) and of a study on several
processes of one JAX job (`Distributed`).
"""

from __future__ import annotations

import dataclasses
import inspect
import warnings
from typing import Any, Callable, Mapping

from .._runtime.checks import real, whole
from .._runtime.errors import InputError
from .._runtime.moved_keywords import moved_into
from ..solve.options import SolverOptions

#: the ways a trial runs (see `StudyOptions.mode`)
MODES = ("gait", "torques", "wheel_speeds")
#: the replay modes' default step limit (`StudyOptions.max_steps`)
MAX_STEPS = 65536


def _mode(where: str, name: str, v) -> str:
    if v not in MODES:
        raise InputError(f'{where}: {name} must be "gait", "torques" or "wheel_speeds"; got {v!r}.')
    return v


def _reset(where: str, name: str, v):
    if not isinstance(v, (bool, list, tuple)):
        raise InputError(f"{where}: {name} must be true, false or a list (one entry per gait boundary); got {v!r}.")
    return v


def _option(default, doc: str, check: Callable | None = None, file: str | None = "value"):
    """A field of an options object: its default, its documentation, its check `(where, name,
    value) -> value` and how a study file gives it (`"value"`: checked as it is; the name of a
    reader of `study`: a table or a path; None: not a key of the file)."""
    return dataclasses.field(default=default, metadata={"doc": doc, "check": check, "file": file})


@dataclasses.dataclass(frozen=True)
class StudyOptions:
    """How a Monte-Carlo study runs its trials (`monte_carlo(..., options=StudyOptions(...))`).
    Every value is checked by `monte_carlo` before any work. The study file of
    `jsphere montecarlo` takes the fields marked "(file)" as keys of the same name."""

    seed: int = _option(
        0,
        "the seed of the draws (`0 <= seed < 2**32`); trial `i` uses the key `fold_in(PRNGKey(seed), i)`: "
        "the same study whatever `batch_size` or device count",
        lambda w, k, v: whole(w, k, v, 0, 2**32 - 1),
    )
    batch_size: int = _option(
        1024,
        "trials per batch (memory stays bounded for any `n`), rounded up to whole vmapped chunks of 64 (`CHUNK`: "
        "results are bitwise the same for any batch size and device count), sharded over as many local devices as "
        "divide it into chunks (or every device of a distributed run). A study folder that exists keeps the batch "
        "size of its manifest (a study file's default: 4096)",
        lambda w, k, v: whole(w, k, v, 1),
    )
    mode: str = _option(
        "gait",
        '`"gait"`: each trial executes the gaits exactly (`gamma(t)` prescribed). `"torques"` or `"wheel_speeds"`: '
        "the commands planned once with the nominal robot (sampled at `plan_rate` Hz) are replayed open loop on "
        'each perturbed robot, through `actuators`, then `settle` seconds without commands: "where does the real '
        'robot stop?" (a study file with `track` defaults to "torques")',
        _mode,
    )
    reset: bool | list = _option(False, "as `simulate_gaits(reset=...)`", _reset)
    Omega0_sd: float = _option(
        0.0,
        "sd of a perturbation of the initial shell angular velocity [1/s]",
        lambda w, k, v: real(w, k, v, unit="1/s"),
    )
    settle: float = _option(
        1.0,
        "seconds without commands after the replayed commands end (replay modes; after the last row of a "
        "`track` table, that row held) [s]",
        lambda w, k, v: real(w, k, v, unit="s"),
    )
    plan_rate: float = _option(
        200.0,
        "the rate at which the gaits' plan is sampled for the replay modes [Hz]",
        lambda w, k, v: real(w, k, v, strict=True, unit="Hz"),
        file=None,
    )
    max_steps: int | None = _option(
        None,
        "solver step limit per trial in the replay modes (noisy commands need many), default `solver.max_steps` "
        "where set, else 65536. Gait mode solves with `simulate_gaits`' limit unless `solver.max_steps` sets it",
        lambda w, k, v: None if v is None else whole(w, k, v, 1),
        file=None,
    )
    actuators: Any = _option(
        None,
        "a `jsphere.Actuators` (gain, delay, white and band-limited noise) through which the replay modes "
        "execute their commands (a study file's `[actuators]` table)",
        file="actuators",
    )
    commands: tuple | None = _option(
        None,
        "`(ts, values)`, a command table to replay instead of the gaits' plan, from `t = 0` (a repeated time "
        "stamp encodes a jump, as for `simulate`); the motors stop at its last time, and the gaits are the "
        'record only (a study file names a table: `commands = "FILE"`, relative to the file)',
        file="commands",
    )
    track: Mapping | None = _option(
        None,
        "a feedback table (`read_track_csv` of `track.csv` of `jsphere track`) run closed loop instead of the "
        'gaits\' plan (`mode` "torques"): every period the command `K = K_ff - G e` of the measured state, clipped '
        "and held, through `actuators` (gain, `delay_s` in whole periods, white noise); the last row is held for "
        '`settle` seconds. `Omega0_sd`, `delay_sd` and `band_sd` must be 0 (a study file: `track = "FILE"`)',
        file="track",
    )
    feedback: Mapping | None = _option(
        None,
        "with `track`: the measured state's noise and delay, the start pose's spread and the torque limit "
        "(`FEEDBACK` of `jsphere.montecarlo.study`, whose defaults are `jsphere track`'s evaluation's; a study "
        "file's `[feedback]` table)",
        file="feedback",
    )

    def checked(self, where: str) -> "StudyOptions":
        """These options with every value checked and converted (`InputError` naming it)."""
        check = lambda f, v: v if f.metadata["check"] is None else f.metadata["check"](where, f.name, v)
        return StudyOptions(**{f.name: check(f, getattr(self, f.name)) for f in dataclasses.fields(self)})


def _document(cls):
    """Append the fields' documentation (their metadata) to `cls`'s docstring."""
    mark = lambda f: " (file)" if f.metadata["file"] is not None else ""
    lines = [f"- `{f.name}` (default `{f.default!r}`){mark(f)}: {f.metadata['doc']}." for f in dataclasses.fields(cls)]
    cls.__doc__ = f"{inspect.cleandoc(cls.__doc__)}\n\n**Fields:**\n\n" + "\n".join(lines)
    return cls


_document(StudyOptions)


@dataclasses.dataclass(frozen=True)
class Distributed:
    """How the processes of a JAX multi-process job find each other (`monte_carlo(...,
    distributed=Distributed(...))`): `coordinator`, `"host:port"` of process 0; `num_processes`;
    `process_id`, this process's, `0 .. num_processes - 1`. Each None: from the cluster's
    environment (SLURM, Open MPI, ...), as `jax.distributed.initialize` finds it."""

    coordinator: str | None = None
    num_processes: int | None = None
    process_id: int | None = None


#: `monte_carlo`'s keywords that moved into `options`, `solver` (`rtol`, `atol`) or `distributed`
_MOVED = {f.name for f in dataclasses.fields(StudyOptions) + dataclasses.fields(Distributed)} | {"rtol", "atol"}


def study_arguments(where: str, options, solver, distributed, moved: dict[str, Any]) -> tuple:
    """`(StudyOptions, SolverOptions | None, distributed)` of a call of `monte_carlo` (or
    `work`, `gather`): `options` may still be a `SolverOptions` and `moved` the keywords that
    moved into the objects, each with a `DeprecationWarning` naming its new spelling
    (`jsphere._runtime.moved_keywords.moved_into`)."""
    unknown = sorted(set(moved) - _MOVED)
    if unknown:
        raise TypeError(f"{where}() got unexpected keyword argument(s) {unknown}.")
    if isinstance(options, SolverOptions):
        message = f"{where}: options=SolverOptions(...) is deprecated; pass solver=SolverOptions(...)."
        warnings.warn(message, DeprecationWarning, stacklevel=3)  # the call of monte_carlo, work or gather
        options, solver = None, options if solver is None else solver
    options = moved_into(where, moved, options, StudyOptions, "options")
    tolerances = {k: moved.pop(k) for k in ("rtol", "atol") if k in moved}
    if tolerances:
        solver = moved_into(where, tolerances, solver, SolverOptions, "solver")
    if moved:  # the keywords of a distributed run
        if distributed is not True:
            raise InputError(f"{where}: {', '.join(moved)} set up a distributed run; pass distributed=True too.")
        distributed = moved_into(where, moved, None, Distributed, "distributed")
    return options, solver, distributed
