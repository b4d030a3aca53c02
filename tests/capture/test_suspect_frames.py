"""Frames of a suspect marker fit at conversion: a swapped or ghost marker whose rigid-body fit
residual is far above the take's median is written as missing, with a warning saying how many;
`--keep-suspect` keeps them."""

from __future__ import annotations

import numpy as np
import pytest

import jsphere
from jsphere.capture.pose import SUSPECT, suspect_frames
from jsphere.capture.synthetic import default_marker_set
from jsphere.capture.trial import read_trial
from jsphere.capture.validation import CaptureWarning
from jsphere.cli.app import main

BODY = default_marker_set(0.15)
NAMES = ["a", "b", "c", "d"]
#: the frames given a ghost marker: marker 0 moved by 3 mm (a fit residual of about 1.3 mm,
#: under `max_rms` = 5 mm, 20x the take's median of ~0.07 mm)
GHOSTS = [20, 21, 55, 90, 91, 92]


@pytest.fixture(scope="module")
def take(tmp_path_factory):
    params = jsphere.RobotParams.paper()
    truth = jsphere.synthetic_trial(
        params, jsphere.random_inputs(params, 1.5, seed=3), 1.5, pos_sd=0.0, rot_sd_deg=0.0, seed=3, name="take"
    )
    m = jsphere.synthetic_markers(truth, BODY, marker_sd=1e-4, seed=4)
    m[GHOSTS, 0, 0] += 3e-3
    folder = tmp_path_factory.mktemp("take")
    raw, inputs = folder / "take.csv", folder / "inputs.csv"
    jsphere.write_motive_csv(raw, truth.t, m, NAMES, units="mm")
    jsphere.write_inputs_csv(inputs, truth.t, truth.inputs, truth.kind)
    return raw, inputs, truth


def test_suspect_frames_are_far_above_the_median():
    rng = np.random.default_rng(0)
    rms = np.abs(rng.normal(1e-4, 2e-5, 500))
    rms[[7, 300]] = [2e-3, 6 * np.median(rms)]
    rms[100] = np.nan  # a gap is not suspect
    assert np.flatnonzero(suspect_frames(rms)).tolist() == [7, 300]
    # residuals near 0 (a noise-free take): only those above the floor
    assert not suspect_frames(np.full(50, 1e-9)).any()
    assert not suspect_frames(np.full(5, np.nan)).any()


def test_convert_leaves_suspect_frames_out_with_a_warning(take):
    raw, inputs, truth = take
    with pytest.warns(
        CaptureWarning, match=rf"{len(GHOSTS)} frame\(s\) whose marker fit residual is more than {SUSPECT:g}x"
    ):
        tr = jsphere.convert_raw(raw, inputs, format="motive", body_markers=BODY)
    assert np.flatnonzero(~tr.valid).tolist() == GHOSTS
    kept = jsphere.convert_raw(raw, inputs, format="motive", body_markers=BODY, keep_suspect=True)
    assert kept.valid.all()
    assert np.hypot(kept.x[GHOSTS] - truth.x[GHOSTS], kept.y[GHOSTS] - truth.y[GHOSTS]).max() > 5e-4


def test_cli_convert_writes_suspect_frames_as_missing_and_keep_suspect_keeps_them(take, tmp_path, capsys):
    raw, inputs, _ = take
    args = ["convert", str(raw), "--format", "motive", "--inputs", str(inputs)]
    assert main([*args, "--out", str(tmp_path / "a.csv")]) == 0
    assert f"{len(GHOSTS)} frame(s)" in capsys.readouterr().err
    assert np.flatnonzero(~read_trial(tmp_path / "a.csv").valid).tolist() == GHOSTS
    assert main([*args, "--out", str(tmp_path / "b.csv"), "--keep-suspect"]) == 0
    assert read_trial(tmp_path / "b.csv").valid.all()
