"""`jsphere convert`: a raw motion-capture export and its inputs table -> a trial CSV
(docs/capture.md)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

NAME = "convert"
EXAMPLES = """
  jsphere convert capture.csv --format motive --inputs inputs.csv --out trial.csv
  jsphere convert session.c3d --format c3d --inputs inputs.csv --rigid-body sphere --units mm --out trial.csv
  jsphere convert capture.csv --format motive --inputs plan.csv --input-kind chi_dot --time-offset auto --out trial.csv
"""


def add_parser(sub) -> None:
    cv = sub.add_parser(
        NAME,
        help="raw motion-capture export + inputs table -> trial CSV (docs/capture.md)",
        description="Convert a raw motion-capture export (Motive CSV, Vicon Nexus CSV or C3D) and the table of "
        "the inputs sent to the wheels into a trial CSV for `jsphere fit` (docs/capture.md): the shell "
        "centre's path and the platform's orientation, checked and resampled. Warnings name the frames "
        "and markers they are about.",
    )
    cv.add_argument("raw", help="the raw export (Motive CSV, Vicon Nexus CSV, or C3D)")
    cv.add_argument("--format", required=True, choices=("motive", "vicon", "c3d"))
    cv.add_argument("--inputs", required=True, help="inputs table: t, chi_dot_1..N or t, K_1..N")
    cv.add_argument(
        "--input-kind",
        choices=("chi_dot", "K"),
        help="which input family to read: from a JointState, velocity (chi_dot) or effort (K); from an inputs table "
        "holding both, its columns",
    )
    cv.add_argument("--out", required=True, help="the trial CSV to write (never one of the input files)")
    cv.add_argument(
        "--units", default="auto", choices=("auto", "m", "mm"), help="length units of the export (default: auto)"
    )
    cv.add_argument("--up-axis", choices=("y", "z"), help="the export's up axis (default: y for Motive, z otherwise)")
    cv.add_argument("--rigid-body", help="Motive rigid body / Vicon subject whose markers to use")
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
    cv.add_argument("--no-cache", action="store_true", help=argparse.SUPPRESS)


def run(args) -> int:
    import functools
    import math
    import warnings

    from .._runtime.errors import InputError
    from .._runtime.files import check_output
    from ..capture.body import read_body_markers
    from ..capture.convert import convert_raw
    from ..capture.inputs import read_inputs_csv
    from ..capture.trial import write_trial
    from ..capture.validation import CaptureWarning

    if not all(math.isfinite(v) for v in args.body_offset):
        raise InputError(
            f"--body-offset X Y Z must be finite numbers [m]; got {' '.join(f'{v:g}' for v in args.body_offset)}."
        )
    time_offset = _time_offset(args.time_offset)
    out = Path(args.out)
    inputs = {"the raw export": args.raw, "the inputs table": args.inputs, "the body markers": args.body_markers}
    check_output(out, inputs=inputs, example=str(out / "trial.csv"))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", CaptureWarning)
        try:
            body = read_body_markers(args.body_markers) if args.body_markers else None
            t_in, u_in, kind, _ = read_inputs_csv(
                args.inputs, kind=args.input_kind, allow_truncated=args.allow_truncated
            )
            convert = functools.partial(
                convert_raw,
                args.raw,
                (t_in, u_in, kind),
                format=args.format,
                units=args.units,
                up_axis=args.up_axis,
                rigid_body=args.rigid_body,
                body_markers=body,
                body_offset=tuple(args.body_offset),
                allow_truncated=args.allow_truncated,
            )
            if time_offset is None:
                time_offset = _estimate_offset(convert, t_in, u_in, kind)
            trial = convert(time_offset=time_offset)
        finally:  # the warnings of a conversion that then fails say what went before
            for w in caught:
                if issubclass(w.category, CaptureWarning):
                    print(f"jsphere convert: warning: {w.message}", file=sys.stderr)
                else:
                    warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)
    write_trial(out, trial)
    print(f"{trial!r} -> {out}")
    return 0


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


def _estimate_offset(convert, t_in, u_in, kind) -> float:
    """`--time-offset auto`: the capture converted once without an offset (its warnings held
    back), the offset estimated from it and the inputs (`estimate_time_offset`), printed."""
    import warnings

    from ..capture.clock import estimate_time_offset

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        first = convert(time_offset=0.0)
    offset, corr = estimate_time_offset(first.t, first.x, first.y, first.q, t_in, u_in, kind)
    print(
        f"jsphere convert: time offset estimated: {offset:+.4f} s (correlation {corr:.3f}); --time-offset {offset:.4f}"
    )
    return offset
