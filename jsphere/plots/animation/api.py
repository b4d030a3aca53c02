"""`animate`: a run as a video (MP4, GIF) or an interactive HTML viewer, drawn from result objects."""

from __future__ import annotations

from pathlib import Path

from ..._runtime.errors import InputError
from .scene import Scene

#: the outputs by suffix
SUFFIXES = (".mp4", ".gif", ".html")
#: frames per second by default: GIF frame delays are whole centiseconds (20 fps: 5 cs); the
#: viewer holds every frame's geometry (15 fps: about 0.5 MB per second of playback)
DEFAULT_FPS = {".mp4": 30.0, ".gif": 20.0, ".html": 15.0}
#: the picture's size [pixels] by default
DEFAULT_SIZE = {".mp4": (640, 480), ".gif": (480, 360), ".html": (900, 700)}


def scenes_of(source, *, params=None, captures=None, trials=None) -> list[Scene]:
    """The `Scene`s of `source` (see `animate`)."""
    from ...capture.trial import Trial
    from ...model.params import RobotParams
    from ...planning.result import Plan
    from ...solve.trajectory import Trajectory
    from . import sources

    many = list(source) if isinstance(source, (list, tuple)) and source else [source]
    if all(isinstance(s, Scene) for s in many):
        return many
    if isinstance(source, Plan):
        return [sources.plan_scene(source)]
    robot = params if params is not None else RobotParams.paper()
    if isinstance(source, Trajectory):
        return [sources.trajectory_scene(source, robot)]
    if isinstance(source, Trial):
        return [sources.trial_scene(source, robot)]
    if hasattr(source, "verdict") and hasattr(source, "params") and hasattr(source, "trials"):  # a FitResult
        if not captures:
            raise InputError("animate: a fit result is shown with its trials; give them as captures=[Trial, ...].")
        found = [t for t in captures if not trials or t.name in trials]
        worst = (source.verdict or {}).get("worst_trial")
        status = f"fit {source.status}".strip()
        return sources.fit_scenes(params if params is not None else source.params, found, worst=worst, status=status)
    raise InputError(
        f"animate: cannot show a {type(source).__name__}; give a Trajectory, Trial, Plan, FitResult (with its "
        "captures) or Scene (`jsphere.animate` also reads the path of a trial or plan CSV, a fit.json or a "
        "Monte-Carlo study folder)."
    )


def check_options(out, *, fps=None, speed=1.0, size=None, view="3d") -> tuple[Path, float, float, tuple[int, int]]:
    """`out`, `fps`, `speed` and `size` of `animate` checked, with the defaults of `out`'s suffix;
    an `InputError` names the first that is out of range."""
    out = Path(out)
    suffix = out.suffix.lower()
    if suffix not in SUFFIXES:
        raise InputError(f"--out {out}: an animation ends in .mp4, .gif or .html; got {out.suffix or 'no suffix'!r}.")
    fps = DEFAULT_FPS[suffix] if fps is None else float(fps)
    if not (0 < fps <= 120):
        raise InputError(f"--fps must be a number of frames per second in (0, 120]; got {fps:g}.")
    speed = float(speed)
    if not (0 < speed < float("inf")):
        raise InputError(f"--speed must be a positive playback factor; got {speed:g}.")
    size = DEFAULT_SIZE[suffix] if size is None else tuple(int(v) for v in size)
    if len(size) != 2 or not all(16 <= v <= 4096 for v in size):
        raise InputError(f"--size must be a width and a height in pixels, 16 to 4096; got {size}.")
    if view not in ("3d", "top"):
        raise InputError(f"--view must be 3d or top; got {view!r}.")
    return out, fps, speed, size


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
    """Show the run `source`, a result object (a `Trajectory`, `Trial`, `Plan`, `FitResult`
    with its `captures`, or `Scene`s), in `out` (`.mp4`, `.gif` or `.html`, written atomically);
    return its path. The arguments are those of `jsphere.animate`, which also reads files."""
    out, fps, speed, size = check_options(out, fps=fps, speed=speed, size=size, view=view)
    scenes = scenes_of(source, params=params, captures=captures, trials=trials)
    from .video import render
    from .viewer import write_html

    if out.suffix.lower() == ".html":
        write_html(scenes, out, fps=fps, speed=speed, size=size, view=view)
    else:
        render(scenes, out, fps=fps, speed=speed, size=size, view=view, progress=progress)
    return out
