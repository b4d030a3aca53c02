"""`jsphere montecarlo`: a Monte-Carlo study described by a TOML file
(`jsphere.montecarlo.study.load_study`), resumable in its output folder."""

from __future__ import annotations

import sys
from pathlib import Path

NAME = "montecarlo"
#: what an interrupted study keeps
RESUMES = "the finished batches are kept in the --out folder: rerun the same command to resume"


def add_parser(sub) -> None:
    mc = sub.add_parser(NAME, help="a Monte-Carlo study of the gaits (TOML description; see load_study)")
    mc.add_argument("config", help="study description (.toml)")
    mc.add_argument("--trials", type=int, help="number of trials (overrides the file)")
    mc.add_argument("--out", default="study", help="output folder; a killed study resumes there (default: ./study)")
    mc.add_argument("--no-plots", action="store_true", help="skip the figure")
    mc.add_argument("--no-cache", action="store_true", help="do not use the persistent compilation cache")


def run(args) -> int:
    import warnings

    from .._runtime.checks import whole
    from .._runtime.errors import InputError, SolverFailure
    from .._runtime.files import atomic_write_json, check_output, dumps_json
    from ..gaits.gaits import simulate_gaits
    from ..montecarlo.run import monte_carlo
    from ..montecarlo.study import load_study

    def one_line(message, category, filename, lineno, file=None, line=None):
        print(f"jsphere montecarlo: warning: {message}", file=sys.stderr, flush=True)

    out = Path(args.out)
    writes = [out / name for name in ("stats.json", "manifest.json", *(() if args.no_plots else ("stop_points.png",)))]
    check_output(out, folder=True, writes=writes, inputs={"the study file": args.config})
    study = load_study(args.config)
    n = whole("jsphere montecarlo", "--trials", args.trials, 1) if args.trials is not None else study["n"]
    with warnings.catch_warnings():
        warnings.showwarning = one_line
        res = monte_carlo(study["params"], study["gaits"], n=n, out=out, progress=True, **study["kwargs"])
    st = res.stats()
    planned = simulate_gaits(study["params"], study["gaits"], reset=study["kwargs"]["reset"])
    st["planned_stop_m"] = [float(planned.x[-1]), float(planned.y[-1])]
    atomic_write_json(out / "stats.json", st)
    print(dumps_json(st), end="")
    why = _report(st, n)
    if st["n_ok"] and not args.no_plots:
        from ..plots import montecarlo_figure

        montecarlo_figure(res, out / "stop_points.png", planned=st["planned_stop_m"])
    print(
        f"{n} trials ({st['n_ok']} ok, {st['n_failed']} failed, {st['n_rejected']} rejected) in {res.elapsed_s:.1f} s; "
        f"results in {out}/"
    )
    if not st["n_ok"]:
        if st["n_rejected"] == n:
            raise InputError(f"every draw was rejected ({why}); no statistics. Check the [vary] distributions.")
        raise SolverFailure(
            f"no trial succeeded ({st['n_failed']} solver failures, {st['n_rejected']} rejected draws); no statistics."
        )
    return 0


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
