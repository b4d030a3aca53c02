"""Monte-Carlo studies of gait motions: vmapped batches, deterministic seeds, resumable files.

Each trial `i` draws its parameters from `jax.random.fold_in(PRNGKey(seed), i)`, so a study is
the same whatever the batch size or the number of devices; a draw that breaks a rule of
`RobotParams` is rejected (not simulated) or, for "truncate" distributions, drawn again;
batches are sharded over all local devices; finished batches are written atomically to `out/`
and a killed study resumes there (a corrupt batch file is recomputed).

`monte_carlo` checks its arguments, lays the study out in batches (`_Run`), computes this
process's batches (`_own_batches`), collects the other processes' (`_other_batches`) and joins
them into a `MonteCarloResult`. The modules beside this one hold the steps' parts: `study` (the
checks and the study file), `sampling` (the draws), `batch` (the compiled batch), `store` (the
study folder) and `result` (the outcome and its statistics).
"""

from __future__ import annotations

import dataclasses
import hashlib
import math
import os
import time
from pathlib import Path
from typing import Mapping, Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._runtime.checks import real, whole
from .._runtime.errors import InputError
from .._runtime.progress import Progress
from ..controls import Sampled
from ..gaits.gaits import Gait, simulate_gaits
from ..model.params import RobotParams
from ..solve.options import SolverOptions, default_solver, resolve, unused
from ..solve.simulate import tolerances
from .batch import CHUNK as CHUNK
from .batch import Replay, Trials, run_batch
from .result import REJECTED as REJECTED
from .result import MonteCarloResult
from .sampling import MAX_REDRAWS as MAX_REDRAWS
from .sampling import REASONS as REASONS
from .sampling import Actuators, Draws
from .store import BATCH_KEYS, StudyFolder, fingerprint
from .study import MODES, check_settings, check_vary

#: the progress lines' prefix
_PROGRESS = "jsphere montecarlo:"
#: seconds between two progress lines where no bar is drawn
_LINE_S = 10.0
#: seconds between two looks for another process's batch file
_POLL_S = 0.2
#: `monte_carlo`'s default step limit of the replay modes
MAX_STEPS = 65536


