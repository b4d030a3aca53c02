"""A long capture, fitted with the default (robust) loss: three 15 s trials and one 30 s trial of
torque multisines, 1 mm and 0.5 deg noise, seven free parameters including `m0` and `I0`,
started at the paper's values. The fit converges (exit 0) with every value within 3 standard
errors of the truth, the noise levels at the capture's, and almost no frame set aside: a
redescending loss cannot carry the fit into a valley where much of the data are called
outliers."""

import json

import pytest
from robots import torque_trials, unseen_robot

import jsphere
from jsphere.cli.app import main

#: a few fits or plans each, tens of seconds on 2 cores: the slow lane, which CI runs
pytestmark = pytest.mark.slow

FREE7 = "r_m[2],j,I[0,0],I[1,1],I[2,2],m0,I0"


def test_a_long_capture_fits_within_three_standard_errors(tmp_path, capsys):
    robot = unseen_robot()
    paths = []
    for tr in torque_trials(robot, (15.0, 15.0, 15.0, 30.0)):
        paths.append(tmp_path / f"{tr.name}.csv")
        jsphere.write_trial(paths[-1], tr)
    out = tmp_path / "fit.json"
    rc = main(["fit", *map(str, paths), "--free", FREE7, "--no-plots", "--out", str(out)])
    doc = json.loads(out.read_text())
    z = {n: (doc["values"][n] - float(jsphere.get_value(robot, n))) / doc["stderr"][n] for n in doc["free"]}
    assert rc == 0 and doc["status"] == "converged", doc["status_reason"]
    assert all(abs(v) < 3 for v in z.values()), z
    assert doc["sigma_pos_m"] == pytest.approx(1e-3, rel=0.1)
    assert doc["sigma_rot_deg"] == pytest.approx(0.5, rel=0.1)
    frames = sum(len(jsphere.read_trial(p).t) for p in paths)
    assert doc["verdict"]["set_aside"] < 0.01 * frames
