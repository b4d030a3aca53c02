"""Vendors' own C3D files (`c3d/`, sources and licences in `c3d/SOURCE.md`): Vicon Nexus,
Qualisys Track Manager, NDI Optotrak and a force-plate-only file. Positions are compared with
the file's numbers read by the small reader below (the C3D layout parsed with `struct`), and
with ezc3d's."""

from __future__ import annotations

import struct
import warnings
from pathlib import Path

import numpy as np
import pytest

import jsphere
from jsphere._runtime.errors import InputError
from jsphere.capture.c3d import c3d_layout
from jsphere.capture.validation import CaptureWarning
from jsphere.cli.app import main

HERE = Path(__file__).resolve().parent / "c3d"
VICON = HERE / "vicon_nexus_box.c3d"
QTM = HERE / "qualisys_qtm_gait.c3d"
KISTLER = HERE / "kistler_force_plates.c3d"
OPTOTRAK = HERE / "optotrak_cut.c3d"

UM = 1e-6  # 1 micrometre [m]


def c3d_parameters(raw: bytes) -> dict[str, object]:
    """`{"GROUP:NAME": value}` of a little-endian C3D file's parameter section: strings for
    character arrays (a list for 2-D ones), numbers for scalars, tuples otherwise."""
    p0 = (raw[0] - 1) * 512
    pos, groups, out = p0 + 4, {}, {}
    while True:
        n = abs(struct.unpack("b", raw[pos : pos + 1])[0])
        gid = struct.unpack("b", raw[pos + 1 : pos + 2])[0]
        if n == 0:
            break
        name = raw[pos + 2 : pos + 2 + n].decode("ascii")
        at = pos + 2 + n
        nxt = struct.unpack("<h", raw[at : at + 2])[0]
        if gid < 0:
            groups[-gid] = name
        else:
            typ, nd = struct.unpack("b", raw[at + 2 : at + 3])[0], raw[at + 3]
            dims = list(raw[at + 4 : at + 4 + nd])
            v = raw[at + 4 + nd : at + 4 + nd + abs(typ) * int(np.prod(dims))]
            if typ == -1:
                w = dims[0] if dims else len(v)
                value = [v[i : i + w].decode("latin-1").strip() for i in range(0, len(v), w)] if w else [""]
                value = value[0] if nd <= 1 else value
            else:
                value = struct.unpack("<" + {1: "b", 2: "h", 4: "f"}[typ] * (len(v) // abs(typ)), v)
                value = value[0] if nd == 0 else value
            out[(gid, name)] = value
        if nxt == 0:
            break
        pos = at + nxt
    return {f"{groups[g]}:{name}": v for (g, name), v in out.items()}


def vendor_points(path: Path) -> tuple[np.ndarray, list[str], float, str]:
    """The points of a C3D file in floating-point storage, as written: `(frames, points, 3)` in
    the file's units (NaN where the residual word is negative), labels, rate, units; every whole
    frame the file holds."""
    raw = path.read_bytes()
    n_points, n_analog = struct.unpack("<2H", raw[2:6])
    assert struct.unpack("<f", raw[12:16])[0] < 0  # a negative scale: floats
    start = 512 * (struct.unpack("<H", raw[16:18])[0] - 1)
    width = 4 * n_points + n_analog
    frames = (len(raw) - start) // (4 * width)
    data = np.frombuffer(raw, "<f4", count=frames * width, offset=start).reshape(frames, width)
    words = data[:, : 4 * n_points].reshape(frames, n_points, 4).astype(float)
    xyz = words[..., :3]
    xyz[words[..., 3] < 0] = np.nan
    par = c3d_parameters(raw)
    labels = par["POINT:LABELS"] if isinstance(par["POINT:LABELS"], list) else [par["POINT:LABELS"]]
    units = par["POINT:UNITS"] if isinstance(par["POINT:UNITS"], str) else par["POINT:UNITS"][0]
    return xyz, labels, float(par["POINT:RATE"]), units


def _cli(argv, capsys) -> tuple[int, str]:
    code = main([*map(str, argv), "--no-cache"])
    err = capsys.readouterr().err
    assert "Traceback" not in err, err
    return int(code), err


def _inputs(tmp_path: Path, duration: float) -> Path:
    """An inputs table of resting wheels covering `duration` seconds."""
    t = np.arange(0.0, duration + 0.05, 0.01)
    p = tmp_path / "inputs.csv"
    p.write_text("t,chi_dot_1,chi_dot_2,chi_dot_3\n" + "".join(f"{v:.2f},0,0,0\n" for v in t))
    return p


def _assert_vendor_positions(data, path: Path) -> np.ndarray:
    """`data` (from `read_c3d`) holds the file's points, millimetres to metres, Z up as written."""
    xyz, labels, rate, units = vendor_points(path)
    assert units == "mm" and data.names == tuple(labels)
    np.testing.assert_allclose(data.t, np.arange(len(xyz)) / rate, rtol=0, atol=1e-12)
    assert np.array_equal(np.isnan(data.markers), np.isnan(xyz))
    assert np.nanmax(np.abs(data.markers - xyz / 1000.0)) < UM
    ezc3d = pytest.importorskip("ezc3d")
    pts = np.transpose(ezc3d.c3d(str(path))["data"]["points"][:3], (2, 1, 0))
    assert np.nanmax(np.abs(pts - xyz)) == 0.0  # ezc3d reads the same numbers
    return xyz


def test_vicon_nexus_c3d_box_converts_to_the_markers_centroid(tmp_path, capsys):
    data = jsphere.read_c3d(VICON)
    xyz = _assert_vendor_positions(data, VICON)
    assert data.markers.shape == (130, 51, 3)
    box = [i for i, n in enumerate(data.names) if n.startswith("boite:")]
    full = np.isfinite(xyz[:, box]).all(axis=(1, 2))  # a hand hides some of them in 17 frames
    assert len(box) == 8 and full.sum() == 113 and full[0]
    body = tmp_path / "box.csv"  # the box's markers about their centroid, as they sit in frame 0 [m]
    b0 = xyz[0, box] / 1000.0 - xyz[0, box].mean(0) / 1000.0
    body.write_text(
        "name,x,y,z\n" + "".join(f"{data.names[i]},{x:.9f},{y:.9f},{z:.9f}\n" for i, (x, y, z) in zip(box, b0))
    )
    inputs, out = _inputs(tmp_path, 1.3), tmp_path / "box_trial.csv"
    code, err = _cli(
        ["convert", VICON, "--format", "c3d", "--inputs", inputs, "--out", out, "--body-markers", body], capsys
    )
    assert code == 0, err
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", CaptureWarning)  # the box is lifted: not a ball on a floor
        trial = jsphere.read_trial(out)
    centroid = xyz[:, box].mean(1) / 1000.0
    assert trial.n_frames == 130 and trial.valid.all()  # the frames with hidden markers fit the others
    # the trial file holds 1 um steps: its centre is the vendor's centroid to the rounding
    for got, want in ((trial.x, centroid[:, 0]), (trial.y, centroid[:, 1]), (trial.z, centroid[:, 2])):
        assert np.max(np.abs(got[full] - want[full])) <= 0.5 * UM + 1e-9
    assert np.ptp(centroid[full, 2]) > 0.3  # the box is lifted by 30 cm in these frames
    # the 51 markers of a box and a person are not one rigid body: refused, one line naming the file
    code, err = _cli(["convert", VICON, "--format", "c3d", "--inputs", inputs, "--out", tmp_path / "all.csv"], capsys)
    assert (
        code == 2 and err.count("\n") == 1 and "vicon_nexus_box.c3d: the markers do not move as one rigid body" in err
    )
    assert not (tmp_path / "all.csv").exists()


def test_qtm_c3d_with_spaced_parameter_names_reads(tmp_path, capsys):
    par = c3d_parameters(QTM.read_bytes())
    assert par["MANUFACTURER:SOFTWARE"] == "Qualisys Track Manager"
    assert par["PROCESSING:Uncropped Measurement Length"] == pytest.approx(8.155, abs=1e-3)
    layout = c3d_layout(QTM)
    assert (layout["frames"], layout["frames_in_file"], layout["points"]) == (100, 100, 55)
    data = jsphere.read_c3d(QTM)
    _assert_vendor_positions(data, QTM)
    assert data.markers.shape == (100, 55, 3) and np.isfinite(data.markers).all()
    # a walking person is not one rigid body: refused, one line naming the file
    inputs, out = _inputs(tmp_path, 0.5), tmp_path / "t.csv"
    code, err = _cli(["convert", QTM, "--format", "c3d", "--inputs", inputs, "--out", out], capsys)
    assert code == 2 and err.count("\n") == 1 and not out.exists(), err
    assert "qualisys_qtm_gait.c3d: the markers do not move as one rigid body" in err


def test_corrupt_parameter_names_are_still_refused(tmp_path, monkeypatch):
    """A control byte in a name, or a name that starts with a space, is a corrupt record."""
    raw = QTM.read_bytes()
    at = raw.index(b"Uncropped Measurement Length")
    for patch, name in ((b"\x01", "control.c3d"), (b" ", "leading.c3d")):
        p = tmp_path / name
        p.write_bytes(raw[:at] + patch + raw[at + 1 :])
        with pytest.raises(InputError, match=rf"{name}: the C3D file is corrupt: parameter record 47 \(its name"):
            jsphere.read_c3d(p)


def test_force_plates_without_markers_are_refused(tmp_path, capsys):
    msg = (
        r"kistler_force_plates\.c3d: the C3D file holds no marker trajectories \(its header declares 0 points; "
        r"only 16 analog channels, 2 force plates\)"
    )
    with pytest.raises(InputError, match=msg):
        jsphere.read_c3d(KISTLER)
    out = tmp_path / "t.csv"
    code, err = _cli(["convert", KISTLER, "--format", "c3d", "--inputs", _inputs(tmp_path, 1.0), "--out", out], capsys)
    assert code == 2 and err.count("\n") == 1 and "holds no marker trajectories" in err and not out.exists(), err
    assert "export the take's markers (3D point data) to C3D" in err


def test_optotrak_file_cut_short_names_both_counts(tmp_path, capsys):
    with pytest.raises(InputError, match=r"optotrak_cut\.c3d: the file is cut short: the header declares 1149 frames"):
        jsphere.read_c3d(OPTOTRAK)
    out = tmp_path / "t.csv"
    code, err = _cli(["convert", OPTOTRAK, "--format", "c3d", "--inputs", _inputs(tmp_path, 1.0), "--out", out], capsys)
    assert code == 2 and err.count("\n") == 1 and "declares 1149 frames but the file holds 29" in err, err
    assert "--allow-truncated" in err and "allow_truncated" not in err
    with pytest.warns(CaptureWarning, match=r"declares 1149 frames but the file holds 29; using the 29 frames"):
        data = jsphere.read_c3d(OPTOTRAK, allow_truncated=True)
    xyz, labels, rate, _ = vendor_points(OPTOTRAK)
    assert data.markers.shape == (29, 54, 3) and rate == 30.0 and data.names == tuple(labels)
    assert np.array_equal(np.isnan(data.markers), np.isnan(xyz))
    assert np.nanmax(np.abs(data.markers - xyz / 1000.0)) < UM