def monte_carlo(
    params: RobotParams,
    gaits: Sequence[Gait],
    *,
    vary: Mapping[str, Sequence],
    n: int,
    seed: int = 0,
    batch_size: int = 1024,
    reset=False,
    rtol: float | None = None,
    atol: float | None = None,
    mode: str = "gait",
    actuators: Actuators | None = None,
    Omega0_sd: float = 0.0,
    plan_rate: float = 200.0,
    settle: float = 1.0,
    commands: tuple | None = None,
    max_steps: int = 65536,
    out: str | os.PathLike | None = None,
    progress: bool | None = None,
    process_index: int | None = None,
    process_count: int | None = None,
    wait_timeout: float = 24 * 3600.0,
    options: SolverOptions | None = None,
) -> MonteCarloResult:
    """Run the gaits `n` times with parameters drawn from `vary`; return the stop points.

    **Arguments:**
    - `params`: the nominal `RobotParams`; `gaits`: a list as for `simulate_gaits`.
    - `vary`: `{name: ("normal", mean, sd) | ("uniform", low, high)}` with names as in
      `jsphere fit --free`: `"j"`, `"m0"`, `"I[0,0]"`, `"r_m[2]"`, or `"R_m"` (the distance
      `|r_m|`, keeping its direction). Every drawn parameter set is checked against the rules
      of `RobotParams` (`jsphere.model.params.RULES`: positive masses, a valid inertia tensor, the
      centre of mass inside the shell, ...); a draw that breaks one is not simulated: its
      status is `REJECTED` and `stats()` counts it by the rule it breaks. A distribution
      followed by `"truncate"` (`("normal", 0.8, 0.3, "truncate")`) is truncated to the valid
      range instead: while a draw is invalid, every "truncate" distribution is drawn again
      (at most `MAX_REDRAWS` times), which samples it conditioned on a valid robot.
    - `n`, `seed`: number of trials and the seed (`0 <= seed < 2**32`). Trial `i` uses the key
      `fold_in(PRNGKey(seed), i)`: the same study whatever `batch_size` or device count.
    - `batch_size`: trials per compiled call (memory stays bounded for any `n`); rounded up to
      a multiple of 64 times the number of local devices, over which each batch is sharded.
      Inside, trials run in vmapped chunks of 64 (`CHUNK`), so results are bitwise identical
      for any batch size and device count.
    - `mode`: `"gait"` (default): each trial executes the gaits exactly (the paper's
      model: `gamma(t)` prescribed, the motors supply whatever torque it takes). `"torques"` or
      `"wheel_speeds"`: the commands planned once with the nominal `params` (sampled at
      `plan_rate` Hz) are replayed open loop on each perturbed robot, through `actuators`
      (gain, delay, white and band-limited noise; `Actuators`), for the gaits' duration plus
      `settle` seconds: "where does the real robot stop?".
    - `commands`: `(ts, values)`, a command table to replay instead of the gaits' plan (e.g.
      the kinematic control (2.9) for the paper's Fig. 2 comparison); starts at `t = 0`, repeat
      a time stamp to encode a jump (wheel-speed jumps are impulses, see `simulate`); the motors
      stop at its last time. `gaits` is then not replayed (pass the gaits the commands belong
      to, for the record).
    - `rtol`, `atol`: the solver's tolerances; default 1e-8, 1e-10 (float32 parameters: 1e-5,
      1e-7, as `simulate`).
    - `max_steps`: solver step limit per trial in the replay modes (noisy commands need many
      steps: the noise is interpolated smoothly and the solver follows it). Gait mode solves
      with `simulate_gaits`' limit (16384) unless `options.max_steps` sets it.
    - `Omega0_sd`: sd of a perturbation of the initial shell angular velocity [1/s].
    - `out`: a folder. Each finished batch is written there atomically, with a manifest; run
      the same call again after an interruption and it resumes (a folder holding a different
      study is refused). A batch file that cannot be read (cut short, overwritten) is
      recomputed, with a `MonteCarloWarning` naming it; the hidden temporary files a killed
      run leaves are removed.
    - `progress`: `None` (default): a progress bar on stderr when it is a terminal; `True`: the
      bar, or a line every few seconds where stderr is not a terminal; `False`: none
      (`jsphere._runtime.progress`). The first batch, which compiles, is shown apart and left
      out of the rate.
    - `process_index`, `process_count`: for several processes (hosts) sharing one study: each
      computes the batches `k` with `k % process_count == process_index` and writes them to
      `out` (which all processes must see), then reads the others' batches from there (waiting
      up to `wait_timeout` s). Default: `jax.process_index()` / `jax.process_count()`, i.e. one
      process unless `jax.distributed.initialize()` was called (see docs/montecarlo.md).
    - `options`: a `SolverOptions`; its `rtol`, `atol`, `max_steps` and `solver` are used
      (`resolve` with monte_carlo's own default `max_steps=65536`: an option at
      `SolverOptions`' default takes the keyword's value, a keyword at its default leaves a set
      option, both set and different is an error). `throw` and `batch_steps` are
      monte_carlo's own: a failed trial is reported in `status`, and every trial takes its own
      steps, so that its result does not depend on the other trials of its chunk. `adjoint`
      set is an error (nothing is differentiated). A solver other than `Dopri8` is part of
      the study's fingerprint.

    Every argument is checked before any work; a bad one raises `InputError` naming it.

    Returns a `MonteCarloResult` (`x_final`, `y_final`, ... arrays of length `n`; `.stats()`).
    """
    settings = check_settings(
        "monte_carlo",
        {
            "n": n,
            "seed": seed,
            "batch_size": batch_size,
            "settle": settle,
            "Omega0_sd": Omega0_sd,
            "plan_rate": plan_rate,
            "max_steps": max_steps,
            "wait_timeout": wait_timeout,
        },
    )
    opts = _solver_options(options, rtol, atol, settings)
    actuators = _check_mode(mode, actuators, opts.rtol, opts.atol)
    pi, pc = _check_processes(process_index, process_count, out)
    spec = check_vary(params, vary)
    rtol, atol = tolerances(params.R0.dtype, opts.rtol, opts.atol, where="monte_carlo")
    gaits = _check_gaits(gaits)
    if commands is not None and mode == "gait":
        raise ValueError("monte_carlo: `commands` are replayed; use mode='torques' or 'wheel_speeds'.")
    replay = None if mode == "gait" else _replay(params, gaits, mode, commands, reset, actuators, settings)
    run = _Run.create(
        params,
        gaits,
        spec,
        settings,
        reset=reset,
        rtol=rtol,
        atol=atol,
        solver=opts.solver,
        gait_max_steps=SolverOptions().max_steps if options is None else options.max_steps,
        replay=replay,
        commands=commands is not None,
        out=out,
        process=(pi, pc),
    )
    if run.folder is not None:
        run.folder.open(run.fingerprint, run.n, run.seed, vary, set(run.mine), pc == 1)
    t_start = time.perf_counter()
    parts = _own_batches(run, Progress(progress))
    _other_batches(run, parts, settings["wait_timeout"])
    res = _result(run, parts, time.perf_counter() - t_start)
    if run.folder is not None:
        run.folder.write_stats(res.stats())
    return res


