"""What several commands share: repeatable `NAME=VALUE` options (`--fix`, `--bound`), the mapping
of flags to the library's options objects (`options_of`), the checks of flags' numbers
(`check_flags`), the robot of `--params`, a result JSON's `--out`, and the library's `progress`
argument from `-q/--quiet`."""

from __future__ import annotations

import argparse
import contextlib
import math
import sys
from pathlib import Path

from .._runtime.errors import InputError


def split_top_level(text: str) -> list[str]:
    """`text` cut at its commas outside brackets: `"m=2.5,I[0,0]=1e-3"` -> `["m=2.5", "I[0,0]=1e-3"]`
    (a JSON list keeps its commas: `"r_m=[0,0,-0.02]"` is one item)."""
    items, depth, start = [], 0, 0
    for i, ch in enumerate(text):
        if ch in "[(":
            depth += 1
        elif ch in "])":
            depth -= 1
        elif ch == "," and depth == 0:
            items.append(text[start:i])
            start = i + 1
    items.append(text[start:])
    return [item.strip() for item in items if item.strip()]


def _is_assignment(value: str) -> bool:
    """Whether `value` reads as NAME=VALUE rather than a file (an existing path is a file)."""
    name = value.partition("=")[0]
    return "=" in value and bool(name.strip()) and not Path(value).exists()


class Assignments(argparse.Action):
    """`--fix NAME=VALUE`, repeatable, each value possibly a comma-separated list
    (`--fix m=2.5,j=1e-4`), and several after one option (`--fix m=2.5 m0=0.8`). The first value
    after the option is always an assignment (a wrong one is reported as such); from the first
    later value that is not `NAME=VALUE` on, the values are the command's positional files, which
    go to `spill` (`--fix m=2.5 trial.csv` leaves `trial.csv` to the files)."""

    def __init__(self, option_strings, dest, spill: str, **kwargs):
        self.spill = spill
        super().__init__(option_strings, dest, nargs="+", **kwargs)

    def __call__(self, parser, namespace, values, option_string=None):
        got = list(getattr(namespace, self.dest, None) or [])
        files = list(getattr(namespace, self.spill, None) or [])
        for i, value in enumerate(values):
            if files or (i and not _is_assignment(value)):
                files.append(value)
            else:
                got += split_top_level(value) or [value]
        setattr(namespace, self.dest, got)
        setattr(namespace, self.spill, files)


def progress(args) -> bool | None:
    """The `progress` argument of the library for a command: bars where stderr is a terminal
    (lines through the `jsphere` logger elsewhere), none with `--quiet`."""
    return False if args.quiet else None


def options_of(cls, args, **given):
    """The options object `cls` (a dataclass) of a command's flags: each field that has a flag of
    its name (`--max-iter` -> `max_iter`) set from it (a flag of several values as a tuple), and
    `given` (fields whose flag needs converting) over them; the other fields keep their defaults."""
    import dataclasses

    names = {f.name for f in dataclasses.fields(cls)} - set(given)
    flags = {name: getattr(args, name) for name in names if hasattr(args, name)}
    return cls(**{k: tuple(v) if isinstance(v, list) else v for k, v in flags.items()}, **given)


def positive(v) -> bool:
    return 0 < v < math.inf


def nonnegative(v) -> bool:
    return 0 <= v < math.inf


def at_least(low: int):
    return lambda v: v >= low


def check_flags(args, rules: dict) -> None:
    """`InputError` `"--FLAG must be WHAT; got VALUE."` for the first flag whose value fails its
    test; `rules` maps each flag to `(test, what)` (a flag not given, None, is not tested)."""
    for flag, (test, what) in rules.items():
        value = getattr(args, flag[2:].replace("-", "_"))
        if value is not None and not test(value):
            raise InputError(f"{flag} must be {what}; got {value:g}.")


def robot(args):
    """The robot of `--params` (a parameter file), else the paper's."""
    from ..model.params import RobotParams

    return RobotParams.load(args.params) if args.params else RobotParams.paper()


def json_result(args) -> tuple[Path, dict]:
    """The `--out` of a command whose result is JSON (`InputError` for another suffix) and the
    inputs it must not overwrite: the trial files and `--params`."""
    out = Path(args.out)
    if not out.is_dir() and out.suffix.lower() != ".json":
        raise InputError(f"--out {out}: the result is JSON; give a path ending in .json.")
    trials = [t for t in args.trials if not Path(t).is_dir()]
    return out, {"the trial file": trials, "the parameter file (--params)": args.params}


@contextlib.contextmanager
def warnings_as_lines(command: str):
    """Each warning while the block runs as one line on stderr: `jsphere COMMAND: warning: ...`."""
    import warnings

    def one_line(message, *args, **kwargs):
        print(f"jsphere {command}: warning: {message}", file=sys.stderr, flush=True)

    with warnings.catch_warnings():
        warnings.showwarning = one_line
        yield


def add_imu_flags(group, sigmas=(None, None, None)) -> None:
    """The flags of onboard sensors on the parser `group`: the IMU's mounting (`--imu-position`,
    `--imu-rotation`) and the channels' noise levels (`--sigma-gyro`, `--sigma-acc`,
    `--sigma-encoder`) with defaults `sigmas` (None: estimated)."""
    group.add_argument(
        "--imu-position",
        nargs=3,
        type=float,
        default=(0.0, 0.0, 0.0),
        metavar=("X", "Y", "Z"),
        help="the IMU's position [m], platform components from the shell's centre (default 0 0 0)",
    )
    group.add_argument(
        "--imu-rotation",
        nargs=4,
        type=float,
        default=(1.0, 0.0, 0.0, 0.0),
        metavar=("QW", "QX", "QY", "QZ"),
        help="the IMU's orientation: a scalar-first quaternion mapping IMU components to platform components "
        "(default 1 0 0 0)",
    )
    slip = "; a larger one down-weights encoders whose rollers slip"
    for name, what, default, more in zip(
        ("gyro", "acc", "encoder"),
        ("gyro noise [rad/s]", "accelerometer noise [m/s^2]", "encoder noise [rad]"),
        sigmas,
        ("", "", slip),
    ):
        shown = "estimated" if default is None else f"{default:.3g}"
        group.add_argument(f"--sigma-{name}", type=float, default=default, help=f"{what} (default: {shown}){more}")
