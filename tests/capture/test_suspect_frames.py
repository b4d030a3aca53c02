"""Frames of a suspect marker fit at conversion: a swapped or ghost marker whose rigid-body fit
residual stands out of the take's own noise is written as missing, with a warning saying how
many; `--keep-suspect` keeps them. A take whose noise varies from frame to frame loses no more
than 2 % of its frames; a frame within twice the export's own marker error is not suspect; every
other frame left out (a residual above 5 mm, a frame outside the inputs table) is counted and
said; markers that do not move as one rigid body are refused."""

from __future__ import annotations

import numpy as np
import pytest

import jsphere
from jsphere._runtime.errors import InputError
from jsphere.capture.markers import MarkerData
from jsphere.capture.pose import SUSPECT, markers_to_trial, suspect_frames, suspect_limit
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
        CaptureWarning,
        match=rf"{len(GHOSTS)} of 151 frame\(s\) whose marker fit residual stands out of the take's noise .* "
        r"left out as missing \(--keep-suspect keeps them\)",
    ):
        tr = jsphere.convert_raw(raw, inputs, format="motive", options=jsphere.ConvertOptions(body_markers=BODY))
    assert np.flatnonzero(~tr.valid).tolist() == GHOSTS
    with pytest.warns(CaptureWarning, match=r"are kept, as --keep-suspect asks"):
        kept = jsphere.convert_raw(
            raw, inputs, format="motive", options=jsphere.ConvertOptions(body_markers=BODY, keep_suspect=True)
        )
    assert kept.valid.all()
    assert np.hypot(kept.x[GHOSTS] - truth.x[GHOSTS], kept.y[GHOSTS] - truth.y[GHOSTS]).max() > 5e-4


def test_cli_convert_writes_suspect_frames_as_missing_and_keep_suspect_keeps_them(take, tmp_path, capsys):
    raw, inputs, _ = take
    args = ["convert", str(raw), "--format", "motive", "--inputs", str(inputs)]
    assert main([*args, "--out", str(tmp_path / "a.csv")]) == 0
    err = capsys.readouterr().err
    assert f"{len(GHOSTS)} of 151 frame(s)" in err and "keep_suspect" not in err
    assert np.flatnonzero(~read_trial(tmp_path / "a.csv").valid).tolist() == GHOSTS
    assert main([*args, "--out", str(tmp_path / "b.csv"), "--keep-suspect"]) == 0
    assert read_trial(tmp_path / "b.csv").valid.all()


def test_a_take_whose_noise_varies_loses_at_most_2_percent_and_a_ghost_is_still_caught():
    """Residuals spread log-normally (a real take: markers seen by more or fewer cameras, 15 %
    of its frames above 5x its median) set aside at most 2 % of the frames; a ghost far out of
    that spread is caught, and a clean take's threshold stays at 5x its median."""
    rng = np.random.default_rng(1)
    rms = 7.6e-5 * np.exp(1.5 * rng.standard_normal(2000))
    assert np.mean(rms > 5 * np.median(rms)) > 0.1
    assert suspect_frames(rms).mean() <= 0.02
    rms[[100, 900]] = 0.2  # 20 cm: a marker of another body taken for one of the robot's
    assert suspect_frames(rms)[[100, 900]].all()
    clean = 1e-4 * np.sqrt(rng.chisquare(6, 500) / 12)
    assert suspect_limit(clean) == pytest.approx(SUSPECT * np.median(clean))
    assert not suspect_frames(clean).any()


def test_the_exports_own_marker_error_floors_the_threshold():
    """A frame whose residual is within twice the marker error the export reports for it is noisy,
    not swapped: it is kept; the same residual where the export reports a small error is suspect."""
    rms = np.full(200, 1e-4)
    rms[[10, 50]] = 1.0e-3
    error = np.full(200, 0.1e-3)
    error[10] = 0.8e-3  # the exporter saw the markers that far apart on frame 10
    assert np.flatnonzero(suspect_frames(rms)).tolist() == [10, 50]
    assert np.flatnonzero(suspect_frames(rms, error)).tolist() == [50]
    error[50] = np.nan  # not reported on that frame: the take's own threshold
    assert np.flatnonzero(suspect_frames(rms, error)).tolist() == [50]