def _solver_options(options: SolverOptions | None, rtol, atol, settings: dict) -> SolverOptions:
    """The solver settings of a study: `options` resolved with the keywords (`max_steps`
    defaults to `MAX_STEPS`); `settings["max_steps"]` becomes the replay modes' step limit."""
    unused(options, where="monte_carlo", adjoint="monte_carlo does not differentiate its solves")
    opts = resolve(
        options,
        where="monte_carlo",
        defaults={"max_steps": MAX_STEPS},
        rtol=rtol,
        atol=atol,
        max_steps=settings["max_steps"],
    )
    settings["max_steps"] = opts.max_steps
    return opts


def _check_mode(mode: str, actuators: Actuators | None, rtol, atol) -> Actuators:
    """Check the tolerances, `mode` and `actuators`; the actuators of the study (ideal ones by
    default)."""
    for name, tol in (("rtol", rtol), ("atol", atol)):
        if tol is not None:
            real("monte_carlo", name, tol, strict=True)
    if mode not in MODES:
        raise InputError(f"monte_carlo: mode must be 'gait', 'torques' or 'wheel_speeds'; got {mode!r}.")
    if actuators is not None and mode == "gait":
        raise InputError("monte_carlo: actuators apply to replayed commands; use mode='torques' or 'wheel_speeds'.")
    if actuators is not None and not isinstance(actuators, Actuators):
        raise InputError(f"monte_carlo: actuators must be a jsphere.Actuators; got {type(actuators).__name__}.")
    return actuators or Actuators()


def _check_processes(process_index, process_count, out) -> tuple[int, int]:
    """`(index, count)` of this process among those sharing the study (JAX's by default)."""
    pi = jax.process_index() if process_index is None else whole("monte_carlo", "process_index", process_index, 0)
    pc = jax.process_count() if process_count is None else whole("monte_carlo", "process_count", process_count, 1)
    if not 0 <= pi < pc:
        raise InputError(f"monte_carlo: process_index must be in [0, process_count); got {pi} of {pc}.")
    if pc > 1 and out is None:
        raise InputError(
            "monte_carlo: with several processes, pass `out`, a folder that every process can read and write."
        )
    return pi, pc


def _check_gaits(gaits) -> list[Gait]:
    if isinstance(gaits, (str, bytes)) or not isinstance(gaits, Sequence):
        raise InputError(f"monte_carlo: gaits must be a non-empty list of jsphere.Gait; got {type(gaits).__name__}.")
    gaits = list(gaits)
    if not gaits or not all(isinstance(g, Gait) for g in gaits):
        raise InputError(
            "monte_carlo: gaits must be a non-empty list of jsphere.Gait (e.g. [acceleration(), braking()])."
        )
    return gaits


