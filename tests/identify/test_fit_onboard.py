"""Fits from the robot's own sensors (IMU and wheel encoders), as a user runs them: `jsphere fit`
on onboard-sensor trial files with the IMU's mounting given. The trials are the paper's robot
driven by torque multisines from rest (3 trials of 3 s at 100 Hz; gyro 0.003 rad/s and
accelerometer 0.03 m/s^2 white noise, constant biases, encoders of 4096 counts per turn).

The right mounting gives exit 0, every estimate within 3 standard errors of the truth, the
biases and the noise levels recovered; a wrong mounting is a misfit put down to a model error
that names the mounting. The fits run in the slow lane (CI runs it); the refusals in the default
lane."""

from __future__ import annotations

import json
import math

import jax.numpy as jnp
import numpy as np
import pytest

import jsphere
from jsphere._runtime.errors import ExitCode, InputError
from jsphere.capture.onboard import OnboardNoise, synthetic_onboard_trial, write_onboard_trial
from jsphere.capture.trial import read_trials
from jsphere.cli.app import main
from jsphere.identify.fit import fit
from jsphere.identify.options import FitOptions
from jsphere.model.names import get_value
from jsphere.model.rotations import quat_exp, quat_mul
from jsphere.model.sensors import Mounting

FREE = ["I[2,2]", "m0", "j"]
MOUNTING = Mounting((0.02, -0.01, -0.04), (math.cos(0.3), 0.0, math.sin(0.3), 0.0))
NOISE = OnboardNoise(0.003, 0.03, (0.01, -0.02, 0.005), (0.1, 0.0, -0.2), counts_per_turn=4096)


@pytest.fixture(scope="module")
def folder(paper, tmp_path_factory):
    """The trial files, as `jsphere convert` or a robot's logger would leave them."""
    d = tmp_path_factory.mktemp("onboard")
    for s in range(3):
        controls = jsphere.random_inputs(paper, 3.0, kind="torques", seed=s)
        tr = synthetic_onboard_trial(paper, controls, 3.0, mounting=MOUNTING, noise=NOISE, seed=s, name=f"run{s}")
        write_onboard_trial(d / f"run{s}.csv", tr)
    return d


@pytest.fixture(scope="module")
def cli_fit(folder, tmp_path_factory):
    out = tmp_path_factory.mktemp("fit") / "fit.json"
    pos = [f"{v:.6g}" for v in np.asarray(MOUNTING.position)]
    rot = [f"{v:.15g}" for v in np.asarray(MOUNTING.rotation)]
    argv = ["fit", str(folder), "--free", ",".join(FREE), "--imu-position", *pos, "--imu-rotation", *rot]
    code = main([*argv, "--out", str(out), "--quiet"])
    return code, json.loads(out.read_text()), out


@pytest.mark.slow
def test_the_right_mounting_recovers_the_robot_within_its_standard_errors(paper, cli_fit):
    code, doc, out = cli_fit
    assert code == ExitCode.OK, doc["status_reason"]
    assert doc["status"] == "converged" and doc["loss"] == "l2"
    for name in FREE:
        truth, value, se = float(get_value(paper, name)), doc["values"][name], doc["stderr"][name]
        assert 0 < se < 1e-2 * abs(truth), (name, se)
        assert abs(value - truth) < 3 * se, (name, value, truth, se)
    for t in doc["trials"]:  # the biases, to 4 sd of a mean over the trial's samples
        b = t["nuisance"]
        np.testing.assert_allclose([b[f"gyro_bias_{a}"] for a in "xyz"], NOISE.gyro_bias, atol=4 * 0.003 / 10)
        np.testing.assert_allclose([b[f"acc_bias_{a}"] for a in "xyz"], NOISE.acc_bias, atol=4 * 0.03 / 10)
    s = doc["sigmas"]
    assert abs(s["gyro"] / 0.003 - 1) < 0.1 and abs(s["acc"] / 0.03 - 1) < 0.1
    assert abs(s["encoders"] / (2 * math.pi / 4096 / math.sqrt(12)) - 1) < 0.1
    assert all(0.8 < c["ratio"] < 1.2 for c in doc["verdict"]["channels"].values())
    assert doc["channel_share"]["encoders"]["m0"] > 0.5  # the encoders carry the information
    assert (out.parent / "fit_overlay.png").stat().st_size > 10_000
    assert (out.parent / "fit_residuals.png").stat().st_size > 10_000


