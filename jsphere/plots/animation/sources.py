"""The runs an animation shows, read from what jsphere computes or writes: a `Trajectory`, a
`Trial` (a capture or a synthetic trial), a `Plan` or a plan table (`jsphere plan`), a fit with
its trials (each capture with the fitted model's replay ghosted over it, the worst-fitting
trial first) and a Monte-Carlo study folder (a handful of trials' paths, the stop points with
their 95 % ellipse). Each becomes a list of `Scene`s. Inputs are only read, never written."""

from __future__ import annotations

import json
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from ..._runtime.errors import InputError
from .scene import Scene, body_from_poses, body_from_trajectory, body_from_trial, platform_from_table

if TYPE_CHECKING:
    from ...model.params import RobotParams

#: the columns of a plan table that the animation reads (`Plan.table`)
PLAN_COLUMNS = ("t", "x", "y", "gamma_1", "gamma_2", "gamma_3", "heading")
#: Monte-Carlo trials whose paths are drawn
MONTECARLO_PATHS = 5


# ------------------------------------------------------------------------------ from objects


def trajectory_scene(traj, params: RobotParams, *, title: str = "", target=None) -> Scene:
    """A `Trajectory` (a simulation of `params`)."""
    return Scene([body_from_trajectory(traj, label="simulated")], params, title=title or "simulated run", target=target)


def trial_scene(trial, params: RobotParams, *, title: str = "") -> Scene:
    """A `Trial`: its measured poses."""
    return Scene([body_from_trial(params, trial)], params, title=title or f"trial {trial.name} (measured poses)")


def plan_scene(plan, *, title: str = "") -> Scene:
    """A `Plan`: its accurate trajectory and its target."""
    tgt = np.asarray(plan.target, float)
    body = body_from_trajectory(plan.trajectory, label="plan")
    head = "feasible plan" if plan.feasible else "plan (NOT feasible)"
    text = title or f"{head} to ({tgt[0]:.3f}, {tgt[1]:.3f}) m in {plan.duration:.2f} s"
    return Scene([body], plan.params, title=text, target=(float(tgt[0]), float(tgt[1])))


def fit_scenes(params: RobotParams, trials, *, worst: str | None = None, status: str = "") -> list[Scene]:
    """A fit: per trial, the capture (solid) and the fitted model `params` replaying it (`compare`:
    simulated from the trial's own initial pose, its initial velocities estimated as the fit
    estimates them) ghosted over it, with the residual on screen; the worst-fitting trial first
    (`worst`, a fit's `verdict["worst_trial"]`; else the largest RMS position residual)."""
    from ...identify.compare import compare

    trials = list(trials)
    res = compare(params, trials)
    rms = {r["name"]: float(r["rms_pos_m"]) for r in res.trials}
    order = sorted(range(len(trials)), key=lambda i: -rms.get(trials[i].name, 0.0))
    if worst is not None:
        order = sorted(order, key=lambda i: trials[i].name != worst)
    scenes = []
    for rank, i in enumerate(order):
        tr, model = trials[i], res.predicted[i]
        bodies = [body_from_trial(params, tr, label=f"{tr.name} (capture)"), body_from_trial(params, model, ghost=True)]
        bodies[1].label = "fitted model"
        which = " - worst fit" if rank == 0 and len(trials) > 1 else ""
        rms_text = f"RMS {1e3 * rms[tr.name]:.2f} mm" if tr.name in rms else ""
        head = f"{status}; " if status else ""
        title = f"{head}trial {tr.name}{which}, {rms_text}\ncapture (blue) and fitted model (orange, faint)"
        scenes.append(Scene(bodies, params, title=title, residual=True))
    return scenes


def montecarlo_scene(folder, study, params: RobotParams | None = None, *, paths: int = MONTECARLO_PATHS) -> Scene:
    """A Monte-Carlo study folder (`jsphere montecarlo --out`) with its study file (`.toml`):
    the study's gaits executed by the robots drawn for its first `paths` successful trials
    (growing together), and all the stop points of the folder with the 95 % ellipse of its
    `stats.json` at the end. `params`: the nominal robot (default: the study's)."""
    from ...gaits.gaits import simulate_gaits
    from ...model.names import set_value
    from ...montecarlo.study import load_study

    folder = Path(folder)
    manifest, stats = _read_json(folder / "manifest.json"), _read_json(folder / "stats.json")
    st = load_study(study)
    base = params if params is not None else st["params"]
    names = list(manifest.get("vary", {}))
    batches = sorted(folder.glob("batch_*.npz"))
    if not batches:
        raise InputError(f"{folder}: no batch files (batch_*.npz); run the study there first (jsphere montecarlo).")
    vals, xs, ys, index = [], [], [], []
    for path in batches:
        try:
            with np.load(path, allow_pickle=False) as z:
                ok = np.asarray(z["status"]) == 0
                first = int(path.stem.split("_")[-1]) * int(manifest.get("batch_size", ok.size))
                index.append(first + np.flatnonzero(ok))
                vals.append(np.asarray(z["vals"])[ok])
                xs.append(np.asarray(z["x"])[ok])
                ys.append(np.asarray(z["y"])[ok])
        except Exception as e:  # noqa: BLE001 - any unreadable file is named
            raise InputError(
                f"{path}: not a batch of a study ({e}); run the study again (jsphere montecarlo)."
            ) from None
    vals, index = np.concatenate(vals), np.concatenate(index)
    cloud = np.stack([np.concatenate(xs), np.concatenate(ys)], axis=-1)
    if not len(cloud):
        raise InputError(f"{folder}: no successful trial; nothing to animate.")
    reset = st["kwargs"].get("reset", False)
    bodies = []
    for i in range(min(paths, len(vals))):
        p = base
        for name, v in zip(names, vals[i]):  # the robot drawn for the trial
            p = set_value(p, name, v)
        tr = simulate_gaits(p, st["gaits"], reset=reset)
        bodies.append(body_from_trajectory(tr, label=f"trial {index[i]}"))
    ellipse = _ellipse(stats) if stats.get("ellipse") else None
    title = f"Monte-Carlo study {folder.name}: {len(bodies)} of {len(cloud)} trials; stop points and 95 % ellipse at the end"
    return Scene(bodies, base, title=title, cloud=cloud, ellipse=ellipse)


