"""A study file's `track = "FILE"`: the feedback table of `jsphere track` run closed loop on every
perturbed robot, from the study file and from the command line."""

import json
import shutil
from pathlib import Path

import jax.numpy as jnp
import numpy as np
import pytest

import jsphere
from jsphere._runtime.errors import InputError
from jsphere.cli.app import main
from jsphere.model.state import Flat, State
from jsphere.montecarlo.study import FEEDBACK, load_study
from jsphere.planning.tracking.evaluate import FIELDS, Conditions, run_one
from jsphere.planning.tracking.table import column_names, read_track_csv

P = jsphere.RobotParams.paper()
#: the paper's centre-of-mass offset, exactly as the robot has it
RM2 = repr(float(P.r_m[2]))
#: a study's measurement and start with no errors at all
EXACT = "[feedback]\n" + "".join(f"{k} = 0.0\n" for k in FEEDBACK if k != "max_torque")


EXAMPLES = Path(__file__).resolve().parents[2] / "examples"


@pytest.fixture(scope="module")
def tables(tmp_path_factory):
    """A folder with the example's feedback table (the paper's straight-line gaits with gains at
    20 Hz, `jsphere track examples/commands_straight_line.csv --rate 20`) and the command table
    it tracks."""
    folder = tmp_path_factory.mktemp("track")
    for name in ("track_straight_line.csv", "commands_straight_line.csv"):
        shutil.copy(EXAMPLES / name, folder / name)
    return folder, read_track_csv(folder / "track_straight_line.csv")


def _study(folder: Path, text: str, name="study.toml") -> Path:
    path = folder / name
    path.write_text(text)
    return path


def test_track_key_loads_the_table_and_the_feedback_defaults(tables):
    folder, tr = tables
    (folder / "sub").mkdir(exist_ok=True)
    study = _study(
        folder / "sub", f'track = "../track_straight_line.csv"\n[vary]\n"r_m[2]" = ["normal", {RM2}, 1e-4]\n'
    )
    o = load_study(study).options
    assert o.mode == "torques" and o.commands is None
    want = read_track_csv(folder / "track_straight_line.csv")
    for k in ("t", "K_ff", "x", "y", "q", "omega", "Omega", "G"):
        np.testing.assert_array_equal(o.track[k], want[k])
    assert o.track["G"].shape == (81, 3, 11) and np.abs(o.track["G"]).max() > 0
    assert o.feedback == FEEDBACK
    assert FEEDBACK["delay_s"] == Conditions().delay_s and FEEDBACK["max_torque"] == jsphere.Limits().max_torque
    study = _study(
        folder, 'track = "track_straight_line.csv"\n[feedback]\ndelay_s = 0.02\n[vary]\nj = ["normal", 2e-4, 0.0]\n'
    )
    assert load_study(study).options.feedback["delay_s"] == 0.02


def _two_wheel_table(path: Path) -> None:
    cols = column_names(2)
    row = np.zeros(len(cols))
    row[cols.index("qw")] = 1.0
    rows = [row, row.copy()]
    rows[1][0] = 0.05
    path.write_text(",".join(cols) + "\n" + "\n".join(",".join(repr(float(v)) for v in r) for r in rows) + "\n")


@pytest.mark.parametrize(
    "text,match",
    [
        ('track = "track_straight_line.csv"\ngaits = [{kind = "acceleration"}]\n', "gaits"),
        ('track = "track_straight_line.csv"\nmode = "torques"\ncommands = "commands_straight_line.csv"\n', "commands"),
        ('track = "missing.csv"\n', "no such file"),
        ('track = "two.csv"\n', "3 wheels"),
        ('track = "commands_straight_line.csv"\n', "not a track table"),
        ("track = 3\n", "path of a feedback table"),
        ('track = "track_straight_line.csv"\nmode = "wheel_speeds"\n', "torques"),
        ('track = "track_straight_line.csv"\n[feedback]\nnoise = 1.0\n', "unknown key"),
        ('track = "track_straight_line.csv"\n[feedback]\npos_sd = -1.0\n', "pos_sd"),
        ('track = "track_straight_line.csv"\n[feedback]\nmax_torque = 0.0\n', "max_torque"),
        ('track = "track_straight_line.csv"\n[actuators]\nband_sd = 0.001\n', "band_sd"),
        ('track = "track_straight_line.csv"\nOmega0_sd = 0.1\n', "Omega0_sd"),
        ('mode = "torques"\n[feedback]\ndelay_s = 0.01\n', "track"),
    ],
)
def test_a_bad_track_key_names_the_file_and_the_key(tables, text, match):
    folder, _ = tables
    _two_wheel_table(folder / "two.csv")
    study = _study(folder, text + f'[vary]\n"r_m[2]" = ["normal", {RM2}, 1e-4]\n', "bad.toml")
    with pytest.raises(InputError, match=match) as e:
        load_study(study)
    assert str(study) in str(e.value)


