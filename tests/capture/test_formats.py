"""Raw exports as the capture systems write them: Motive 2/3 in any length unit with every column
family, Qualisys QTM TSV (3D and 6DOF), Vicon Nexus with devices, several subjects and model
outputs. The files are written here to the vendors' documented layouts from synthetic poses, read,
converted, and compared with the poses they came from."""

import numpy as np
import pytest

import jsphere
from jsphere.capture.markers import UP_TO_Z
from jsphere.capture.synthetic import default_marker_set
from jsphere.model.rotations import quat_from_rotmat_np, quat_mul_np, rotmat_np

T1 = 1.5
BODY = default_marker_set(0.15)
NAMES = ["m1", "m2", "m3", "m4"]
BODY_BY_NAME = dict(zip(NAMES, BODY))  # matched to an export's markers by name, in any order


@pytest.fixture(scope="module")
def truth(paper):
    """A noiseless, gap-free wheel-speed trial and noisy markers of it (0.1 mm, 3% missing)."""
    c = jsphere.random_inputs(paper, T1, kind="wheel_speeds", seed=1)
    tr = jsphere.synthetic_trial(paper, c, T1, pos_sd=0.0, rot_sd_deg=0.0, name="truth")
    m = jsphere.synthetic_markers(tr, BODY, marker_sd=1e-4, dropout=0.03, seed=5)
    return tr, m


def _inputs(tmp_path, tr):
    p = tmp_path / "inputs.csv"
    jsphere.write_inputs_csv(p, tr.t, tr.inputs, tr.kind)
    return p


def _angle_deg(q1, q2):
    d = quat_mul_np(q1 * np.array([1, -1, -1, -1]), q2)
    return np.rad2deg(2 * np.arcsin(np.clip(np.linalg.norm(d[:, 1:], axis=1), 0, 1)))


def _check(tr, truth_trial, pos=5e-4, ang=0.5):
    """The converted trial `tr` holds the truth's poses to the noise level, and its inputs."""
    v = tr.valid
    assert v.mean() > 0.9
    np.testing.assert_allclose(tr.t, truth_trial.t[: tr.n_frames], atol=1e-9)
    assert np.hypot(tr.x[v] - truth_trial.x[v], tr.y[v] - truth_trial.y[v]).max() < pos
    assert _angle_deg(tr.q[v], truth_trial.q[v]).max() < ang
    np.testing.assert_allclose(tr.z[v], 0.15, atol=pos)
    np.testing.assert_allclose(tr.inputs, truth_trial.inputs, rtol=1e-8, atol=1e-9)


def _pose(tr):
    """The platform's pose `(q, p)` of a trial, its centre at the shell radius 0.15 m."""
    return tr.q, np.stack([tr.x, tr.y, np.full(tr.n_frames, 0.15)], axis=1)


def _cells(v, fmt):
    return ["" if not np.isfinite(x) else format(x + 0.0, fmt) for x in v]


# --------------------------------------------------------------------------- Motive 2 and 3


