"""`jsphere fit`: robot parameters fitted to captured trials (docs/identification.md)."""

from __future__ import annotations

import sys

from .._runtime.errors import ExitCode, InputError
from .options import Assignments, add_imu_flags, json_result, options_of, progress, robot, warnings_as_lines

NAME = "fit"
EXAMPLES = """
  jsphere fit --free j --fix m=2.5 examples/data/ws_01.csv --out fit.json
  jsphere fit trials/*.csv --free 'R_m,j,I[0,0],I[1,1],I[2,2],I0' --fix m=2.5,m0=0.8 --bound j=0:1e-3 --out fit.json
  jsphere fit trials/*.csv --free R_m,j --fix m0=0.8 --fit-time-offset --out fit.json
  jsphere fit runs/*.csv --free 'r_m[2],j,I[2,2],m0' --imu-position 0.02 -0.01 -0.04 --out fit.json   (onboard sensors)
"""
#: what an interrupted fit keeps
RESUMES = "the finished stages are kept in the checkpoint beside --out: rerun the same command to resume"


def add_parser(sub) -> None:
    ft = sub.add_parser(
        NAME,
        help="fit robot parameters to captured trials (docs/identification.md)",
        description="Fit a robot's free parameters to captured trials (poses, the robot's own IMU and encoders, or "
        "both) by Levenberg-Marquardt through the simulation; writes the result JSON, its figures and, while it runs, "
        "a checkpoint from which a killed fit resumes. The last line on stdout is the verdict.",
    )
    ft.add_argument("trials", nargs="*", metavar="TRIAL", help="trial CSV files or folders of them (docs/capture.md)")
    ft.add_argument(
        "--free",
        required=True,
        help="comma-separated names to fit: fields (j, m0, I0, I, r_m, k_tau) or components (I[0,0], r_m[2]), or R_m; "
        "onboard: also imu_position [m], imu_rotation [rad, about the IMU's axes, applied to --imu-rotation]",
    )
    ft.add_argument(
        "--fix",
        action=Assignments,
        spill="trials_after_options",
        metavar="NAME=VALUE",
        help="set and hold a parameter (e.g. m=2.5; a JSON list for a whole field); repeat it or list several "
        "(--fix m=2.5,m0=0.8)",
    )
    ft.add_argument(
        "--bound",
        action=Assignments,
        spill="trials_after_options",
        metavar="NAME=LO:HI",
        help="bounds of a free name (e.g. j=0:1e-3; an empty side is open); repeat it or list several",
    )
    ft.add_argument("--params", help="start values (.toml or .json; default: the paper's robot)")
    ft.add_argument(
        "--out", default="fit.json", help="result JSON (default fit.json); plots and the checkpoint go beside it"
    )
    ft.add_argument("--n-starts", type=int, default=2, help="starts vmapped together (default 2)")
    ft.add_argument("--seed", type=int, default=0, help="seed of the start design (a Latin hypercube over the bounds)")
    ft.add_argument(
        "--shooting",
        choices=("auto", "single", "multiple"),
        default="auto",
        help="multiple: segments with their own initial states, joined by raising the weight of their defects, then single "
        "shooting; auto (default): multiple when a trial is longer than two segments",
    )
    ft.add_argument(
        "--segment",
        type=float,
        default=2.0,
        metavar="SECONDS",
        help="segment length of multiple shooting [s] (default 2)",
    )
    ft.add_argument("--max-iter", type=int, default=40, help="Levenberg-Marquardt iterations per stage (default 40)")
    ft.add_argument("--sigma-pos", type=float, help="position noise [m] (default: estimated)")
    ft.add_argument("--sigma-rot-deg", type=float, help="orientation noise [deg] (default: estimated)")
    ft.add_argument(
        "--fit-time-offset",
        action="store_true",
        help="estimate each trial's clock offset between its inputs and its capture (inputs at t + offset) as a "
        "nuisance value; fit.json reports time_offset and time_offset_stderr [s] in trial order",
    )
    ft.add_argument(
        "--max-time-offset",
        type=float,
        default=0.5,
        metavar="SECONDS",
        help="the largest clock offset, either way [s] (default 0.5)",
    )
    ft.add_argument(
        "--loss",
        choices=("l2", "huber", "cauchy", "soft_l1"),
        default="cauchy",
        help="how each frame's residuals enter the cost: cauchy (default), huber or soft_l1 set aside ghost frames and "
        "marker swaps, listed under 'outliers' in the result JSON by trial file; l2: plain least squares (onboard-sensor "
        "trials are always fitted by least squares)",
    )
    ft.add_argument(
        "--restart",
        action="store_true",
        help="ignore the checkpoint a killed fit left (by default the fit resumes from it)",
    )
    ft.add_argument("--no-plots", action="store_true", help="skip the figures")
    _add_sensor_flags(ft)


