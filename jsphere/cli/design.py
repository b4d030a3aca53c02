"""`jsphere design`: input programmes that identify the free parameters best (D-optimal), as
inputs tables for the robot (docs/design.md)."""

from __future__ import annotations

import math
from pathlib import Path

from .._runtime.errors import ExitCode, InputError
from .options import add_imu_flags, at_least, check_flags, options_of, positive, progress, robot

NAME = "design"
EXAMPLES = """
  jsphere design --free 'r_m[2],j,I[2,2]' --duration 8 --kind K --trials 2 --out design.csv
  jsphere design --free j --duration 4 --kind K --max-torque 0.05 --restarts 8 --steps 100 --out design.csv
  jsphere design --free 'r_m[2]' --duration 6 --kind chi_dot --params robot.toml --sigma-pos 5e-4 --out d.csv
  jsphere design --free 'r_m[2],j,I[2,2]' --duration 8 --kind K --onboard --imu-position 0.02 -0.01 -0.04 --out d.csv
"""


def add_parser(sub) -> None:
    dp = sub.add_parser(
        NAME,
        help="input programmes that identify the free parameters best (D-optimal); inputs tables",
        description="Compute input programmes for identification trials that maximise the log-determinant of the "
        "Fisher information of the free parameters (the per-trial initial velocities as nuisance values, as in "
        "`jsphere fit`), within motor limits, smooth and at rest at both ends (docs/design.md). Writes one inputs "
        "table per trial (`--out`, or <stem>_k for k = 1..M when M > 1) and <stem>.json with the predicted "
        "standard errors of the design and of random multisines of the design's RMS amplitude (scaled down where "
        "that breaks a motor limit further than the design does).",
    )
    dp.add_argument("--free", required=True, help="the names to identify, as for fit: 'r_m[2],j,I[2,2]'")
    dp.add_argument("--duration", type=float, required=True, help="length of each trial [s]")
    dp.add_argument(
        "--kind",
        choices=("K", "chi_dot"),
        required=True,
        help="the inputs: axle torques K [N m] or wheel speeds chi_dot [rad/s] (inertias need K)",
    )
    dp.add_argument("--params", help="a parameter file (.toml or .json) instead of the paper's robot")
    dp.add_argument("--trials", type=int, default=1, help="number of trials M (default 1)")
    dp.add_argument("--max-torque", help="wheel torque limit [N m] (default 0.1; the scale of K programmes)")
    dp.add_argument("--max-wheel-speed", help="wheel speed limit [rad/s] (default 20; 'none' for no limit with K)")
    dp.add_argument("--max-tilt", help="platform tilt limit [rad] (default 0.35; 'none' for no limit)")
    dp.add_argument("--max-torque-rate", help="torque rate limit [N m/s] (default 1; 'none' for no limit)")
    dp.add_argument("--sigma-pos", type=float, help="position noise of the capture [m] (default 1e-3)")
    dp.add_argument("--sigma-rot-deg", type=float, help="orientation noise of the capture [deg] (default 0.5)")
    sensors = dp.add_argument_group(
        "onboard sensors", "trials of the robot's own IMU and wheel encoders (docs/onboard.md)"
    )
    sensors.add_argument(
        "--onboard", action="store_true", help="design for the onboard sensors instead of motion capture"
    )
    add_imu_flags(sensors, (0.003, 0.03, 2 * math.pi / 4096 / math.sqrt(12)))  # DesignOptions' defaults
    dp.add_argument("--restarts", type=int, default=4, help="random starts of the search, vmapped (default 4)")
    dp.add_argument("--steps", type=int, default=60, help="Adam steps of the search (default 60)")
    dp.add_argument("--seed", type=int, default=0, help="seed of the starts and of the baseline (default 0)")
    dp.add_argument("--rate", type=float, default=100.0, help="rows per second of the tables (default 100)")
    dp.add_argument(
        "--capture-rate",
        type=float,
        default=100.0,
        help="capture rate of the predicted standard errors [Hz] (default 100)",
    )
    dp.add_argument(
        "--out",
        default="design.csv",
        help="the inputs table (M = 1), or the stem of design_1.csv .. (M > 1); <stem>.json beside it (default design.csv)",
    )
    dp.add_argument(
        "--baseline-out",
        metavar="FILE",
        help="also write the baseline's tables (random multisines), named as --out: to run them on the robot too",
    )


def run(args) -> int:
    from .._runtime.files import check_output
    from ..design.excitation import DesignOptions, design_excitation
    from ..design.result import json_path, table_paths
    from .plan import _limits

    whole = "a whole number >= "
    check_flags(
        args,
        {
            "--duration": (positive, "a positive number of seconds"),
            "--trials": (at_least(1), whole + "1"),
            "--sigma-pos": (positive, "a number > 0 (metres)"),
            "--sigma-rot-deg": (positive, "a number > 0 (degrees)"),
            "--sigma-gyro": (positive, "a number > 0 (rad/s)"),
            "--sigma-acc": (positive, "a number > 0 (m/s^2)"),
            "--sigma-encoder": (positive, "a number > 0 (rad)"),
            "--restarts": (at_least(1), whole + "1"),
            "--steps": (at_least(0), whole + "0"),
            "--seed": (at_least(0), whole + "0"),
            "--rate": (positive, "a positive number of rows per second"),
            "--capture-rate": (positive, "a positive rate [Hz]"),
        },
    )
    capture = [f for f in ("--sigma-pos", "--sigma-rot-deg") if getattr(args, f[2:].replace("-", "_")) is not None]
    if args.onboard and capture:
        raise InputError(
            f"{capture[0]} is the motion capture's noise; with --onboard give --sigma-gyro, --sigma-acc, --sigma-encoder."
        )
    out = Path(args.out)
    tables = table_paths(out, args.trials)
    baseline = [] if args.baseline_out is None else table_paths(args.baseline_out, args.trials)
    if {Path(p).resolve() for p in baseline} & {Path(p).resolve() for p in [*tables, json_path(out)]}:
        raise InputError(f"--baseline-out {args.baseline_out}: the design writes that file itself; give another name.")
    check_output(
        out,
        writes=[*tables, *baseline, json_path(out)],
        inputs={"the parameter file (--params)": args.params},
        example=str(out / "design.csv"),
    )
    options = options_of(
        DesignOptions,
        args,
        sensors="onboard" if args.onboard else "capture",
        sigma_pos=1e-3 if args.sigma_pos is None else args.sigma_pos,
        sigma_rot=math.radians(0.5 if args.sigma_rot_deg is None else args.sigma_rot_deg),
    )
    result = design_excitation(
        robot(args), args.free, args.duration, args.kind, limits=_limits(args), options=options, progress=progress(args)
    )
    print(result.table())
    written = result.save(out, baseline=args.baseline_out)
    print(f"wrote {', '.join(str(p) for p in written)}")
    return ExitCode.OK