def test_motive_mean_marker_error_is_read_and_keeps_noisy_frames(take, tmp_path):
    """The rigid body's `Mean Marker Error` column of a Motive export is read (in metres) and
    passed on: frames the export itself reports as that noisy are kept."""
    _, inputs, truth = take
    m = jsphere.synthetic_markers(truth, BODY, marker_sd=1e-4, seed=4)
    noisy = [30, 31, 80]
    m[noisy] += np.random.default_rng(5).normal(0.0, 1.2e-3, m[noisy].shape)
    raw = tmp_path / "noisy.csv"
    jsphere.write_motive_csv(raw, truth.t, m, NAMES, rb_q=truth.q, rb_p=np.zeros((truth.t.size, 3)), units="mm")
    lines = raw.read_text().splitlines()
    col = lines[5].split(",").index("Mean Marker Error")
    for k in range(truth.t.size):  # the exporter's error: 0.1 mm, 2 mm on the noisy frames
        cells = lines[7 + k].split(",")
        cells[col] = "2.000000" if k in noisy else "0.100000"
        lines[7 + k] = ",".join(cells)
    raw.write_text("\n".join(lines) + "\n")
    data = jsphere.read_motive_csv(raw, use="markers")
    assert data.marker_error is not None and data.marker_error[noisy] == pytest.approx(2e-3)
    tr = markers_to_trial(data, inputs, options=jsphere.ConvertOptions(body_markers=BODY))
    assert tr.valid.all()
    bare = MarkerData(data.t, data.markers, data.names, data.source, data.lines)
    with pytest.warns(CaptureWarning, match=r"stands out of the take's noise"):
        tr = markers_to_trial(bare, inputs, options=jsphere.ConvertOptions(body_markers=BODY))
    assert set(np.flatnonzero(~tr.valid)) == set(noisy)


def test_frames_above_max_rms_and_outside_the_inputs_are_counted_and_said(take, tmp_path):
    """A frame whose fit residual passes 5 mm, and frames after the inputs table's end, are left
    out with warnings counting them and saying why."""
    raw, _, truth = take
    data = jsphere.read_motive_csv(raw)
    m = data.markers.copy()
    m[[40, 41], 1] += 0.03  # a marker 3 cm off: a residual far above 5 mm
    t_in, u = truth.t[:120], truth.inputs[:120]
    with pytest.warns(CaptureWarning) as caught:
        tr = markers_to_trial(
            MarkerData(data.t, m, data.names, data.source),
            (t_in, u, truth.kind),
            options=jsphere.ConvertOptions(body_markers=BODY),
        )
    said = [str(w.message) for w in caught]
    assert any("2 of 151 frame(s) are left out as missing: their marker fit residual is above 5 mm" in s for s in said)
    assert any(
        "31 of 151 capture frame(s) are left out: they lie outside the inputs table's time range" in s
        and "31 after its end" in s
        for s in said
    )
    assert tr.t.size == 120 and {40, 41} <= set(np.flatnonzero(~tr.valid).tolist())


def test_markers_that_do_not_move_as_one_rigid_body_are_refused(take, tmp_path, capsys):
    """Two of the four markers moving on their own (a person, several bodies): more than half the
    frames would be left out, so the conversion is refused (exit 2), saying why and what to give."""
    _, inputs, truth = take
    m = jsphere.synthetic_markers(truth, BODY, marker_sd=1e-4, seed=4)
    swing = 0.05 * np.sin(2 * np.pi * 1.3 * truth.t)[:, None]
    m[:, 2:, 0] += swing
    raw = tmp_path / "two_bodies.csv"
    jsphere.write_motive_csv(raw, truth.t, m, NAMES, units="mm")
    with pytest.raises(InputError, match=r"the markers do not move as one rigid body: \d+ of the 151 frames"):
        jsphere.convert_raw(raw, inputs, format="motive")
    args = ["convert", str(raw), "--format", "motive", "--inputs", str(inputs), "--out", str(tmp_path / "t.csv")]
    assert main(args) == 2
    err = capsys.readouterr().err
    assert "do not move as one rigid body" in err and "--body-markers FILE" in err
