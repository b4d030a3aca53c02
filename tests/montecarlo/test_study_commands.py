"""A study file's `commands = "FILE"`: the command table of `jsphere plan --commands` or
`jsphere design` replayed on every perturbed robot, from the command line."""

import json
from pathlib import Path

import numpy as np
import pytest

import jsphere
from jsphere._runtime.errors import InputError
from jsphere.capture.inputs import write_inputs_csv
from jsphere.cli.app import main
from jsphere.montecarlo.study import load_study

GAITS = [jsphere.acceleration(), jsphere.braking()]
VARY = '[vary]\n"r_m[2]" = ["normal", -0.0270146, 1e-4]\n'


@pytest.fixture(scope="module")
def nominal(paper):
    """The paper's gaits on the paper's robot sampled at 50 Hz (a time stamp once: a command table
    has no jumps): times, torques, wheel speeds and positions."""
    tr = jsphere.simulate_gaits(paper, GAITS, rate=50.0)
    ts = np.asarray(tr.ts)
    keep = np.r_[np.diff(ts) > 0, True]
    return {k: np.asarray(getattr(tr, k))[keep] for k in ("ts", "K", "chi_dot", "x", "y")}


def _plan_table(path, tr) -> None:
    """A table with both families, as `jsphere plan --out` writes it (`t, K_i, chi_dot_i, x, y`)."""
    cols = ["t", "K_1", "K_2", "K_3", "chi_dot_1", "chi_dot_2", "chi_dot_3", "x", "y"]
    rows = np.column_stack([tr["ts"], tr["K"], tr["chi_dot"], tr["x"], tr["y"]])
    path.write_text(",".join(cols) + "\n" + "\n".join(",".join(f"{v:.12g}" for v in r) for r in rows) + "\n")


@pytest.mark.parametrize("mode,column", [("torques", "K"), ("wheel_speeds", "chi_dot")])
def test_commands_key_reads_the_family_of_the_mode(tmp_path, nominal, mode, column):
    _plan_table(tmp_path / "plan.csv", nominal)
    (tmp_path / "sub").mkdir()
    study = tmp_path / "sub" / "study.toml"
    study.write_text(f'mode = "{mode}"\ncommands = "../plan.csv"\n{VARY}')
    ts, values = load_study(study).options.commands
    np.testing.assert_allclose(ts, nominal["ts"], rtol=1e-11)
    np.testing.assert_allclose(values, nominal[column], rtol=1e-11, atol=1e-14)
    with pytest.warns(DeprecationWarning, match=r'load_study\(\.\.\.\)\["kwargs"\] is deprecated'):
        kwargs = load_study(study)["kwargs"]
    assert kwargs["mode"] == mode and kwargs["commands"][0] is not None and list(kwargs["vary"]) == ["r_m[2]"]


def test_the_study_files_keys_are_the_study_and_its_options():
    """A study file's keys: `trials`, `params`, `gaits`, `vary` and the fields of `StudyOptions`
    that a file gives (not the step limit and plan rate, which have no key)."""
    import dataclasses

    from jsphere.montecarlo.study import STUDY_KEYS

    fields = {f.name for f in dataclasses.fields(jsphere.StudyOptions)}
    assert STUDY_KEYS == {"trials", "params", "gaits", "vary"} | fields - {"max_steps", "plan_rate"}


@pytest.mark.parametrize(
    "text,table,match",
    [
        ('commands = "c.csv"\n', "t,K_1,K_2,K_3\n0,0,0,0\n1,0,0,0\n", "mode"),
        ('mode = "torques"\ncommands = "missing.csv"\n', None, "no such file"),
        ('mode = "torques"\ncommands = 3\n', None, "path of a command table"),
        ('mode = "torques"\ncommands = "c.csv"\n', "t,chi_dot_1,chi_dot_2,chi_dot_3\n0,0,0,0\n1,0,0,0\n", "K_1"),
        ('mode = "torques"\ncommands = "c.csv"\n', "t,K_1,K_2\n0,0,0\n1,0,0\n", "3 wheels"),
        ('mode = "torques"\ncommands = "c.csv"\n', "t,K_1,K_2,K_3\n0.5,0,0,0\n1,0,0,0\n", "t = 0"),
        ('mode = "wheel_speeds"\ncommands = "c.csv"\n', "t,chi_dot_1,chi_dot_2,chi_dot_3\n0,0,0,0\n0,1,1,1\n", "c.csv"),
    ],
)
def test_a_bad_commands_key_names_the_file_and_the_key(tmp_path, text, table, match):
    if table is not None:
        (tmp_path / "c.csv").write_text(table)
    study = tmp_path / "study.toml"
    study.write_text(text + VARY)
    with pytest.raises(InputError, match=match) as e:
        load_study(study)
    assert str(study) in str(e.value)


@pytest.mark.slow
def test_jsphere_montecarlo_replays_the_table(tmp_path, paper, nominal, capsys):
    """The CLI's study equals `monte_carlo(..., commands=...)`; with no spread the trials stop
    where the nominal robot does under the table (`planned_stop_m`), next to the gaits' own stop."""
    write_inputs_csv(tmp_path / "commands.csv", nominal["ts"], nominal["K"], "torques")
    study = tmp_path / "study.toml"
    study.write_text(
        'trials = 64\nseed = 3\nbatch_size = 64\nmode = "torques"\ncommands = "commands.csv"\nsettle = 0.5\n'
        '[vary]\n"r_m[2]" = ["normal", -0.0270146, 0.0]\n'
    )
    out = tmp_path / "out"
    assert main(["montecarlo", str(study), "--out", str(out), "--no-cache", "--no-plots"]) == 0
    stats = json.loads((out / "stats.json").read_text())
    assert stats["n_ok"] == 64
    ts, K = load_study(study).options.commands
    res = jsphere.monte_carlo(
        paper,
        GAITS,
        vary={"r_m[2]": ("normal", -0.0270146, 0.0)},
        n=64,
        options=jsphere.StudyOptions(seed=3, batch_size=64, mode="torques", commands=(ts, K), settle=0.5),
        progress=False,
    )
    assert stats["mean_xy_m"] == pytest.approx(res.stats()["mean_xy_m"], abs=1e-15)
    assert stats["mean_xy_m"] == pytest.approx(stats["planned_stop_m"], abs=1e-6)
    assert stats["planned_stop_m"] == pytest.approx([nominal["x"][-1], nominal["y"][-1]], abs=5e-3)
    assert "planned stop" in capsys.readouterr().out


def test_the_example_study_of_a_command_table_loads():
    root = Path(__file__).resolve().parents[2] / "examples"
    study = load_study(root / "study_commands.toml")
    ts, K = study.options.commands
    assert study.options.mode == "torques" and K.shape == (len(ts), 3) and ts[0] == 0.0
    assert np.abs(K).max() > 1e-3  # the gaits' torques, not an empty table