def write_motive3(path, t, markers, rb_q, rb_p, *, units="Centimeters", rotation="Quaternion", order=None):
    """A Motive 3 CSV export (docs.optitrack.com, Data Export: CSV) of a Y-up take: line 1 with the
    take's settings, a blank line, the rows Type, Name, ID, Parent and the kinds, `Frame,Time
    (Seconds),...`. Column families: Rigid Body `robot` (Rotation X, Y, Z, W, Position, Mean
    Marker Error), Rigid Body Marker (Position, Marker Quality), labelled Marker `robot:m1..4`, a
    Bone and Bone Marker of a skeleton, and an unlabelled marker. Blank cells are occlusions.
    `order`: a permutation of the column groups after Frame and Time."""
    s = {"Meters": 1.0, "Centimeters": 100.0, "Millimeters": 1000.0}[units]
    C = UP_TO_Z["y"]
    M = len(t)
    raw = np.einsum("ji,mkj->mki", C, markers) * s
    q_m = quat_mul_np(np.broadcast_to(quat_from_rotmat_np(C.T), rb_q.shape), rb_q)[:, [1, 2, 3, 0]]
    p_m = rb_p @ C * s
    fmt = {"Meters": ".6f", "Centimeters": ".4f", "Millimeters": ".3f"}[units]
    if rotation == "Quaternion":
        rot, rot_axes = q_m, list("XYZW")
    else:  # Euler angles [deg] in the order Rotation Type names
        from scipy.spatial.transform import Rotation

        rot, rot_axes = Rotation.from_quat(q_m).as_euler(rotation, degrees=True), list("XYZ")
    nr = len(rot_axes)
    groups = []  # (type, name, id, parent, kinds, axes, values (M, n), formats)
    groups.append(
        (
            "Rigid Body",
            "robot",
            "1",
            "",
            ["Rotation"] * nr + ["Position"] * 3 + ["Mean Marker Error"],
            rot_axes + list("XYZ") + [""],
            np.concatenate([rot, p_m, np.full((M, 1), 0.0002 * s)], axis=1),
            [".6f"] * nr + [fmt] * 4,
        )
    )
    for k, n in enumerate(NAMES):
        solved = (rotmat_np(rb_q) @ BODY[k] + rb_p) @ C * s
        groups.append(
            (
                "Rigid Body Marker",
                f"robot:{n}",
                f"{k + 2}",
                "robot",
                ["Position"] * 3 + ["Marker Quality"],
                list("XYZ") + [""],
                np.concatenate([solved, np.ones((M, 1))], axis=1),
                [fmt] * 3 + [".4f"],
            )
        )
        groups.append(
            ("Marker", f"robot:{n}", f"{k + 10}", "robot", ["Position"] * 3, list("XYZ"), raw[:, k], [fmt] * 3)
        )
    groups.append(
        (
            "Bone",
            "Skel:Hip",
            "20",
            "Skel",
            ["Rotation"] * nr + ["Position"] * 3,
            rot_axes + list("XYZ"),
            np.zeros((M, nr + 3)),
            [fmt] * (nr + 3),
        )
    )
    groups.append(
        ("Bone Marker", "Skel:WaistLFront", "21", "Skel:Hip", ["Position"] * 3, list("XYZ"), np.ones((M, 3)), [fmt] * 3)
    )
    stray = np.full((M, 3), np.nan)
    stray[M // 3 : M // 2] = np.array([2.0, 0.01, -1.0]) * s  # a reflection seen for a while
    groups.append(("Marker", "Unlabeled 1000", "30", "", ["Position"] * 3, list("XYZ"), stray, [fmt] * 3))
    if order is not None:
        groups = [groups[i] for i in order]
    row = {k: [] for k in ("types", "names", "ids", "parents", "kinds", "axes", "formats")}
    values = []
    for typ, name, gid, parent, kinds, axes, vals, fmts in groups:
        n = len(kinds)
        row["types"] += [typ] * n
        row["names"] += [name] * n
        row["ids"] += [gid] * n
        row["parents"] += [parent] * n
        row["kinds"] += kinds
        row["axes"] += axes
        row["formats"] += fmts
        values.append(vals)
    data = np.concatenate(values, axis=1)
    lines = [
        f"Format Version,1.24,Take Name,lab_take,Take Notes,,Capture Frame Rate,100.000000,Export Frame Rate,100.000000,"
        f"Capture Start Time,2025-03-14 10.12.31.512 AM,Capture Start Frame,0,Total Frames in Take,{M},Total Exported "
        f"Frames,{M},Rotation Type,{rotation},Length Units,{units},Coordinate Space,Global",
        "",
        ",Type," + ",".join(row["types"]),
        ",Name," + ",".join(row["names"]),
        ",ID," + ",".join(row["ids"]),
        ",Parent," + ",".join(row["parents"]),
        ",," + ",".join(row["kinds"]),
        "Frame,Time (Seconds)," + ",".join(row["axes"]),
    ]
    for i in range(M):
        cells = ["" if not np.isfinite(v) else format(v + 0.0, f) for v, f in zip(data[i], row["formats"])]
        lines.append(",".join([str(i), f"{t[i]:.6f}", *cells]))
    path.write_text("\r\n".join(lines) + "\r\n")
    return path


@pytest.mark.parametrize("units", ["Centimeters", "Meters", "Millimeters"])
def test_motive3_every_unit_and_column_family(tmp_path, truth, units):
    tr, m = truth
    q, p = _pose(tr)
    raw = write_motive3(tmp_path / "take.csv", tr.t, m, q, p, units=units, order=[7, 2, 0, 8, 1, 3, 4, 5, 6, 9])
    data = jsphere.read_motive_csv(raw)
    # the labelled markers in the order of their columns, not the solved, bone or unlabelled ones
    assert sorted(data.names) == [f"robot:{n}" for n in NAMES]
    mine = data.markers[:, [data.names.index(f"robot:{n}") for n in NAMES]]
    np.testing.assert_array_equal(np.isnan(mine), np.isnan(m))
    np.testing.assert_allclose(mine, m, atol=2e-6, equal_nan=True)
    _check(
        jsphere.convert_raw(
            raw, _inputs(tmp_path, tr), format="motive", options=jsphere.ConvertOptions(body_markers=BODY_BY_NAME)
        ),
        tr,
    )
    # Motive's own rigid-body pose, in the same units
    rb = jsphere.read_motive_csv(raw, use="rigid_body")
    tr_rb = jsphere.markers_to_trial(rb, _inputs(tmp_path, tr))
    np.testing.assert_allclose(tr_rb.x, tr.x, atol=2e-6)
    assert _angle_deg(tr_rb.q, tr.q).max() < 1e-3


def test_motive_centimetres_declared_and_contradicted(tmp_path, truth):
    tr, m = truth
    raw = tmp_path / "take.csv"
    jsphere.write_motive_csv(raw, tr.t, m, NAMES, units="cm")
    assert "Length Units,Centimeters" in raw.read_text()
    np.testing.assert_allclose(jsphere.read_motive_csv(raw, units="cm").markers, m, atol=1e-6, equal_nan=True)
    with pytest.raises(ValueError, match="--units mm was given but the file says its lengths are in cm"):
        jsphere.read_motive_csv(raw, units="mm")
    raw.write_text(raw.read_text().replace("Length Units,Centimeters", "Length Units,Inches"))
    with pytest.raises(jsphere.InputError, match="Length Units 'Inches' not understood; export in Meters, Centimeters"):
        jsphere.read_motive_csv(raw)


def test_motive_euler_rotation_type(tmp_path, truth):
    """Euler rotation types: the markers are read; the rigid body's pose is an error naming the setting."""
    tr, m = truth
    q, p = _pose(tr)
    raw = write_motive3(tmp_path / "take.csv", tr.t, m, q, p, rotation="XYZ")
    assert jsphere.read_motive_csv(raw).markers.shape == m.shape
    with pytest.raises(jsphere.InputError, match="Rotation Type is 'XYZ' .*Rotation Type = Quaternion"):
        jsphere.read_motive_csv(raw, use="rigid_body")


def test_cli_converts_a_centimetre_motive3_take(tmp_path, truth):
    from jsphere.cli.app import main

    tr, m = truth
    q, p = _pose(tr)
    raw = write_motive3(tmp_path / "take.csv", tr.t, m, q, p)
    body = tmp_path / "body.csv"
    body.write_text("name,x,y,z\n" + "".join(f"{n},{b[0]},{b[1]},{b[2]}\n" for n, b in zip(NAMES, BODY)))
    out = tmp_path / "trial.csv"
    args = ["convert", str(raw), "--format", "motive", "--inputs", str(_inputs(tmp_path, tr)), "--out", str(out)]
    assert main([*args, "--body-markers", str(body), "--units", "cm"]) == 0
    _check(jsphere.read_trial(out), tr)


# --------------------------------------------------------------------------- Qualisys QTM


def _qtm_header(M, kind, names, *, version=False):
    """The header of a QTM TSV export as QTM writes it (no FILE_VERSION line unless asked for)."""
    lines = ["FILE_VERSION\t2.0.0"] if version else []
    lines += [
        f"NO_OF_FRAMES\t{M}",
        "NO_OF_CAMERAS\t8",
        f"NO_OF_MARKERS\t{len(names)}" if kind == "3D" else f"NO_OF_BODIES\t{len(names)}",
        "FREQUENCY\t100",
        "NO_OF_ANALOG\t0",
        "ANALOG_FREQUENCY\t0",
        "DESCRIPTION\t--",
        "TIME_STAMP\t2025-03-14, 10:12:31.512\t12345.67800000",
        f"DATA_INCLUDED\t{kind}",
    ]
    if kind == "3D":
        lines += ["EVENT\tstart\t1\t0.000", "MARKER_NAMES\t" + "\t".join(names)]
        lines.append("TRAJECTORY_TYPES\t" + "\t".join(["Measured"] * len(names)))
    else:
        lines.append("BODY_NAMES\t" + "\t".join(names))
    return lines


def _write_tsv(path, lines):
    path.write_bytes(("\r\n".join(lines) + "\r\n").encode())  # QTM writes CRLF line ends
    return path


def write_qtm_3d(path, t, markers, names, *, columns=True, time=True, gaps="zeros"):
    """A QTM 3D TSV export as QTM writes it (QTM manual, Motion data (.tsv)): the header, the
    column row `Frame Time <m> X ...` ending in a tab, rows without one, millimetres in QTM's
    Z-up frame; a marker not seen is zeros (or blanks)."""
    raw = markers * 1000.0
    lines = _qtm_header(len(t), "3D", names)
    if columns:
        lines.append("\t".join(["Frame", "Time"][: 2 * time] + [f"{n} {a}" for n in names for a in "XYZ"]) + "\t")
    for i in range(len(t)):
        v = raw[i].reshape(-1)
        cells = [format(x, ".3f") if np.isfinite(x) else ("0.000" if gaps == "zeros" else "") for x in v]
        lines.append("\t".join([str(i + 1), f"{t[i]:.5f}"][: 2 * time] + cells))
    return _write_tsv(path, lines)


_QTM_6D_FIELDS = ["X", "Y", "Z", "Roll", "Pitch", "Yaw", "Residual"] + [f"Rot[{i}]" for i in range(9)]


def write_qtm_6d(path, t, bodies, *, names="first", gaps="NaN"):
    """A QTM 6DOF TSV export as QTM writes it: `BODY_NAMES`,
    then per body the columns `<body> X`, `Y`, `Z` [mm], `Roll`, `Pitch`, `Yaw` [deg] (QTM
    standard: R = Rx Ry Rz), `Residual`, `Rot[0]`..`Rot[8]` (the rotation matrix column by
    column), every row ending in a tab. `names="all"` names the body on every column,
    `"none"` on none."""
    from scipy.spatial.transform import Rotation

    lines = _qtm_header(len(t), "6D", list(bodies))
    head = ["Frame", "Time"]
    for b in bodies:
        pre = {"first": [f"{b} "] + [""] * 15, "all": [f"{b} "] * 16, "none": [""] * 16}[names]
        head += [p + f for p, f in zip(pre, _QTM_6D_FIELDS)]
    lines.append("\t".join(head) + "\t")
    for i in range(len(t)):
        cells = []
        for q, p in bodies.values():
            if not np.all(np.isfinite(q[i])):
                cells += [gaps] * len(_QTM_6D_FIELDS)
                continue
            R = rotmat_np(q[i])
            ang = Rotation.from_matrix(R).as_euler("XYZ", degrees=True)
            cells += _cells(np.concatenate([p[i] * 1000.0, ang, [0.4], R.reshape(-1, order="F")]), ".5f")
        lines.append("\t".join([str(i + 1), f"{t[i]:.5f}", *cells]) + "\t")
    return _write_tsv(path, lines)


@pytest.mark.parametrize(
    ("columns", "time", "gaps"), [(True, True, "zeros"), (True, True, "blank"), (False, False, "zeros")]
)
def test_qualisys_3d(tmp_path, truth, columns, time, gaps):
    tr, m = truth
    raw = write_qtm_3d(tmp_path / "take.tsv", tr.t, m, NAMES, columns=columns, time=time, gaps=gaps)
    data = jsphere.read_qualisys_tsv(raw)
    assert data.names == tuple(NAMES)
    np.testing.assert_allclose(data.t, tr.t, atol=1e-9)
    np.testing.assert_array_equal(np.isnan(data.markers), np.isnan(m))
    np.testing.assert_allclose(data.markers, m, atol=1e-6, equal_nan=True)
    _check(
        jsphere.convert_raw(
            raw, _inputs(tmp_path, tr), format="qualisys", options=jsphere.ConvertOptions(body_markers=BODY)
        ),
        tr,
    )


@pytest.mark.parametrize(("names", "gaps"), [("first", "NaN"), ("all", "0.00000"), ("none", "")])
def test_qualisys_6dof(tmp_path, truth, names, gaps):
    tr, _ = truth
    q, p = _pose(tr)
    q, p = q.copy(), p.copy()
    q[40:43], p[40:43] = np.nan, np.nan  # the body not seen
    other = (np.tile([1.0, 0, 0, 0], (tr.n_frames, 1)), np.zeros((tr.n_frames, 3)))
    raw = write_qtm_6d(tmp_path / "take_6d.tsv", tr.t, {"robot": (q, p), "wand": other}, names=names, gaps=gaps)
    with pytest.raises(
        jsphere.InputError, match=r"several 6DOF bodies \['robot', 'wand'\]; choose one with --rigid-body"
    ):
        jsphere.read_qualisys_tsv(raw)
    data = jsphere.read_qualisys_tsv(raw, rigid_body="robot")
    assert data.markers.shape == (tr.n_frames, 0, 3)
    gap = np.zeros(tr.n_frames, bool)
    gap[40:43] = True
    np.testing.assert_array_equal(np.isnan(data.rb_q[:, 0]), gap)
    trial = jsphere.convert_raw(
        raw, _inputs(tmp_path, tr), format="qualisys", options=jsphere.ConvertOptions(rigid_body="robot")
    )
    v = trial.valid
    np.testing.assert_allclose(trial.x[v], tr.x[v], atol=2e-6)
    assert _angle_deg(trial.q[v], tr.q[v]).max() < 2e-3  # Rot[] written to 5 decimals, as QTM does


def test_qualisys_6dof_euler_only_and_cli(tmp_path, truth):
    """Without Rot[] columns the QTM-standard angles are read; the command line converts it."""
    from jsphere.cli.app import main

    tr, _ = truth
    q, p = _pose(tr)
    raw = write_qtm_6d(tmp_path / "t_6d.tsv", tr.t, {"robot": (q, p)})
    lines = raw.read_text().splitlines()
    k = next(i for i, r in enumerate(lines) if r.startswith("Frame"))
    lines = lines[:k] + ["\t".join(c.split("\t")[:9]) for c in lines[k:]]  # drop Rot[0..8]
    raw.write_text("\n".join(lines) + "\n")
    data = jsphere.read_qualisys_tsv(raw)
    assert _angle_deg(data.rb_q, q).max() < 1e-4
    out = tmp_path / "trial.csv"
    assert (
        main(["convert", str(raw), "--format", "qualisys", "--inputs", str(_inputs(tmp_path, tr)), "--out", str(out)])
        == 0
    )
    assert _angle_deg(jsphere.read_trial(out).q, tr.q).max() < 1e-3


def _rx_ry_rz(roll, pitch, yaw):
    """QTM's standard rotation (roll about X, pitch about the new Y, yaw about the new Z) [deg]."""
    a, b, c = np.radians([roll, pitch, yaw])
    Rx = np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])
    Ry = np.array([[np.cos(b), 0, np.sin(b)], [0, 1, 0], [-np.sin(b), 0, np.cos(b)]])
    Rz = np.array([[np.cos(c), -np.sin(c), 0], [np.sin(c), np.cos(c), 0], [0, 0, 1]])
    return Rx @ Ry @ Rz


