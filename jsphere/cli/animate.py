"""`jsphere animate`: a run seen moving, as a video (MP4, GIF) or an interactive HTML viewer
(docs/animation.md); and `jsphere.animate`, which reads the command's inputs (a trial or plan
CSV, a fit's JSON with its trials, a Monte-Carlo study folder) into the results
`jsphere.plots.animation.animate` draws. Inputs are only read, never written."""

from __future__ import annotations

import json
from pathlib import Path
from typing import TYPE_CHECKING

from .._runtime.errors import ExitCode, InputError
from .options import progress

if TYPE_CHECKING:
    from ..model.params import RobotParams
    from ..plots.animation.scene import Scene

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


def run(args) -> int:
    from .._runtime.files import check_output
    from ..plots.animation.api import check_options

    out = check_options(args.out)[0]  # an animation's suffix, before any file is looked at
    source = Path(args.input)
    inputs = {
        "the input": None if source.is_dir() else args.input,
        "the file given": [m for m in args.more if not Path(m).is_dir()],
        "the parameter file (--params)": args.params,
    }
    check_output(out, inputs=inputs, example=str(Path(args.out) / "run.mp4"))
    if source.is_dir() and out.resolve().is_relative_to(source.resolve()):
        raise InputError(
            f"--out {out}: inside the study folder {source}, which is input; write the animation elsewhere."
        )
    params = None
    if source.suffix.lower() == ".csv" and source.is_file():
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


#: the columns of a plan table that the animation reads (`Plan.table`)
PLAN_COLUMNS = ("t", "x", "y", "gamma_1", "gamma_2", "gamma_3", "heading")


def animate(
    source,
    out,
    *,
    params=None,
    captures=None,
    trials=None,
    fps: float | None = None,
    speed: float = 1.0,
    size: tuple[int, int] | None = None,
    view: str = "3d",
    progress=None,
) -> Path:
    """Show a run: write `out` (`.mp4`, `.gif` or `.html`, atomically) and return its path.

    **The picture**: the shell as a translucent sphere with meridians that turn with its own
    attitude, the platform (the polygon through the wheel centres) and each omniwheel at their
    geometry (`wheel_r`, `wheel_n`, `wheel_alpha`, `Rw`; the spokes turn with `chi_i`, the roller
    axis `alpha_i` at the contact), the centre of mass `r_m`, the path on the floor and the
    target; the time, speed and wheel rates `chi_dot_i` on screen. Axes: jsphere's fixed frame
    [m], Z up. `jsphere.plots.animation.scene` says where each piece comes from.

    **Arguments:**
    - `source`: a `Trajectory`; a `Trial`; a `Plan`; a `FitResult` with `captures` (its trials:
      each capture with the fitted model's replay ghosted over it, the residual on screen, the
      worst-fitting trial first); a `Scene` or a list of them (a study's:
      `jsphere.plots.animation.sources.montecarlo_scene`); or the path of a trial CSV, a
      plan CSV (`jsphere plan`), a fit's JSON (its trials beside it, or their files in
      `captures`) or a Monte-Carlo study folder (its study file in `captures`, else the one
      beside the folder with the folder's `[vary]`), read here into those results.
    - `params`: the robot drawn (default: the source's own, else the paper's).
    - `trials`: the names of a fit's trials to show (default all).
    - `fps`: frames per second (default 30; 20 for GIF, 15 for HTML); `speed`: playback factor (a run of `T`
      s plays in `T / speed` s, within one frame); `size`: `(width, height)` [pixels];
      `view`: `"3d"` or `"top"` (from above).
    - `progress`: as elsewhere in jsphere (`None`: a bar on a terminal).

    A 10 s run at 30 frames per second renders in well under 30 s on 2 cores
    (docs/performance.md)."""
    from ..plots.animation.api import animate as draw
    from ..plots.animation.api import check_options

    check_options(out, fps=fps, speed=speed, size=size, view=view)  # before any file is read
    if isinstance(source, (str, Path)):
        source, captures = scenes_from_path(source, captures or (), params=params, trials=trials), None
    options = dict(fps=fps, speed=speed, size=size, view=view, progress=progress)
    return draw(source, out, params=params, captures=captures, trials=trials, **options)


def _read_json(path: Path) -> dict:
    try:
        return json.loads(path.read_text())
    except FileNotFoundError:
        raise InputError(f"{path} does not exist; give a study folder that jsphere montecarlo wrote.") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise InputError(f"{path}: not valid JSON ({e}).") from None


