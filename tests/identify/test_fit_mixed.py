"""Trials of both kinds in one fit: motion-capture trials and onboard-sensor trials of the same
robot share the free parameters, each kind with its own model, nuisance values, noise levels
and verdict.

The stack's padding is checked against each part's own normal equations (default lane); the
fits as a user runs them (the command line on a folder of both kinds of files) in the slow lane:
the right model passes within 3 standard errors with the information of both parts added, a
wrong IMU mounting is a misfit put down to the onboard sensors."""

from __future__ import annotations

import json
import math

import jax.numpy as jnp
import numpy as np
import pytest

import jsphere
from jsphere._runtime.errors import ExitCode, InputError
from jsphere.capture.onboard import OnboardNoise, synthetic_onboard_trial, write_onboard_trial
from jsphere.capture.trial import read_trials, write_trial
from jsphere.cli.app import main
from jsphere.identify.fit import fit
from jsphere.identify.mixed import stack
from jsphere.identify.options import FitOptions
from jsphere.model.names import get_value
from jsphere.model.sensors import Mounting
from jsphere.numerics.lm import marginal_information

FREE = ["I[2,2]", "m0", "j"]
MOUNTING = Mounting((0.02, -0.01, -0.04), (math.cos(0.3), 0.0, math.sin(0.3), 0.0))
NOISE = OnboardNoise(0.003, 0.03, (0.01, -0.02, 0.005), (0.1, 0.0, -0.2), counts_per_turn=4096)
FLAGS = ["--imu-position", *map(str, np.asarray(MOUNTING.position))]
FLAGS += ["--imu-rotation", *map(repr, np.asarray(MOUNTING.rotation).tolist())]


def test_the_stack_adds_each_parts_information():
    """Padded residuals and anchors give the free parameters the information of the two parts'
    own normal equations, summed."""
    rng = np.random.default_rng(0)
    S, P, own, K = 1, 3, (11, 9), (40, 30)
    parts = []
    for T, n, k in zip((2, 3), own, K):
        parts.append((rng.normal(size=(S, T, k)), True, rng.normal(size=(S, T, k, P + n)), None))
    nu = jnp.asarray(np.zeros((S, 5, max(own))))
    n_res = max(k + max(own) - n for k, n in zip(K, own))
    res, ok, J, _ = stack(
        [(jnp.asarray(r), jnp.ones(r.shape[:2], bool), jnp.asarray(j), a) for r, _, j, a in parts], nu, P, 2, own, n_res
    )
    assert res.shape == (S, 5, n_res) and J.shape == (S, 5, n_res, P + max(own)) and bool(ok.all())
    whole = marginal_information(res[0], J[0], P)
    apart = sum(marginal_information(jnp.asarray(r[0]), jnp.asarray(j[0]), P) for r, _, j, _ in parts)
    np.testing.assert_allclose(whole, apart, rtol=1e-10)


def test_trials_of_both_kinds_share_one_input_kind(paper):
    onboard = synthetic_onboard_trial(paper, jsphere.random_inputs(paper, 1.0, kind="torques", seed=1), 1.0)
    pose = jsphere.synthetic_trial(paper, jsphere.random_inputs(paper, 1.0, kind="wheel_speeds", seed=1), 1.0)
    with pytest.raises(InputError, match="share one input kind"):
        fit([pose, onboard], paper, FREE, progress=False)


@pytest.fixture(scope="module")
def folder(paper, tmp_path_factory):
    """Two motion-capture trials and two onboard-sensor trials of 3 s, as files."""
    d = tmp_path_factory.mktemp("mixed")
    for s in range(2):
        controls = jsphere.random_inputs(paper, 3.0, kind="torques", seed=s)
        tr = synthetic_onboard_trial(paper, controls, 3.0, mounting=MOUNTING, noise=NOISE, seed=s, name=f"imu{s}")
        write_onboard_trial(d / f"imu{s}.csv", tr)
        controls = jsphere.random_inputs(paper, 3.0, kind="torques", seed=10 + s)
        write_trial(d / f"mocap{s}.csv", jsphere.synthetic_trial(paper, controls, 3.0, seed=s, name=f"mocap{s}"))
    return d