def test_qualisys_6dof_conventions(tmp_path):
    """One body in QTM's layout (the name in the X column only, rows ending in a tab, CRLF):
    Rot[0..8] is R column by column and the angles are R = Rx(roll) Ry(pitch) Rz(yaw); a yaw
    of 90 deg turns the body's x axis onto global +Y."""
    angles = [(0.0, 0.0, 0.0), (0.0, 0.0, 90.0), (30.0, 20.0, 10.0), (-120.0, 45.0, 160.0)]
    Rs = [_rx_ry_rz(*a) for a in angles]
    rows = []
    for i, (a, R) in enumerate(zip(angles, Rs)):
        cells = [100.0 * i, -50.0, 20.0, *a, 0.5, *R.T.reshape(-1)]  # R.T row by row: R column by column
        rows.append("\t".join([str(i + 1), f"{0.01 * i:.5f}", *(f"{x:.5f}" for x in cells)]) + "\t")
    head = "\t".join(["Frame", "Time", "box X", *_QTM_6D_FIELDS[1:]]) + "\t"
    raw = _write_tsv(tmp_path / "box_6d.tsv", [*_qtm_header(4, "6D", ["box"]), head, *rows])
    for path in (raw, tmp_path / "angles_6d.tsv"):
        if path != raw:  # the same file without its Rot[] columns
            lines = [r.split("\t") for r in raw.read_text().splitlines()]
            path.write_text("\n".join("\t".join(c[:9] if len(c) > 9 else c) for c in lines) + "\n")
        data = jsphere.read_qualisys_tsv(path)
        np.testing.assert_allclose(data.t, [0.0, 0.01, 0.02, 0.03])
        np.testing.assert_allclose(data.rb_p, [[0.1 * i, -0.05, 0.02] for i in range(4)], atol=1e-9)
        R_read = np.stack([rotmat_np(q) for q in data.rb_q])
        np.testing.assert_allclose(R_read, np.stack(Rs), atol=2e-5)
        np.testing.assert_allclose(R_read[1] @ [1.0, 0, 0], [0, 1.0, 0], atol=2e-5)


