"""`jsphere montecarlo`: a Monte-Carlo study described by a TOML file (docs/montecarlo.md),
resumable in its output folder, on one process, every process of a JAX multi-process job
(`--distributed`), or independent jobs (`--worker`, then `--gather`)."""

from __future__ import annotations

import sys
from pathlib import Path

from .._runtime.errors import InputError, SolverFailure
from .options import progress, warnings_as_lines

NAME = "montecarlo"
EXAMPLES = """
  jsphere montecarlo examples/study_straight_line.toml --out study
  jsphere montecarlo examples/study_straight_line.toml --trials 100000 --seed 1 --batch-size 8192 --out study-1
  srun jsphere montecarlo study.toml --out /shared/study --distributed        # every task of a SLURM job
  jsphere montecarlo study.toml --out /shared/study --worker                   # in each job of an array
  jsphere montecarlo study.toml --out /shared/study --gather                   # once the workers are done
"""
#: `--claim-timeout`'s default [s] (`jsphere.montecarlo.workers.CLAIM_TIMEOUT`)
CLAIM_TIMEOUT_S = 3600.0
#: what an interrupted study keeps
RESUMES = "the finished batches are kept in the --out folder: rerun the same command to resume"


def add_parser(sub) -> None:
    mc = sub.add_parser(
        NAME,
        help="a Monte-Carlo study of the gaits, a command table or a feedback table (TOML study file; docs/montecarlo.md)",
        description='Run the gaits of a study file, or replay its command table (commands = "FILE", as written '
        'by plan --commands or design) or run its feedback table closed loop (track = "FILE", as written by '
        "track --out), many times with parameters drawn from its [vary] "
        "distributions (docs/montecarlo.md). Writes OUT/stats.json (stop points in jsphere's frame, metres), "
        "OUT/stop_points.png and the finished batches, from which a killed study resumes; prints a short "
        "summary.",
    )
    mc.add_argument("config", help="study description (.toml)")
    mc.add_argument("--trials", type=int, help="number of trials (overrides the file)")
    mc.add_argument("--seed", type=int, help="seed of the draws, in [0, 2**32) (overrides the file)")
    mc.add_argument("--batch-size", type=int, help="trials per compiled call (overrides the file; default 4096)")
    mc.add_argument("--out", default="study", help="output folder; a killed study resumes there (default: ./study)")
    mc.add_argument("--no-plots", action="store_true", help="skip the figure")
    mc.add_argument(
        "--frame",
        choices=("jsphere", "paper"),
        default="jsphere",
        help="frame of the figure: jsphere's (default, as stats.json) or the paper's figure frame (x_fig = -y, y_fig = x)",
    )
    many = mc.add_argument_group("several processes or jobs (docs/montecarlo.md, examples/cluster/)")
    how = many.add_mutually_exclusive_group()
    how.add_argument(
        "--distributed",
        action="store_true",
        help="one study on every process of a JAX multi-process job (SLURM, Open MPI, ... detected; else "
        "--coordinator, --num-processes, --process-id); process 0 writes OUT",
    )
    how.add_argument(
        "--worker",
        action="store_true",
        help="compute the batches of OUT that no other worker holds, then exit (no waiting); OUT shared by all",
    )
    how.add_argument(
        "--gather",
        action="store_true",
        help="join the batches of OUT: statistics and figure; reports the workers' compute time recorded in OUT "
        "(time_*.json) and, apart, the gather's own",
    )
    many.add_argument("--coordinator", metavar="HOST:PORT", help="with --distributed: process 0's address and a port")
    many.add_argument("--num-processes", type=int, metavar="N", help="with --distributed: the number of processes")
    many.add_argument("--process-id", type=int, metavar="I", help="with --distributed: this process's id, 0 .. N-1")
    many.add_argument(
        "--claim-timeout",
        type=float,
        default=CLAIM_TIMEOUT_S,
        metavar="S",
        help=f"with --worker: take over a batch claimed S seconds ago and still missing (default {CLAIM_TIMEOUT_S:.0f}; "
        "longer than a batch takes)",
    )


