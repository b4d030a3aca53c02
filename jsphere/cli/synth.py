"""`jsphere synth`: synthetic capture-like trial CSVs from random input programs."""

from __future__ import annotations

from pathlib import Path

from .._runtime.errors import InputError
from .options import at_least, check_flags, nonnegative, positive, robot

NAME = "synth"
EXAMPLES = """
  jsphere synth --out trials --trials 5 --duration 8
  jsphere synth --out trials --kind torques --params robot.toml --pos-sd 5e-4 --seed 10
  jsphere synth --out trials --trials 5 --glitches
  jsphere synth --onboard --kind torques --out runs --imu-position 0.02 -0.01 -0.04
"""


def add_parser(sub) -> None:
    sy = sub.add_parser(
        NAME,
        help="synthetic capture-like trial CSVs from random input programs",
        description="Simulate a robot driven by random input programs and write capture-like trial CSVs, with "
        "position and orientation noise and lost frames, as `jsphere convert` writes them (docs/capture.md): "
        "data to try `jsphere fit` on. Trial i uses the seed SEED + i.",
    )
    sy.add_argument("--out", required=True, help="output folder")
    sy.add_argument("--trials", type=int, default=3, help="number of trials (default 3)")
    sy.add_argument("--kind", default="wheel_speeds", choices=("wheel_speeds", "torques"))
    sy.add_argument("--params", help="a parameter file (.toml or .json); default: the paper's robot")
    sy.add_argument("--duration", type=float, default=6.0, help="trial length [s] (default 6)")
    sy.add_argument("--seed", type=int, default=0, help="trial i uses seed + i")
    sy.add_argument("--pos-sd", type=float, default=1e-3, help="position noise [m] (default 1e-3)")
    sy.add_argument("--rot-sd-deg", type=float, default=0.5, help="orientation noise per axis [deg] (default 0.5)")
    sy.add_argument("--dropout", type=float, default=0.02, help="fraction of frames lost (default 0.02)")
    sy.add_argument(
        "--glitches",
        action="store_true",
        help="spoil frames as a real capture does: about 1 %% ghost frames (the position off by 1-5 cm for one frame) "
        "and 2 marker-swap bursts per trial (5-15 frames, the orientation off by 30-90 deg); the rows spoiled are "
        "printed",
    )
    g = sy.add_argument_group("onboard-sensor trials", "the robot's own IMU and wheel encoders instead of poses")
    g.add_argument(
        "--onboard",
        action="store_true",
        help="write onboard-sensor trials: gyro and accelerometer readings with noise and a bias per trial (drawn with "
        "sd 0.01 rad/s and 0.1 m/s^2, printed), wheel encoder angles in counts",
    )
    g.add_argument("--imu-position", nargs=3, type=float, default=(0.0, 0.0, 0.0), metavar=("X", "Y", "Z"))
    g.add_argument(
        "--imu-rotation", nargs=4, type=float, default=(1.0, 0.0, 0.0, 0.0), metavar=("QW", "QX", "QY", "QZ")
    )
    g.add_argument("--gyro-sd", type=float, default=0.003, help="gyro noise [rad/s] (default 0.003)")
    g.add_argument("--acc-sd", type=float, default=0.03, help="accelerometer noise [m/s^2] (default 0.03)")
    g.add_argument("--counts-per-turn", type=int, default=4096, help="encoder counts per turn (default 4096; 0: exact)")


def run(args) -> int:
    from .._runtime.files import check_output
    from ..capture.synthetic import add_glitches, random_inputs, synthetic_trial
    from ..capture.trial import write_trial

    check_flags(
        args,
        {
            "--trials": (at_least(1), "at least 1"),
            "--duration": (positive, "a positive number of seconds"),
            "--pos-sd": (nonnegative, "a finite number >= 0 (metres)"),
            "--rot-sd-deg": (nonnegative, "a finite number >= 0 (degrees)"),
            "--dropout": (lambda v: 0.0 <= v < 1.0, "a fraction in [0, 1)"),
            "--seed": (at_least(0), "an integer >= 0"),
        },
    )
    out = Path(args.out)
    names = [f"{'onboard_' if args.onboard else ''}{args.kind}_{i:02d}" for i in range(args.trials)]
    check_output(out, folder=True, writes=[out / f"{n}.csv" for n in names], inputs={"the parameter file": args.params})
    params = robot(args)
    if args.onboard:
        return _onboard(args, params, out, names)
    for i, name in enumerate(names):
        seed = args.seed + i
        controls = random_inputs(params, args.duration, kind=args.kind, seed=seed)
        trial = synthetic_trial(
            params,
            controls,
            args.duration,
            pos_sd=args.pos_sd,
            rot_sd_deg=args.rot_sd_deg,
            dropout=args.dropout,
            seed=seed,
            name=name,
        )
        spoiled = ""
        if args.glitches:
            trial, rows = add_glitches(trial, seed=seed)
            spoiled = f" (glitches in rows {', '.join(map(str, rows))})"
        write_trial(out / f"{trial.name}.csv", trial)
        print(f"{trial!r} -> {out / (trial.name + '.csv')}{spoiled}")
    return 0


def _onboard(args, params, out: Path, names: list[str]) -> int:
    """`jsphere synth --onboard`: onboard-sensor trials, each with its own biases."""
    import numpy as np

    from ..capture.onboard import OnboardNoise, synthetic_onboard_trial, write_onboard_trial
    from ..capture.synthetic import random_inputs
    from ..model.sensors import Mounting

    check_flags(
        args,
        {
            "--gyro-sd": (nonnegative, "a finite number >= 0 (rad/s)"),
            "--acc-sd": (nonnegative, "a finite number >= 0 (m/s^2)"),
            "--counts-per-turn": (at_least(0), "an integer >= 0 (0: exact angles)"),
        },
    )
    if not np.all(np.isfinite([*args.imu_position, *args.imu_rotation])) or np.linalg.norm(args.imu_rotation) < 1e-6:
        raise InputError("--imu-position X Y Z and --imu-rotation QW QX QY QZ must be finite, the quaternion nonzero.")
    mounting = Mounting(args.imu_position, args.imu_rotation)
    for i, name in enumerate(names):
        seed = args.seed + i
        rng = np.random.default_rng([seed, 7])
        noise = OnboardNoise(
            args.gyro_sd,
            args.acc_sd,
            tuple(rng.normal(0.0, 0.01, 3)),
            tuple(rng.normal(0.0, 0.1, 3)),
            args.counts_per_turn,
        )
        controls = random_inputs(params, args.duration, kind=args.kind, seed=seed)
        trial = synthetic_onboard_trial(
            params, controls, args.duration, mounting=mounting, noise=noise, seed=seed, name=name
        )
        path = out / f"{name}.csv"
        write_onboard_trial(path, trial)
        biases = ", ".join(f"{v:+.4f}" for v in (*noise.gyro_bias, *noise.acc_bias))
        print(f"onboard trial {name!r}: {len(trial.t)} samples, biases (gyro rad/s, acc m/s^2) {biases} -> {path}")
    return 0
