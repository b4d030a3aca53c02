"""A study's description, checked before any work with an `InputError` that names the value: its
distributions (`check_vary`), its tables and the study file of `jsphere montecarlo` (`load_study`)."""

from __future__ import annotations

import dataclasses
import warnings
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np

from .._runtime.checks import real, whole
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
#: the keys of a study's `[feedback]` table (the closed loop of a `track` table) and their units
_FEEDBACK_UNITS = {"start_sd": "m", "heading_sd": "rad", "delay_s": "s", "pos_sd": "m", "att_sd": "rad"}
_FEEDBACK_UNITS |= {"omega_sd": "rad/s", "wheel_sd": "rad/s", "max_torque": "N m"}
#: their defaults: the start pose's spread and the fed-back state's delay and noise of `jsphere
#: track`'s evaluation (`jsphere.planning.tracking.Conditions`), the torque limit of `Limits`
FEEDBACK = {k: getattr(Conditions(), k) for k in list(_FEEDBACK_UNITS)[:-1]} | {"max_torque": Limits().max_torque}


def _check_table(where: str, name: str, values, keys: list, units: Mapping | None = None) -> dict:
    """The table `name` of a study (`where`: the study file or `monte_carlo`), `values`, with
    known `keys` only, each a finite number >= 0 in `units` (`max_torque` > 0); else an
    `InputError` naming the key."""
    if not isinstance(values, Mapping):
        raise InputError(f"{where}: {name} must be a table (e.g. [{name}] {keys[0]} = 0.01); got {values!r}.")
    unknown = sorted(set(values) - set(keys))
    if unknown:
        raise InputError(f"{where}: [{name}]: unknown key(s) {unknown}; expected {keys}.")
    label = f"{where}: [{name}]"
    return {k: real(label, k, v, strict=k == "max_torque", unit=units[k] if units else "") for k, v in values.items()}


def check_feedback(where: str, values: Mapping) -> dict:
    """The `FEEDBACK` settings `values` checked (finite numbers >= 0, the torque limit > 0) and
    completed with the defaults; `InputError` naming the key under `where`."""
    return FEEDBACK | _check_table(where, "feedback", values, sorted(FEEDBACK), _FEEDBACK_UNITS)


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


def _check_distribution(name: str, spec) -> tuple[str, float, float, bool]:
    """`(kind, a, b, truncate)` of one valid entry of `vary`, else `InputError` naming it."""
    form = f"vary[{name!r}] must be ['normal', mean, sd] or ['uniform', low, high], optionally followed by '{TRUNCATE}'"
    if not isinstance(spec, (tuple, list)) or len(spec) not in (3, 4) or spec[0] not in DISTRIBUTIONS:
        raise InputError(f"{form}; got {spec!r}.")
    if len(spec) == 4 and spec[3] != TRUNCATE:
        raise InputError(f"{form}; got {spec[3]!r} as its last entry.")
    kind = spec[0]
    a, b = (real(f"vary[{name!r}]", f"the {label}", v, low=None) for label, v in zip(DISTRIBUTIONS[kind], spec[1:3]))
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
        field, index = parse_name(name)
        if name != "R_m":
            get_value(params, name)  # checks the index fits
        kind, a, b, truncate = _check_distribution(name, spec)
        if get_value(params, name).ndim != 0:
            raise InputError(f"vary[{name!r}]: vary scalar components (e.g. 'I[0,0]'), not a whole field.")
        # what the name sets: `R_m` sets every `r_m[i]`, and `I` is symmetric
        t = ("r_m", None) if field == "R_m" else (field, tuple(sorted(index)) if field == "I" else index)
        clash = lambda u: u == t or (t[0] == u[0] == "r_m" and None in (t[1], u[1]))
        other = next((o for o, u in seen.items() if clash(u)), None)
        if other is not None:
            raise InputError(f"vary: {other!r} and {name!r} set the same value; vary one of them.")
        seen[name] = t
        out.append((name, kind, a, b, truncate))
    return out


# --- the study file of `jsphere montecarlo` ---

