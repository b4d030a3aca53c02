"""`jsphere synth`: synthetic capture-like trial CSVs from random input programs."""

from __future__ import annotations

from pathlib import Path

from .options import at_least, check_flags, nonnegative, positive, robot

NAME = "synth"
EXAMPLES = """
  jsphere synth --out trials --trials 5 --duration 8
  jsphere synth --out trials --kind torques --params robot.toml --pos-sd 5e-4 --seed 10
  jsphere synth --out trials --trials 5 --glitches
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
    names = [f"{args.kind}_{i:02d}" for i in range(args.trials)]
    check_output(out, folder=True, writes=[out / f"{n}.csv" for n in names], inputs={"the parameter file": args.params})
    params = robot(args)
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