def montecarlo_scene(folder, study, params: RobotParams | None = None) -> Scene:
    """A Monte-Carlo study folder with its study file (`.toml`): `sources.montecarlo_scene` of
    the folder's trials and `stats.json`. `params`: the nominal robot (default: the study's)."""
    import numpy as np

    from ..montecarlo.store import read_result
    from ..montecarlo.study import load_study
    from ..plots.animation.sources import montecarlo_scene as scene

    folder = Path(folder)
    result, stats = read_result(folder), _read_json(folder / "stats.json")
    st = load_study(study)
    if not np.any(result.status == 0):
        raise InputError(f"{folder}: no successful trial; nothing to animate.")
    base = params if params is not None else st.params
    return scene(result, base, st.gaits, reset=st.options.reset, stats=stats, title=f"Monte-Carlo study {folder.name}")


def _csv_header(path: Path) -> list[str]:
    from ..capture.text import read_text

    for line in read_text(path).splitlines():
        if line.strip() and not line.lstrip().startswith("#"):
            return [c.strip() for c in line.split(",")]
    raise InputError(f"{path}: the file holds no table (no header line); give a trial CSV or a plan CSV.")


def plan_table_scene(path, params: RobotParams | None = None) -> Scene:
    """A plan table (`jsphere plan --out plan.csv`): the platform's attitude from its `gamma_1..3`
    and `heading`, the wheel rates `chi_dot_i`, the target from `plan.json` beside it (else the
    last row). `params`: the robot planned for (default: the paper's)."""
    import numpy as np

    from ..model.params import RobotParams
    from ..plots.animation.scene import Scene, body_from_poses, platform_from_table

    path = Path(path)
    params = params if params is not None else RobotParams.paper()
    try:
        data = np.genfromtxt(path, delimiter=",", names=True, dtype=float, encoding="utf-8")
    except ValueError as e:
        raise InputError(f"{path}: not a plan table ({e}).") from None
    cols = data.dtype.names or ()
    missing = [c for c in PLAN_COLUMNS if c not in cols]
    if missing:
        raise InputError(f"{path}: a plan table needs the columns {', '.join(missing)}; write it with jsphere plan.")
    data = np.atleast_1d(data)
    if len(data) < 2 or not np.all(np.isfinite([data[c] for c in PLAN_COLUMNS])):
        raise InputError(f"{path}: a plan table needs at least two rows of finite numbers; write it with jsphere plan.")
    N = params.n_wheels
    rates = [f"chi_dot_{i + 1}" for i in range(N)]
    chi_dot = np.stack([data[c] for c in rates], axis=-1) if all(c in cols for c in rates) else None
    gamma = np.stack([data["gamma_1"], data["gamma_2"], data["gamma_3"]], axis=-1)
    R = platform_from_table(params, gamma, data["heading"])
    body = body_from_poses(params, data["t"], data["x"], data["y"], R, chi_dot=chi_dot, label="plan")
    target, feasible = _plan_record(path.with_suffix(".json"), (float(data["x"][-1]), float(data["y"][-1])))
    title = f"{feasible or 'plan'} ({path.name}) to ({target[0]:.3f}, {target[1]:.3f}) m in {body.duration:.2f} s"
    return Scene([body], params, title=title, target=target)


def _plan_record(info: Path, target: tuple[float, float]) -> tuple[tuple[float, float], str]:
    """The target and the feasibility text of the plan's JSON record `info` (if it is there)."""
    feasible = ""
    if info.is_file():
        try:
            rec = json.loads(info.read_text())
            if isinstance(rec.get("target"), list) and len(rec["target"]) >= 2:
                target = (float(rec["target"][0]), float(rec["target"][1]))
            feasible = "feasible plan" if rec.get("feasible") else "plan (NOT feasible)"
        except (ValueError, TypeError, UnicodeDecodeError):
            pass
    return target, feasible