def _add_sensor_flags(ft) -> None:
    sensors = ft.add_argument_group(
        "onboard-sensor trials", "trials of the robot's own IMU and wheel encoders (docs/onboard.md)"
    )
    add_imu_flags(sensors)
    sensors.add_argument(
        "--estimate-initial-state",
        action="store_true",
        help="fit each trial's initial motion (shell and platform angular velocities, the platform's tilt) instead of "
        "starting it at rest: for trials cut from a longer run",
    )
    sensors.add_argument(
        "--zero-order-hold",
        action="store_true",
        help="the torques are held between samples (a digital controller's), whatever the trial files say",
    )


def run(args) -> int:
    """`jsphere fit`: the output path, options, parameter file and trials checked before anything
    is compiled; a finished fit writes its files whatever its verdict, the exit code says it."""
    import math

    from .._runtime.files import check_output, remove_stale_temporaries
    from ..capture.trial import read_trials
    from ..identify.fit import fit
    from ..identify.options import FitOptions
    from ..identify.verdict import headline

    args.trials = [*args.trials, *(getattr(args, "trials_after_options", None) or [])]  # after --fix, --bound
    if not args.trials:
        raise InputError("give at least one trial file or folder (e.g. jsphere fit trials/*.csv --free j).")
    out, inputs = json_result(args)
    ckpt = out.with_name(out.name + ".ckpt.npz")
    figures = [out.with_name(f"{out.stem}_{k}.png") for k in ("overlay", "residuals")]
    check_output(out, writes=[ckpt, *([] if args.no_plots else figures)], inputs=inputs, example=str(out / "fit.json"))
    fix = _parse_assignments(args.fix, "--fix")
    bounds = _parse_bounds(args.bound)
    params = robot(args)
    trials = read_trials(args.trials)
    sigma_rot = None if args.sigma_rot_deg is None else math.radians(args.sigma_rot_deg)
    options = options_of(
        FitOptions,
        args,
        sigma_rot=sigma_rot,
        start_at_rest=not args.estimate_initial_state,
    )
    for f in [(out, ".tmp"), *((g, None) for g in figures)]:  # what a killed writer left
        remove_stale_temporaries(*f)
    with warnings_as_lines(NAME):  # a checkpoint that cannot be used
        res = fit(
            trials,
            params,
            args.free,
            fix=fix,
            bounds=bounds,
            options=options,
            checkpoint=ckpt,
            restart=args.restart,
            progress=progress(args),
        )
    written = res.save(out)
    if not args.no_plots:
        from ..plots import fit_figures

        written += fit_figures(res, out.parent, stem=out.stem)
    ckpt.unlink(missing_ok=True)
    print(res.table())
    for w in res.identifiability["warnings"]:
        print(f"jsphere fit: warning: {w}", file=sys.stderr)
    print(f"wrote {', '.join(str(p) for p in written)}  ({res.elapsed_s:.1f} s)")
    print(f"jsphere fit: {headline(res.status, res.status_reason, res.verdict)}")  # the last line: the verdict
    return {"converged": ExitCode.OK, "not_converged": ExitCode.NOT_CONVERGED, "misfit": ExitCode.MISFIT}[res.status]


def _parse_assignments(items, option: str) -> dict:
    out = {}
    for item in items or []:
        name, eq, value = item.partition("=")
        if not eq or not name.strip() or not value.strip():
            raise InputError(f"{option} expects NAME=VALUE (e.g. {option} m=2.5); got {item!r}.")
        if name.strip() in out:
            raise InputError(f"{option}: {name.strip()!r} is given twice.")
        out[name.strip()] = value.strip()
    return out


def _parse_bounds(items) -> dict:
    import math

    out = {}
    for name, value in _parse_assignments(items, "--bound").items():
        lo, colon, hi = value.partition(":")
        if not colon:
            raise InputError(
                f"--bound {name}={value}: expected LO:HI with either side empty for an open end (e.g. j=0:1e-3)."
            )
        try:
            out[name] = (float(lo) if lo.strip() else None, float(hi) if hi.strip() else None)
        except ValueError:
            raise InputError(f"--bound {name}={value}: LO and HI must be numbers.") from None
        if any(v is not None and math.isnan(v) for v in out[name]):
            raise InputError(
                f"--bound {name}={value}: LO and HI must be numbers, not NaN (leave a side empty for an open end)."
            )
    return out
