"""Monte-Carlo studies of gait motions (`monte_carlo`): the arguments checked and the study laid
out in batches (`prepare`, a `_Run`), the batches missing from its folder computed (`_batches`)
on this process's devices or, with JAX's distributed runtime, on every process's
(`distributed`), and joined into a `MonteCarloResult`.
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
from .._runtime.cores import split_devices, trial_mesh
from .._runtime.errors import InputError
from .._runtime.progress import Progress
from ..controls import Sampled
from ..gaits.gaits import Gait, simulate_gaits
from ..model.params import RobotParams
from ..model.state import Flat
from ..planning.tracking.evaluate import Conditions
from ..solve.options import SolverOptions, default_solver, solver_options, unused
from ..solve.simulate import tolerances
from .batch import CHUNK as CHUNK
from .batch import ClosedLoop, Replay, Trials, run_batch
from .distributed import batch_template, gather_batch, global_indices, share_from_process_0, start_distributed
from .options import MAX_STEPS as MAX_STEPS
from .options import Distributed, StudyOptions, study_arguments
from .result import REJECTED as REJECTED
from .result import ComputeTime, MonteCarloResult
from .sampling import MAX_REDRAWS as MAX_REDRAWS
from .sampling import REASONS as REASONS
from .sampling import Actuators, Uncertainty
from .store import BATCH_KEYS, StudyFolder, fingerprint
from .study import check_closed_loop, check_commands, check_feedback, check_track, check_vary

#: the progress lines' prefix
_PROGRESS = "jsphere montecarlo:"
#: seconds between two progress lines where no bar is drawn
_LINE_S = 10.0


def monte_carlo(
    params: RobotParams,
    gaits: Sequence[Gait],
    *,
    vary: Mapping[str, Sequence],
    n: int,
    options: StudyOptions | None = None,
    solver: SolverOptions | None = None,
    out: str | os.PathLike | None = None,
    progress: bool | None = None,
    distributed: bool | Distributed | None = None,
    **deprecated,
) -> MonteCarloResult:
    """Run the gaits `n` times with parameters drawn from `vary`; return the stop points.

    **Arguments:**
    - `params`: the nominal `RobotParams`; `gaits`: a list as for `simulate_gaits`.
    - `vary`: `{name: ("normal", mean, sd) | ("uniform", low, high)}` with names as in
      `jsphere fit --free` (`"j"`, `"I[0,0]"`, `"r_m[2]"`, `"R_m"`: `|r_m|`, keeping its
      direction). Trial `i` draws from `fold_in(PRNGKey(seed), i)`: the same study whatever the
      batch size, devices or processes. A draw that breaks a rule of `RobotParams`
      (`jsphere.model.params.RULES`) is not simulated: its status is `REJECTED`, counted by
      `stats()` by the rule it breaks. A distribution followed by `"truncate"` is drawn again
      instead while the draw is invalid (at most `MAX_REDRAWS` times).
    - `n`: the number of trials; `options`: a `StudyOptions` (each field documented there).
    - `solver`: a `SolverOptions`; its `rtol`, `atol`, `max_steps` and `solver` are used
      (tolerances as `simulate`'s). A failed trial is reported in `status` (no `throw`) and
      every trial takes its own steps (no `batch_steps`); `adjoint` set is an error.
    - `out`: a folder. Each finished batch is written there atomically, with a manifest; the
      same call after an interruption resumes (a folder of a different study is refused), and
      with a larger `n` computes only the new batches. A batch file that cannot be read is
      recomputed, with a `MonteCarloWarning` naming it; a killed run's temporary files go.
    - `progress`: `None` (default): a progress bar on stderr when it is a terminal; `True`: the
      bar, or a line every few seconds; `False`: none. The first batch (it compiles) is apart.
    - `distributed`: run the study on every device of every process of a JAX multi-process
      job, all calling `monte_carlo` with the same arguments (`jsphere.montecarlo.distributed`):
      process 0 writes `out`, and every process returns the whole study, bitwise that of one
      process. `True` or a `Distributed` starts JAX's distributed runtime unless it is running
      (`start_distributed`; JAX starts it only before it makes any array); `None` (default):
      distributed when it runs with several processes.
    - `**deprecated`: the keywords that moved into `options` (`seed=`, ...), `solver` (`rtol=`,
      `atol=`; `options=SolverOptions(...)`) and `distributed` (`coordinator=`, ...) work for
      one release, with a `DeprecationWarning` naming the new spelling.

    Every argument is checked before any work; a bad one raises `InputError` naming it.

    Returns a `MonteCarloResult` (`x_final`, `y_final`, ... arrays of length `n`; `.stats()`).
    """
    options, solver, distributed = study_arguments("monte_carlo", options, solver, distributed, deprecated)
    distributed = start_distributed(distributed)
    run = prepare(params, gaits, vary=vary, n=n, options=options, solver=solver, out=out, distributed=distributed)
    t_start = time.perf_counter()
    parts = _batches(run, Progress(progress if run.writer else False))
    res = _result(run, parts, time.perf_counter() - t_start)
    if run.folder is not None and run.writer:
        run.folder.write_stats(res.stats())
    return res


def prepare(
    params: RobotParams,
    gaits: Sequence[Gait],
    *,
    vary: Mapping[str, Sequence],
    n: int,
    options: StudyOptions,
    solver: SolverOptions | None = None,
    out: str | os.PathLike | None = None,
    distributed: bool = False,
) -> "_Run":
    """Check the arguments of a study (those of `monte_carlo`, `options` a `StudyOptions`) and
    lay it out in batches (`_batch_size`), over this process's devices or (`distributed`) every
    process's."""
    n = whole("monte_carlo", "n", n, 1)
    o = options.checked("monte_carlo")
    unused(solver, where="monte_carlo", adjoint="monte_carlo does not differentiate its solves")
    # the replay modes' step limit: `max_steps` where given, else `solver.max_steps`, else `MAX_STEPS`
    opts = solver_options(solver, where="monte_carlo", max_steps=o.max_steps).or_defaults(max_steps=MAX_STEPS)
    o = dataclasses.replace(o, max_steps=opts.max_steps)
    for name, tol in (("rtol", opts.rtol), ("atol", opts.atol)):
        if tol is not None:
            real("monte_carlo", name, tol, strict=True)
    actuators = _check_actuators(o)
    spec = check_vary(params, vary)
    rtol, atol = tolerances(params.R0.dtype, opts.rtol, opts.atol, where="monte_carlo")
    gaits = _check_gaits(gaits)
    if o.track is not None:
        replay = _closed_loop(params, o, actuators)
    else:
        replay = None if o.mode == "gait" else _replay(params, gaits, o, actuators)
    # gait mode's step limit: simulate_gaits' unless the solver sets one
    gait_max_steps = SolverOptions().max_steps if solver is None or replay is not None else solver.max_steps
    distributed = distributed and jax.process_count() > 1
    B = _batch_size(o.batch_size, n, out, distributed)
    # each device runs its share of every batch: locally, as many devices as divide it into whole chunks
    devices = jax.devices() if distributed else split_devices(B // CHUNK, jax.local_devices())
    mesh = trial_mesh(devices) if len(devices) > 1 else None
    draws, seed = _draws(spec, params.R0.dtype), jnp.asarray(o.seed, jnp.uint32)
    trials = Trials(
        params, gaits, draws, seed, o.reset, rtol, atol, o.Omega0_sd, replay, mesh, opts.solver, gait_max_steps
    )
    # the fingerprint: what of the options changes a study's results (the defaults leave it as it is)
    record = () if replay is None else _replay_record(replay, o.plan_rate, o.commands is not None)
    settings = (o.reset, o.mode if replay is None else replay.mode, repr(record), o.Omega0_sd)
    if opts.solver is not None and not eqx.tree_equal(opts.solver, default_solver()):
        settings += (("solver", repr(opts.solver)),)
    if gait_max_steps != SolverOptions().max_steps:
        settings += (("max_steps", gait_max_steps),)
    fp = fingerprint(params, gaits, spec, o.seed, B, settings, rtol, atol)
    program = f"{fingerprint(params, gaits, spec, 0, B, settings, rtol, atol)}|{len(devices)}"
    folder = StudyFolder(Path(out), B, len(spec)) if out is not None else None
    writer = not distributed or jax.process_index() == 0
    return _Run(trials, dict(vary), n, o.seed, B, -(-n // B), folder, fp, program, distributed, writer)


def _batch_size(batch_size: int, n: int, out, distributed: bool) -> int:
    """A study's batch size: `batch_size` (at most `n`) rounded up to whole chunks, or the one in
    the manifest of a study folder `out` that exists (process 0's, in a distributed run), which
    an extended study, workers on other nodes and `--gather` keep."""
    B = -(-max(1, min(batch_size, n)) // CHUNK) * CHUNK
    if out is None:
        return B
    recorded = StudyFolder.manifest_batch_size(out) if not distributed or jax.process_index() == 0 else None
    if distributed:
        recorded = int(share_from_process_0(np.int32(recorded or 0))) or None
    return recorded if recorded is not None and recorded % CHUNK == 0 else B


def _check_actuators(o: StudyOptions) -> Actuators:
    """The actuators of the study (ideal ones by default), with the options that gait mode does
    not take (actuators, commands) and `feedback` without `track` refused."""
    if o.mode == "gait" and (o.actuators is not None or o.commands is not None):
        what = "actuators apply to replayed commands" if o.actuators is not None else "`commands` are replayed"
        raise InputError(f"monte_carlo: {what}; use mode='torques' or 'wheel_speeds'.")
    if o.actuators is not None and not isinstance(o.actuators, Actuators):
        raise InputError(f"monte_carlo: actuators must be a jsphere.Actuators; got {type(o.actuators).__name__}.")
    if o.feedback is not None and o.track is None:
        raise InputError("monte_carlo: `feedback` sets up the closed loop of a `track` table; give `track`.")
    return o.actuators or Actuators()


def _check_gaits(gaits) -> list[Gait]:
    ok = isinstance(gaits, Sequence) and not isinstance(gaits, (str, bytes)) and len(gaits) > 0
    if not ok or not all(isinstance(g, Gait) for g in gaits):
        raise InputError(
            "monte_carlo: gaits must be a non-empty list of jsphere.Gait (e.g. [acceleration(), braking()])."
        )
    return list(gaits)


def _replay(params, gaits, o: StudyOptions, actuators: Actuators) -> Replay:
    """The commands a replay mode replays: `o.commands`, or the gaits' plan on the nominal robot
    sampled at `o.plan_rate`; the motors stop at its last time stamp."""
    if o.commands is None:
        nominal = simulate_gaits(params, gaits, reset=o.reset, rate=o.plan_rate)
        tsn, u = np.asarray(nominal.ts), np.asarray(nominal.K if o.mode == "torques" else nominal.chi_dot)
    else:
        tsn, u = np.asarray(o.commands[0], np.float64), np.asarray(o.commands[1], np.float64)
        Sampled(jnp.asarray(tsn), jnp.asarray(u))  # validates the table
        check_commands("monte_carlo: commands", tsn, u, params.n_wheels)
    # the motors stop when the plan ends: a jump to zero at its last time stamp
    tsn, u = np.concatenate([tsn, tsn[-1:]]), np.concatenate([u, np.zeros_like(u[:1])])
    keep = actuators.delay_s == 0 and actuators.delay_sd == 0  # jumps stay where the plan has them
    jump_ts = tuple(float(t) for t in tsn[1:][np.diff(tsn) == 0] if t > 0) if keep else ()
    plan = (jnp.asarray(tsn, params.R0.dtype), jnp.asarray(u, params.R0.dtype))
    return Replay(o.mode, plan, actuators, o.settle, o.max_steps, jump_ts)


def _closed_loop(params, o: StudyOptions, actuators: Actuators) -> ClosedLoop:
    """The closed loop of a feedback table `o.track` (`read_track_csv`'s dict) on a study's
    robots: its rows at their rate, the reference as flat states, the conditions of the
    evaluation from `o.feedback` (`check_feedback`), the actuators and the settling time."""
    track = o.track
    if o.mode != "torques" or o.commands is not None:
        raise InputError("monte_carlo: a `track` table commands torques; use mode='torques' and no `commands`.")
    check_closed_loop("monte_carlo", o.Omega0_sd, actuators)
    fb = check_feedback("monte_carlo", o.feedback or {})
    h = check_track("monte_carlo: track", track, params.n_wheels)
    t, K_ff, G = (np.asarray(track[k], np.float64) for k in ("t", "K_ff", "G"))
    dt = params.R0.dtype
    ref = np.zeros((len(t), Flat.size + params.n_wheels))
    ref[:, Flat.q_shell] = [1.0, 0.0, 0.0, 0.0]
    for name in ("q", "omega", "Omega", "x", "y"):
        ref[:, getattr(Flat, name)] = track[name]
    motors = {"gain_sd": actuators.gain_sd, "motor_delay_s": actuators.delay_s, "white_sd": actuators.white_sd}
    conditions = Conditions(**{k: v for k, v in fb.items() if k != "max_torque"}, **motors, settle=o.settle)
    K_ff, ref, G, target = (jnp.asarray(a, dt) for a in (K_ff, ref, G, [ref[-1, Flat.x], ref[-1, Flat.y]]))
    return ClosedLoop(h, K_ff, ref, G, target, conditions, fb["max_torque"], int(math.ceil(o.settle / h - 1e-9)))


def _draws(spec: Sequence[tuple], dtype) -> Uncertainty:
    """A study's distributions from the `[(name, kind, a, b, truncate)]` of `check_vary`, as
    arrays of `dtype` (no name varied: an empty distribution)."""
    ab = np.array([[a, b] for _, _, a, b, _ in spec], dtype=np.float64).reshape(len(spec), 2)
    names, kinds = tuple(e[0] for e in spec), tuple(e[1] for e in spec)
    truncate = jnp.asarray(np.array([e[4] for e in spec], dtype=bool))
    return Uncertainty(names, kinds, jnp.asarray(ab[:, 0], dtype), jnp.asarray(ab[:, 1], dtype), None, "vary", truncate)


def _replay_record(replay: Replay | ClosedLoop, plan_rate: float, commands: bool) -> tuple:
    """What of a replay changes a study's results, for its fingerprint: its settings and a hash of
    its given `commands` (None for the gaits' own plan) or of its closed loop's table."""
    digest = lambda *arrays: hashlib.sha256(b"".join(np.ascontiguousarray(a).tobytes() for a in arrays)).hexdigest()
    if isinstance(replay, ClosedLoop):
        table = digest(replay.K_ff, replay.ref, replay.G)
        return ("track", replay.ts_h, replay.conditions.to_json(), replay.max_torque, replay.n_settle, table)
    cmd_fp = digest(replay.plan[1], replay.plan[0]) if commands else None
    return (replay.actuators, plan_rate, replay.settle, cmd_fp, replay.max_steps)


@dataclasses.dataclass(frozen=True)
class _Run:
    """A checked study laid out in batches: `n` trials with seed `seed` in `n_batches` batches of
    `batch_size` (a multiple of `CHUNK`; computed as `padded` trials, whole chunks on every
    device), with `vary` as given; with a `folder`, batches are read from it and written to it
    (by the `writer`: process 0 of a `distributed` job, the only process otherwise).
    `fingerprint` identifies the study in its folder's manifest; `program` the compiled batch
    (the study but its seed, and the devices)."""

    trials: Trials
    vary: Mapping
    n: int
    seed: int
    batch_size: int
    n_batches: int
    folder: StudyFolder | None
    fingerprint: str
    program: str
    distributed: bool = False
    writer: bool = True

    @property
    def padded(self) -> int:
        """The trials computed per batch: `batch_size` rounded up to whole chunks on every device."""
        unit = CHUNK * (1 if self.trials.mesh is None else self.trials.mesh.devices.size)
        return -(-self.batch_size // unit) * unit

    def trials_of(self, k: int) -> int:
        """The trials of batch `k` that belong to the study (the last batch may hold more)."""
        return min(self.batch_size, self.n - k * self.batch_size)

    def compute(self, k: int) -> dict:
        """Batch `k`, written to the folder (if any, by the writer). In a distributed run every
        process computes its shard of the batch and gets the whole batch back."""
        lo, hi = k * self.batch_size, k * self.batch_size + self.padded  # the trials after the batch's are dropped
        start, t0 = time.time(), time.perf_counter()
        if self.distributed:
            out = gather_batch(run_batch(self.trials, global_indices(self.trials.mesh, lo, hi)))
        else:
            out = jax.device_get(run_batch(self.trials, jnp.arange(lo, hi, dtype=jnp.int32)))
        part = dict(zip(BATCH_KEYS, (np.asarray(a)[: self.batch_size] for a in out)))
        seconds = time.perf_counter() - t0
        if self.folder is not None and self.writer:  # the time record first: a batch file always has one
            self.folder.save_time(k, self.trials_of(k), start, seconds)
            self.folder.save_batch(k, part)
        return part


def _batches(run: _Run, progress: Progress) -> list[dict]:
    """The batches of a study: those in its folder, read by the writer (which opens the folder
    and removes a killed run's temporary files), then the others computed (`_compute`). In a
    distributed run process 0 shares what it read, or the refusal of its folder."""
    parts: list = [None] * run.n_batches
    refused = None
    if run.writer and run.folder is not None:
        try:
            run.folder.open(run.fingerprint, run.n, run.seed, run.vary)
            run.folder.remove_temporary_files(range(run.n_batches), others=True)
            parts = run.folder.load_batches(range(run.n_batches), stacklevel=3)
        except InputError as e:
            if not run.distributed:
                raise
            refused = e
    if run.distributed and share_from_process_0(np.int32(refused is not None)):
        if refused is not None:
            raise refused
        raise InputError(f"monte_carlo: process 0 could not use out = {run.folder.path}; its message says why.")
    done = share_from_process_0(np.array([p is not None for p in parts], np.int32)) if run.distributed else ()
    if np.any(done):
        template = batch_template(run.trials, run.padded, run.batch_size)
        for k in np.flatnonzero(done):
            got = parts[k] if run.writer else {key: np.zeros(a.shape, a.dtype) for key, a in template.items()}
            parts[k] = share_from_process_0({key: np.asarray(got[key], template[key].dtype) for key in BATCH_KEYS})
    _compute(run, parts, progress)
    return parts


def _compute(run: _Run, parts: list, progress: Progress) -> None:
    """Compute the batches missing from `parts` into them. The first batch computed (which
    compiles) comes first, then a bar over the others, whose rate starts after it."""
    todo = [k for k in range(run.n_batches) if parts[k] is None]
    if not todo:
        return
    trials = [run.trials_of(k) for k in todo]
    if len(todo) < run.n_batches and run.folder is not None:
        progress.say(f"{_PROGRESS} {run.n_batches - len(todo)} batch(es) read from {run.folder.path}")
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


def _result(run: _Run, parts: list[dict], elapsed_s: float) -> MonteCarloResult:
    """The study's outcome: the batches joined, cut to `n` trials; with a folder (read by the
    writer), the batches' compute time as recorded there."""
    timed = None
    if run.folder is not None and run.writer:
        timed = ComputeTime.of(run.folder.load_times(range(run.n_batches)))
    names = run.trials.draws.names
    return MonteCarloResult.of_batches(parts, names, run.n, run.seed, elapsed_s=elapsed_s, compute_time=timed)
