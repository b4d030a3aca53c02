"""`jsphere animate`: a run seen moving, as a video (MP4, GIF) or an interactive HTML viewer
(docs/animation.md)."""

from __future__ import annotations

from pathlib import Path

from .options import progress

NAME = "animate"
EXAMPLES = """
  jsphere animate plan.csv --out plan.mp4
  jsphere animate trials/ws_00.csv --out ws_00.gif --speed 2 --size 480 360
  jsphere animate fit.json trials/*.csv --trial ws_01 --out fit.html
  jsphere animate study/ study.toml --view top --out study.mp4
"""


def add_parser(sub) -> None:
    an = sub.add_parser(
        NAME,
        help="a run seen moving: MP4, GIF or an interactive HTML viewer (docs/animation.md)",
        description="Draw the robot moving: the shell rolling with its meridians, the platform and its omniwheels "
        "turning inside, the centre of mass, the path on the floor and the target, with the time, speed and "
        "wheel rates on screen. INPUT is a trial CSV (a capture or a synthetic trial), a plan CSV (jsphere plan), "
        "a fit.json (each trial's capture with the fitted model ghosted over it, the worst fit first; its trials "
        "beside it or given after it) or a Monte-Carlo study folder (its study file beside it or given after "
        "it). --out ends in .mp4, .gif or .html (one self-contained file that opens offline).",
    )
    an.add_argument("input", metavar="INPUT", help="trial or plan CSV, fit.json, or Monte-Carlo study folder")
    an.add_argument(
        "more", nargs="*", metavar="FILE", help="a fit's trial files (or folders), or a study folder's .toml"
    )
    an.add_argument("--out", required=True, metavar="FILE", help="the animation: FILE.mp4, FILE.gif or FILE.html")
    an.add_argument(
        "--params",
        metavar="FILE",
        help="the robot drawn (.toml or .json); default the input's own (a plan's: the robot its JSON records) or the "
        "paper's; for a plan, a robot other than the one it was made for is refused",
    )
    an.add_argument("--fps", type=float, help="frames per second (default 30; 20 for .gif, 15 for .html)")
    an.add_argument(
        "--speed", type=float, default=1.0, help="playback factor: a run of T s plays in T/SPEED s (default 1)"
    )
    an.add_argument(
        "--size",
        type=int,
        nargs=2,
        metavar=("W", "H"),
        help="picture size in pixels (default 640 480; .gif 480 360; .html 900 700)",
    )
    an.add_argument("--trial", action="append", metavar="NAME", help="a fit's trial to show (repeatable; default all)")
    an.add_argument("--view", choices=("3d", "top"), default="3d", help="camera: 3d (default) or top (from above)")
    an.add_argument("--no-cache", action="store_true", help="do not use the persistent compilation cache")


def run(args) -> int:
    from .._runtime.errors import ExitCode, InputError
    from .._runtime.files import check_output
    from ..plots.animation.api import SUFFIXES, animate

    out = Path(args.out)
    if out.suffix.lower() not in SUFFIXES:
        raise InputError(f"--out {out}: an animation ends in .mp4, .gif or .html; got {out.suffix or 'no suffix'!r}.")
    inputs = {
        "the input": args.input if not Path(args.input).is_dir() else None,
        "the file given": [m for m in args.more if not Path(m).is_dir()],
        "the parameter file (--params)": args.params,
    }
    check_output(out, inputs=inputs, example=str(Path(args.out) / "run.mp4"))
    folder = Path(args.input)
    if folder.is_dir() and out.resolve().is_relative_to(folder.resolve()):
        raise InputError(
            f"--out {out}: inside the study folder {folder}, which is input; write the animation elsewhere."
        )
    params = None
    if Path(args.input).suffix.lower() == ".csv" and Path(args.input).is_file():
        from .track import plan_robot

        params = plan_robot(args.input, args.params)  # a plan's robot, checked against --params
    elif args.params:
        from ..model.params import RobotParams

        params = RobotParams.load(args.params)
    written = animate(
        args.input,
        out,
        params=params,
        captures=args.more,
        trials=args.trial,
        fps=args.fps,
        speed=args.speed,
        size=args.size,
        view=args.view,
        progress=progress(args),
    )
    print(f"wrote {written}")
    return ExitCode.OK
