"""OptiTrack Motive's own CSV exports (tests/capture/real/motive/SOURCE.md): a format 1.21 take
converts with the marker positions and the rigid body's marker error of the file, read here by a
few lines of csv parsing, within 1 micrometre, and no frame of that clean take is set aside;
format 1.23 takes holding no labelled marker or rigid body, and older layouts, are refused
saying so."""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np
import pytest

import jsphere
from jsphere.cli.app import main

HERE = Path(__file__).parent / "motive"
TAKE_121 = HERE / "motive121_cmu_static.csv"


def _columns(path: Path) -> tuple[dict[tuple[str, str, str], int], np.ndarray]:
    """`{(name, kind, axis): column}` and the data rows (blank cells NaN) of a Motive export, by
    the csv module: the name row is the second row after line 1's blank line, the kind row the
    one before the `Frame` row, the axis row the `Frame` row."""
    with open(path, newline="") as f:
        rows = list(csv.reader(f))
    i_frame = next(i for i, r in enumerate(rows) if r and r[0] == "Frame")
    head = [i for i in range(1, i_frame) if any(rows[i])]
    names, kinds, axes = rows[head[1]], rows[i_frame - 1], rows[i_frame]
    cols = {(names[j], kinds[j], axes[j]): j for j in range(2, len(axes))}
    data = np.array([[float(c) if c else np.nan for c in r] for r in rows[i_frame + 1 :] if r], float)
    return cols, data


@pytest.fixture(scope="module")
def inputs(tmp_path_factory):
    path = tmp_path_factory.mktemp("inputs") / "inputs.csv"
    t = np.arange(0.0, 2.1, 0.01)
    jsphere.write_inputs_csv(path, t, np.zeros((t.size, 3)), "wheel_speeds")
    return path


def test_motive_121_markers_and_marker_error_equal_the_files_numbers():
    cols, raw = _columns(TAKE_121)
    data = jsphere.read_motive_csv(TAKE_121)
    assert data.names == ("Rigid Body 1:Marker1", "Rigid Body 1:Marker2", "Rigid Body 1:Marker3")
    assert data.t == pytest.approx(raw[:, 1], abs=1e-9)
    for k, name in enumerate(data.names):
        x, y, z = (raw[:, cols[(name, "Position", a)]] for a in "XYZ")  # metres, Y up
        expected = np.stack([x, -z, y], axis=1)  # jsphere's Z-up frame
        assert np.nanmax(np.abs(data.markers[:, k] - expected)) < 1e-6
    error = raw[:, cols[("Rigid Body 1", "Error Per Marker", "")]]
    assert data.marker_error is not None and np.nanmax(np.abs(data.marker_error - error)) < 1e-9


def test_motive_121_converts_with_no_frame_set_aside(inputs, tmp_path, capsys):
    """The centre of the converted trial (the markers' centroid, no body offset) is the file's
    centroid within 1 micrometre, on every one of the 250 frames: the clean take loses none."""
    cols, raw = _columns(TAKE_121)
    out = tmp_path / "trial.csv"
    assert main(["convert", str(TAKE_121), "--format", "motive", "--inputs", str(inputs), "--out", str(out)]) == 0
    assert "left out" not in capsys.readouterr().err
    trial = jsphere.read_trial(out)
    assert trial.t.size == 250 and trial.valid.mean() >= 0.98 and trial.valid.all()
    names = [f"Rigid Body 1:Marker{i}" for i in (1, 2, 3)]
    centroid = np.mean([[raw[:, cols[(n, "Position", a)]] for a in "XYZ"] for n in names], axis=0).T
    expected = np.stack([centroid[:, 0], -centroid[:, 2], centroid[:, 1]], axis=1)
    assert np.max(np.abs(np.stack([trial.x, trial.y, trial.z], axis=1) - expected)) < 1e-6


@pytest.mark.parametrize(
    "name, what",
    [
        ("motive123_no_columns.csv", "no marker or rigid-body columns"),
        ("motive123_unlabelled_only.csv", "only 18 unlabelled marker"),
    ],
)
def test_motive_123_takes_without_labelled_markers_are_refused(name, what, inputs, tmp_path, capsys):
    args = [
        "convert",
        str(HERE / name),
        "--format",
        "motive",
        "--inputs",
        str(inputs),
        "--out",
        str(tmp_path / "t.csv"),
    ]
    assert main(args) == 2
    err = capsys.readouterr().err
    assert "holds no labelled markers or rigid body" in err and what in err


@pytest.mark.parametrize("version", ["1.2", "1.1"])
def test_older_motive_layouts_are_refused_naming_the_version(version, tmp_path):
    old = tmp_path / "old.csv"
    old.write_text(TAKE_121.read_text().replace("Format Version,1.21,", f"Format Version,{version},", 1))
    with pytest.raises(jsphere.InputError, match=rf"Motive CSV format version {version}, an older layout"):
        jsphere.read_motive_csv(old)
    info = tmp_path / "info.csv"
    info.write_text("comment,exported by Motive\ninfo,version,1.1\ninfo,framecount,3\n")
    with pytest.raises(jsphere.InputError, match=r"format version 1\.1 \(Motive 1\.x\), an older layout"):
        jsphere.read_motive_csv(info)