@pytest.mark.slow
def test_a_wrong_mounting_is_a_model_error_that_names_the_mounting(paper, folder):
    trials = read_trials([folder])
    assert all(type(t).__name__ == "OnboardTrial" for t in trials)
    res = fit(trials, paper, FREE, options=FitOptions(imu_position=(0.0, 0.0, 0.0)), progress=False)
    assert res.status == "misfit" and res.verdict["diagnosis"] == "model error"
    assert "--imu-position, --imu-rotation" in res.status_reason
    assert set(res.verdict["correlated"]) == {"run0", "run1", "run2"}


@pytest.mark.slow
def test_a_freed_mounting_is_fitted_from_a_wrong_start_with_the_robot(paper, folder, tmp_path):
    """`--free imu_rotation,imu_position` from a mounting 3 degrees and 7 mm off: exit 0, the
    robot and the mounting within 3 standard errors of the truth."""
    delta = np.array([0.03, -0.02, 0.04])
    start = np.asarray(quat_mul(MOUNTING.rotation, quat_exp(delta)))
    pos = np.asarray(MOUNTING.position) + np.array([0.004, -0.003, 0.005])
    free = [*FREE, "imu_rotation", "imu_position"]
    out = tmp_path / "fit.json"
    argv = ["fit", str(folder), "--free", ",".join(free), "--imu-position", *map(str, pos)]
    code = main([*argv, "--imu-rotation", *map(repr, start.tolist()), "--out", str(out), "--quiet"])
    doc = json.loads(out.read_text())
    assert code == ExitCode.OK, doc["status_reason"]
    truth = {n: float(get_value(paper, n)) for n in FREE}
    truth |= {f"imu_rotation[{k}]": -delta[k] for k in range(3)}  # the correction that undoes the error
    truth |= {f"imu_position[{k}]": float(MOUNTING.position[k]) for k in range(3)}
    for name, v in truth.items():
        assert abs(doc["values"][name] - v) < 3 * doc["stderr"][name], (name, doc["values"][name], v)
    assert doc["stderr"]["imu_rotation[0]"] < 1e-3 and doc["stderr"]["imu_position[0]"] < 1e-3
    rot = np.asarray(doc["mounting"]["rotation"])
    assert 2 * math.acos(min(1.0, abs(float(rot @ np.asarray(MOUNTING.rotation))))) < 1e-3
    np.testing.assert_allclose(doc["values"]["imu_position"], doc["mounting"]["position"])


def test_the_mounting_is_free_only_in_onboard_fits(paper):
    from jsphere.identify.free import FreeParams

    with pytest.raises(InputError, match="'imu_rotation' is the IMU's mounting"):
        FreeParams(paper, "j,imu_rotation")
    with pytest.raises(ValueError, match="imu_position has 3 components"):
        FreeParams(paper, "imu_position[3]", mounting=MOUNTING)
    fp = FreeParams(paper, "j,imu_position[1],imu_rotation[2]", mounting=MOUNTING)
    assert fp.names == ["j", "imu_position[1]", "imu_rotation[2]"]
    theta = fp.theta0.copy()
    assert theta[1] == pytest.approx(-0.01) and theta[2] == 0.0
    theta[1:] = (0.05, 0.1)
    pos, rot = fp.mounting_at(jnp.asarray(theta), MOUNTING.position, MOUNTING.rotation)
    np.testing.assert_allclose(pos, (0.02, 0.05, -0.04))
    np.testing.assert_allclose(rot, quat_mul(MOUNTING.rotation, quat_exp(jnp.array([0.0, 0.0, 0.1]))))
    assert float(fp.to_params(jnp.asarray(theta)).j) == pytest.approx(float(paper.j))


