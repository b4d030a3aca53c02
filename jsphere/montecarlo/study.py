"""A study's description: its distributions (`check_vary`), the feedback of a closed loop
(`check_feedback`) and the study file of `jsphere montecarlo` (`load_study`, whose keys are
`StudyOptions`' fields), each checked before any work, with an `InputError` that names the
value."""

from __future__ import annotations

import dataclasses
import math
import warnings
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np

from .._runtime.checks import is_number, real, whole
from .._runtime.errors import InputError
from .._runtime.files import tomllib
from ..gaits.gaits import acceleration, braking, turn
from ..model.limits import Limits
from ..model.names import get_value, parse_name
from ..model.params import RobotParams
from ..planning.tracking.evaluate import Conditions
from .options import StudyOptions
from .sampling import Actuators

#: the distributions of `vary` and the names of their two numbers
DISTRIBUTIONS = {"normal": ("mean", "sd"), "uniform": ("low", "high")}
#: the optional last entry of a distribution: redraw until the parameter set is valid
TRUNCATE = "truncate"
#: the keys of a study's `[feedback]` table (the closed loop of a `track` table) and their
#: defaults: the start pose's spread and the fed-back state's delay and noise of `jsphere
#: track`'s evaluation (`jsphere.planning.tracking.Conditions`), the torque limit of `Limits`
FEEDBACK = {
    **{
        k: getattr(Conditions(), k)
        for k in ("start_sd", "heading_sd", "delay_s", "pos_sd", "att_sd", "omega_sd", "wheel_sd")
    },
    "max_torque": Limits().max_torque,
}
#: their units
_FEEDBACK_UNITS = {
    "start_sd": "m",
    "heading_sd": "rad",
    "delay_s": "s",
    "pos_sd": "m",
    "att_sd": "rad",
    "omega_sd": "rad/s",
    "wheel_sd": "rad/s",
    "max_torque": "N m",
}


def check_feedback(where: str, values: Mapping) -> dict:
    """The `FEEDBACK` settings `values` checked (finite numbers >= 0, the torque limit > 0) and
    completed with the defaults; `InputError` naming the key under `where`."""
    if not isinstance(values, Mapping):
        raise InputError(f"{where} must be a table (e.g. [feedback] delay_s = 0.01); got {values!r}.")
    unknown = sorted(set(values) - set(FEEDBACK))
    if unknown:
        raise InputError(f"{where}: unknown key(s) {unknown}; expected {sorted(FEEDBACK)}.")
    out = dict(FEEDBACK)
    for k, v in values.items():
        out[k] = real(where, k, v, strict=k == "max_torque", unit=_FEEDBACK_UNITS[k])
    return out


def check_commands(where: str, ts: np.ndarray, values: np.ndarray, n_wheels: int) -> None:
    """A command table to replay, `(ts, values)`: it starts at `t = 0` with one column per
    wheel, else an `InputError` under `where`."""
    if ts[0] != 0.0:
        raise InputError(f"{where}: the table must start at t = 0; its first time is {ts[0]:g} s.")
    if values.ndim != 2 or values.shape[1] != n_wheels:
        raise InputError(f"{where}: the robot has {n_wheels} wheels; the table has {values.shape[1:]} columns.")


def check_track(where: str, tab: Mapping, n_wheels: int) -> float:
    """The control period [s] of a feedback table `tab` (`read_track_csv`'s dict): one torque
    column per wheel, at least two rows, equally spaced; else an `InputError` under `where`."""
    t, K_ff = np.asarray(tab["t"], np.float64), np.asarray(tab["K_ff"])
    if K_ff.ndim != 2 or K_ff.shape[1] != n_wheels or np.shape(tab["G"]) != (len(t), n_wheels, 11):
        raise InputError(f"{where}: the robot has {n_wheels} wheels; the table has gains for {K_ff.shape[-1]}.")
    if len(t) < 2 or not np.allclose(np.diff(t), t[1] - t[0], rtol=1e-6, atol=0.0):
        raise InputError(f"{where}: the table needs at least 2 rows, one per control period (equally spaced t).")
    return float(t[1] - t[0])


