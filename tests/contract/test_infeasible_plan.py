"""A plan that cannot meet its request exits 3 and writes its best plan (plan.csv, plan.json)
but no commands table for the robot, even with `--commands`; `--write-infeasible` writes the
table with a first comment line `# NOT FEASIBLE: ...`, which jsphere's readers of commands
tables (`read_inputs_csv`, `jsphere convert --inputs`, a study's `commands =`) skip."""

import json

import numpy as np
import pytest

import jsphere
from jsphere._runtime.errors import ExitCode
from jsphere.cli.app import main
from jsphere.montecarlo.study import load_study

#: a few fits or plans each, tens of seconds on 2 cores: the slow lane, which CI runs
pytestmark = pytest.mark.slow

#: a wheel-speed limit that 0.3 m in at most 12 s cannot respect (the best plan needs ~1.4 rad/s)
LIMIT = 0.5


def _plan(folder, *extra) -> int:
    argv = ["plan", "--to", "0.3", "0.1", "--max-wheel-speed", str(LIMIT), "--restarts", "1", "--rate", "50"]
    argv += ["--no-plots", "--commands", str(folder / "commands.csv"), "--out", str(folder / "plan.csv"), *extra]
    return main(argv)


def test_an_infeasible_plan_writes_no_commands(tmp_path, capsys):
    (tmp_path / "commands.csv").write_text("t,chi_dot_1,chi_dot_2,chi_dot_3\n0,1,1,1\n1,1,1,1\n")  # an earlier run's
    assert _plan(tmp_path) == ExitCode.INFEASIBLE == 3
    assert not (tmp_path / "commands.csv").exists() and not (tmp_path / "commands.json").exists()
    info = json.loads((tmp_path / "plan.json").read_text())
    assert info["feasible"] is False and info["limits"]["wheel_speed_rad_s"]["max"] > LIMIT
    assert (tmp_path / "plan.csv").is_file()  # the best plan found
    err = capsys.readouterr().err
    assert "No commands were written" in err and "--write-infeasible" in err


def test_write_infeasible_marks_the_commands_as_not_feasible(tmp_path, capsys):
    assert _plan(tmp_path, "--write-infeasible") == 3
    first = (tmp_path / "commands.csv").read_text().splitlines()[0]
    assert first.startswith("# NOT FEASIBLE:") and "wheel_speed_rad_s exceeded" in first
    assert json.loads((tmp_path / "commands.json").read_text())["feasible"] is False
    t, values, kind, _ = jsphere.read_inputs_csv(tmp_path / "commands.csv")  # the comment line is skipped
    assert kind == "wheel_speeds" and t[0] == 0.0 and np.max(np.abs(values)) > LIMIT
    study = tmp_path / "study.toml"
    study.write_text('mode = "wheel_speeds"\ncommands = "commands.csv"\n[vary]\nj = ["normal", 2.7e-4, 1e-6]\n')
    ts, replayed = load_study(study)["kwargs"]["commands"]
    np.testing.assert_array_equal(replayed, values)
