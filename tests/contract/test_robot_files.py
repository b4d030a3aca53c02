"""Robot files are read strictly: a missing required key or an unknown key stops `jsphere fit`
and `jsphere synth` with exit code 2 naming the key and the file; an optional key left out is
named once on stderr with the default used; a fit.json whose `values` disagree with its
`params` (the copy the robot is read from) is refused naming the parameter and both values."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

import jsphere
from jsphere._runtime.errors import ExitCode
from jsphere.cli.app import main

#: a few fits or plans each, tens of seconds on 2 cores: the slow lane, which CI runs
pytestmark = pytest.mark.slow

EXAMPLE = Path(__file__).resolve().parents[2] / "examples" / "robot.toml"


def _robot(tmp_path: Path, drop: str | None = None, add: str | None = None) -> Path:
    """examples/robot.toml with the line `drop = ...` removed and the line `add` appended."""
    lines = EXAMPLE.read_text().splitlines()
    if drop is not None:
        kept = [ln for ln in lines if not ln.startswith(f"{drop} ")]
        assert len(kept) == len(lines) - 1, drop
        lines = kept
    path = tmp_path / "robot.toml"
    path.write_text("\n".join(lines + ([add] if add else [])) + "\n")
    return path


@pytest.fixture(scope="module")
def trial_csv(tmp_path_factory) -> Path:
    p = jsphere.RobotParams.paper()
    trial = jsphere.synthetic_trial(p, jsphere.random_inputs(p, 1.0, seed=0), 1.0, rate=50.0, seed=0, name="t0")
    path = tmp_path_factory.mktemp("trials") / "t0.csv"
    jsphere.write_trial(path, trial)
    return path


def _fit(trial_csv, robot, tmp_path) -> int:
    out = tmp_path / "fit.json"
    return main(["fit", str(trial_csv), "--free", "j", "--params", str(robot), "--out", str(out), "--no-plots", "-q"])


def _synth(robot, tmp_path) -> int:
    out = tmp_path / "synth"
    return main(["synth", "--params", str(robot), "--trials", "1", "--duration", "0.5", "--out", str(out), "-q"])


def test_example_robot_loads_without_a_line_on_stderr(tmp_path, capsys):
    assert _synth(EXAMPLE, tmp_path) == ExitCode.OK
    assert "warning" not in capsys.readouterr().err


@pytest.mark.parametrize("command", ["fit", "synth"])
def test_a_missing_required_key_stops_the_command_naming_it(tmp_path, trial_csv, capsys, command):
    robot = _robot(tmp_path, drop="m")
    rc = _fit(trial_csv, robot, tmp_path) if command == "fit" else _synth(robot, tmp_path)
    err = capsys.readouterr().err
    assert rc == ExitCode.BAD_INPUT
    assert str(robot) in err and "missing required key 'm'" in err and len(err.strip().splitlines()) == 1


@pytest.mark.parametrize("command", ["fit", "synth"])
def test_an_unknown_key_stops_the_command_naming_it(tmp_path, trial_csv, capsys, command):
    robot = _robot(tmp_path, add="k_torque = 0.95")
    rc = _fit(trial_csv, robot, tmp_path) if command == "fit" else _synth(robot, tmp_path)
    err = capsys.readouterr().err
    assert rc == ExitCode.BAD_INPUT
    assert str(robot) in err and "unknown key 'k_torque'" in err and "did you mean 'k_tau'" in err


def test_a_left_out_wheel_inertia_is_named_once_with_its_default(tmp_path, capsys):
    robot = _robot(tmp_path, drop="j")
    assert _synth(robot, tmp_path) == ExitCode.OK
    notes = [ln for ln in capsys.readouterr().err.splitlines() if "leaves out" in ln]
    assert len(notes) == 1 and notes[0].startswith(
        f"warning: {robot} leaves out j; using j = 0 kg m^2 (massless wheels)."
    )
    assert float(jsphere.RobotParams.load(robot).j) == 0.0


@pytest.fixture(scope="module")
def fit_json(trial_csv, tmp_path_factory) -> Path:
    """A fit result as `jsphere fit --out` writes it (free j and the whole I, a few iterations)."""
    res = jsphere.fit(
        jsphere.read_trials([trial_csv]),
        jsphere.RobotParams.paper(),
        "j,I",
        n_starts=1,
        adam_steps=0,
        max_iter=3,
        progress=False,
    )
    path = tmp_path_factory.mktemp("fit") / "fit.json"
    res.save(path, plots=False)
    return path


def test_a_fit_json_as_written_loads(fit_json, tmp_path):
    doc = json.loads(fit_json.read_text())
    p = jsphere.RobotParams.load(fit_json)
    assert float(p.j) == doc["values"]["j"] and float(p.I[2, 2]) == doc["values"]["I[2,2]"]
    doc["values"]["j"] *= 1 + 1e-12  # a rounding of the copy: still the same number
    path = tmp_path / "rounded.json"
    path.write_text(json.dumps(doc))
    assert float(jsphere.RobotParams.load(path).j) == doc["params"]["j"]


@pytest.mark.parametrize(("name", "shown"), [("j", "values['j']"), ("I", "values['I'][2,2]")])
def test_a_fit_json_with_edited_values_is_refused_naming_the_parameter(fit_json, tmp_path, capsys, name, shown):
    doc = json.loads(fit_json.read_text())
    if name == "j":
        doc["values"]["j"] = 2.0 * doc["params"]["j"]
    else:
        doc["values"]["I"][2][2] = 0.03
    path = tmp_path / "edited.json"
    path.write_text(json.dumps(doc))
    assert _synth(path, tmp_path) == ExitCode.BAD_INPUT
    err = capsys.readouterr().err
    assert str(path) in err and shown in err and "disagrees with params" in err
    value = doc["values"]["j"] if name == "j" else 0.03
    assert repr(float(value)) in err