def check_closed_loop(where: str, Omega0_sd: float, actuators) -> None:
    """The closed loop of a `track` table starts as `feedback` says (`start_sd`, `heading_sd`)
    and takes the actuators' gain, fixed delay and white noise: an `InputError` under `where`
    for a setting it does not model."""
    act = actuators or Actuators()
    if Omega0_sd != 0 or act.delay_sd != 0 or act.band_sd != 0:
        raise InputError(
            f"{where}: the closed loop of a track table starts from the feedback's start_sd and heading_sd and "
            "takes the actuators' gain_sd, delay_s and white_sd; set Omega0_sd, delay_sd and band_sd to 0 "
            f"(got {Omega0_sd}, {act.delay_sd}, {act.band_sd})."
        )


def _target(params: RobotParams, name: str) -> tuple:
    """What a name sets, for finding two names that set the same value."""
    field, index = parse_name(name)
    if field == "R_m":
        return ("r_m",)
    if field == "I" and len(index) == 2:
        index = tuple(sorted(index))
    return (field, index)


def _check_distribution(name: str, spec) -> tuple[str, float, float, bool]:
    """`(kind, a, b, truncate)` of one valid entry of `vary`, else `InputError` naming it."""
    form = f"vary[{name!r}] must be ['normal', mean, sd] or ['uniform', low, high], optionally followed by '{TRUNCATE}'"
    if not isinstance(spec, (tuple, list)) or len(spec) not in (3, 4) or spec[0] not in DISTRIBUTIONS:
        raise InputError(f"{form}; got {spec!r}.")
    if len(spec) == 4 and spec[3] != TRUNCATE:
        raise InputError(f"{form}; got {spec[3]!r} as its last entry.")
    kind = spec[0]
    for label, v in zip(DISTRIBUTIONS[kind], spec[1:3]):
        if not is_number(v) or not math.isfinite(v):
            raise InputError(f"vary[{name!r}]: the {label} must be a finite number; got {v!r}.")
    a, b = float(spec[1]), float(spec[2])
    if kind == "normal" and not b >= 0:
        raise InputError(f"vary[{name!r}]: the standard deviation must be >= 0; got {b}.")
    if kind == "uniform" and not b >= a:
        raise InputError(f"vary[{name!r}]: uniform needs low <= high; got ({a}, {b}).")
    return kind, a, b, len(spec) == 4


def check_vary(params: RobotParams, vary: Mapping[str, Sequence]) -> list[tuple[str, str, float, float, bool]]:
    """`[(name, kind, a, b, truncate)]` of a valid `vary`, else `InputError` naming the entry."""
    if not isinstance(vary, Mapping):
        raise InputError(
            f'vary must be a table {{name: [kind, a, b]}}, e.g. {{"r_m[2]": ["normal", -0.027, 1e-4]}}; got {vary!r}.'
        )
    out, seen = [], {}
    for name, spec in vary.items():
        if not isinstance(name, str):
            raise InputError(f"vary: parameter names are strings such as 'j' or 'I[0,0]'; got {name!r}.")
        parse_name(name)
        if name != "R_m":
            get_value(params, name)  # checks the index fits
        kind, a, b, truncate = _check_distribution(name, spec)
        if get_value(params, name).ndim != 0:
            raise InputError(f"vary[{name!r}]: vary scalar components (e.g. 'I[0,0]'), not a whole field.")
        t = _target(params, name)
        other = next(
            (o for o, ot in seen.items() if ot == t or (t[0] == ot[0] == "r_m" and (len(t) == 1 or len(ot) == 1))), None
        )
        if other is not None:
            raise InputError(f"vary: {other!r} and {name!r} set the same value; vary one of them.")
        seen[name] = t
        out.append((name, kind, a, b, truncate))
    return out


# --- the study file of `jsphere montecarlo` ---

