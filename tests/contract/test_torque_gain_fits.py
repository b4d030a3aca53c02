"""The torque gain `k_tau`: with torque inputs the masses and inertias are known only relative to
the torque constant. Synthetic torque trials of a robot whose motors give 0.9 of the commanded
torque (`k_tau = 0.9`), fitted with `jsphere fit`:

- `k_tau` fixed at 1, every mass and inertia free: the fit absorbs the gain into them (each
  1/0.9 of the truth, exit 0) and its report says they are relative to the torque constant;
- `k_tau` freed with the platform mass fixed at its true value: `k_tau` comes back within 3
  standard errors of 0.9;
- `k_tau` freed with every mass and inertia: the scale is reported as not identified (no
  standard error on those names, a warning naming `k_tau`), not a small standard error.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest

import jsphere
from jsphere._runtime.errors import ExitCode
from jsphere.cli.app import main

#: a few fits or plans each, tens of seconds on 2 cores: the slow lane, which CI runs
pytestmark = pytest.mark.slow

GAIN = 0.9
#: every inertial parameter of the robot that scales with the torque gain (m free: R_m stays)
INERTIAL = "m0,m,I0,I[0,0],I[1,1],I[2,2],j"


@pytest.fixture(scope="module")
def truth():
    return jsphere.RobotParams.paper().replace(k_tau=GAIN)


@pytest.fixture(scope="module")
def trials(truth, tmp_path_factory) -> list[str]:
    folder = tmp_path_factory.mktemp("torque_trials")
    paths = []
    for i in range(2):
        u = jsphere.random_inputs(truth, 3.0, kind="torques", seed=i)
        path = folder / f"t{i}.csv"
        jsphere.write_trial(path, jsphere.synthetic_trial(truth, u, 3.0, rate=50.0, seed=i, name=f"t{i}"))
        paths.append(str(path))
    return paths


def _fit(trials, tmp_path: Path, free: str, *extra: str) -> tuple[int, dict]:
    out = tmp_path / "fit.json"
    args = ["fit", *trials, "--free", free, "--n-starts", "1", "--max-iter", "15", "--out", str(out), "--no-plots"]
    rc = main([*args, "-q", *extra])
    return rc, json.loads(out.read_text())


def test_with_the_gain_fixed_the_masses_are_relative_to_the_torque_constant(trials, truth, tmp_path):
    rc, doc = _fit(trials, tmp_path, INERTIAL)
    assert rc == ExitCode.OK
    assert "relative to the torque constant (k_tau = 1 assumed)" in doc["units_note"]
    for name in ("m", "I[0,0]", "I[2,2]"):  # the gain absorbed: each fitted value is truth / 0.9
        value, se, true = doc["values"][name], doc["stderr"][name], float(jsphere.get_value(truth, name))
        assert value / true == pytest.approx(1 / GAIN, rel=0.02), (name, value / true)
        assert abs(value - true) > 5 * se and abs(value - true / GAIN) < 3 * se


def test_the_gain_freed_with_a_mass_fixed_is_recovered(trials, tmp_path):
    rc, doc = _fit(trials, tmp_path, "k_tau,m0,I[2,2]", "--fix", "m=2.5")
    assert rc == ExitCode.OK
    k, se = doc["values"]["k_tau"], doc["stderr"]["k_tau"]
    assert 0 < se < 0.05 and abs(k - GAIN) < 3 * se, (k, se)
    assert "k_tau = 1 assumed" not in doc["units_note"]


def test_the_gain_freed_with_every_mass_and_inertia_is_not_identified(trials, tmp_path, capsys):
    rc, doc = _fit(trials, tmp_path, f"k_tau,{INERTIAL}")
    assert rc == ExitCode.OK
    assert all(doc["stderr"][n] is None for n in doc["free"]), doc["stderr"]  # infinite: null in JSON
    assert doc["identifiability"]["symmetries"]["mass_scale"]["relative_sd"] is None
    warning = next(w for w in doc["identifiability"]["warnings"] if "k_tau" in w)
    assert "not identified" in warning and "--fix m0=" in warning
    assert "not determined in scale" in doc["units_note"]
    assert "warning: the torque gain k_tau is free" in capsys.readouterr().out