def test_qualisys_3d_marker_names_with_spaces(tmp_path, truth):
    """QTM's default marker names hold a space ("New 0000"): the columns `New 0000 X` match them."""
    tr, m = truth
    names = [f"New {i:04d}" for i in range(len(NAMES))]
    data = jsphere.read_qualisys_tsv(write_qtm_3d(tmp_path / "new.tsv", tr.t, m, names))
    assert data.names == tuple(names)
    np.testing.assert_allclose(data.markers, m, atol=1e-6, equal_nan=True)


def test_qualisys_errors(tmp_path, truth):
    tr, m = truth
    raw = write_qtm_3d(tmp_path / "a.tsv", tr.t, m, NAMES)
    text = raw.read_text()
    (tmp_path / "b.tsv").write_text(text.replace("DATA_INCLUDED\t3D", "DATA_INCLUDED\t2D"))
    with pytest.raises(jsphere.InputError, match="DATA_INCLUDED is '2D'; export 3D or 6DOF data"):
        jsphere.read_qualisys_tsv(tmp_path / "b.tsv")
    (tmp_path / "c.tsv").write_text("\n".join(text.splitlines()[:-20]) + "\n")
    with pytest.raises(jsphere.InputError, match=rf"declares {tr.n_frames} frames \(NO_OF_FRAMES\) but the file holds"):
        jsphere.read_qualisys_tsv(tmp_path / "c.tsv")
    with pytest.warns(jsphere.CaptureWarning, match="cut short"):
        assert jsphere.read_qualisys_tsv(tmp_path / "c.tsv", allow_truncated=True).t.shape == (tr.n_frames - 20,)
    k = text.index("Frame\t")
    (tmp_path / "d.tsv").write_text(text[k:])
    with pytest.raises(jsphere.InputError, match="Include TSV header"):
        jsphere.read_qualisys_tsv(tmp_path / "d.tsv")