#: the gaits a study file names, by their `kind`
GAITS = {"acceleration": acceleration, "braking": braking, "turn": turn}
#: the keys of a study file: the study's own (`trials`, the robot, the gaits, the
#: distributions) and every field of `StudyOptions` that a file gives
STUDY_KEYS = {"trials", "params", "gaits", "vary"} | {
    f.name for f in dataclasses.fields(StudyOptions) if f.metadata["file"] is not None
}
#: the keys of a study file that name a file or hold a table or a list: their type and form
_FORMS = {
    "params": (str, "the path of a parameter file (.toml or .json)"),
    "gaits": (list, 'a non-empty list of tables, e.g. gaits = [{kind = "acceleration"}, {kind = "braking"}]'),
    "vary": (dict, 'a table of distributions, e.g. [vary] "r_m[2]" = ["normal", -0.027, 1e-4]'),
    "actuators": (dict, "a table (e.g. [actuators] gain_sd = 0.02)"),
    "commands": (str, "the path of a command table (.csv)"),
    "track": (str, "the path of a feedback table (track.csv of jsphere track)"),
    "feedback": (dict, "a table (e.g. [feedback] delay_s = 0.01)"),
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
        use = "use the attributes of the Study (params, gaits, n, vary, options)"
        warnings.warn(f'load_study(...)["{key}"] is deprecated; {use}.', DeprecationWarning, stacklevel=2)
        if key != "kwargs":
            return getattr(self, key)
        return {"vary": self.vary} | {f.name: getattr(self.options, f.name) for f in dataclasses.fields(StudyOptions)}


def load_study(path) -> Study:
    """Read a Monte-Carlo study description (TOML) into a `Study`, checking every value before
    any work (an `InputError` names the file and the key). Its keys, each optional but `[vary]`:
    `trials` (1000; `--trials` overrides it), `params` (a parameter file relative to this file;
    default: the paper's robot, or the robot of a plan's command table), `gaits` (tables such as
    `{kind = "acceleration", theta_max = 0.1, T = 2.0}`; default acceleration and braking),
    `[vary]` (names as in `jsphere fit --free`, distributions as `monte_carlo` takes them) and
    the fields of `StudyOptions` marked "(file)" (`batch_size` 4096 unless given); e.g.

        trials = 10000
        mode = "torques"
        commands = "plan-commands.csv"
        [vary]
        "r_m[2]" = ["normal", -0.0270146, 1e-4]
        m0 = ["normal", 0.8, 0.3, "truncate"]   # truncated to valid robots (m0 > 0)
        [actuators]               # replay modes only; see jsphere.Actuators
        gain_sd = 0.02

    A plan's command table (`study_commands`) brings the robot its record names, which `params`
    must match; a feedback table (`track`, `study_track`, with `[feedback]`: `FEEDBACK`) takes
    the place of `gaits` and `commands`.
    """
    path = Path(path)
    cfg = _read_toml(path)
    n = whole(str(path), "trials", cfg["trials"], 1) if "trials" in cfg else 1000
    given = {"batch_size": 4096, "mode": "torques" if "track" in cfg else "gait"}
    for f in dataclasses.fields(StudyOptions):
        if f.metadata["file"] == "value" and f.name in cfg:
            given[f.name] = f.metadata["check"](str(path), f.name, cfg[f.name])
    params = RobotParams.load((path.parent / cfg["params"]).resolve()) if "params" in cfg else RobotParams.paper()
    if "commands" in cfg and "track" not in cfg:
        params = _commands_robot(path, cfg, params)
    gaits = _study_gaits(path, cfg.get("gaits", [{"kind": "acceleration"}, {"kind": "braking"}]))
    if "actuators" in cfg:
        fields = [f.name for f in dataclasses.fields(Actuators)]
        given["actuators"] = Actuators(**_check_table(str(path), "actuators", cfg["actuators"], fields))
    if "commands" in cfg and "track" not in cfg:
        given["commands"] = study_commands(path, cfg["commands"], given["mode"], params.n_wheels)
    if "track" in cfg:
        given["track"] = study_track(path, cfg, given["mode"], params.n_wheels)
        given["feedback"] = check_feedback(str(path), cfg.get("feedback", {}))
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
    """The study file's table, with only known keys, a `[vary]` table and each key of `_FORMS` of its form."""
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
    for key, (kind, form) in _FORMS.items():
        if key in cfg and (not isinstance(cfg[key], kind) or cfg[key] == []):
            raise InputError(f"{path}: {key} must be {form}; got {cfg[key]!r}.")
    return cfg


def _commands_robot(path: Path, cfg: dict, params: RobotParams) -> RobotParams:
    """The robot of a study that replays a plan's command table: the one the plan records beside
    the table (`planned_robot`) unless the study names `params`, which must be the same robot."""
    from ..planning.result import planned_robot, robot_difference

    name = cfg["commands"]
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
    gaits = []
    for k, g in enumerate(gait_list):
        if not isinstance(g, dict):
            raise InputError(
                f'{path}: gaits[{k}] must be a table such as {{kind = "acceleration", theta_max = 0.1}}; got {g!r}.'
            )
        g = dict(g)
        kind = g.pop("kind", None)
        if kind not in GAITS:
            raise InputError(f"{path}: gaits[{k}].kind must be one of {tuple(GAITS)}; got {kind!r}.")
        try:
            gaits.append(GAITS[kind](**g))
        except (TypeError, ValueError) as e:
            raise InputError(f"{path}: gaits[{k}]: {e}") from None
    return gaits


def _read_table(path: Path, key: str, name: str, read):
    """The file that a study file's `key` names (`name`, relative to the study file), as `read`
    reads it; `InputError` naming the file and the key when it is missing or cannot be read."""
    table = (path.parent / name).resolve()
    if not table.is_file():
        raise InputError(f"{path}: {key} = {name!r}: no such file {table}.")
    try:
        return read(table)
    except ValueError as e:
        raise InputError(f"{path}: {key} = {name!r}: {e}") from None


def study_commands(path: Path, name, mode: str, n_wheels: int) -> tuple[np.ndarray, np.ndarray]:
    """`(ts, values)` of the command table a study file's `commands` key names: its `K_1..N` or
    `chi_dot_1..N` columns, as `mode` replays them (`read_inputs_csv`, `check_commands`), else an
    `InputError` naming the file and the key."""
    from ..capture.inputs import read_inputs_csv

    if mode == "gait":
        raise InputError(
            f'{path}: commands are replayed through the actuators; set mode = "torques" (columns K_1..K_N) or '
            f'mode = "wheel_speeds" (columns chi_dot_1..N).'
        )
    ts, values = _read_table(path, "commands", name, lambda table: read_inputs_csv(table, kind=mode)[:2])
    check_commands(f"{path}: commands = {name!r}", ts, values, n_wheels)
    return ts, values


def study_track(path: Path, cfg: dict, mode: str, n_wheels: int) -> dict:
    """The feedback table a study file's `track` key names (`read_track_csv`, `check_track`), in
    place of `gaits` and `commands` and in mode "torques", else an `InputError` naming the file
    and the key."""
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
    tab = _read_table(path, "track", name, read_track_csv)
    check_track(f"{path}: track = {name!r}", tab, n_wheels)
    return tab
