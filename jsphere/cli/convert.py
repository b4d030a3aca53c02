"""`jsphere convert`: a raw motion-capture export and its inputs table -> a trial CSV
(docs/capture.md)."""

from __future__ import annotations

import sys
from pathlib import Path

from .options import options_of

NAME = "convert"
EXAMPLES = """
  jsphere convert capture.csv --format motive --inputs inputs.csv --out trial.csv
  jsphere convert take_1.csv --format motive --inputs design_1.csv --body-markers body.csv --params robot.toml \\
      --out trials/t1.csv
  jsphere convert session.c3d --format c3d --inputs inputs.csv --units mm --out trial.csv
  jsphere convert capture.csv --format motive --inputs plan.csv --input-kind chi_dot --time-offset auto --out trial.csv
  jsphere convert run.bag --format rosbag --pose-topic /mocap/robot/pose --inputs-topic /joint_states \\
      --input-kind chi_dot --joints wheel_1,wheel_2,wheel_3 --out trial.csv
  jsphere convert run_bag/ --format rosbag --pose-topic /tf --child-frame robot --inputs-topic /joint_states \\
      --out trial.csv
  jsphere convert take.tsv --format qualisys --inputs run_bag/ --inputs-topic /joint_states --out trial.csv
  jsphere convert run_bag/ --format rosbag --imu-topic /imu/data --inputs-topic /joint_states --input-kind K \
      --joints wheel_1,wheel_2,wheel_3 --out runs/run1.csv
"""


def add_parser(sub) -> None:
    cv = sub.add_parser(
        NAME,
        help="raw motion-capture export or ROS bag + inputs -> trial CSV (docs/capture.md)",
        description="Convert a raw motion-capture export (Motive CSV, Vicon Nexus CSV, C3D, Qualisys TSV) or the "
        "poses of a ROS bag, and the inputs sent to the wheels (a table, or a JointState topic of a ROS bag) into a "
        "trial CSV for `jsphere fit` (docs/capture.md): the shell centre's path and the platform's orientation, "
        "checked and resampled. Warnings name the frames and markers they are about.",
    )
    cv.add_argument("raw", help="the raw export (Motive CSV, Vicon Nexus CSV, C3D, Qualisys TSV) or a ROS bag")
    cv.add_argument("--format", required=True, choices=("motive", "vicon", "c3d", "qualisys", "rosbag"))
    cv.add_argument(
        "--inputs",
        help="inputs table (t, chi_dot_1..N or t, K_1..N), or a ROS bag read with --inputs-topic "
        "(default with --format rosbag: the bag itself)",
    )
    cv.add_argument("--out", required=True, help="the trial CSV to write (never one of the input files)")
    cv.add_argument(
        "--units", default="auto", choices=("auto", "m", "cm", "mm"), help="length units of the export (default: auto)"
    )
    cv.add_argument("--up-axis", choices=("y", "z"), help="the export's up axis (default: y for Motive, z otherwise)")
    cv.add_argument("--rigid-body", help="Motive rigid body / Qualisys 6DOF body (or Vicon subject) to use")
    cv.add_argument("--subject", help="Vicon Nexus subject whose trajectories to use (needed when there are several)")
    cv.add_argument(
        "--pose-topic",
        help="ROS bag: the topic of the poses: PoseStamped, PoseWithCovarianceStamped, TransformStamped, Odometry, or "
        "a TFMessage topic such as /tf",
    )
    cv.add_argument(
        "--child-frame",
        metavar="NAME",
        help="ROS bag with a TFMessage --pose-topic (/tf): the child frame whose transforms are the poses (default: "
        "the topic's one moving child frame)",
    )
    cv.add_argument("--inputs-topic", help="ROS bag: the sensor_msgs/JointState topic of the wheel inputs")
    cv.add_argument(
        "--input-kind",
        choices=("chi_dot", "K"),
        help="which input family to read: from a JointState, velocity (chi_dot) or effort (K); from an inputs table "
        "holding both, its columns (default for a JointState: chi_dot)",
    )
    cv.add_argument("--joints", help="ROS bag: the wheels' joint names in wheel order, comma-separated (default: all)")
    cv.add_argument(
        "--params",
        help="the robot (.toml or .json): the inputs must have one column per wheel, and the shell centre's height "
        "must be its R0 (a warning names the options that put the centre there: a take converted without "
        "--body-markers or --body-offset tracks the markers' centroid)",
    )
    cv.add_argument(
        "--body-markers",
        help="CSV name,x,y,z: the markers in the platform frame [m] (default: from the first full frame)",
    )
    cv.add_argument(
        "--body-offset",
        type=float,
        nargs=3,
        default=(0.0, 0.0, 0.0),
        metavar=("X", "Y", "Z"),
        help="shell centre relative to the marker centroid, platform frame [m]",
    )
    cv.add_argument(
        "--time-offset",
        default="0",
        help="added to the capture times to match the inputs' clock [s], or 'auto': estimated from the data (wheel "
        "speeds: the measured velocity against the one the inputs imply) and printed",
    )
    cv.add_argument(
        "--allow-truncated",
        action="store_true",
        help="convert an export cut short (fewer frames than its header declares, a last row cut off) "
        "with a warning instead of an error",
    )
    cv.add_argument(
        "--keep-suspect",
        action="store_true",
        help="keep the frames whose marker fit residual stands out of the take's own noise (at least 5x its median "
        "and beyond its spread, and above twice the marker error the export reports: a swapped or ghost marker); by "
        "default they are written as missing, with a warning saying how many",
    )
    _add_onboard_flags(cv)