# --------------------------------------------------------------------------- Vicon Nexus


def write_nexus(path, t, subjects, *, rate=100.0):
    """A Vicon Nexus 2 CSV export ("Export data to a CSV file"): a `Devices` section (a force
    plate at 1000 Hz), `Model Outputs`, then `Trajectories` of every subject (`Subject:Marker`
    names in each X column, a units row `mm`) and an unlabelled trajectory `*12`."""
    M = len(t)
    lines = ["Devices", "1000", ",,Force Plate 1 - Force,,,Force Plate 1 - Moment", "Frame,Sub Frame,Fx,Fy,Fz,Mx"]
    lines.append(",,N,N,N,N.mm")
    for i in range(3):
        for sub in range(10):
            lines.append(f"{i + 1},{sub},0.1,0.2,9.8,0.0")
    lines += ["", "Model Outputs", f"{rate:g}", ",,robot:Angles,,", "Frame,Sub Frame,X,Y,Z", ",,deg,deg,deg"]
    lines += [f"{i + 1},0,1.0,2.0,3.0" for i in range(M)]
    lines += ["", "Trajectories", f"{rate:g}"]
    names = [f"{s}:{n}" for s, (ns, _) in subjects.items() for n in ns] + ["*12"]
    raws = [m * 1000.0 for _, m in subjects.values()] + [np.full((M, 1, 3), 500.0)]
    raw = np.concatenate(raws, axis=1)
    lines.append(",," + ",".join(f"{n},," for n in names).rstrip(","))
    lines.append("Frame,Sub Frame," + ",".join(["X", "Y", "Z"] * len(names)))
    lines.append(",," + ",".join(["mm"] * 3 * len(names)))
    for i in range(M):
        lines.append(",".join([str(i + 1), "0", *_cells(raw[i].reshape(-1), ".3f")]))
    lines += ["", "Segments", f"{rate:g}"]
    path.write_text("\n".join(lines) + "\n")
    return path