def _replay(params, gaits, mode, commands, reset, actuators, settings) -> Replay:
    """The commands a replay mode replays: `commands`, or the gaits' plan on the nominal robot
    sampled at `plan_rate`; the motors stop at its last time stamp."""
    if commands is None:
        nominal = simulate_gaits(params, gaits, reset=reset, rate=settings["plan_rate"])
        tsn = np.asarray(nominal.ts)
        u = np.asarray(nominal.K if mode == "torques" else nominal.chi_dot)
    else:
        tsn, u = np.asarray(commands[0], np.float64), np.asarray(commands[1], np.float64)
        Sampled(jnp.asarray(tsn), jnp.asarray(u))  # validates the table
        if tsn[0] != 0.0 or u.shape[1:] != (params.n_wheels,):
            raise ValueError(
                f"monte_carlo: commands must start at t = 0 and have {params.n_wheels} columns; got t0 = {tsn[0]}, shape {u.shape}."
            )
    # the motors stop when the plan ends: a jump to zero at its last time stamp
    tsn, u = np.concatenate([tsn, tsn[-1:]]), np.concatenate([u, np.zeros_like(u[:1])])
    jump_ts = ()
    if actuators.delay_s == 0 and actuators.delay_sd == 0:  # jumps stay where the plan has them
        jump_ts = tuple(float(t) for t in tsn[1:][np.diff(tsn) == 0] if t > 0)
    plan = (jnp.asarray(tsn, params.R0.dtype), jnp.asarray(u, params.R0.dtype))
    return Replay(mode, plan, actuators, settings["settle"], settings["max_steps"], jump_ts)


def _replay_record(replay: Replay, plan_rate: float, commands: bool) -> tuple:
    """What of a replay changes a study's results, for its fingerprint: the actuators, the plan's
    rate, the settling time, a hash of the given `commands` (None for the gaits' own plan) and
    the step limit."""
    cmd_fp = None
    if commands:
        ts, u = replay.plan
        cmd_fp = hashlib.sha256(np.ascontiguousarray(u).tobytes() + np.ascontiguousarray(ts).tobytes()).hexdigest()
    return (replay.actuators, plan_rate, replay.settle, cmd_fp, replay.max_steps)


def _solver_record(solver, gait_max_steps: int | None) -> tuple:
    """The solver settings that change a study's results beyond its tolerances and the replay's
    step limit, for its fingerprint: a solver other than the default and gait mode's step limit
    where it is not `simulate_gaits`' default. Empty for the defaults, so that a study's
    fingerprint does not depend on whether they were given."""
    record = ()
    if solver is not None and not eqx.tree_equal(solver, default_solver()):
        record += (("solver", repr(solver)),)
    if gait_max_steps is not None and gait_max_steps != SolverOptions().max_steps:
        record += (("max_steps", gait_max_steps),)
    return record


@dataclasses.dataclass(frozen=True)
class _Run:
    """A checked study laid out in batches: `n` trials with seed `seed` in `n_batches` batches of
    `batch_size` (a multiple of `CHUNK` times the number of local devices); this process
    computes the batches `mine`, and with a `folder` writes them there. `fingerprint`
    identifies the study in its folder's manifest; `program` the compiled batch (the study
    but its seed, and the devices)."""

    trials: Trials
    n: int
    seed: int
    batch_size: int
    n_batches: int
    mine: tuple[int, ...]
    folder: StudyFolder | None
    fingerprint: str
    program: str

    @classmethod
    def create(
        cls, params, gaits, spec, settings, *, reset, rtol, atol, solver, gait_max_steps, replay, commands, out, process
    ) -> "_Run":
        n, seed = settings["n"], settings["seed"]
        devices = jax.local_devices()
        unit = CHUNK * len(devices)
        B = int(math.ceil(max(1, min(settings["batch_size"], n)) / unit) * unit)
        n_batches = int(math.ceil(n / B))
        mesh = None
        if len(devices) > 1:  # each device runs its share of every batch
            from jax.sharding import Mesh

            mesh = Mesh(np.array(devices), ("trials",))
        trials = Trials(
            params,
            gaits,
            Draws.from_spec(spec, params.R0.dtype),
            jnp.asarray(seed, jnp.uint32),
            reset,
            rtol,
            atol,
            settings["Omega0_sd"],
            replay,
            mesh,
            solver,
            gait_max_steps if replay is None else SolverOptions().max_steps,
        )
        record = () if replay is None else _replay_record(replay, settings["plan_rate"], commands)
        options = (reset, "gait" if replay is None else replay.mode, repr(record), settings["Omega0_sd"])
        options += _solver_record(solver, gait_max_steps if replay is None else None)
        fp = fingerprint(params, gaits, spec, seed, B, options, rtol, atol)
        program = f"{fingerprint(params, gaits, spec, 0, B, options, rtol, atol)}|{len(devices)}"
        mine = tuple(k for k in range(n_batches) if k % process[1] == process[0])  # all of them on one host
        folder = StudyFolder(Path(out), B, len(spec)) if out is not None else None
        return cls(trials, n, seed, B, n_batches, mine, folder, fp, program)

    def compute(self, k: int) -> dict:
        """Batch `k`, written to the folder (if any)."""
        idx = jnp.arange(k * self.batch_size, (k + 1) * self.batch_size, dtype=jnp.int32)
        part = dict(zip(BATCH_KEYS, (np.asarray(a) for a in jax.device_get(run_batch(self.trials, idx)))))
        if self.folder is not None:
            self.folder.save_batch(k, part)
        return part