#: the gaits a study file names, by their `kind`
GAITS = {"acceleration": acceleration, "braking": braking, "turn": turn}
GAIT_KINDS = tuple(GAITS)
#: the keys of a study file: the study's own (`trials`, the robot, the gaits, the
#: distributions) and every field of `StudyOptions` that a file gives
STUDY_KEYS = {"trials", "params", "gaits", "vary"} | {
    f.name for f in dataclasses.fields(StudyOptions) if f.metadata["file"] is not None
}


@dataclasses.dataclass(frozen=True)
class Study:
    """A study file read and checked (`load_study`): the robot `params`, the `gaits`, the number
    of trials `n`, the distributions `vary` and the `options` (`StudyOptions`): the arguments
    of `monte_carlo(params, gaits, vary=vary, n=n, options=options)`."""

    params: RobotParams
    gaits: list
    n: int
    vary: dict
    options: StudyOptions

    def __getitem__(self, key: str):
        """`study["params"]`, `["gaits"]`, `["n"]` and `["kwargs"]` (the keywords of the study:
        `vary` and the options set) of a study read as a dict; kept for one release."""
        warnings.warn(
            f'load_study(...)["{key}"] is deprecated; use the attributes of the Study (params, gaits, n, vary, '
            "options).",
            DeprecationWarning,
            stacklevel=2,
        )
        if key != "kwargs":
            return getattr(self, key)
        return {"vary": self.vary} | {f.name: getattr(self.options, f.name) for f in dataclasses.fields(StudyOptions)}


def load_study(path) -> Study:
    """Read a Monte-Carlo study description (TOML) into a `Study`. Its keys (every one optional
    but `vary`) are `trials` (1000 unless given; `--trials` overrides it), `params` (the path
    of a parameter file relative to this file; default: the paper's robot, or the robot of a
    plan's command table), `gaits` (a list of tables `{kind = "acceleration", theta_max = 0.1,
    T = 2.0}`, default acceleration and braking), `[vary]`, and the fields of `StudyOptions`
    that a file gives, under their names (`seed`, `batch_size` (4096 unless given), `mode`,
    `reset`, `Omega0_sd`, `settle`, `[actuators]`, `commands`, `track`, `[feedback]`); e.g.

        trials = 10000
        seed = 0
        mode = "torques"
        commands = "plan-commands.csv"
        [vary]                    # names as in `jsphere fit --free`
        "r_m[2]" = ["normal", -0.0270146, 1e-4]
        m0 = ["normal", 0.8, 0.3, "truncate"]   # truncated to valid robots (m0 > 0)
        [actuators]               # replay modes only; see jsphere.Actuators
        gain_sd = 0.02

    A distribution is `["normal", mean, sd]` or `["uniform", low, high]` with finite numbers
    (`sd >= 0`, `low <= high`), optionally followed by `"truncate"` (docs/montecarlo.md).
    `commands` names a command table, as `jsphere plan --commands` or `jsphere design` write it
    (`study_commands`): a plan's table has a record beside it (the `.json` of the same name)
    that names the robot the plan was made for: without `params` the study runs that robot; a
    `params` that names another robot is an `InputError`. `track` names a feedback table
    (`study_track`), with the measurement model of `[feedback]` (`FEEDBACK`); it takes the
    place of `gaits` and `commands`.

    Every value is checked here, before any work: a bad one raises `InputError` naming the file
    and the key.
    """
    path = Path(path)
    cfg = _read_toml(path)
    n = whole(str(path), "trials", cfg["trials"], 1) if "trials" in cfg else 1000
    given = {"batch_size": 4096, "mode": "torques" if "track" in cfg else "gait"}
    for f in dataclasses.fields(StudyOptions):
        if f.metadata["file"] == "value" and f.name in cfg:
            given[f.name] = f.metadata["check"](str(path), f.name, cfg[f.name])
    params = _study_params(path, cfg)
    if "commands" in cfg and "track" not in cfg:
        params = _commands_robot(path, cfg, params)
    gaits = _study_gaits(path, cfg.get("gaits", [{"kind": "acceleration"}, {"kind": "braking"}]))
    if "actuators" in cfg:
        given["actuators"] = _study_actuators(path, cfg["actuators"])
    if "commands" in cfg and "track" not in cfg:
        given["commands"] = study_commands(path, cfg["commands"], given["mode"], params.n_wheels)
    if "track" in cfg:
        given["track"] = study_track(path, cfg, given["mode"], params.n_wheels)
        given["feedback"] = check_feedback(f"{path}: [feedback]", cfg.get("feedback", {}))
        check_closed_loop(str(path), given.get("Omega0_sd", 0.0), given.get("actuators"))
    elif "feedback" in cfg:
        raise InputError(f'{path}: [feedback] sets up the closed loop of a feedback table; add track = "track.csv".')
    vary = dict(cfg["vary"])
    try:  # the checks monte_carlo makes before any work, with this file's name
        check_vary(params, vary)
    except ValueError as e:
        raise InputError(f"{path}: {e}") from None
    return Study(params, gaits, n, vary, StudyOptions(**given))