def run(args) -> int:
    from .._runtime.checks import real
    from .._runtime.files import check_output
    from ..montecarlo.distributed import start_distributed
    from ..montecarlo.options import Distributed
    from ..montecarlo.run import monte_carlo
    from ..montecarlo.workers import gather, work

    setup = {"--coordinator": args.coordinator, "--num-processes": args.num_processes, "--process-id": args.process_id}
    given = [name for name, v in setup.items() if v is not None]
    if given and not args.distributed:
        raise InputError(f"{NAME}: {', '.join(given)} set up a distributed run; add --distributed.")
    distributed = Distributed(args.coordinator, args.num_processes, args.process_id) if args.distributed else False
    if distributed:  # before the study file makes any JAX array
        start_distributed(distributed)
    out = Path(args.out)
    writes = [out / name for name in ("stats.json", "manifest.json", *(() if args.no_plots else ("stop_points.png",)))]
    check_output(out, folder=True, writes=writes, inputs={"the study file": args.config})
    params, gaits, study = study_of(args)
    with warnings_as_lines(NAME):
        if args.worker:
            timeout = real(NAME, "--claim-timeout", args.claim_timeout, unit="s")
            report = work(params, gaits, **study, out=out, claim_timeout=timeout, progress=progress(args))
            print(report.summary())
            return 0
        if args.gather:
            res = gather(params, gaits, **study, out=out)
        else:
            res = monte_carlo(params, gaits, **study, out=out, progress=progress(args), distributed=distributed)
    return _finish(args, params, gaits, study, res, out)


def study_of(args) -> tuple:
    """`(params, gaits, {"vary", "n", "options"})`: the study of the study file `args.config` with
    the flags that override its keys (`--trials`, `--seed`, `--batch-size`), checked under the
    flags' names."""
    import dataclasses

    from .._runtime.checks import whole
    from ..montecarlo.options import StudyOptions
    from ..montecarlo.study import load_study

    study = load_study(args.config)
    n = whole(NAME, "--trials", args.trials, 1) if args.trials is not None else study.n
    flags = {"seed": "--seed", "batch_size": "--batch-size"}
    fields = {f.name: f for f in dataclasses.fields(StudyOptions)}
    given = {
        k: fields[k].metadata["check"](NAME, f, getattr(args, k))
        for k, f in flags.items()
        if getattr(args, k) is not None
    }
    options = dataclasses.replace(study.options, **given)
    return study.params, study.gaits, {"vary": study.vary, "n": n, "options": options}


def _finish(args, params, gaits, study: dict, res, out: Path) -> int:
    """Write `stats.json` (with the planned stop) and the figure of a study's result `res`, print
    its summary; `InputError` or `SolverFailure` when no trial succeeded."""
    import jax

    from .._runtime.files import atomic_write_json
    from ..gaits.gaits import simulate_gaits

    if args.distributed and jax.process_index() != 0:
        return 0  # process 0 writes the files and the summary
    st, o, n = res.stats(), study["options"], study["n"]
    if o.track is not None:  # the table's last reference: where the controller holds the robot
        st["planned_stop_m"] = [float(o.track["x"][-1]), float(o.track["y"][-1])]
    elif o.commands is None:
        planned = simulate_gaits(params, gaits, reset=o.reset)
        st["planned_stop_m"] = [float(planned.x[-1]), float(planned.y[-1])]
    else:
        st["planned_stop_m"] = replayed_stop(params, o)
    atomic_write_json(out / "stats.json", st)
    why = _report(st, n)
    written = [out / "stats.json"]
    if st["n_ok"] and not args.no_plots:
        from ..plots import montecarlo_figure

        montecarlo_figure(res, out / "stop_points.png", planned=st["planned_stop_m"], frame=args.frame)
        written.append(out / "stop_points.png")
    print(summary(st, n, res.elapsed_s, written, gathered=res.compute_time if args.gather else None))
    if not st["n_ok"]:
        if st["n_rejected"] == n:
            raise InputError(f"every draw was rejected ({why}); no statistics. Check the [vary] distributions.")
        raise SolverFailure(
            f"no trial succeeded ({st['n_failed']} solver failures, {st['n_rejected']} rejected draws); no statistics."
        )
    return 0