def _own_batches(run: _Run, progress: Progress) -> list[dict | None]:
    """The batches of the study, with this process's ones filled in: read from the folder, else
    (or if the file is corrupt) computed. The first batch computed (which compiles) comes
    first, then a bar over the others, whose rate starts after it."""
    parts: list = [None] * run.n_batches
    for k in run.mine:
        if run.folder is not None and run.folder.has_batch(k):
            parts[k] = run.folder.load_batch(k, stacklevel=3)
    todo = [k for k in run.mine if parts[k] is None]
    if not todo:
        return parts
    trials = [min(run.batch_size, run.n - k * run.batch_size) for k in todo]
    if len(todo) < len(run.mine):
        progress.say(f"{_PROGRESS} {len(run.mine) - len(todo)} batch(es) read from {run.folder.path}")
    with progress.compiling("montecarlo", run.program, f"{_PROGRESS} batch 1/{len(todo)}"):
        parts[todo[0]] = run.compute(todo[0])
    t0 = last = time.perf_counter()
    with progress.bar(sum(trials), "jsphere montecarlo", "trial", initial=trials[0]) as bar:
        for count, k in enumerate(todo[1:], start=1):
            parts[k] = run.compute(k)
            bar.update(trials[count])
            now = time.perf_counter()
            if now - last >= _LINE_S or count + 1 == len(todo):
                last = now
                rate = sum(trials[1 : count + 1]) / (now - t0)
                left = sum(trials[count + 1 :]) / rate
                progress.step(
                    f"{_PROGRESS} batch {count + 1}/{len(todo)}  {sum(trials[: count + 1])}/{sum(trials)} trials  "
                    f"{rate:,.0f} trials/s  eta {left:,.0f} s"
                )
    return parts


def _other_batches(run: _Run, parts: list, wait_timeout: float) -> None:
    """Fill in the other processes' batches from the shared folder, waiting up to `wait_timeout`
    s for each to appear; one that cannot be read is computed here (the same bytes as its
    owner's)."""
    deadline = time.monotonic() + wait_timeout
    for k in range(run.n_batches):
        while parts[k] is None:
            if run.folder.has_batch(k):
                parts[k] = run.folder.load_batch(k, stacklevel=3)
                if parts[k] is None:
                    parts[k] = run.compute(k)
            elif time.monotonic() > deadline:
                raise TimeoutError(
                    f"monte_carlo: batch {k} ({run.folder.batch_path(k)}) did not appear within "
                    f"{wait_timeout} s; is every process running?"
                )
            else:
                time.sleep(_POLL_S)


def _result(run: _Run, parts: list[dict], elapsed_s: float) -> MonteCarloResult:
    """The study's outcome: the batches joined, cut to `n` trials."""
    cat = {key: np.concatenate([p[key] for p in parts])[: run.n] for key in parts[0]}
    samples = {name: cat["vals"][:, j] for j, name in enumerate(run.trials.draws.names)}
    return MonteCarloResult(
        n=run.n,
        seed=run.seed,
        samples=samples,
        x_final=cat["x"],
        y_final=cat["y"],
        speed_final=cat["speed"],
        status=cat["status"],
        gamma3_sd_after=cat["gamma3_sd"],
        elapsed_s=elapsed_s,
        reject_code=cat["reject"],
    )