def _read_toml(path: Path) -> dict:
    """The study file's table, with only known keys and a `[vary]` table."""
    try:
        cfg = tomllib.loads(path.read_text())
    except FileNotFoundError:
        raise InputError(f"{path}: no such study file.") from None
    except tomllib.TOMLDecodeError as e:
        raise InputError(f"{path}: not valid TOML: {e}") from None
    unknown = sorted(set(cfg) - STUDY_KEYS)
    if unknown:
        raise InputError(f"{path}: unknown key(s) {unknown}; expected {sorted(STUDY_KEYS)}.")
    if "vary" not in cfg:
        raise InputError(f'{path}: a study needs a [vary] table, e.g. "r_m[2]" = ["normal", -0.027, 1e-4].')
    if not isinstance(cfg["vary"], dict):
        raise InputError(
            f'{path}: vary must be a table of distributions, e.g. [vary] "r_m[2]" = ["normal", -0.027, 1e-4]; '
            f"got {cfg['vary']!r}."
        )
    return cfg


def _study_params(path: Path, cfg: dict) -> RobotParams:
    """The robot of a study file: its `params` file (relative to the study file), else the paper's."""
    if "params" not in cfg:
        return RobotParams.paper()
    if not isinstance(cfg["params"], str):
        raise InputError(
            f"{path}: params must be the path of a parameter file (.toml or .json); got {cfg['params']!r}."
        )
    return RobotParams.load((path.parent / cfg["params"]).resolve())


def _commands_robot(path: Path, cfg: dict, params: RobotParams) -> RobotParams:
    """The robot of a study that replays a plan's command table: the robot the plan records
    beside the table (`planned_robot`) when the study names no `params`; `params` when it names
    the same robot; an `InputError` naming both when it names another. `params` as it is for a
    table without such a record."""
    from ..planning.result import planned_robot, robot_difference

    name = cfg["commands"]
    if not isinstance(name, str):
        return params  # study_commands names the bad value
    try:
        recorded = planned_robot((path.parent / name).resolve())
    except InputError as e:
        raise InputError(f"{path}: commands = {name!r}: {e}") from None
    if recorded is None:
        return params
    if "params" not in cfg:
        return recorded.params
    diff = robot_difference(recorded.params, params)
    if diff is not None:
        raise InputError(
            f"{path}: params = {cfg['params']!r} is not the robot the commands {name!r} were planned for, "
            f"{recorded.describe()} (plan vs params: {diff}); leave params out to use the plan's robot, or plan "
            f"again with --params {cfg['params']}."
        )
    return params