def _fit_trials(fit_path: Path, record: dict, given) -> list:
    """The trials of the fit `record`: the files `given` (or those in the folders given), else
    `<name>.csv` beside the fit's JSON; an error names the trials that are missing."""
    from ..capture.onboard import refuse_onboard
    from ..capture.trial import read_trials

    names = [t.get("name") for t in record.get("trials", []) if isinstance(t, dict)]
    if given:
        trials = read_trials(given)
        refuse_onboard(trials, "jsphere animate")
        if names and not {t.name for t in trials} & set(names):
            raise InputError(
                f"{fit_path}: none of the trial files given is one of the fit's trials ({', '.join(names)})."
            )
        return [t for t in trials if not names or t.name in names]
    if not names:
        raise InputError(f"{fit_path}: the fit names no trials; give its trial files after it.")
    missing = [n for n in names if not (fit_path.parent / f"{n}.csv").is_file()]
    if missing:
        raise InputError(
            f"{fit_path}: the fit's trials {', '.join(missing)} are missing (looked for <name>.csv beside it); give "
            f"the trial files after the fit: jsphere animate {fit_path} trials/*.csv --out fit.mp4."
        )
    trials = read_trials([fit_path.parent / f"{n}.csv" for n in names])
    refuse_onboard(trials, "jsphere animate")
    return trials


def fit_file_scenes(path: Path, extra=(), *, params: RobotParams | None = None, trials=None) -> list[Scene]:
    """The scenes of a fit's JSON with its trials (`sources.fit_scenes`)."""
    from ..model.params import RobotParams
    from ..plots.animation.sources import fit_scenes

    record = _read_json(path)
    if not isinstance(record, dict) or "params" not in record or "trials" not in record:
        raise InputError(f"{path}: not a fit result (no params and trials); give a fit.json of jsphere fit.")
    found = _fit_trials(path, record, list(extra))
    model = params if params is not None else RobotParams.load(path)
    if trials:
        unknown = [n for n in trials if n not in {t.name for t in found}]
        if unknown:
            have = ", ".join(t.name for t in found)
            raise InputError(f"--trial {', '.join(unknown)}: not a trial of {path} ({have}).")
        found = [t for t in found if t.name in trials]
    worst = (record.get("verdict") or {}).get("worst_trial")
    return fit_scenes(model, found, worst=worst, status=f"fit {record.get('status', '')}".strip())


def scenes_from_path(path, extra=(), *, params: RobotParams | None = None, trials=None) -> list[Scene]:
    """The scenes of a file or folder: `animate` of a path, `extra` its `captures`."""
    from ..capture.onboard import refuse_onboard
    from ..capture.trial import read_trial
    from ..model.params import RobotParams
    from ..plots.animation.sources import trial_scene

    path = Path(path)
    if not path.exists():
        raise InputError(f"{path} does not exist; give a trial or plan CSV, a fit.json or a Monte-Carlo study folder.")
    if path.is_dir():
        if not (path / "manifest.json").is_file():
            raise InputError(
                f"{path} is a folder but not a Monte-Carlo study (no manifest.json); give a study folder, a trial "
                "or plan CSV, or a fit.json."
            )
        study = [Path(e) for e in extra if str(e).lower().endswith(".toml")]
        if not study:
            study = _find_study(path)
        return [montecarlo_scene(path, study[0], params)]
    suffix = path.suffix.lower()
    if suffix == ".csv":
        if {"heading", "gamma_1"} <= set(_csv_header(path)):
            return [plan_table_scene(path, params)]
        trial = read_trial(path)
        refuse_onboard([trial], "jsphere animate")
        return [trial_scene(trial, params if params is not None else RobotParams.paper())]
    if suffix == ".json":
        return fit_file_scenes(path, extra, params=params, trials=trials)
    raise InputError(
        f"{path}: unknown kind of input ({path.suffix or 'no suffix'}); give a trial or plan CSV (.csv), a fit "
        "result (.json) or a Monte-Carlo study folder."
    )


def _find_study(folder: Path) -> list[Path]:
    """The study file of a study folder: the one `.toml` beside the folder (or in it) whose
    `[vary]` is the folder's."""
    import tomllib

    vary = _read_json(folder / "manifest.json").get("vary", {})
    found = []
    for cand in sorted([*folder.glob("*.toml"), *folder.parent.glob("*.toml")]):
        try:
            cfg = tomllib.loads(cand.read_text())
        except (OSError, ValueError, UnicodeDecodeError):
            continue
        if {k: list(v) for k, v in (cfg.get("vary") or {}).items()} == vary:
            found.append(cand)
    if len(found) != 1:
        what = "no study file" if not found else f"{len(found)} study files"
        raise InputError(
            f"{folder}: {what} with its [vary] beside it; give the study file after the folder: "
            f"jsphere animate {folder} study.toml --out study.mp4."
        )
    return found