def _add_onboard_flags(cv) -> None:
    """The flags of an onboard-sensor trial from a ROS bag (docs/onboard.md)."""
    g = cv.add_argument_group(
        "onboard-sensor trials (ROS bag)",
        "the robot's own IMU and wheel encoders instead of poses: an onboard-sensor trial for jsphere fit",
    )
    g.add_argument("--imu-topic", help="the sensor_msgs/Imu topic of the IMU on the platform (instead of --pose-topic)")
    g.add_argument(
        "--encoder-topic",
        help="the sensor_msgs/JointState topic whose position holds the wheels' angles (default: --inputs-topic)",
    )
    g.add_argument(
        "--hold",
        action="store_true",
        help="the inputs are held between messages (a digital controller's torques) rather than samples of a smooth "
        "programme",
    )


def _run_onboard(args) -> int:
    """`jsphere convert --format rosbag --imu-topic ...`: an onboard-sensor trial."""
    from .._runtime.errors import InputError
    from .._runtime.files import check_output
    from ..capture.onboard import write_onboard_trial
    from ..capture.rosbag import read_rosbag_onboard
    from ..model.params import RobotParams

    if args.format != "rosbag":
        raise InputError(f"--imu-topic reads a ROS bag; give --format rosbag (got --format {args.format}).")
    if args.pose_topic or not args.inputs_topic:
        raise InputError(
            "--imu-topic makes an onboard-sensor trial: give --inputs-topic (the wheels' JointState), not --pose-topic."
        )
    out = Path(args.out)
    check_output(out, inputs={"the ROS bag": args.raw, "the robot": args.params}, example=str(out / "trial.csv"))
    robot = RobotParams.load(args.params) if args.params else None
    trial = read_rosbag_onboard(
        args.raw,
        args.imu_topic,
        args.inputs_topic,
        input_kind=args.input_kind or "K",
        encoder_topic=args.encoder_topic,
        joints=args.joints,
        n_wheels=robot.n_wheels if robot is not None else None,
        hold=args.hold,
        name=out.stem,
    )
    write_onboard_trial(out, trial)
    print(
        f"onboard trial {trial.name!r}: {len(trial.t)} samples over {trial.t[-1]:.3f} s, {trial.n_wheels} wheels, "
        f"{trial.kind}{' held' if trial.hold else ''} -> {out}"
    )
    return 0


