"""`jsphere plan`: a rest-to-rest manoeuvre within motor limits, as a CSV of wheel commands
(docs/planning.md)."""

from __future__ import annotations

import sys
from pathlib import Path

from .options import progress

NAME = "plan"
EXAMPLES = """
  jsphere plan --to 0.8 -0.5 --heading 1.0 --out plan.csv
  jsphere plan --to 0.5 0 --max-torque 0.05 --max-time 8 --restarts 32 --no-plots --out plan.csv
  jsphere plan --to 0.8 0 --rate 100 --commands commands.csv --command-kind chi_dot --out plan.csv
  jsphere plan --to 0.6 0.3 --robust fit.json --samples 64 --quantile 0.95 --out robust.csv
"""


def add_parser(sub) -> None:
    pp = sub.add_parser(
        NAME,
        help="plan a rest-to-rest manoeuvre to (X, Y) within motor limits; CSV of wheel commands",
        description="Plan a rest-to-rest manoeuvre from rest at the origin to (X, Y) [m], optionally with a final "
        "heading, within motor limits, by gradients through the gait dynamics (docs/planning.md). Writes the "
        "wheel commands as CSV, a JSON report and a figure; a plan that cannot meet the request is still "
        "written (exit 3).",
    )
    pp.add_argument(
        "--to",
        nargs=2,
        type=float,
        required=True,
        metavar=("X", "Y"),
        help="target position [m] (robot starts at rest at the origin)",
    )
    pp.add_argument("--heading", type=float, help="final platform heading [rad] (default: free)")
    pp.add_argument("--max-torque", help="wheel torque limit [N m] (default 0.1; 'none' for no limit)")
    pp.add_argument("--max-wheel-speed", help="wheel speed limit [rad/s] (default 20)")
    pp.add_argument("--max-tilt", help="platform tilt limit [rad] (default 0.35)")
    pp.add_argument("--max-torque-rate", help="torque rate limit [N m/s] (default 1)")
    pp.add_argument("--max-time", type=float, help="longest manoeuvre [s] (default 12)")
    pp.add_argument("--energy-weight", type=float, default=0.0, help="cost per joule of motor energy (default 0)")
    pp.add_argument("--time-weight", type=float, default=1e-3, help="cost per second of duration (default 1e-3)")
    pp.add_argument("--rate", type=float, default=1000.0, help="rows per second of the CSV (default 1000)")
    pp.add_argument("--restarts", type=int, default=16, help="random restarts, the best is kept (default 16)")
    pp.add_argument("--seed", type=int, default=0, help="seed of the restarts (default 0)")
    pp.add_argument("--params", help="a parameter file (.toml or .json) instead of the paper's robot")
    pp.add_argument(
        "--out",
        default="plan.csv",
        help="CSV of t, K_i, chi_dot_i, x, y, gamma_1..3, heading, tilt (default plan.csv); .json and .png beside it",
    )
    pp.add_argument(
        "--commands",
        metavar="FILE",
        help="also write the commands for the robot as an inputs table at --rate: t, chi_dot_1..N or t, K_1..N "
        "(docs/lab.md), the table that `jsphere convert --inputs` reads",
    )
    pp.add_argument(
        "--command-kind",
        choices=("chi_dot", "K"),
        default="chi_dot",
        help="the commands' family: wheel speeds chi_dot [rad/s] or axle torques K [N m] (default chi_dot)",
    )
    pp.add_argument("--no-plots", action="store_true", help="skip the figure")
    rb = pp.add_argument_group("robust to the robot's uncertainty (docs/planning.md)")
    rb.add_argument(
        "--robust",
        metavar="FILE",
        help="a fit result (fit.json: values, stderr, correlation) or a study (.toml: its [vary] table): plan for "
        "every robot it allows, executed as wheel speeds; plan.json gets miss_mc",
    )
    rb.add_argument("--samples", type=int, default=64, help="parameter sets drawn for the robust search (default 64)")
    rb.add_argument(
        "--quantile",
        type=float,
        default=0.95,
        help="the search minimises the mean loss of the drawn sets above this quantile (default 0.95; 0: all)",
    )
    rb.add_argument(
        "--check-samples",
        type=int,
        default=1000,
        help="fresh parameter sets on which miss_mc compares the nominal and the robust plan (default 1000)",
    )
    pp.add_argument("--no-cache", action="store_true", help="do not use the persistent compilation cache")