def test_onboard_fits_refuse_what_does_not_apply(paper, folder):
    trials = read_trials([folder])
    with pytest.raises(InputError, match="share one clock"):
        fit(trials, paper, FREE, options=FitOptions(fit_time_offset=True), progress=False)
    with pytest.raises(InputError, match="imu_rotation is a zero quaternion"):
        fit(trials, paper, FREE, options=FitOptions(imu_rotation=(0, 0, 0, 0)), progress=False)


@pytest.mark.slow
def test_trials_cut_from_a_run_need_their_initial_motion_fitted(paper, folder):
    """Trials cut 1 s into the runs (the robot in motion): started at rest the fit is a misfit;
    with `start_at_rest=False` (`--estimate-initial-state`) it recovers the robot within 3
    standard errors, with larger standard errors."""
    cut = []
    for t in read_trials([folder]):
        k = 100
        cut.append(
            type(t)(t.t[k:] - t.t[k], t.gyro[k:], t.acc[k:], t.chi[k:] - t.chi[k], t.inputs[k:], t.kind, name=t.name)
        )
    mount = {"imu_position": tuple(np.asarray(MOUNTING.position)), "imu_rotation": tuple(np.asarray(MOUNTING.rotation))}
    rest = fit(cut, paper, FREE, options=FitOptions(**mount), progress=False)
    assert rest.status == "misfit"
    moving = fit(cut, paper, FREE, options=FitOptions(**mount, start_at_rest=False), progress=False)
    assert moving.status == "converged", moving.status_reason
    for name in FREE:
        assert abs(moving.values[name] - float(get_value(paper, name))) < 3 * moving.stderr[name], name
    assert {"Omega0_x", "tilt0_y", "omega0_z", "chi0_3"} <= set(moving.trials[0]["nuisance"])


@pytest.mark.slow
def test_a_killed_onboard_fit_resumes_to_the_same_result(paper, folder, tmp_path):
    trials = read_trials([folder])
    mount = {"imu_position": tuple(np.asarray(MOUNTING.position)), "imu_rotation": tuple(np.asarray(MOUNTING.rotation))}
    options, ckpt = FitOptions(**mount), tmp_path / "fit.ckpt.npz"

    def kill(line):
        if "LM stage 1 it   2" in line:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        fit(trials, paper, FREE, options=options, checkpoint=ckpt, progress=kill)
    lines = []
    resumed = fit(trials, paper, FREE, options=options, checkpoint=ckpt, progress=lines.append)
    assert any("resuming from" in line for line in lines)
    whole = fit(trials, paper, FREE, options=options, progress=False)
    assert resumed.values == whole.values and resumed.stderr == whole.stderr


def test_zero_order_hold_is_an_option_of_the_fit_as_of_the_file(paper, folder):
    from jsphere.identify.fit import _pack

    trials = read_trials([folder])
    assert _pack(trials, paper, FitOptions().checked(onboard=True), True).measure == "onboard"
    held = _pack(trials, paper, FitOptions(zero_order_hold=True).checked(onboard=True), True)
    assert held.hold and held.measure == "onboard-held"


@pytest.mark.slow
def test_commands_that_need_poses_refuse_onboard_trials_in_one_line(folder, cli_fit, tmp_path, capsys):
    _, _, fit_json = cli_fit
    trial = str(folder / "run0.csv")
    assert main(["compare", trial, "--params", str(fit_json), "--out", str(tmp_path / "c.json")]) == ExitCode.BAD_INPUT
    assert main(["animate", trial, "--out", str(tmp_path / "a.gif")]) == ExitCode.BAD_INPUT
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 2 and all("an onboard-sensor trial (IMU and encoders, no poses)" in e for e in err)
