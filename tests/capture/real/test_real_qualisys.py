"""Qualisys Track Manager's own TSV exports (`tests/capture/real/qualisys/SOURCE.md`): QTM 2.x 3D
and 6DOF takes without a `Frame`/`Time` column, and a TSV 2.0.0 3D take. Each is converted by
`jsphere convert`, and the trial's positions are compared with the file's numbers read here by a
few lines of tab splitting, not by jsphere's reader, within 1 micrometre after millimetres ->
metres."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import jsphere
from jsphere.cli.app import main
from jsphere.model.rotations import rotmat_np

HERE = Path(__file__).parent / "qualisys"
UM = 1e-6  # one micrometre [m]


def _tsv(path: Path) -> tuple[dict[str, list[str]], list[str] | None, np.ndarray]:
    """The header variables, the column row (None without one) and the numbers of a QTM TSV
    export: tab-separated cells, blank -> NaN; trailing blank cells dropped."""
    lines = path.read_text().splitlines()
    meta, k = {}, 0
    while lines[k].split("\t")[0].isupper() and not lines[k].startswith(" "):
        cells = lines[k].split("\t")
        meta[cells[0]] = cells[1:]
        k += 1
    columns = None
    try:
        float(lines[k].split("\t")[0])
    except ValueError:
        columns = [c.strip() for c in lines[k].split("\t")]
        k += 1
    rows = [[float(c) if c.strip() else np.nan for c in line.split("\t")] for line in lines[k:] if line.strip()]
    width = max(len(r) for r in rows)
    return meta, columns, np.array([r + [np.nan] * (width - len(r)) for r in rows])


def _inputs(path: Path, duration: float) -> Path:
    """An inputs table of 3 wheels at rest over `[0, duration]` s."""
    t = np.arange(0.0, duration + 0.02, 0.01)
    path.write_text("t,chi_dot_1,chi_dot_2,chi_dot_3\n" + "".join(f"{v:.2f},0,0,0\n" for v in t))
    return path


def _convert(tmp_path: Path, raw: Path, duration: float, *options: str) -> jsphere.Trial:
    out = tmp_path / f"{raw.stem}.csv"
    args = ["convert", str(raw), "--format", "qualisys", "--inputs", str(_inputs(tmp_path / "u.csv", duration))]
    assert main([*args, *options, "--out", str(out)]) == 0
    return jsphere.read_trial(out)


def _body_markers(path: Path, names: list[str], frame: np.ndarray) -> Path:
    """Body markers in metres about their centroid, from one frame of the export (mm)."""
    b = frame / 1000.0 - (frame / 1000.0).mean(0)
    path.write_text("name,x,y,z\n" + "".join(f"{n},{x:.6f},{y:.6f},{z:.6f}\n" for n, (x, y, z) in zip(names, b)))
    return path


def test_qtm2_6dof_take(tmp_path):
    """QTM 2.x 6DOF: one column row ` X ... Rot[8]` for three bodies, 16 values and a blank cell
    per body, no Frame/Time (times from FREQUENCY), Yaw-Pitch-Roll angles; the Foot IMU is not
    seen in the last 7 frames (zeros, residual -1): gaps."""
    raw = HERE / "imusim_swing_6D.tsv"
    meta, columns, data = _tsv(raw)
    assert columns[:7] == ["X", "Y", "Z", "Yaw", "Pitch", "Roll", "Residual"] and data.shape == (904, 51)
    rate = float(meta["FREQUENCY"][0])
    for i, body in enumerate(meta["BODY_NAMES"]):
        g = data[:, 17 * i : 17 * i + 16]
        trial = _convert(tmp_path, raw, 904 / rate, "--rigid-body", body)
        np.testing.assert_allclose(trial.t, np.arange(904) / rate, atol=1e-6)  # written to the microsecond
        unseen = g[:, 6] < 0
        assert unseen.sum() == (7 if body == "Foot IMU" else 0)
        assert np.all(np.isnan(trial.x[unseen])) and np.all(np.isfinite(trial.x[~unseen]))
        p = np.stack([trial.x, trial.y, trial.z], axis=1)[~unseen]
        assert np.max(np.abs(p - g[~unseen, :3] / 1000.0)) < UM
        R = g[~unseen, 7:16].reshape(-1, 3, 3).transpose(0, 2, 1)  # Rot[0..2]: the first column
        assert np.max(np.abs(rotmat_np(trial.q[~unseen]) - R)) < 5e-5  # Rot has 5 decimals


def test_qtm2_6dof_angles_only(tmp_path):
    """The same take with its Rot columns left out: the angles, applied in the file's column order
    Yaw, Pitch, Roll about the rotated axes (`R_z R_y R_x`), give QTM's own rotation matrices."""
    lines = (HERE / "imusim_swing_6D.tsv").read_text().splitlines()
    keep = [j for j in range(51) if j % 17 < 7 or j % 17 == 16]  # X Y Z Yaw Pitch Roll Residual, blank
    head = lines[10].split("\t")
    body = [lines[10 + 1 + m].split("\t") for m in range(904)]
    raw = tmp_path / "angles_6D.tsv"
    raw.write_text("\n".join([*lines[:10], "\t".join(head[:7]), *("\t".join(r[j] for j in keep) for r in body)]))
    _, _, data = _tsv(HERE / "imusim_swing_6D.tsv")
    d = jsphere.read_qualisys_tsv(raw, rigid_body="Lower Leg IMU")
    R = data[:, 34 + 7 : 34 + 16].reshape(-1, 3, 3).transpose(0, 2, 1)
    assert np.max(np.abs(rotmat_np(d.rb_q) - R)) < 5e-5
    assert np.max(np.abs(d.rb_p - data[:, 34:37] / 1000.0)) < UM