def run(args) -> int:
    import math

    from .._runtime.errors import ExitCode
    from .._runtime.files import atomic_write_json, check_output
    from ..model.params import RobotParams
    from ..planning.plan import Objective, plan
    from ..solve.options import SolverOptions

    out = Path(args.out)
    writes = [out.with_suffix(".json"), *([] if args.no_plots else [out.with_suffix(".png")])]
    if args.commands:
        if Path(args.commands).resolve() in {p.resolve() for p in [out, *writes]}:
            from .._runtime.errors import InputError

            raise InputError(
                f"--commands {args.commands}: the plan writes that file itself; give the commands another name."
            )
        writes.append(Path(args.commands))
    check_output(
        out,
        writes=writes,
        inputs={"the parameter file (--params)": args.params, "the uncertainty file (--robust)": args.robust},
        example=str(Path(args.out) / "plan.csv"),
    )
    limits = _limits(args)
    params = RobotParams.load(args.params) if args.params else RobotParams.paper()
    obj = Objective(energy=args.energy_weight, time=args.time_weight)
    uncertainty, params = _uncertainty(args) if args.robust else (None, params)
    options = SolverOptions(programs=args.programs)  # the verifications' program kept for the next run
    pl = plan(
        params,
        tuple(args.to),
        heading=args.heading,
        limits=limits,
        objective=obj,
        restarts=args.restarts,
        rate=args.rate,
        seed=args.seed,
        allow_infeasible=True,
        progress=progress(args),
        options=options,
    )
    robust = _robust(args, params, uncertainty, limits, obj, pl, options) if args.robust else None
    pl = robust.plan if robust else pl
    print(pl.summary())
    pl.to_csv(out)
    info = {
        "feasible": pl.feasible,
        "shortfall": pl.shortfall,
        "target": [None if math.isnan(v) else v for v in pl.target.tolist()],
        "duration_s": pl.duration,
        "errors": pl.errors,
        "limits": pl.limits_report,
        "iterations": pl.iterations,
        "elapsed_s": pl.elapsed_s,
        "restarts": pl.restarts,
        "rate_hz": pl.rate,
    }
    if robust:
        info["miss_mc"] = robust.miss_mc
        info["robust"] = robust.to_json()
    atomic_write_json(out.with_suffix(".json"), info)
    written = [out, out.with_suffix(".json")]
    if args.commands:
        pl.write_commands(args.commands, args.command_kind, args.rate)
        written.append(Path(args.commands))
    if not args.no_plots:
        from ..plots import plan_figure

        plan_figure(pl, out.with_suffix(".png"))
        written.append(out.with_suffix(".png"))
    print(f"wrote {', '.join(str(p) for p in written)}")
    if not pl.feasible:
        print(
            "jsphere plan: WARNING: the request cannot be met within the limits; the files hold the best plan "
            "found: " + "; ".join(pl.shortfall),
            file=sys.stderr,
        )
        return ExitCode.INFEASIBLE
    return ExitCode.OK


def _limits(args):
    """The `Limits` of the options (a limit given as 'none', 'off' or 'inf' is switched off)."""
    from .._runtime.errors import InputError
    from ..planning.plan import Limits

    none = {"none", "off", "inf"}
    lim_kw = {}
    for name in ("max_torque", "max_wheel_speed", "max_tilt", "max_torque_rate"):
        v = getattr(args, name)
        if v is not None:
            try:
                lim_kw[name] = None if str(v).lower() in none else float(v)
            except ValueError:
                raise InputError(f"--{name.replace('_', '-')} {v}: expected a number or 'none' (no limit).") from None
    if args.max_time is not None:
        lim_kw["max_time"] = float(args.max_time)
    return Limits(**lim_kw)


def _robust(args, params, uncertainty, limits, obj, nominal, options):
    """`plan_robust` for `--robust FILE`, from the nominal plan; prints its summary."""
    from ..planning.robust import plan_robust

    robust = plan_robust(
        params,
        tuple(args.to),
        uncertainty,
        heading=args.heading,
        limits=limits,
        objective=obj,
        samples=args.samples,
        quantile=args.quantile,
        check_samples=args.check_samples,
        restarts=min(args.restarts, 4),
        rate=args.rate,
        seed=args.seed,
        progress=progress(args),
        nominal=nominal,
        options=options,
    )
    print(robust.summary())
    return robust


def _uncertainty(args):
    """The `Uncertainty` of `--robust` and the nominal parameters: a fit result's estimate and
    covariance (its `params` unless `--params` is given), or a study's `vary` table (its
    parameters unless `--params` is given)."""
    from .._runtime.errors import InputError
    from .._runtime.files import read_mapping
    from ..model.params import RobotParams
    from ..planning.uncertainty import Uncertainty

    path = Path(args.robust)
    if path.suffix.lower() == ".toml":
        from ..montecarlo.study import check_vary, load_study

        study = load_study(path)
        params = RobotParams.load(args.params) if args.params else study["params"]
        try:
            entries = check_vary(params, study["kwargs"]["vary"])
        except ValueError as e:
            raise InputError(f"{path}: {e}") from None
        unc = Uncertainty.from_vary(entries, source=str(path))
        return unc, unc.nominal(params)
    if path.suffix.lower() != ".json":
        raise InputError(f"--robust {path}: expected a fit result (.json) or a Monte-Carlo study (.toml).")
    fit = read_mapping(path)
    params = RobotParams.load(args.params) if args.params else RobotParams.load(path)
    unc = Uncertainty.from_fit(fit, source=str(path))
    return unc, unc.nominal(params)
