"""`jsphere compare`: a model scored on captured trials it was not fitted to (docs/lab.md)."""

from __future__ import annotations

from .._runtime.errors import ExitCode
from .options import json_result

NAME = "compare"
EXAMPLES = """
  jsphere compare held_out/*.csv --params fit.json --out compare.json
  jsphere compare trial_07.csv trial_08.csv --params robot.toml --no-plots --out compare.json
"""


def add_parser(sub) -> None:
    cp = sub.add_parser(
        NAME,
        help="score a model on captured trials: fit %%, whiteness of the residuals (docs/lab.md)",
        description="Simulate each trial with the given parameters from its own initial pose (its initial "
        "velocities estimated as the fit estimates them) and score it: the normalised fit "
        "100 (1 - |y - y_hat| / |y - mean(y)|) of x, y and the orientation, the residuals' autocorrelation (the "
        "fraction of lags outside the 99 % band, and the Ljung-Box test) and their cross-correlation with the "
        "inputs, per trial and overall, and a verdict: 'consistent' (exit 0) when the residuals of every trial "
        "and channel are white, 'model error' (exit 6) when they are correlated in time, 'capture defects' "
        "(exit 6) when they are white but more than 5 %% of a trial's frames were set aside. Writes compare.json "
        "(with the top-level 'verdict') and a figure per trial.",
    )
    cp.add_argument("trials", nargs="+", metavar="TRIAL", help="trial CSV files or folders of them (docs/capture.md)")
    cp.add_argument(
        "--params", required=True, metavar="FILE", help="the model: a fit.json or a parameter file (.toml or .json)"
    )
    cp.add_argument(
        "--out", default="compare.json", help="result JSON (default compare.json); the figures go beside it"
    )
    cp.add_argument("--lags", type=int, default=25, help="largest lag of the correlations [samples] (default 25)")
    cp.add_argument(
        "--fit-time-offset",
        action="store_true",
        help="estimate each trial's clock offset too (as jsphere fit --fit-time-offset)",
    )
    cp.add_argument(
        "--max-time-offset", type=float, default=0.5, metavar="SECONDS", help="the largest clock offset [s]"
    )
    cp.add_argument(
        "--loss",
        choices=("l2", "huber", "cauchy", "soft_l1"),
        default="cauchy",
        help="the loss of the initial-velocity estimate, as jsphere fit's (default cauchy): frames it sets aside "
        "(ghost frames, marker swaps) are counted and listed per trial under 'outliers' and left out of the "
        "whiteness test; the fit scores are on every frame",
    )
    cp.add_argument("--no-plots", action="store_true", help="skip the figures")


def run(args) -> int:
    from .._runtime.files import check_output
    from ..capture.trial import read_trials
    from ..identify.compare import compare
    from ..model.params import RobotParams

    out, inputs = json_result(args)
    check_output(out, inputs=inputs, example=str(out / "compare.json"))
    params = RobotParams.load(args.params)
    trials = read_trials(args.trials)
    figures = [] if args.no_plots else [out.with_name(f"{out.stem}_{figure_name(t.name)}.png") for t in trials]
    check_output(out, writes=figures, inputs=inputs, example=str(out / "compare.json"))
    res = compare(
        params,
        trials,
        lags=args.lags,
        fit_time_offset=args.fit_time_offset,
        max_time_offset=args.max_time_offset,
        loss=args.loss,
    )
    written = res.save(out)
    if not args.no_plots:
        from ..plots import compare_figure

        written += [compare_figure(t, f) for t, f in zip(res.trials, figures)]
    print(res.table())
    for t in res.trials:
        if t["outliers"]["count"]:
            print(
                f"{t['name']}: {t['outliers']['count']} of {t['measured']} frames set aside by the {args.loss} loss "
                "(left out of the whiteness test; the fit scores include them)"
            )
    print(f"wrote {', '.join(str(p) for p in written)}")
    print(res.headline())
    return ExitCode.OK if res.consistent else ExitCode.MISFIT


def figure_name(name: str) -> str:
    """A trial's name as part of a file name (letters, digits, `-`, `_`, `.`; others `_`)."""
    return "".join(c if c.isalnum() or c in "-_." else "_" for c in name) or "trial"