def test_qtm2_3d_take(tmp_path):
    """QTM 2.x 3D: no column row, no Frame/Time, `NaN` cells; a leg's 14 markers, of which the
    three of the upper-leg IMU move as one rigid body: converted with those three as the body
    markers, the trial's position is their centroid."""
    raw = HERE / "imusim_swing_3D.tsv"
    meta, columns, data = _tsv(raw)
    assert columns is None and data.shape == (904, 42)
    names = meta["MARKER_NAMES"]
    chosen = [f"Upper Leg IMU - {i}" for i in (1, 2, 3)]
    m = data.reshape(904, 14, 3)[:, [names.index(n) for n in chosen]]
    body = _body_markers(tmp_path / "body.csv", chosen, m[0])
    trial = _convert(tmp_path, raw, 904 / 256, "--body-markers", str(body))
    ok = np.isfinite(trial.x)
    assert ok.sum() >= 0.98 * 904
    centroid = m.mean(1) / 1000.0
    p = np.stack([trial.x, trial.y, trial.z], axis=1)
    assert np.max(np.abs(p[ok] - centroid[ok])) < UM
    np.testing.assert_allclose(trial.t, np.arange(904) / 256, atol=1e-6)


def test_qtm_tsv2_3d_take(tmp_path):
    """QTM TSV 2.0.0 3D (`FILE_VERSION`, `Frame`/`Time` columns, a tab ending each column row):
    an arm's 5 markers; the reader gives every marker's numbers, and a conversion with the
    forearm's 3 markers as the body markers gives their centroid where the fit keeps a frame."""
    raw = HERE / "pyeyesweb_arm_3D_trimmed.tsv"
    meta, columns, data = _tsv(raw)
    names = meta["MARKER_NAMES"]
    assert meta["FILE_VERSION"] == ["2.0.0"] and columns[:2] == ["Frame", "Time"]
    d = jsphere.read_qualisys_tsv(raw)
    assert d.names == tuple(names)
    np.testing.assert_allclose(d.t, data[:, 1], atol=1e-9)
    xyz = data[:, 2 : 2 + 3 * len(names)].reshape(len(data), -1, 3) / 1000.0
    assert np.max(np.abs(d.markers - xyz)) < UM
    chosen = ["RWristOut", "RWristIn", "RElbowOut"]
    m = xyz[:, [names.index(n) for n in chosen]]
    body = _body_markers(tmp_path / "body.csv", chosen, m[0] * 1000.0)
    trial = _convert(tmp_path, raw, float(data[-1, 1]), "--body-markers", str(body))
    ok = np.isfinite(trial.x)
    assert ok.sum() >= 0.5 * len(data)
    p = np.stack([trial.x, trial.y, trial.z], axis=1)
    assert np.max(np.abs(p[ok] - m.mean(1)[ok])) < UM


@pytest.mark.parametrize("name", ["imusim_swing_6D.tsv", "imusim_swing_3D.tsv", "pyeyesweb_arm_3D_trimmed.tsv"])
def test_source_listed(name):
    """Each file is listed in SOURCE.md with its licence beside it."""
    text = (HERE / "SOURCE.md").read_text()
    assert f"`{name}`" in text
    assert (HERE / ("LICENSE-IMUSim.txt" if name.startswith("imusim") else "LICENSE-PyEyesWeb.txt")).exists()