def test_nexus_devices_subjects_and_model_outputs(tmp_path, truth):
    from jsphere.cli.app import main

    tr, m = truth
    wand = np.broadcast_to(np.array([[0.5, 0.5, 1.0], [0.6, 0.5, 1.0], [0.5, 0.62, 1.0]]), (tr.n_frames, 3, 3))
    raw = write_nexus(tmp_path / "trial01.csv", tr.t, {"robot": (NAMES, m), "wand": (["t1", "t2", "t3"], wand)})
    with pytest.raises(
        jsphere.InputError, match=r"several subjects \['robot', 'wand'\]; choose one with --subject NAME"
    ):
        jsphere.read_vicon_csv(raw)
    with pytest.raises(jsphere.InputError, match=r"no subject 'ball' .*the file has \['robot', 'wand'\]"):
        jsphere.read_vicon_csv(raw, subject="ball")
    data = jsphere.read_vicon_csv(raw, subject="robot")
    assert data.names == tuple(f"robot:{n}" for n in NAMES)
    np.testing.assert_allclose(data.t, tr.t, atol=1e-12)
    np.testing.assert_allclose(data.markers, m, atol=1e-6, equal_nan=True)
    inputs = _inputs(tmp_path, tr)
    _check(
        jsphere.convert_raw(
            raw, inputs, format="vicon", options=jsphere.ConvertOptions(subject="robot", body_markers=BODY)
        ),
        tr,
    )
    out = tmp_path / "trial.csv"
    args = ["convert", str(raw), "--format", "vicon", "--inputs", str(inputs), "--out", str(out)]
    assert main(args) == 2
    assert main([*args, "--subject", "robot", "--body-offset", *(str(v) for v in -BODY.mean(0))]) == 0
    _check(jsphere.read_trial(out), tr, pos=1e-3, ang=1.0)
    one = write_nexus(tmp_path / "one.csv", tr.t, {"robot": (NAMES, m)})
    assert jsphere.read_vicon_csv(one).names == data.names  # one subject: no choice to make