def run(args) -> int:
    import dataclasses
    import math
    import warnings

    from .._runtime.errors import InputError
    from .._runtime.files import check_output
    from ..capture.body import read_body_markers
    from ..capture.convert import convert_raw
    from ..capture.options import ConvertOptions
    from ..capture.trial import write_trial
    from ..capture.validation import CaptureWarning
    from ..model.params import RobotParams

    if args.imu_topic:
        return _run_onboard(args)
    if not all(math.isfinite(v) for v in args.body_offset):
        raise InputError(
            f"--body-offset X Y Z must be finite numbers [m]; got {' '.join(f'{v:g}' for v in args.body_offset)}."
        )
    time_offset = _time_offset(args.time_offset)
    out = Path(args.out)
    inputs = {
        "the raw export": args.raw,
        "the inputs table": args.inputs,
        "the body markers": args.body_markers,
        "the robot": args.params,
    }
    check_output(out, inputs=inputs, example=str(out / "trial.csv"))
    robot = RobotParams.load(args.params) if args.params else None
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", CaptureWarning)
        try:
            body = read_body_markers(args.body_markers) if args.body_markers else None
            options = options_of(  # `--params`: its wheels and R0 are checked
                ConvertOptions,
                args,
                n_wheels=robot.n_wheels if robot is not None else None,
                body_markers=body,
                body_offset=tuple(args.body_offset),
                time_offset=time_offset or 0.0,
                shell_radius=float(robot.R0) if robot is not None else None,
            )
            if time_offset is None:
                options = dataclasses.replace(options, time_offset=_estimate_offset(args, options))
            trial = convert_raw(args.raw, args.inputs, format=args.format, options=options)
            if options.n_wheels is not None and trial.n_wheels != options.n_wheels:
                raise InputError(
                    f"{args.inputs or args.raw}: the inputs hold {trial.n_wheels} wheels but the robot ({args.params}) has "
                    f"{options.n_wheels}; give one column per wheel."
                )
        finally:  # the warnings of a conversion that then fails say what went before
            for w in caught:
                if issubclass(w.category, CaptureWarning):
                    print(f"jsphere convert: warning: {w.message}", file=sys.stderr)
                else:
                    warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)
    write_trial(out, trial)
    print(f"{trial!r} -> {out}")
    print(_centre_summary(trial, robot, args.params))
    return 0


def _centre_summary(trial, robot, params) -> str:
    """The summary's line on the shell centre's height (`centre_height`), and what it was
    checked against: the robot's R0, or nothing without `--params`."""
    from ..capture.centre import centre_height

    h = centre_height(trial)
    height = "no heights" if h is None else h.summary()
    if robot is None:
        return (
            f"jsphere convert: shell centre height {height}; not checked against the shell radius: give --params "
            "ROBOT to check it"
        )
    return f"jsphere convert: shell centre height {height}; the robot's R0 ({params}) is {float(robot.R0):.4f} m"


def _time_offset(value: str) -> float | None:
    """The `--time-offset` in seconds, None for `auto`."""
    import math

    from .._runtime.errors import InputError

    if value.strip().lower() == "auto":
        return None
    try:
        v = float(value)
    except ValueError:
        v = math.nan
    if not math.isfinite(v):
        raise InputError(f"--time-offset must be a finite number of seconds or 'auto'; got {value!r}.")
    return v


def _estimate_offset(args, options) -> float:
    """`--time-offset auto`: the capture converted once without an offset (its warnings held
    back), the offset estimated from its poses and the inputs (`estimate_time_offset`: the
    inputs table as written, or the inputs of a ROS bag as the conversion resampled them),
    printed."""
    import dataclasses
    import warnings

    from ..capture.clock import estimate_time_offset
    from ..capture.convert import convert_raw
    from ..capture.inputs import read_inputs_csv

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        first = convert_raw(
            args.raw, args.inputs, format=args.format, options=dataclasses.replace(options, time_offset=0.0)
        )
        if args.inputs is not None and options.inputs_topic is None:
            t_in, u_in, kind, _ = read_inputs_csv(
                args.inputs, kind=options.input_kind, allow_truncated=options.allow_truncated
            )
        else:
            t_in, u_in, kind = first.t, first.inputs, first.kind
    offset, corr = estimate_time_offset(first.t, first.x, first.y, first.q, t_in, u_in, kind)
    print(
        f"jsphere convert: time offset estimated: {offset:+.4f} s (correlation {corr:.3f}); --time-offset {offset:.4f}"
    )
    return offset