@pytest.mark.slow
def test_jsphere_montecarlo_of_a_track_table_is_the_tracking_closed_loop(tables, tmp_path):
    """No spread, exact motors and an exact measurement: every trial is the tracking
    evaluation's closed loop on the nominal robot, and `stats.json` says where it stops next
    to the table's last reference (the planned stop)."""
    folder, tr = tables
    study = _study(
        folder,
        f'trials = 64\nseed = 1\nbatch_size = 64\ntrack = "track_straight_line.csv"\nsettle = 1.0\n{EXACT}'
        f'[vary]\n"r_m[2]" = ["normal", {RM2}, 0.0]\n',
        "exact.toml",
    )
    out = tmp_path / "out"
    assert main(["montecarlo", str(study), "--out", str(out), "--no-cache", "--no-plots"]) == 0
    stats = json.loads((out / "stats.json").read_text())
    assert stats["n_ok"] == 64
    c = Conditions(**{**{k: 0.0 for k in FIELDS}, "settle": 1.0})
    ref = np.zeros((len(tr["t"]), Flat.size + 3))  # the reference as flat states; only these parts enter
    ref[:, Flat.q], ref[:, Flat.omega], ref[:, Flat.Omega] = tr["q"], tr["omega"], tr["Omega"]
    ref[:, Flat.x], ref[:, Flat.y] = tr["x"], tr["y"]
    target = jnp.asarray([tr["x"][-1], tr["y"][-1]])
    K_ff, G = jnp.asarray(tr["K_ff"]), jnp.asarray(tr["G"])
    _, speed, _, zT = run_one(P, jnp.zeros(2, jnp.uint32), 0.05, K_ff, jnp.asarray(ref), G, target, c, 0.1, 20, 1.0)
    np.testing.assert_allclose(stats["mean_xy_m"], [zT[Flat.x], zT[Flat.y]], rtol=0, atol=1e-12)
    assert stats["sd_xy_m"] == pytest.approx([0.0, 0.0], abs=1e-12)
    assert stats["planned_stop_m"] == [tr["x"][-1], tr["y"][-1]]
    # the controller brings the nominal robot to its planned stop (the plan rolls it 26 cm)
    assert np.hypot(*np.subtract(stats["mean_xy_m"], stats["planned_stop_m"])) < 2e-3
    assert np.hypot(*stats["planned_stop_m"]) > 0.2
    assert stats["speed_final_m_s"]["max"] == pytest.approx(float(speed), abs=1e-12)


@pytest.mark.slow  # (the command-line test above runs the same closed loop in the default lane)
def test_monte_carlo_with_a_track_table_is_the_tracking_closed_loop(tables):
    """`monte_carlo(track=...)` (the first rows of the table, a short settling) with no spread and
    exact motors and measurement: every trial is the tracking evaluation's closed loop."""
    _, tr = tables
    small = {k: v[:6] for k, v in tr.items()}
    exact = {k: 0.0 for k in FEEDBACK if k != "max_torque"}
    res = jsphere.monte_carlo(
        P,
        [jsphere.acceleration()],
        vary={"j": ("normal", float(P.j), 0.0)},
        n=64,
        options=jsphere.StudyOptions(batch_size=64, mode="torques", track=small, feedback=exact, settle=0.1),
        progress=False,
    )
    c = Conditions(**{**{k: 0.0 for k in FIELDS}, "settle": 0.1})
    ref = np.zeros((6, Flat.size + 3))
    ref[:, Flat.q], ref[:, Flat.omega], ref[:, Flat.Omega] = small["q"], small["omega"], small["Omega"]
    ref[:, Flat.x], ref[:, Flat.y] = small["x"], small["y"]
    target = jnp.asarray([small["x"][-1], small["y"][-1]])
    K_ff, G = jnp.asarray(small["K_ff"]), jnp.asarray(small["G"])
    _, _, _, zT = run_one(P, jnp.zeros(2, jnp.uint32), 0.05, K_ff, jnp.asarray(ref), G, target, c, 0.1, 2, 1.0)
    assert np.all(res.status == 0)
    np.testing.assert_allclose(res.x_final, float(zT[Flat.x]), rtol=0, atol=1e-13)
    np.testing.assert_allclose(res.y_final, float(zT[Flat.y]), rtol=0, atol=1e-13)


def _misses(study: Path, target) -> np.ndarray:
    s = load_study(study)
    res = jsphere.monte_carlo(s.params, s.gaits, vary=s.vary, n=s.n, options=s.options, progress=False)
    assert np.all(res.status == 0)
    return np.hypot(res.x_final - target[0], res.y_final - target[1])


@pytest.mark.slow
def test_the_closed_loop_lands_much_closer_than_the_open_loop_replay(tables):
    """Robots a few per cent off the model, motors off by a few per cent, a start a few mm off:
    the closed loop of the table stops far closer to the planned stop than the open-loop replay
    of the same plan's torques (`commands = `) through the same motors."""
    folder, tr = tables
    common = (
        "trials = 64\nseed = 2\nbatch_size = 64\nsettle = 1.0\n"
        f'[vary]\n"r_m[2]" = ["normal", {RM2}, {0.05 * abs(float(P.r_m[2]))!r}]\n'
        f'j = ["normal", {float(P.j)!r}, {0.05 * float(P.j)!r}]\n'
        "[actuators]\ngain_sd = 0.025\nwhite_sd = 5e-4\n"
    )
    closed = _study(folder, 'track = "track_straight_line.csv"\n' + common, "closed.toml")
    opened = _study(folder, 'mode = "torques"\ncommands = "commands_straight_line.csv"\n' + common, "open.toml")
    target = (tr["x"][-1], tr["y"][-1])
    m_closed, m_open = _misses(closed, target), _misses(opened, target)
    assert m_closed.mean() < m_open.mean() / 5
    assert m_closed.mean() < 2e-3


def test_the_example_study_of_a_track_table_loads():
    root = Path(__file__).resolve().parents[2] / "examples"
    study = load_study(root / "study_track.toml")
    tab = study.options.track
    assert study.options.mode == "torques" and tab["G"].shape == (len(tab["t"]), 3, 11)
    assert np.abs(tab["G"]).max() > 0 and np.hypot(tab["x"][-1], tab["y"][-1]) > 0.1
    State.at_rest(study.params)  # the example's robot is valid