# --------------------------------------------------------------------------- a fit from a centimetre take


@pytest.mark.slow
def test_fit_from_a_centimetre_motive3_take(tmp_path):
    """R_m and j fitted from Motive 3 takes in centimetres (markers 1 mm noise, Parent row,
    rigid body, solved markers, a stray unlabelled marker) land within 3 SE of the truth."""
    truth_params = jsphere.RobotParams.paper().replace(R_m=0.029, j=3.2e-4)
    trials = []
    for i in range(2):
        u = jsphere.random_inputs(truth_params, T1, kind="wheel_speeds", seed=i)
        tr = jsphere.synthetic_trial(truth_params, u, T1, rate=50.0, pos_sd=0.0, rot_sd_deg=0.0, seed=i, name=f"t{i}")
        m = jsphere.synthetic_markers(tr, BODY, marker_sd=1e-3, dropout=0.02, seed=10 + i)
        q, p = _pose(tr)
        raw = write_motive3(tmp_path / f"take{i}.csv", tr.t, m, q, p)
        trials.append(
            jsphere.convert_raw(
                raw, _inputs(tmp_path, tr), format="motive", options=jsphere.ConvertOptions(body_markers=BODY)
            )
        )
    res = jsphere.fit(trials, jsphere.RobotParams.paper(), "R_m,j", fix={"m": 2.5}, n_starts=1, max_iter=30)
    assert res.converged
    for name in ("R_m", "j"):
        print(
            f"{name}: {res.values[name]:.6g} +- {res.stderr[name]:.3g} (truth {float(jsphere.get_value(truth_params, name)):.6g})"
        )
        want = float(jsphere.get_value(truth_params, name))
        se = res.stderr[name]
        assert 0 < se < 0.2 * abs(want)
        assert abs(res.values[name] - want) < 3 * se, (name, res.values[name], want, se)
