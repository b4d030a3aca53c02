"""`jsphere track`: feedback gains along a plan as a table a robot's controller runs, and the
plan replayed open and closed loop on drawn robots (docs/tracking.md)."""

from __future__ import annotations

from pathlib import Path

from .._runtime.errors import ExitCode, InputError

NAME = "track"
EXAMPLES = """
  jsphere track plan.csv --out track.csv
  jsphere track plan.json --robust fit.json --samples 1000 --out track.csv
  jsphere track plan.csv --vary study.toml --rate 200 --q-pos 1e6 --r 1e4 --out track.csv
  jsphere track plan.csv --weights weights.toml --samples 0 --out track.csv
"""

#: the keys of a `--weights` file
WEIGHT_KEYS = ("q_pos", "q_att", "q_rate", "r", "expected")


def add_parser(sub) -> None:
    pp = sub.add_parser(
        NAME,
        help="time-varying feedback gains along a plan (track.csv) and its miss open and closed loop",
        description="Linearise the model along a plan (jsphere plan) and compute time-varying linear-quadratic "
        "feedback gains with a terminal regulator that holds the target at rest; write them as a table a robot's "
        "controller runs (K = K_ff - G e, zero-order hold) and track.json; replay the plan open loop and closed loop "
        "on drawn robots (docs/tracking.md).",
    )
    pp.add_argument("plan", metavar="PLAN", help="a plan CSV or plan.json written by jsphere plan")
    pp.add_argument("--out", default="track.csv", help="the gain table (default track.csv); track.json beside it")
    pp.add_argument(
        "--params",
        help="the robot the plan was made for (.toml or .json); default the robot the plan's JSON records (else "
        "the paper's); a different robot is refused",
    )
    pp.add_argument("--rate", type=float, default=100.0, help="control rate, rows per second (default 100)")
    w = pp.add_argument_group("weights (docs/tracking.md)")
    w.add_argument("--q-pos", type=float, help="weight of the position error [1/m^2] (default 2.5e5)")
    w.add_argument("--q-att", type=float, help="weight of the attitude error [1/rad^2] (default 400)")
    w.add_argument("--q-rate", type=float, help="weight of the angular-velocity errors [s^2/rad^2] (default 4)")
    w.add_argument("--r", type=float, help="weight of the torque correction [1/(N m)^2] (default 2500)")
    w.add_argument("--weights", metavar="FILE", help=f"a .toml or .json file with {', '.join(WEIGHT_KEYS)}")
    pp.add_argument("--max-torque", type=float, default=0.1, help="wheel torque limit [N m] (default 0.1)")
    ev = pp.add_argument_group("evaluation")
    src = ev.add_mutually_exclusive_group()
    src.add_argument("--robust", metavar="FILE", help="draw the robots from a fit result (fit.json) or a study (.toml)")
    src.add_argument("--vary", metavar="FILE", help="draw the robots from a Monte-Carlo study's [vary] table (.toml)")
    ev.add_argument("--samples", type=int, default=1000, help="drawn robots (default 1000; 0: no evaluation)")
    ev.add_argument("--seed", type=int, default=0, help="seed of the draws (default 0)")


def _weights(args):
    """The `Weights` of the options: a `--weights` file, then the single flags over it."""
    from .._runtime.files import read_mapping
    from ..planning.tracking import Weights

    kw = {}
    if args.weights:
        d = read_mapping(args.weights)
        unknown = sorted(set(d) - set(WEIGHT_KEYS))
        if unknown:
            raise InputError(f"--weights {args.weights}: unknown key(s) {unknown}; expected {list(WEIGHT_KEYS)}.")
        kw.update(d)
        if "expected" in kw and isinstance(kw["expected"], list):
            kw["expected"] = tuple(kw["expected"])
    kw.update({k: getattr(args, k) for k in WEIGHT_KEYS[:4] if getattr(args, k) is not None})  # the single flags
    try:
        return Weights(**kw)
    except (TypeError, ValueError) as e:
        raise InputError(f"--weights: {e}") from None


def run(args) -> int:
    from .._runtime.files import atomic_write_json, check_output
    from ..model.limits import Limits
    from ..planning.tracking import track
    from .plan import uncertainty_of

    out = Path(args.out)
    if not Path(args.plan).exists():
        raise InputError(f"{args.plan}: no such plan (write one with `jsphere plan --out plan.csv`).")
    check_output(
        out,
        writes=[out.with_suffix(".json")],
        inputs={
            "the plan": args.plan,
            "the parameter file (--params)": args.params,
            "--robust": args.robust,
            "--vary": args.vary,
            "--weights": args.weights,
        },
        example=str(out / "track.csv"),
    )
    if out.suffix.lower() != ".csv":
        raise InputError(f"--out {out}: the gain table is a .csv file (track.json is written beside it).")
    weights = _weights(args)
    limits = Limits(max_torque=args.max_torque)
    unc = None
    params = plan_robot(args.plan, args.params)
    if args.vary and Path(args.vary).suffix.lower() != ".toml":
        raise InputError(f"--vary {args.vary}: expected a Monte-Carlo study (.toml) with a [vary] table.")
    if args.robust or args.vary:
        unc, params = uncertainty_of(args.robust or args.vary, params)
    tr = track(
        args.plan,
        params,
        rate=args.rate,
        weights=weights,
        limits=limits,
        uncertainty=unc,
        samples=args.samples,
        seed=args.seed,
    )
    print(tr.summary())
    tr.to_csv(out)
    atomic_write_json(out.with_suffix(".json"), tr.to_json())
    print(f"wrote {out}, {out.with_suffix('.json')}")
    return ExitCode.OK


def plan_robot(plan, params_file):
    """The robot for a plan file and a `--params` file (or None): the robot the plan's JSON
    records, checked against `--params` when both are given (`InputError` naming both when they
    differ), else `--params`, else None (the paper's robot)."""
    from ..model.params import RobotParams
    from ..planning.result import planned_robot, robot_difference

    recorded = planned_robot(plan)
    given = RobotParams.load(params_file) if params_file else None
    if recorded is None or given is None:
        return given if given is not None else (recorded.params if recorded else None)
    diff = robot_difference(recorded.params, given)
    if diff is not None:
        raise InputError(
            f"--params {params_file}: the plan {plan} was made for another robot, {recorded.describe()} (plan vs --params: {diff}); "
            f"leave --params out to use the plan's robot, or plan again with --params {params_file}."
        )
    return given