@pytest.mark.slow
def test_trials_of_both_kinds_are_fitted_together(paper, folder, tmp_path):
    out = tmp_path / "fit.json"
    code = main(["fit", str(folder), "--free", ",".join(FREE), *FLAGS, "--out", str(out), "--quiet"])
    doc = json.loads(out.read_text())
    assert code == ExitCode.OK, doc["status_reason"]
    assert set(doc["verdict"]["parts"]) == {"capture", "onboard"}
    assert all(v["status"] == "converged" for v in doc["verdict"]["parts"].values())
    for name in FREE:
        truth, value, se = float(get_value(paper, name)), doc["values"][name], doc["stderr"][name]
        assert abs(value - truth) < 3 * se, (name, value, truth, se)
    assert abs(doc["sigma_pos_m"] / 1e-3 - 1) < 0.1 and abs(doc["sigmas"]["gyro"] / 0.003 - 1) < 0.1
    assert sorted(doc["outliers"]) == ["imu0.csv", "imu1.csv", "mocap0.csv", "mocap1.csv"]
    assert [t["name"] for t in doc["trials"]] == ["mocap0", "mocap1", "imu0", "imu1"]
    assert "gyro_bias_x" in doc["trials"][2]["nuisance"] and "x0" in doc["trials"][0]["nuisance"]
    for stem in ("fit", "fit_onboard"):
        for kind in ("overlay", "residuals"):
            assert (tmp_path / f"{stem}_{kind}.png").stat().st_size > 10_000
    # each part's information adds up: 1/se^2 of the whole is the sum of the parts' fitted apart
    trials = read_trials([folder])
    mount = np.asarray(MOUNTING.position), np.asarray(MOUNTING.rotation)
    options = FitOptions(imu_position=tuple(mount[0]), imu_rotation=tuple(mount[1]))
    parts = [[t for t in trials if (type(t).__name__ == "OnboardTrial") == onboard] for onboard in (False, True)]
    apart = [fit(p, paper, FREE, options=options, progress=False) for p in parts]
    for name in FREE:
        expected = sum(r.stderr[name] ** -2 for r in apart)
        assert abs(doc["stderr"][name] ** -2 / expected - 1) < 0.15, name


@pytest.mark.slow
def test_a_wrong_mounting_in_a_fit_of_both_kinds_is_put_down_to_the_onboard_sensors(paper, folder):
    trials = read_trials([folder])
    res = fit(trials, paper, FREE, options=FitOptions(imu_position=(0.0, 0.0, 0.0)), progress=False)
    assert res.status == "misfit" and res.verdict["diagnosis"] == "model error"
    assert res.status_reason.startswith("onboard sensors: ") and "--imu-position" in res.status_reason
    assert res.verdict["parts"]["onboard"]["status"] == "misfit"
    assert set(res.verdict["correlated"]) >= {"imu0", "imu1"}


@pytest.mark.slow
def test_a_killed_fit_of_both_kinds_resumes_to_the_same_result(paper, tmp_path):
    """The checkpoint holds both parts' simulated poses and readings: a fit killed in its second
    Levenberg-Marquardt step resumes to the result of a fit never stopped."""
    controls = jsphere.random_inputs(paper, 1.5, kind="torques", seed=3)
    trials = [
        jsphere.synthetic_trial(paper, controls, 1.5, seed=3, name="mocap"),
        synthetic_onboard_trial(paper, controls, 1.5, mounting=MOUNTING, noise=NOISE, seed=3, name="imu"),
    ]
    mount = np.asarray(MOUNTING.position), np.asarray(MOUNTING.rotation)
    options, ckpt = FitOptions(imu_position=tuple(mount[0]), imu_rotation=tuple(mount[1])), tmp_path / "fit.ckpt.npz"

    def kill(line):
        if "LM stage 1 it   2" in line:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        fit(trials, paper, "j,I[2,2]", options=options, checkpoint=ckpt, progress=kill)
    lines = []
    resumed = fit(trials, paper, "j,I[2,2]", options=options, checkpoint=ckpt, progress=lines.append)
    assert any("resuming from" in line for line in lines)
    whole = fit(trials, paper, "j,I[2,2]", options=options, progress=False)
    assert resumed.values == whole.values and resumed.stderr == whole.stderr