def _ellipse(st: dict) -> np.ndarray:
    """The confidence ellipse of `MonteCarloResult.stats()` as `(P, 2)` [m]."""
    minor, major = st["ellipse"]["semi_axes_m"]
    ang, (x0, y0) = st["ellipse"]["angle_rad"], st["mean_xy_m"]
    t = np.linspace(0, 2 * np.pi, 100)
    e1, e2 = np.array([np.cos(ang), np.sin(ang)]), np.array([-np.sin(ang), np.cos(ang)])
    return (np.array([x0, y0])[:, None] + major * np.outer(e1, np.cos(t)) + minor * np.outer(e2, np.sin(t))).T


# ------------------------------------------------------------------------------- from files


def _read_json(path: Path) -> dict:
    try:
        return json.loads(path.read_text())
    except FileNotFoundError:
        raise InputError(f"{path} does not exist; give a study folder that jsphere montecarlo wrote.") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise InputError(f"{path}: not valid JSON ({e}).") from None


def _csv_header(path: Path) -> list[str]:
    from ...capture.text import read_text

    for line in read_text(path).splitlines():
        if line.strip() and not line.lstrip().startswith("#"):
            return [c.strip() for c in line.split(",")]
    raise InputError(f"{path}: the file holds no table (no header line); give a trial CSV or a plan CSV.")


def plan_table_scene(path, params: RobotParams | None = None) -> Scene:
    """A plan table (`jsphere plan --out plan.csv`): the platform's attitude from its `gamma_1..3`
    and `heading`, the wheel rates `chi_dot_i`, the target from `plan.json` beside it (else the
    last row). `params`: the robot planned for (default: the paper's)."""
    from ...model.params import RobotParams

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
    info = path.with_suffix(".json")
    target = (float(data["x"][-1]), float(data["y"][-1]))
    feasible = ""
    if info.is_file():
        try:
            rec = json.loads(info.read_text())
            if isinstance(rec.get("target"), list) and len(rec["target"]) >= 2:
                target = (float(rec["target"][0]), float(rec["target"][1]))
            feasible = "feasible plan" if rec.get("feasible") else "plan (NOT feasible)"
        except (ValueError, TypeError, UnicodeDecodeError):
            pass
    title = f"{feasible or 'plan'} ({path.name}) to ({target[0]:.3f}, {target[1]:.3f}) m in {body.duration:.2f} s"
    return Scene([body], params, title=title, target=target)


def _fit_trials(fit_path: Path, record: dict, given) -> list:
    """The trials of the fit `record`: the files `given` (or those in the folders given), else
    `<name>.csv` beside the fit's JSON; an error names the trials that are missing."""
    from ...capture.trial import read_trials

    names = [t.get("name") for t in record.get("trials", []) if isinstance(t, dict)]
    if given:
        trials = read_trials(given)
        known = {t.name for t in trials}
        if names and not known & set(names):
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
    return read_trials([fit_path.parent / f"{n}.csv" for n in names])


def scenes_from_path(path, extra=(), *, params: RobotParams | None = None, trials=None) -> list[Scene]:
    """The scenes of a file or folder (module docstring). `extra`: a fit's trial files, or a
    Monte-Carlo folder's study file; `params`: the robot drawn (default: the file's own, else
    the paper's); `trials`: the names of a fit's trials to show (default all)."""
    from ...capture.trial import read_trial
    from ...model.params import RobotParams

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
        if "heading" in _csv_header(path) and "gamma_1" in _csv_header(path):
            return [plan_table_scene(path, params)]
        trial = read_trial(path)
        return [trial_scene(trial, params if params is not None else RobotParams.paper())]
    if suffix == ".json":
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
    raise InputError(
        f"{path}: unknown kind of input ({path.suffix or 'no suffix'}); give a trial or plan CSV (.csv), a fit "
        "result (.json) or a Monte-Carlo study folder."
    )


def _find_study(folder: Path) -> list[Path]:
    """The study file of a study folder: the one `.toml` beside the folder (or in it) whose
    `[vary]` is the folder's."""
    vary = _read_json(folder / "manifest.json").get("vary", {})
    found = []
    for cand in sorted([*folder.glob("*.toml"), *folder.parent.glob("*.toml")]):
        try:
            import tomllib

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
