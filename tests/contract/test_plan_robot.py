"""A plan records the robot it was made for: `plan.json` holds its parameters, `jsphere track`
and `jsphere animate` of the plan and a Monte-Carlo study that replays its commands use that
robot without `--params` (`params`), and refuse another robot in one line naming both. The
commands table of a plan that ends at rest ends on exactly 0, and a plan without a heading
prints no heading error."""

import contextlib
import io
import json

import numpy as np
import pytest

import jsphere
from jsphere._runtime.errors import InputError
from jsphere.cli.app import main
from jsphere.montecarlo.study import load_study

#: a few fits or plans each, tens of seconds on 2 cores: the slow lane, which CI runs
pytestmark = pytest.mark.slow

#: a robot that is not the paper's: heavier platform, heavier wheels
ROBOT = jsphere.RobotParams.paper().replace(m=3.5, j=4.0e-4)
TARGET = ("0.3", "0.1")


@pytest.fixture(scope="module")
def planned(tmp_path_factory):
    """`jsphere plan --params robot.toml` with its commands table (one restart, 50 Hz), the
    robot files and what the plan printed."""
    folder = tmp_path_factory.mktemp("plan_robot")
    ROBOT.save(folder / "robot.toml")
    jsphere.RobotParams.paper().save(folder / "paper.toml")
    argv = ["plan", "--to", *TARGET, "--params", folder / "robot.toml", "--family", "gait", "--restarts", "1"]
    argv += ["--rate", "50"]  # a gait plan leaves the tracker torque to spare
    argv += ["--no-plots", "--commands", folder / "commands.csv", "--out", folder / "plan.csv"]
    printed = io.StringIO()
    with contextlib.redirect_stdout(printed):
        code = main([str(a) for a in argv])
    return code, folder, printed.getvalue()


def _last_error_line(capsys) -> list[str]:
    return capsys.readouterr().err.strip().splitlines()


def test_plan_json_records_the_robot(planned):
    code, folder, printed = planned
    assert code == 0, printed
    info = json.loads((folder / "plan.json").read_text())
    assert info["feasible"] is True and "wheel_speed_rad_s" in info["limits"]
    assert info["params_source"] == str(folder / "robot.toml")
    recorded = jsphere.RobotParams.load(folder / "plan.json")
    assert float(recorded.m) == 3.5 and float(recorded.j) == 4.0e-4
    assert json.loads((folder / "commands.json").read_text())["params"] == info["params"]


def test_track_without_params_designs_the_gains_for_the_plans_robot(planned, tmp_path, capsys):
    _, folder, _ = planned
    assert main(["track", str(folder / "plan.csv"), "--samples", "0", "--out", str(tmp_path / "track.csv")]) == 0
    used = json.loads((tmp_path / "track.json").read_text())["params"]
    assert used["m"] == 3.5 and used["j"] == 4.0e-4  # the paper's robot: m = 2.5, j = 2.7395e-4
    # the same robot given explicitly is the same robot
    argv = ["track", str(folder / "plan.csv"), "--samples", "0", "--params", str(folder / "robot.toml")]
    assert main([*argv, "--out", str(tmp_path / "same.csv")]) == 0
    assert json.loads((tmp_path / "same.json").read_text())["params"] == used


def test_track_with_another_robot_is_refused_naming_both(planned, tmp_path, capsys):
    _, folder, _ = planned
    argv = ["track", str(folder / "plan.csv"), "--samples", "0", "--params", str(folder / "paper.toml")]
    capsys.readouterr()
    assert main([*argv, "--out", str(tmp_path / "track.csv")]) == 2
    (line,) = _last_error_line(capsys)
    assert str(folder / "paper.toml") in line and str(folder / "robot.toml") in line
    assert "m 3.5 vs 2.5" in line and "leave --params out" in line and "plan again with --params" in line
    assert not (tmp_path / "track.csv").exists()


def test_animate_of_the_plan_refuses_another_robot(planned, tmp_path, capsys):
    _, folder, _ = planned
    argv = ["animate", str(folder / "plan.csv"), "--params", str(folder / "paper.toml"), "--out"]
    capsys.readouterr()
    assert main([*argv, str(tmp_path / "plan.gif")]) == 2
    (line,) = _last_error_line(capsys)
    assert str(folder / "paper.toml") in line and str(folder / "robot.toml") in line


def _study(folder, name: str, params: str | None) -> str:
    path = folder / name
    lines = ['mode = "wheel_speeds"', 'commands = "commands.csv"', "trials = 4"]
    lines += [f'params = "{params}"'] if params else []
    path.write_text("\n".join(lines) + '\n[vary]\n"r_m[2]" = ["normal", -0.027, 1e-4]\n')
    return str(path)


def test_a_study_replaying_the_commands_runs_the_plans_robot(planned, tmp_path, capsys):
    _, folder, _ = planned
    study = load_study(_study(folder, "study.toml", None))
    assert float(study["params"].m) == 3.5 and float(study["params"].j) == 4.0e-4
    assert float(load_study(_study(folder, "same.toml", "robot.toml"))["params"].m) == 3.5
    other = _study(folder, "other.toml", "paper.toml")
    with pytest.raises(InputError, match="paper.toml.*robot.toml"):
        load_study(other)
    capsys.readouterr()
    assert main(["montecarlo", other, "--out", str(tmp_path / "study")]) == 2
    (line,) = _last_error_line(capsys)
    assert "params = 'paper.toml'" in line and str(folder / "robot.toml") in line


def test_the_commands_end_on_exactly_zero_and_no_heading_error_is_printed(planned):
    _, folder, printed = planned
    t, values, _, _ = jsphere.read_inputs_csv(folder / "commands.csv")
    assert np.all(values[-1] == 0.0) and np.max(np.abs(values)) > 1.0
    plan_table = np.genfromtxt(folder / "plan.csv", delimiter=",", names=True)
    assert all(plan_table[f"{c}_{i}"][-1] == 0.0 for c in ("K", "chi_dot") for i in (1, 2, 3))
    assert "final position error" in printed and "heading error" not in printed