def _study_gaits(path: Path, gait_list) -> list:
    """The gaits of a study file's `gaits` list."""
    if not isinstance(gait_list, list) or not gait_list:
        raise InputError(
            f'{path}: gaits must be a non-empty list of tables, e.g. gaits = [{{kind = "acceleration"}}, '
            f'{{kind = "braking"}}]; got {gait_list!r}.'
        )
    gaits = []
    for k, g in enumerate(gait_list):
        if not isinstance(g, dict):
            raise InputError(
                f'{path}: gaits[{k}] must be a table such as {{kind = "acceleration", theta_max = 0.1}}; got {g!r}.'
            )
        g = dict(g)
        kind = g.pop("kind", None)
        if kind not in GAIT_KINDS:
            raise InputError(f"{path}: gaits[{k}].kind must be one of {GAIT_KINDS}; got {kind!r}.")
        try:
            gaits.append(GAITS[kind](**g))
        except (TypeError, ValueError) as e:
            raise InputError(f"{path}: gaits[{k}]: {e}") from None
    return gaits


def _read_table(path: Path, key: str, name, what: str, read):
    """The file that a study file's `key` names (`name`, relative to the study file; `what`: what
    it names), as `read` reads it; `InputError` naming the file and the key when `name` is no
    path, or the file is missing or cannot be read."""
    if not isinstance(name, str):
        raise InputError(f"{path}: {key} must be the path of {what}; got {name!r}.")
    table = (path.parent / name).resolve()
    if not table.is_file():
        raise InputError(f"{path}: {key} = {name!r}: no such file {table}.")
    try:
        return read(table)
    except ValueError as e:
        raise InputError(f"{path}: {key} = {name!r}: {e}") from None


def study_commands(path: Path, name, mode: str, n_wheels: int) -> tuple[np.ndarray, np.ndarray]:
    """`(ts, values)` of the command table a study file's `commands` key names (relative to the
    study file): its `K_1..N` columns with `mode = "torques"`, its `chi_dot_1..N` columns with
    `mode = "wheel_speeds"` (`read_inputs_csv`). `InputError` naming the file and the key when the
    mode replays nothing, the file cannot be read, or the table does not start at `t = 0` with
    one column per wheel."""
    from ..capture.inputs import read_inputs_csv

    if mode == "gait":
        raise InputError(
            f'{path}: commands are replayed through the actuators; set mode = "torques" (columns K_1..K_N) or '
            f'mode = "wheel_speeds" (columns chi_dot_1..N).'
        )
    read = lambda table: read_inputs_csv(table, kind=mode)[:2]
    ts, values = _read_table(path, "commands", name, "a command table (.csv)", read)
    check_commands(f"{path}: commands = {name!r}", ts, values, n_wheels)
    return ts, values


def study_track(path: Path, cfg: dict, mode: str, n_wheels: int) -> dict:
    """The feedback table a study file's `track` key names (relative to the study file), read by
    `jsphere.planning.tracking.read_track_csv`. `InputError` naming the file and the key when the
    study also has `gaits` or `commands`, its mode is not "torques", the file cannot be read, or
    the table has not one torque column per wheel, at least two rows and one rate."""
    from ..planning.tracking.table import read_track_csv

    name = cfg["track"]
    for other in ("gaits", "commands"):
        if other in cfg:
            raise InputError(
                f"{path}: track = {name!r} and {other}: the feedback table takes the place of the {other}; "
                f"give one of them."
            )
    if mode != "torques":
        raise InputError(
            f'{path}: track: a feedback table commands axle torques; set mode = "torques" or leave it out.'
        )
    tab = _read_table(path, "track", name, "a feedback table (track.csv of jsphere track)", read_track_csv)
    check_track(f"{path}: track = {name!r}", tab, n_wheels)
    return tab


def _study_actuators(path: Path, act) -> Actuators:
    """The `Actuators` of a study file's `[actuators]` table."""
    if not isinstance(act, dict):
        raise InputError(f"{path}: actuators must be a table (e.g. [actuators] gain_sd = 0.02); got {act!r}.")
    fields = [f.name for f in dataclasses.fields(Actuators)]
    unknown = sorted(set(act) - set(fields))
    if unknown:
        raise InputError(f"{path}: [actuators]: unknown key(s) {unknown}; expected {fields}.")
    return Actuators(**{k: real(f"{path}: [actuators]", k, v) for k, v in act.items()})
