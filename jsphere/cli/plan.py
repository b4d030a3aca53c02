"""`jsphere plan`: a rest-to-rest manoeuvre within motor limits, as a CSV of wheel commands
(docs/planning.md)."""

from __future__ import annotations

import sys
from pathlib import Path

from .._runtime.errors import ExitCode, InputError
from .options import options_of, progress, robot

NAME = "plan"
EXAMPLES = """
  jsphere plan --to 0.8 -0.5 --heading 1.0 --out plan.csv
  jsphere plan --to 0.5 0 --max-torque 0.05 --max-time 8 --no-plots --out plan.csv
  jsphere plan --to 0.5 0 --family gait --restarts 32 --out gait-plan.csv
  jsphere plan --to 0.8 0 --rate 100 --commands commands.csv --command-kind chi_dot --out plan.csv
  jsphere plan --to 0.8 0 --params fit.json --out plan.csv && jsphere track plan.csv --out track.csv
  jsphere plan --to 0.6 0.3 --robust fit.json --samples 64 --quantile 0.95 --out robust.csv
"""


def add_parser(sub) -> None:
    pp = sub.add_parser(
        NAME,
        help="plan a rest-to-rest manoeuvre to (X, Y) within motor limits; CSV of wheel commands",
        description="Plan a rest-to-rest manoeuvre from rest at the origin to (X, Y) [m], optionally with a final "
        "heading, within motor limits: the shortest one over free torque profiles (direct multiple shooting), or "
        "one of the paper's gaits (--family gait) (docs/planning.md). Writes the "
        "wheel commands as CSV, a JSON report (with the robot planned for, which jsphere track and animate use) "
        "and a figure. When the request cannot be met within the limits, the best plan found is still written "
        "but the --commands table is not (unless --write-infeasible), and the exit code is 3.",
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
    pp.add_argument(
        "--family",
        choices=("direct", "gait"),
        default="direct",
        help="direct: free torque profiles, the shortest manoeuvre within the limits (default); gait: the paper's "
        "tilt gaits, searched with --restarts (docs/planning.md). --robust plans with gaits",
    )
    pp.add_argument(
        "--restarts", type=int, default=16, help="random restarts of the gait search, the best is kept (default 16)"
    )
    pp.add_argument("--seed", type=int, default=0, help="seed of the restarts (default 0)")
    pp.add_argument(
        "--params",
        help="a parameter file (.toml or .json) instead of the paper's robot; recorded in the plan's JSON",
    )
    pp.add_argument(
        "--out",
        default="plan.csv",
        help="CSV of t, K_i, chi_dot_i, x, y, gamma_1..3, heading, tilt (default plan.csv); .json and .png beside it",
    )
    pp.add_argument(
        "--commands",
        metavar="FILE",
        help="also write the commands for the robot as an inputs table at --rate: t, chi_dot_1..N or t, K_1..N "
        "(docs/lab.md), the table that `jsphere convert --inputs` reads, and its record FILE.json beside it (the "
        "robot, feasibility); only for a feasible plan unless --write-infeasible",
    )
    pp.add_argument(
        "--write-infeasible",
        action="store_true",
        help="write the --commands table even when the plan cannot meet the request; its first line is then a "
        "comment '# NOT FEASIBLE: ...' naming what the plan misses",
    )
    pp.add_argument(
        "--command-kind",
        choices=("chi_dot", "K"),
        default="chi_dot",
        help="the commands' family: wheel speeds chi_dot [rad/s] or axle torques K [N m] (default chi_dot)",
    )
    pp.add_argument("--no-plots", action="store_true", help="skip the figure")
    _add_robust_flags(pp)


def _add_robust_flags(pp) -> None:
    """The flags of a plan robust to the robot's uncertainty."""
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


def run(args) -> int:
    from .._runtime.files import atomic_write_json, check_output
    from ..planning.plan import plan

    out = Path(args.out)
    writes = [out.with_suffix(".json"), *([] if args.no_plots else [out.with_suffix(".png")])]
    if args.commands:
        _check_commands_path(args.commands, [out, *writes])
        writes += [Path(args.commands), Path(args.commands).with_suffix(".json")]
    check_output(
        out,
        writes=writes,
        inputs={"the parameter file (--params)": args.params, "the uncertainty file (--robust)": args.robust},
        example=str(Path(args.out) / "plan.csv"),
    )
    request = _request(args)
    params = robot(args)
    source = str(args.params) if args.params else "the paper's robot (RobotParams.paper())"
    uncertainty = None
    if args.robust:
        uncertainty, params = uncertainty_of(args.robust, params if args.params else None)
        source = (
            f"{args.params} with the means of {args.robust}" if args.params else f"the nominal robot of {args.robust}"
        )
    request["options"] = None  # the verifications' program is kept for the next run (`fast_start`)
    pl = plan(params, tuple(args.to), allow_infeasible=True, **request)
    robust = _robust(args, params, uncertainty, pl, request) if args.robust else None
    pl = robust.plan if robust else pl
    print(pl.summary())
    pl.to_csv(out)
    info = pl.record(source)
    if robust:
        info["miss_mc"] = robust.miss_mc
        info["robust"] = robust.to_json()
    atomic_write_json(out.with_suffix(".json"), info)
    written = [out, out.with_suffix(".json")]
    note = ""
    if args.commands and (pl.feasible or args.write_infeasible):
        written += _write_commands(args, pl, out, info)
        note = "" if pl.feasible else f". {args.commands} is written, its first line '# {INFEASIBLE_MARK}: ...'"
    elif args.commands:
        note = _withhold_commands(Path(args.commands))
    if not args.no_plots:
        from ..plots import plan_figure

        plan_figure(pl, out.with_suffix(".png"))
        written.append(out.with_suffix(".png"))
    print(f"wrote {', '.join(str(p) for p in written)}")
    if not pl.feasible:
        print(
            "jsphere plan: WARNING: the request cannot be met within the limits; "
            f"{out} and {out.with_suffix('.json')} hold the best plan found: {'; '.join(pl.shortfall)}{note}",
            file=sys.stderr,
        )
        return ExitCode.INFEASIBLE
    return ExitCode.OK


#: the first line of a commands table written for a plan that cannot meet its request
INFEASIBLE_MARK = "NOT FEASIBLE"


def _check_commands_path(commands, others) -> None:
    """`InputError` for a `--commands` file that is one of the plan's own files, or whose record
    (the `.json` beside it) would be."""
    path = Path(commands)
    if path.suffix.lower() == ".json":
        raise InputError(
            f"--commands {commands}: the commands table is a CSV (its record {path.name} is written beside it); "
            "give a name ending in .csv."
        )
    own = {p.resolve() for p in others}
    if path.resolve() in own or path.with_suffix(".json").resolve() in own:
        raise InputError(
            f"--commands {commands}: the plan writes that file (or its record {path.with_suffix('.json').name}) "
            "itself; give the commands another name."
        )


def _write_commands(args, pl, out: Path, info: dict) -> list[Path]:
    """Write the `--commands` table (its first line a `# NOT FEASIBLE: ...` comment for a plan
    that cannot meet the request) and its record beside it: the plan it comes from, its kind
    and rate, feasibility and the robot (`planned_robot` reads it). Returns the files written."""
    from .._runtime.files import atomic_write_json

    path = Path(args.commands)
    comment = ""
    if not pl.feasible:
        comment = (
            f"{INFEASIBLE_MARK}: this plan does not meet its request ({'; '.join(pl.shortfall)}); written by "
            "jsphere plan --write-infeasible, not a plan to run on the robot as it is"
        )
    pl.write_commands(path, args.command_kind, args.rate, comment=comment)
    record = {
        "commands": path.name,
        "kind": args.command_kind,
        "rate_hz": args.rate,
        "plan": str(out),
        **{k: info[k] for k in ("feasible", "shortfall", "target", "duration_s", "params", "params_source")},
    }
    atomic_write_json(path.with_suffix(".json"), record)
    return [path, path.with_suffix(".json")]


def _withhold_commands(path: Path) -> str:
    """For a plan that cannot meet the request: no commands table. A table (and its record)
    left at `path` by an earlier run is removed, so that no file there holds commands this run
    did not give. Returns the sentence for the warning."""
    removed = []
    for p in (path, path.with_suffix(".json")):
        if p.is_file():
            p.unlink()
            removed.append(str(p))
    gone = f" (removed {' and '.join(removed)}, left there by an earlier run)" if removed else ""
    return (
        f". No commands were written to {path}{gone}: plan again with other limits or target, or add "
        "--write-infeasible to write them marked NOT FEASIBLE."
    )


def _limits(args):
    """The `Limits` of the flags (of `plan` and `design`; a limit given as 'none', 'off' or 'inf'
    is switched off)."""
    from ..planning.plan import Limits

    limits = {} if getattr(args, "max_time", None) is None else {"max_time": args.max_time}  # (design has none)
    for name in ("max_torque", "max_wheel_speed", "max_tilt", "max_torque_rate"):
        v = getattr(args, name)
        if v is not None:
            try:
                limits[name] = None if str(v).lower() in {"none", "off", "inf"} else float(v)
            except ValueError:
                raise InputError(f"--{name.replace('_', '-')} {v}: expected a number or 'none' (no limit).") from None
    return Limits(**limits)


def _request(args) -> dict:
    """The keywords of `plan` that the flags give (`--robust`'s in `_robust`)."""
    from ..planning.plan import Objective, PlanOptions

    # a robust plan starts from a nominal gait plan
    family = "gait" if args.robust else args.family
    return {
        "heading": args.heading,
        "limits": _limits(args),
        "objective": Objective(energy=args.energy_weight, time=args.time_weight),
        "plan_options": options_of(PlanOptions, args, family=family),
        "progress": progress(args),
    }


def _robust(args, params, uncertainty, nominal, request: dict):
    """The robust plan of `--robust FILE` (`plan` with the `RobustOptions` of its flags), from the
    nominal plan and its request; prints its summary."""
    from ..planning import plan as plan_module
    from ..planning.robust import RobustOptions

    options = options_of(RobustOptions, args, uncertainty=uncertainty, restarts=min(args.restarts, 4), nominal=nominal)
    robust = plan_module.plan(params, tuple(args.to), robust=options, **request)
    print(robust.summary())
    return robust


def uncertainty_of(path, params=None):
    """The `Uncertainty` of `--robust FILE` and the nominal robot: a fit result's estimate and
    covariance, or a study's `vary` table, around `params` (`RobotParams`) when given, else
    around the file's own robot (the fit's, or the study's)."""
    from .._runtime.files import read_mapping
    from ..model.params import RobotParams
    from ..planning.uncertainty import Uncertainty

    path = Path(path)
    if path.suffix.lower() == ".toml":
        import numpy as np

        from ..montecarlo.study import check_vary, load_study

        study = load_study(path)
        params = study.params if params is None else params
        try:
            entries = check_vary(params, study.vary)
        except ValueError as e:
            raise InputError(f"{path}: {e}") from None
        if not entries:
            raise InputError(f"{path}: no parameter is uncertain; give at least one name.")
        names, kinds, a, b, _ = zip(*entries)
        unc = Uncertainty(names, kinds, np.asarray(a, float), np.asarray(b, float), source=str(path))
        return unc, unc.nominal(params)
    if path.suffix.lower() != ".json":
        raise InputError(f"--robust {path}: expected a fit result (.json) or a Monte-Carlo study (.toml).")
    unc = Uncertainty.from_fit(read_mapping(path), source=str(path))
    return unc, unc.nominal(RobotParams.load(path) if params is None else params)