def replayed_stop(params, options) -> list[float]:
    """Where the nominal robot stops under a study's command table: the table as it is (no
    actuator errors), the motors stopped at its last time, then the study's settling time."""
    import numpy as np

    from ..controls import Torques, WheelSpeeds
    from ..model.state import State
    from ..solve.simulate import simulate

    ts, u = options.commands
    ts, u = np.concatenate([ts, ts[-1:]]), np.concatenate([u, np.zeros_like(u[:1])])
    control = (Torques if options.mode == "torques" else WheelSpeeds).from_samples(ts, u)
    t1 = float(ts[-1]) + options.settle
    tr = simulate(params, State.at_rest(params), control, t1, max_steps=options.max_steps or 65536)
    return [float(tr.x[-1]), float(tr.y[-1])]


def summary(st: dict, n: int, elapsed_s: float, written, gathered=None) -> str:
    """A few lines for the terminal: the counts, the stop point's mean and sd [mm] in jsphere's
    frame, and the files. `elapsed_s`: this command's wall time. `gathered`: for `--gather`,
    the `ComputeTime` of the batches the workers recorded; the study's time is then theirs,
    and `elapsed_s` the gather's own."""
    counts = f"{st['n_ok']} ok, {st['n_rejected']} rejected, {st['n_failed']} failed"
    if gathered is None:
        lines = [f"jsphere montecarlo: {n} trials in {elapsed_s:.1f} s: {counts}"]
    else:
        lines = _gathered(gathered, n, counts) + [f"  gathered in {elapsed_s:.1f} s (joining the batch files)"]
    if st["n_ok"]:
        (mx, my), (sx, sy) = st["mean_xy_m"], st["sd_xy_m"]
        px, py = st["planned_stop_m"]
        lines += [
            f"  stop point (jsphere frame): mean ({1e3 * mx:.3f}, {1e3 * my:.3f}) mm, sd ({1e3 * sx:.3f}, "
            f"{1e3 * sy:.3f}) mm",
            f"  planned stop: ({1e3 * px:.3f}, {1e3 * py:.3f}) mm",
        ]
    lines.append(f"  wrote {', '.join(str(p) for p in written)}")
    return "\n".join(lines)


def _gathered(ct, n: int, counts: str) -> list[str]:
    """The lines of `summary` on the workers' computation (`ct`, a `ComputeTime`)."""
    if ct.recorded == 0:
        return [f"jsphere montecarlo: {n} trials (the batches' compute time is not recorded in the folder): {counts}"]
    some = "" if ct.recorded == ct.batches else f" ({ct.recorded} of {ct.batches} batches recorded)"
    return [
        f"jsphere montecarlo: {n} trials in {ct.sum_s:.1f} s of the workers' compute{some}: {counts}",
        f"  {ct.recorded} batch(es) by {ct.processes} process(es), {ct.span_s:.1f} s from the first batch's start "
        "to the last one's end",
    ]


def _report(st: dict, n: int) -> str:
    """Warn on stderr about the rejected draws and the failed solves of the statistics `st`;
    return why draws were rejected (`"reason: count; ..."`)."""
    why = "; ".join(f"{reason}: {k}" for reason, k in st["rejected"].items())
    if st["n_rejected"]:
        print(
            f"jsphere montecarlo: warning: {st['n_rejected']} of {n} draws rejected, not simulated (their parameters "
            f"break a rule of RobotParams): {why}. Narrow the distributions or truncate them (a last entry "
            f'"truncate", docs/montecarlo.md).',
            file=sys.stderr,
        )
    if st["n_failed"]:
        kinds = {"1": "reached max_steps", "2": "gave NaN or inf"}
        how = ", ".join(f"{k} {kinds.get(c, f'ended with status {c}')}" for c, k in st["failed_status"].items())
        print(
            f"jsphere montecarlo: warning: {st['n_failed']} of {n} trials failed in the solver ({how}); they are left "
            "out of the statistics.",
            file=sys.stderr,
        )
    return why
