"""Capture data: the trial CSV format, synthetic trials, raw marker exports."""

import re
import struct
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jsphere
from jsphere.capture.synthetic import RandomSines, eval_controls
from jsphere.capture.trial import detect_position_units, trial_to_csv
from jsphere.capture.validation import MIN_VALID_FRAMES
from jsphere.model.rotations import quat_from_rotvec_np, quat_mul_np, rotmat

T1 = 1.5


# --------------------------------------------------------------------------- fixtures


@pytest.fixture(scope="module")
def truth_ws(paper):
    """A noiseless, gap-free wheel-speed trial (the truth) and its controls."""
    c = jsphere.random_inputs(paper, T1, kind="wheel_speeds", seed=1)
    return jsphere.synthetic_trial(paper, c, T1, pos_sd=0.0, rot_sd_deg=0.0, name="truth_ws"), c


@pytest.fixture(scope="module")
def noisy_ws(paper):
    c = jsphere.random_inputs(paper, T1, kind="wheel_speeds", seed=1)
    return jsphere.synthetic_trial(paper, c, T1, pos_sd=1e-3, rot_sd_deg=0.5, dropout=0.1, seed=7, name="noisy_ws")


@pytest.fixture(scope="module")
def torque_trial(paper):
    c = jsphere.random_inputs(paper, T1, kind="torques", seed=2)
    return jsphere.synthetic_trial(paper, c, T1, dropout=0.05, seed=3, name="tq"), c


def _small_trial(n=30, kind="wheel_speeds", N=3):
    t = np.arange(n) * 0.01
    q = np.tile([1.0, 0.0, 0.0, 0.0], (n, 1))
    return jsphere.Trial(t, 0.01 * t, -0.02 * t, q, np.ones((n, N)), kind, name="small")


def _write(tmp_path, text, name="trial.csv"):
    p = tmp_path / name
    p.write_text(text)
    return p


def _csv(tmp_path, trial, edit=None, name="trial.csv"):
    """Write `trial` and return (path, lines); `edit(lines)` may change the lines first."""
    lines = trial_to_csv(trial).splitlines()
    if edit is not None:
        edit(lines)
    return _write(tmp_path, "\n".join(lines) + "\n", name)


# --------------------------------------------------------------------------- Trial


def test_trial_fields_and_views(paper):
    tr = _small_trial()
    assert tr.n_wheels == 3 and tr.n_frames == 30
    assert tr.duration == pytest.approx(0.29)
    assert tr.valid.all()
    assert tr.input_names == ["chi_dot_1", "chi_dot_2", "chi_dot_3"]
    assert isinstance(tr.controls(), jsphere.WheelSpeeds)
    assert isinstance(_small_trial(kind="torques").controls(), jsphere.Torques)
    # a pytree: numpy leaves, static kind/name
    leaves = jax.tree_util.tree_leaves(tr)
    assert len(leaves) == 6 - 1  # t, x, y, q, inputs (z is None)
    s = tr.state0_guess(paper)
    assert isinstance(s, jsphere.State)
    np.testing.assert_allclose(np.asarray(s.q), [1, 0, 0, 0])


def test_trial_normalises_and_makes_sign_continuous():
    n = 12
    q = np.tile([1.0, 0.0, 0.0, 0.0], (n, 1))
    q[3] = [-1.0005, 0.0, 0.0, 0.0]  # small norm error, flipped sign
    q[5, 2] = np.nan  # a partial gap -> a full gap
    tr = jsphere.Trial(np.arange(n) * 0.1, np.zeros(n), np.zeros(n), q, np.zeros((n, 3)), "torques")
    np.testing.assert_allclose(tr.q[3], [1, 0, 0, 0])
    assert not tr.valid[5] and np.isnan(tr.x[5]) and np.all(np.isnan(tr.q[5]))
    assert tr.valid.sum() == n - 1


def test_trial_state0_guess_uses_first_valid_frame(paper):
    n = 20
    q = np.tile(quat_from_rotvec_np(np.array([0.0, 0.0, 0.3])), (n, 1))
    x = np.linspace(0.5, 0.7, n)
    x[:2] = np.nan
    tr = jsphere.Trial(np.arange(n) * 0.01, x, np.zeros(n), q, np.zeros((n, 3)), "wheel_speeds")
    s = tr.state0_guess(paper)
    assert float(s.x) == pytest.approx(x[2])
    np.testing.assert_allclose(np.asarray(s.q), q[2])
    assert np.all(np.asarray(s.omega) == 0) and np.all(np.asarray(s.Omega) == 0)


def test_trial_rejects_bad_arrays():
    n = 20
    t, z, q = np.arange(n) * 0.01, np.zeros(n), np.tile([1.0, 0, 0, 0], (n, 1))
    with pytest.raises(ValueError, match="kind must be one of"):
        jsphere.Trial(t, z, z, q, np.zeros((n, 3)), "speeds")
    with pytest.raises(ValueError, match=r"q must have shape \(20, 4\)"):
        jsphere.Trial(t, z, z, q[:, :3], np.zeros((n, 3)), "torques")
    u = np.zeros((n, 3))
    u[4, 1] = np.nan
    with pytest.raises(ValueError, match=r"sample 5: input column K_2 is blank or not finite"):
        jsphere.Trial(t, z, z, q, u, "torques")


# --------------------------------------------------------------------------- CSV round trip


def test_csv_round_trip(tmp_path, noisy_ws):
    p = tmp_path / "a.csv"
    jsphere.write_trial(p, noisy_ws)
    back = jsphere.read_trial(p)
    assert back.kind == "wheel_speeds" and back.name == "noisy_ws" and back.z is None
    np.testing.assert_array_equal(back.valid, noisy_ws.valid)
    v = noisy_ws.valid
    np.testing.assert_allclose(back.t, noisy_ws.t, atol=1e-6)
    np.testing.assert_allclose(back.x[v], noisy_ws.x[v], atol=6e-7)
    np.testing.assert_allclose(back.q[v], noisy_ws.q[v], atol=2e-9)
    np.testing.assert_allclose(back.inputs, noisy_ws.inputs, rtol=1e-9, atol=1e-12)
    # gaps are blank cells, not zeros or "nan"
    text = p.read_text()
    assert "nan" not in text.lower().replace("# name: noisy_ws", "")
    assert ",,,,," in text
    assert [t.name for t in jsphere.read_trials([tmp_path])] == ["noisy_ws"]


def test_csv_with_z_and_millimetres(tmp_path):
    tr = _small_trial()
    tr = tr.replace(z=np.full(tr.n_frames, 0.15))
    p = tmp_path / "z.csv"
    jsphere.write_trial(p, tr)
    back = jsphere.read_trial(p)
    np.testing.assert_allclose(back.z, 0.15)
    # the same trial in millimetres, declared in the file
    text = p.read_text().replace("# units: m", "# units: mm")
    lines = text.splitlines()
    hdr = lines.index("t,x,y,qw,qx,qy,qz,z,chi_dot_1,chi_dot_2,chi_dot_3")
    for i in range(hdr + 1, len(lines)):
        c = lines[i].split(",")
        c[1], c[2], c[7] = (str(float(v) * 1000) for v in (c[1], c[2], c[7]))
        lines[i] = ",".join(c)
    pm = _write(tmp_path, "\n".join(lines) + "\n", "mm.csv")
    np.testing.assert_allclose(jsphere.read_trial(pm).x, tr.x, atol=1e-9)
    # ... and detected without the units line
    pa = _write(tmp_path, "\n".join(ln for ln in lines if not ln.startswith("# units")) + "\n", "auto.csv")
    np.testing.assert_allclose(jsphere.read_trial(pa).z, 0.15)
    np.testing.assert_allclose(jsphere.read_trial(pa, units="mm").y, tr.y, atol=1e-9)


def test_detect_position_units():
    assert detect_position_units(np.zeros(3), np.full(3, 0.15)) == "m"
    assert detect_position_units(np.zeros(3), np.full(3, 150.0)) == "mm"
    assert detect_position_units(np.array([1200.0, 3.0])) == "mm"
    assert detect_position_units(np.array([1.2, 0.3])) is None


# --------------------------------------------------------------------------- bad input: one test each


def test_error_missing_column(tmp_path):
    p = _write(tmp_path, "t,x,y,qw,qx,qy,chi_dot_1\n0,0,0,1,0,0,0\n")
    with pytest.raises(ValueError, match=r"trial\.csv, line 1: missing required column\(s\) qz"):
        jsphere.read_trial(p)


def test_error_no_inputs(tmp_path):
    p = _write(tmp_path, "t,x,y,qw,qx,qy,qz\n0,0,0,1,0,0,0\n")
    with pytest.raises(ValueError, match=r"no input columns; add chi_dot_1\.\.chi_dot_N"):
        jsphere.read_trial(p)


def test_error_mixed_inputs(tmp_path):
    p = _write(tmp_path, "t,x,y,qw,qx,qy,qz,chi_dot_1,K_2\n0,0,0,1,0,0,0,0,0\n")
    with pytest.raises(ValueError, match=r"both chi_dot_\* and K_\* columns are present"):
        jsphere.read_trial(p)


def test_error_wheel_numbering_gap(tmp_path):
    p = _write(tmp_path, "t,x,y,qw,qx,qy,qz,chi_dot_1,chi_dot_3\n0,0,0,1,0,0,0,0,0\n")
    with pytest.raises(ValueError, match=r"numbered 1\.\.N without gaps; missing chi_dot_2"):
        jsphere.read_trial(p)


def _line_of(lines, k):
    """Index in `lines` of data row k (0-based) of a file written by trial_to_csv."""
    return 5 + k


def test_error_non_monotonic_time(tmp_path):
    def edit(lines):
        c = lines[_line_of(lines, 7)].split(",")
        c[0] = "0.050000"
        lines[_line_of(lines, 7)] = ",".join(c)

    p = _csv(tmp_path, _small_trial(), edit)
    with pytest.raises(
        ValueError,
        match=r"trial\.csv, line 13: time stamps are not increasing: t = 0\.05 s follows t = 0\.06 s \(line 12\)",
    ):
        jsphere.read_trial(p)


def test_error_duplicated_time(tmp_path):
    def edit(lines):
        lines.insert(_line_of(lines, 4), lines[_line_of(lines, 4)])

    p = _csv(tmp_path, _small_trial(), edit)
    with pytest.raises(ValueError, match=r"line 11: time stamps are duplicated: t = 0\.04 s follows t = 0\.04 s"):
        jsphere.read_trial(p)


def test_error_blank_time(tmp_path):
    def edit(lines):
        c = lines[_line_of(lines, 3)].split(",")
        c[0] = ""
        lines[_line_of(lines, 3)] = ",".join(c)

    p = _csv(tmp_path, _small_trial(), edit)
    with pytest.raises(ValueError, match=r"trial\.csv, line 9: the time t is blank or not finite"):
        jsphere.read_trial(p)


def test_error_nan_row(tmp_path):
    def edit(lines):
        lines[_line_of(lines, 10)] = ",".join(["nan"] * 10)

    p = _csv(tmp_path, _small_trial(), edit)
    with pytest.raises(ValueError, match=r"line 16: the time t is blank"):
        jsphere.read_trial(p)


def test_error_blank_input(tmp_path):
    def edit(lines):
        c = lines[_line_of(lines, 20)].split(",")
        c[8] = ""
        lines[_line_of(lines, 20)] = ",".join(c)

    p = _csv(tmp_path, _small_trial(), edit)
    with pytest.raises(
        ValueError,
        match=r"line 26: input column chi_dot_2 is blank or not finite \(t = 0\.2 s\); inputs may not have gaps",
    ):
        jsphere.read_trial(p)


def test_error_not_a_number(tmp_path):
    def edit(lines):
        c = lines[_line_of(lines, 2)].split(",")
        c[1] = "1,5".replace(",", ";")
        lines[_line_of(lines, 2)] = ",".join(c)

    p = _csv(tmp_path, _small_trial(), edit)
    with pytest.raises(ValueError, match=r"line 8, column x: '1;5' is not a number"):
        jsphere.read_trial(p)


def test_error_ragged_row(tmp_path):
    def edit(lines):
        lines[_line_of(lines, 2)] += ",1"

    p = _csv(tmp_path, _small_trial(), edit)
    with pytest.raises(ValueError, match=r"line 8: 11 cells but the header has 10 columns"):
        jsphere.read_trial(p)


def test_error_non_unit_quaternion(tmp_path):
    def edit(lines):
        c = lines[_line_of(lines, 5)].split(",")
        c[3:7] = ["0", "0", "0", "1.01"]  # a quaternion rounded or scaled by mistake
        lines[_line_of(lines, 5)] = ",".join(c)

    p = _csv(tmp_path, _small_trial(), edit)
    with pytest.raises(
        ValueError, match=r"line 11: the quaternion .* has norm 1\.01, not 1 .*check that the four columns"
    ):
        jsphere.read_trial(p)


def test_small_quaternion_deviation_is_normalised(tmp_path):
    def edit(lines):
        c = lines[_line_of(lines, 5)].split(",")
        c[3] = "1.0004"
        lines[_line_of(lines, 5)] = ",".join(c)

    tr = jsphere.read_trial(_csv(tmp_path, _small_trial(), edit))
    np.testing.assert_allclose(np.linalg.norm(tr.q, axis=1), 1.0, atol=1e-15)


def test_error_too_short(tmp_path):
    with pytest.raises(
        ValueError, match=r"trial\.csv: the trial is too short: 8 rows, 8 valid .* at least 10 valid frames and 0\.2 s"
    ):
        jsphere.read_trial(_csv(tmp_path, _small_trial(n=8)))

    # enough rows but too few valid frames
    def edit(lines):
        for k in range(MIN_VALID_FRAMES - 1, 30):
            c = lines[_line_of(lines, k)].split(",")
            c[1] = ""
            lines[_line_of(lines, k)] = ",".join(c)

    with pytest.raises(ValueError, match=r"too short: 30 rows, 9 valid"):
        jsphere.read_trial(_csv(tmp_path, _small_trial(), edit), max_gap_fraction=1.0)
    # enough frames but under 0.2 s
    tr = _small_trial(n=15)
    tr = tr.replace(t=tr.t / 10)
    with pytest.raises(ValueError, match=r"too short: .* over 0\.014 s"):
        jsphere.read_trial(_csv(tmp_path, tr))


def test_error_too_many_gaps(tmp_path):
    def edit(lines):
        for k in range(0, 60, 3):
            for j in (0, 1):
                kk = k + j
                c = lines[_line_of(lines, kk)].split(",")
                c[4] = ""
                lines[_line_of(lines, kk)] = ",".join(c)

    p = _csv(tmp_path, _small_trial(n=60), edit)
    with pytest.raises(ValueError, match=r"too many gaps: 67% of the 60 frames have no pose \(limit 50%\)"):
        jsphere.read_trial(p)
    assert jsphere.read_trial(p, max_gap_fraction=0.7).valid.sum() == 20


def test_error_units(tmp_path):
    tr = _small_trial().replace(z=np.full(30, 0.15))
    p = _csv(tmp_path, tr)
    with pytest.raises(ValueError, match=r"the units given \('mm'\) disagree with the file's '# units:' line \('m'\)"):
        jsphere.read_trial(p, units="mm")
    p2 = _write(
        tmp_path,
        "\n".join(ln for ln in p.read_text().splitlines() if not ln.startswith("# units")) + "\n",
        "nounits.csv",
    )
    with pytest.raises(ValueError, match=r"the units given \('mm'\) disagree with the data, which look like metres"):
        jsphere.read_trial(p2, units="mm")
    with pytest.raises(ValueError, match=r"the units given must be 'auto', 'm' or 'mm'; got 'cm'"):
        jsphere.read_trial(p2, units="cm")
    p3 = _write(tmp_path, p.read_text().replace("# units: m", "# units: inch"), "inch.csv")
    with pytest.raises(ValueError, match=r"inch\.csv: the '# units:' line says 'inch'"):
        jsphere.read_trial(p3)


def test_error_missing_file_and_header(tmp_path):
    with pytest.raises(FileNotFoundError, match="does not exist"):
        jsphere.read_trial(tmp_path / "nope.csv")
    with pytest.raises(ValueError, match="no header line"):
        jsphere.read_trial(_write(tmp_path, "# only a comment\n"))
    with pytest.raises(ValueError, match="no data rows"):
        jsphere.read_trial(_write(tmp_path, "t,x,y,qw,qx,qy,qz,K_1\n"))


# --------------------------------------------------------------------------- synthetic trials


def test_random_inputs_is_a_module_ramped_from_zero(paper):
    a = jsphere.random_inputs(paper, 2.0, seed=0)
    b = jsphere.random_inputs(paper, 2.0, seed=1)
    assert isinstance(a, jsphere.WheelSpeeds) and isinstance(a.fn, RandomSines)
    # same structure and static parts: one compilation serves every seed
    da, sa = eqx.partition(a, eqx.is_array)
    db, sb = eqx.partition(b, eqx.is_array)
    assert jax.tree_util.tree_structure(da) == jax.tree_util.tree_structure(db) and eqx.tree_equal(sa, sb)
    assert not np.allclose(a.fn.freq, b.fn.freq)
    np.testing.assert_allclose(np.asarray(a(jnp.array(0.0))), 0.0, atol=1e-15)
    _, rate0 = a.value_and_rate(jnp.array(0.0))
    np.testing.assert_allclose(np.asarray(rate0), 0.0, atol=1e-12)
    u = np.asarray(eval_controls(a, jnp.linspace(0, 10, 2001)))
    amp = 3.0
    c = jsphere.random_inputs(paper, 2.0, amplitude=amp, kind="torques", seed=3)
    assert isinstance(c, jsphere.Torques)
    uc = np.asarray(eval_controls(c, jnp.linspace(0, 10, 2001)))
    assert np.abs(uc).max() <= amp and np.abs(uc).max() > 0.3 * amp
    assert np.abs(u).max() > 1.0
    with pytest.raises(ValueError, match="kind must be one of"):
        jsphere.random_inputs(paper, 2.0, kind="speeds")


def test_synthetic_trial_noise_and_gaps(truth_ws, noisy_ws):
    truth, c = truth_ws
    assert truth.kind == "wheel_speeds" and truth.n_frames == int(T1 * 100) + 1
    np.testing.assert_allclose(np.diff(truth.t), 0.01, atol=1e-12)
    assert truth.valid.all()
    # the robot moved and tilted: an exciting trial
    assert np.hypot(truth.x - truth.x[0], truth.y - truth.y[0]).max() > 0.02
    # recorded inputs are the commands at the sample times
    np.testing.assert_allclose(truth.inputs, np.asarray(eval_controls(c, jnp.asarray(truth.t))), atol=1e-14)
    np.testing.assert_array_equal(noisy_ws.inputs, truth.inputs)
    # noise levels
    v = noisy_ws.valid
    dx = np.concatenate([noisy_ws.x[v] - truth.x[v], noisy_ws.y[v] - truth.y[v]])
    assert 0.7e-3 < dx.std() < 1.3e-3
    # rotation noise: angle of q_true^-1 q_noisy; per axis sd 0.5 deg
    qt = truth.q[v] * np.array([1, -1, -1, -1])
    dq = quat_mul_np(qt, noisy_ws.q[v])
    rv = 2 * dq[:, 1:] * np.sign(dq[:, :1])
    assert 0.35 < np.rad2deg(rv.std()) < 0.65
    # gaps: about 10%, in bursts, first frame kept
    frac = 1 - v.mean()
    assert 0.03 < frac < 0.2 and v[0]
    assert np.all(np.isnan(noisy_ws.q[~v])) and np.all(np.isnan(noisy_ws.x[~v]))
    # sign-continuous quaternions
    qv = noisy_ws.q[v]
    assert np.all(np.sum(qv[1:] * qv[:-1], axis=1) > 0)


def test_synthetic_trial_is_deterministic(paper, noisy_ws):
    c = jsphere.random_inputs(paper, T1, kind="wheel_speeds", seed=1)
    again = jsphere.synthetic_trial(paper, c, T1, pos_sd=1e-3, rot_sd_deg=0.5, dropout=0.1, seed=7, name="noisy_ws")
    np.testing.assert_array_equal(again.x, noisy_ws.x)
    np.testing.assert_array_equal(again.q, noisy_ws.q)


def test_synthetic_torque_trial(torque_trial, paper):
    tr, c = torque_trial
    assert tr.kind == "torques" and tr.input_names == ["K_1", "K_2", "K_3"]
    np.testing.assert_allclose(tr.inputs, np.asarray(eval_controls(c, jnp.asarray(tr.t))), atol=1e-15)
    # the platform stays near its rest attitude (gamma_z close to 1) but does move
    g = np.asarray(rotmat(jnp.asarray(tr.q[tr.valid])))[:, 2, 2]
    assert g.min() > 0.8 and g.min() < 0.9999


@pytest.mark.slow
def test_replaying_a_trial_reproduces_it(paper, truth_ws):
    """The trial's recorded inputs, interpolated (`Trial.controls`), replay the motion from
    `state0_guess` to well under the noise level: the inputs are recorded consistently."""
    truth, _ = truth_ws
    traj = jsphere.simulate(paper, truth.state0_guess(paper), truth.controls(), float(truth.t[-1]), ts=truth.t)
    err = np.hypot(np.asarray(traj.x) - truth.x, np.asarray(traj.y) - truth.y).max()
    assert err < 1e-4
    ang = 2 * np.arcsin(
        np.clip(np.linalg.norm(quat_mul_np(truth.q * [1, -1, -1, -1], np.asarray(traj.q))[:, 1:], axis=1), 0, 1)
    )
    assert np.rad2deg(ang.max()) < 0.02


def test_synthetic_trial_round_trips_through_csv(tmp_path, torque_trial):
    tr, _ = torque_trial
    p = tmp_path / "tq.csv"
    jsphere.write_trial(p, tr)
    back = jsphere.read_trial(p)
    assert back.kind == "torques"
    np.testing.assert_array_equal(back.valid, tr.valid)
    assert re.search(r"^t,x,y,qw,qx,qy,qz,K_1,K_2,K_3$", p.read_text(), re.MULTILINE)


# --------------------------------------------------------------------------- raw marker exports

from jsphere.capture.markers import UP_TO_Z  # noqa: E402
from jsphere.capture.synthetic import default_marker_set  # noqa: E402
from jsphere.model.rotations import quat_from_rotmat_np, rotmat_np  # noqa: E402

BODY = default_marker_set(0.15)
NAMES = ["a", "b", "c", "d"]


def _angle_deg(q1, q2):
    d = quat_mul_np(q1 * np.array([1, -1, -1, -1]), q2)
    return np.rad2deg(2 * np.arcsin(np.clip(np.linalg.norm(d[:, 1:], axis=1), 0, 1)))


def _random_rotations(rng, n):
    return rotmat_np(quat_from_rotvec_np(rng.normal(0, 1.0, (n, 3))))


def test_rigid_body_pose_exact_gaps_and_reflection():
    rng = np.random.default_rng(0)
    M = 50
    R = _random_rotations(rng, M)
    p = rng.normal(0, 1.0, (M, 3))
    m = np.einsum("mij,kj->mki", R, BODY) + p[:, None]
    m[3, 1] = np.nan  # 3 markers left: still a pose
    m[4, :2] = np.nan  # 2 markers: a gap
    q, pp, rms = jsphere.rigid_body_pose(m, BODY)
    ok = np.ones(M, bool)
    ok[4] = False
    np.testing.assert_array_equal(np.isfinite(rms), ok)
    np.testing.assert_allclose(rotmat_np(q[ok]), R[ok], atol=1e-12)
    np.testing.assert_allclose(pp[ok], p[ok], atol=1e-12)
    assert np.nanmax(rms) < 1e-12
    # a mirrored marker set: the best proper rotation, never a reflection
    mirror = m.copy()
    mirror[..., 0] *= -1
    qm, _, rms_m = jsphere.rigid_body_pose(mirror, BODY)
    Rm = rotmat_np(qm[ok])
    np.testing.assert_allclose(np.linalg.det(Rm), 1.0, atol=1e-12)
    full = ok.copy()
    full[3] = False  # three points can always be mirrored by a rotation
    assert np.min(rms_m[full]) > 1e-3
    # collinear markers: a gap; a swapped marker beyond max_rms: a gap
    line = np.array([[0.0, 0, 0], [0.05, 0, 0], [0.1, 0, 0]])
    ql, _, _ = jsphere.rigid_body_pose(np.tile(line, (2, 1, 1)), line)
    assert np.all(np.isnan(ql))
    sw = m.copy()
    sw[0, [0, 1]] = sw[0, [1, 0]]
    qs, _, _ = jsphere.rigid_body_pose(sw, BODY, max_rms=0.005)
    assert np.all(np.isnan(qs[0])) and np.all(np.isfinite(qs[1]))


def test_up_axis_conversion_is_a_rotation():
    C = UP_TO_Z["y"]
    np.testing.assert_allclose(C @ [0, 1, 0], [0, 0, 1])
    assert np.linalg.det(C) == pytest.approx(1.0)
    np.testing.assert_allclose(rotmat_np(quat_from_rotmat_np(C)), C, atol=1e-15)


@pytest.fixture(scope="module")
def markers_truth(truth_ws):
    """Noisy markers (0.1 mm, 3% missing) of the noiseless trial; the truth trial."""
    truth, _ = truth_ws
    m = jsphere.synthetic_markers(truth, BODY, marker_sd=1e-4, dropout=0.03, seed=5)
    return m, truth


def _inputs_file(tmp_path, truth):
    p = tmp_path / "inputs.csv"
    jsphere.write_inputs_csv(p, truth.t, truth.inputs, truth.kind)
    return p


def _check_recovery(tr, truth, pos=1e-3, ang=1.0):
    v = tr.valid
    assert v.mean() > 0.9
    dpos = np.hypot(tr.x[v] - truth.x[v], tr.y[v] - truth.y[v])
    assert dpos.max() < pos
    assert _angle_deg(tr.q[v], truth.q[v]).max() < ang
    np.testing.assert_allclose(tr.z[v], 0.15, atol=pos)
    np.testing.assert_allclose(tr.inputs, truth.inputs, rtol=1e-8, atol=1e-9)
    return dpos.max(), _angle_deg(tr.q[v], truth.q[v]).max()


def test_motive_round_trip_mm_y_up(tmp_path, markers_truth):
    m, truth = markers_truth
    raw = tmp_path / "take.csv"
    jsphere.write_motive_csv(raw, truth.t, m, NAMES, units="mm")
    data = jsphere.read_motive_csv(raw)
    assert data.names == tuple(f"robot:{n}" for n in NAMES)
    # blank cells are gaps, not zeros
    np.testing.assert_array_equal(np.isnan(data.markers), np.isnan(m))
    np.testing.assert_allclose(data.markers, m, atol=1e-6, equal_nan=True)
    tr = jsphere.markers_to_trial(
        data, _inputs_file(tmp_path, truth), options=jsphere.ConvertOptions(body_markers=BODY)
    )
    _check_recovery(tr, truth, pos=5e-4, ang=0.5)
    assert tr.name == "take"


def test_motive_estimated_body_and_offset(tmp_path, markers_truth):
    """Body markers from the first full frame (platform at rest, q = 1 there), the shell centre
    given as an offset from the marker centroid."""
    m, truth = markers_truth
    raw = tmp_path / "take.csv"
    jsphere.write_motive_csv(raw, truth.t, m, NAMES, units="m")
    tr = jsphere.convert_raw(
        raw, _inputs_file(tmp_path, truth), format="motive", options=jsphere.ConvertOptions(body_offset=-BODY.mean(0))
    )
    _check_recovery(tr, truth, pos=1e-3, ang=1.0)


def test_motive_rigid_body_columns_xyzw(tmp_path, truth_ws):
    """Motive's own pose: quaternion columns X, Y, Z, W in a Y-up frame."""
    truth, _ = truth_ws
    z = np.full(truth.n_frames, 0.15)
    p = np.stack([truth.x, truth.y, z], 1)
    raw = tmp_path / "rb.csv"
    m = jsphere.synthetic_markers(truth, BODY, marker_sd=0.0)
    jsphere.write_motive_csv(raw, truth.t, m, NAMES, rb_q=truth.q, rb_p=p, units="mm")
    assert "Rotation,Rotation,Rotation,Rotation,Position" in raw.read_text()
    data = jsphere.read_motive_csv(raw, use="rigid_body", rigid_body="robot")
    tr = jsphere.markers_to_trial(data, _inputs_file(tmp_path, truth))
    np.testing.assert_allclose(tr.x, truth.x, atol=1e-6)
    assert _angle_deg(tr.q, truth.q).max() < 1e-3


def test_vicon_round_trip(tmp_path, markers_truth):
    m, truth = markers_truth
    raw = tmp_path / "trial01.csv"
    jsphere.write_vicon_csv(raw, truth.t, m, NAMES)
    text = raw.read_text().splitlines()
    assert text[0] == "Trajectories" and text[3].startswith("Frame,Sub Frame,X,Y,Z") and ",mm,mm" in text[4]
    # other sections before and after the trajectories are skipped
    raw.write_text(
        "Devices\n1000\n,,Force\nFrame,Sub Frame,Fx\n,,N\n1,0,0.5\n\n" + raw.read_text() + "\nModel Outputs\n100\n"
    )
    data = jsphere.read_vicon_csv(raw)
    np.testing.assert_allclose(data.t, truth.t, atol=1e-12)
    np.testing.assert_array_equal(np.isnan(data.markers), np.isnan(m))
    tr = jsphere.markers_to_trial(
        data, _inputs_file(tmp_path, truth), options=jsphere.ConvertOptions(body_markers=BODY)
    )
    _check_recovery(tr, truth, pos=5e-4, ang=0.5)


def c3d_shell(n_points: int, n_frames: int, declared: int | None = None, *, integers: bool = False) -> bytes:
    """The bytes of a minimal C3D file (Intel; float data, or 16-bit integers): a header declaring
    `declared` (default `n_frames`) frames of `n_points` points, an empty parameter section,
    `n_frames` zero frames."""
    head = bytearray(512)
    head[0], head[1] = 2, 0x50
    struct.pack_into("<4H", head, 2, n_points, 0, 1, n_frames if declared is None else declared)
    struct.pack_into("<fH", head, 12, 0.1 if integers else -1.0, 3)
    params = bytearray(512)
    params[1:4] = bytes([0x50, 1, 84])
    return bytes(head + params) + bytes((8 if integers else 16) * n_points * n_frames)


class _FakeEzc3d:
    """Stands in for the `ezc3d` module: `ezc3d.c3d(path)` returns the dict layout of ezc3d."""

    def __init__(self, points, residuals, labels, rate=100.0, units="mm"):
        self.content = {
            "parameters": {
                "POINT": {"LABELS": {"value": labels}, "RATE": {"value": [rate]}, "UNITS": {"value": [units]}}
            },
            "data": {"points": points, "meta_points": {"residuals": residuals}},
        }

    def c3d(self, path):
        return self.content


def test_c3d_through_ezc3d(tmp_path, monkeypatch, markers_truth):
    import sys

    m, truth = markers_truth
    M, K = m.shape[:2]
    pts = np.ones((4, K, M))
    pts[:3] = np.transpose(np.nan_to_num(m, nan=0.0), (2, 1, 0)) * 1000.0  # gaps as zeros ...
    res = np.where(np.isnan(m[..., 0]).T, -1.0, 0.5)[None]  # ... flagged by residual -1
    monkeypatch.setitem(sys.modules, "ezc3d", _FakeEzc3d(pts, res, NAMES))
    raw = tmp_path / "trial.c3d"
    raw.write_bytes(c3d_shell(K, M))  # a header the structure check accepts; the fake reads nothing
    data = jsphere.read_c3d(raw)
    np.testing.assert_array_equal(np.isnan(data.markers), np.isnan(m))
    tr = jsphere.markers_to_trial(
        data, _inputs_file(tmp_path, truth), options=jsphere.ConvertOptions(body_markers=BODY)
    )
    _check_recovery(tr, truth, pos=5e-4, ang=0.5)


def test_c3d_without_ezc3d(tmp_path, monkeypatch):
    import sys

    monkeypatch.setitem(sys.modules, "ezc3d", None)
    (tmp_path / "x.c3d").write_bytes(c3d_shell(3, 4))  # a sound file: only reading it needs ezc3d
    with pytest.raises(ImportError, match=r"pip install ezc3d"):
        jsphere.read_c3d(tmp_path / "x.c3d")


# --------------------------------------------------------------------------- raw exports: bad input


def test_raw_error_units_mismatch(tmp_path, markers_truth):
    m, truth = markers_truth
    raw = tmp_path / "take.csv"
    jsphere.write_motive_csv(raw, truth.t, m, NAMES, units="mm")
    with pytest.raises(ValueError, match=r"take\.csv: --units m was given but the file says its lengths are in mm"):
        jsphere.read_motive_csv(raw, units="m")
    # a file whose header lies: says Meters, holds millimetres
    bad = tmp_path / "bad.csv"
    bad.write_text(raw.read_text().replace("Length Units,Millimeters", "Length Units,Meters"))
    with pytest.raises(ValueError, match=r"declared in 'm' but the marker spread looks like millimetres"):
        jsphere.read_motive_csv(bad)
    # no units anywhere: detected from the spread
    vic = tmp_path / "v.csv"
    jsphere.write_vicon_csv(vic, truth.t, m, NAMES)
    nounits = tmp_path / "nounits.csv"
    lines = vic.read_text().splitlines()
    lines[4] = ","
    nounits.write_text("\n".join(lines) + "\n")
    np.testing.assert_allclose(jsphere.read_vicon_csv(nounits).markers, m, atol=1e-6, equal_nan=True)
    with pytest.raises(ValueError, match=r"declared in 'm' but the marker spread looks like millimetres"):
        jsphere.read_vicon_csv(nounits, units="m")


def test_raw_error_not_the_format(tmp_path):
    p = tmp_path / "x.csv"
    p.write_text("t,x\n0,1\n")
    with pytest.raises(ValueError, match=r"x\.csv, line 1: not a Motive CSV export"):
        jsphere.read_motive_csv(p)
    with pytest.raises(ValueError, match=r"no 'Trajectories' section"):
        jsphere.read_vicon_csv(p)
    with pytest.raises(ValueError, match=r"format must be one of"):
        jsphere.convert_raw(p, p, format="trc")


def test_raw_error_times(tmp_path, markers_truth):
    m, truth = markers_truth
    t = truth.t.copy()
    t[20] = t[19]
    raw = tmp_path / "take.csv"
    jsphere.write_motive_csv(raw, t, m, NAMES)
    with pytest.raises(
        ValueError, match=r"take\.csv, line 28: time stamps are duplicated: t = 0\.19 s follows t = 0\.19 s \(line 27\)"
    ):
        jsphere.read_motive_csv(raw)
    vic = tmp_path / "v.csv"
    jsphere.write_vicon_csv(vic, truth.t, m, NAMES)
    lines = vic.read_text().splitlines()
    lines[10] = "3," + lines[10].split(",", 1)[1]  # frame 3 after frame 6
    vic.write_text("\n".join(lines) + "\n")
    with pytest.raises(ValueError, match=r"v\.csv, line 11: time stamps are not increasing"):
        jsphere.read_vicon_csv(vic)


def test_raw_error_too_few_markers_and_too_many_gaps(tmp_path, markers_truth):
    m, truth = markers_truth
    raw = tmp_path / "two.csv"
    jsphere.write_motive_csv(raw, truth.t, m[:, :2], NAMES[:2])
    with pytest.raises(
        ValueError, match=r"two\.csv: no complete rigid-body columns .* and fewer than 3 marker columns"
    ):
        jsphere.read_motive_csv(raw)
    vic = tmp_path / "two_v.csv"
    jsphere.write_vicon_csv(vic, truth.t, m[:, :2], NAMES[:2])
    with pytest.raises(ValueError, match=r"two_v\.csv: 2 marker\(s\) .* a pose needs at least 3 markers"):
        jsphere.markers_to_trial(jsphere.read_vicon_csv(vic), _inputs_file(tmp_path, truth))
    mm = m.copy()
    mm[::2, :2] = np.nan  # every other frame keeps only 2 markers
    raw2 = tmp_path / "gappy.csv"
    jsphere.write_motive_csv(raw2, truth.t, mm, NAMES)
    with pytest.raises(ValueError, match=r"gappy\.csv: too many gaps: 50% .*|gappy\.csv: too many gaps"):
        jsphere.markers_to_trial(
            jsphere.read_motive_csv(raw2),
            _inputs_file(tmp_path, truth),
            options=jsphere.ConvertOptions(body_markers=BODY, max_gap_fraction=0.4),
        )


def test_inputs_table_errors(tmp_path, markers_truth):
    m, truth = markers_truth
    p = tmp_path / "in.csv"
    p.write_text("t,chi_dot_1,chi_dot_2\n0,1,2\n0.1,1,\n0.2,1,2\n")
    with pytest.raises(ValueError, match=r"in\.csv, line 3: input column chi_dot_2 is blank"):
        jsphere.read_inputs_csv(p)
    p.write_text("t,K_1\n0,1\n0.2,1\n0.1,1\n")
    with pytest.raises(ValueError, match=r"in\.csv, line 4: time stamps are not increasing"):
        jsphere.read_inputs_csv(p)
    p.write_text("time,K_1\n0,1\n")
    with pytest.raises(ValueError, match=r"line 1: missing required column t"):
        jsphere.read_inputs_csv(p)
    p.write_text("t,K_1,chi_dot_1\n0,1,1\n1,1,1\n")
    with pytest.raises(ValueError, match=r"both chi_dot_\* and K_\* columns"):
        jsphere.read_inputs_csv(p)
    raw = tmp_path / "take.csv"
    jsphere.write_motive_csv(raw, truth.t, m, NAMES)
    late = (truth.t + 100.0, truth.inputs, "wheel_speeds")
    with pytest.raises(ValueError, match=r"do not overlap the inputs' .* share a clock \(--time-offset SECONDS"):
        jsphere.markers_to_trial(jsphere.read_motive_csv(raw), late, options=jsphere.ConvertOptions(body_markers=BODY))
    tr = jsphere.markers_to_trial(
        jsphere.read_motive_csv(raw), late, options=jsphere.ConvertOptions(body_markers=BODY, time_offset=100.0)
    )
    assert tr.t[0] == pytest.approx(100.0)


# --------------------------------------------------------------------------- CLI


def test_cli_synth_and_convert(tmp_path, markers_truth, capsys):
    from jsphere.cli.app import main

    assert main(["synth", "--out", str(tmp_path / "syn"), "--trials", "1", "--duration", str(T1), "--no-cache"]) == 0
    [f] = sorted((tmp_path / "syn").glob("*.csv"))
    tr = jsphere.read_trial(f)
    assert tr.kind == "wheel_speeds" and tr.n_frames == int(T1 * 100) + 1 and f.name == "wheel_speeds_00.csv"
    m, truth = markers_truth
    raw = tmp_path / "v.csv"
    jsphere.write_vicon_csv(raw, truth.t, m, NAMES)
    out = tmp_path / "conv.csv"
    args = ["convert", str(raw), "--format", "vicon", "--inputs", str(_inputs_file(tmp_path, truth)), "--out", str(out)]
    assert main([*args, "--body-offset", *(str(v) for v in -BODY.mean(0))]) == 0
    _check_recovery(jsphere.read_trial(out), truth, pos=1e-3, ang=1.0)
    body = tmp_path / "body.csv"
    body.write_text("name,x,y,z\n" + "".join(f"{n},{b[0]},{b[1]},{b[2]}\n" for n, b in zip(NAMES, BODY)))
    assert main([*args, "--body-markers", str(body)]) == 0
    _check_recovery(jsphere.read_trial(out), truth, pos=5e-4, ang=0.5)
    assert main([*args, "--units", "m"]) == 2
    assert "--units m was given but the file says its lengths are in mm" in capsys.readouterr().err


# --------------------------------------------------------------------------- the shipped example dataset

DATA = Path(__file__).resolve().parents[2] / "examples" / "data"


def test_example_dataset_reads_and_converts():
    trials = jsphere.read_trials([DATA])
    assert [t.name for t in trials] == ["tq_01", "tq_02", "ws_01", "ws_02", "ws_03"]
    assert all(abs(np.median(np.diff(t.t)) - 0.01) < 1e-9 and t.valid.mean() > 0.95 for t in trials)
    assert sum(f.stat().st_size for f in DATA.rglob("*") if f.is_file()) < 300 * 1024
    truth = jsphere.RobotParams.load(DATA / "truth.toml")
    assert float(truth.R_m) != pytest.approx(float(jsphere.RobotParams.paper().R_m), rel=1e-3)  # perturbed
    body = jsphere.read_body_markers(DATA / "raw" / "body_markers.csv")
    assert sorted(body) == ["m1", "m2", "m3", "m4"]
    inputs = DATA / "raw" / "inputs.csv"
    a = jsphere.convert_raw(
        DATA / "raw" / "motive.csv", inputs, format="motive", options=jsphere.ConvertOptions(body_markers=body)
    )
    b = jsphere.convert_raw(
        DATA / "raw" / "vicon.csv", inputs, format="vicon", options=jsphere.ConvertOptions(body_markers=body)
    )
    v = a.valid & b.valid
    assert v.mean() > 0.95
    np.testing.assert_allclose(a.x[v], b.x[v], atol=2e-6)  # one motion, two exporters
    np.testing.assert_allclose(a.z[v], float(truth.R0), atol=1e-3)


def test_convert_keywords_of_the_options_still_work():
    """`convert_raw` and `markers_to_trial` take their options as a `ConvertOptions`; the same
    options given as keywords make the same trial, each with a `DeprecationWarning` naming its
    spelling in `ConvertOptions`; a keyword that never was an option is a `TypeError`."""
    body = jsphere.read_body_markers(DATA / "raw" / "body_markers.csv")
    raw, inputs = DATA / "raw" / "motive.csv", DATA / "raw" / "inputs.csv"
    options = jsphere.ConvertOptions(body_markers=body, time_offset=0.01, name="t")
    want = jsphere.convert_raw(raw, inputs, format="motive", options=options)
    with pytest.warns(
        DeprecationWarning,
        match=r"convert_raw: body_markers= is deprecated; pass options=ConvertOptions\(body_markers=\.\.\.\)",
    ):
        got = jsphere.convert_raw(raw, inputs, format="motive", body_markers=body, time_offset=0.01, name="t")
    assert got.name == want.name == "t"
    np.testing.assert_array_equal(got.t, want.t)
    np.testing.assert_array_equal(got.q, want.q)
    data = jsphere.read_motive_csv(raw)
    with pytest.warns(DeprecationWarning, match=r"ConvertOptions\(max_gap_fraction=\.\.\.\)"):
        got = jsphere.markers_to_trial(data, inputs, body_markers=body, time_offset=0.01, max_gap_fraction=0.5)
    np.testing.assert_array_equal(got.x, want.x)
    with pytest.raises(TypeError, match="unexpected keyword argument 'units'"):
        jsphere.markers_to_trial(data, inputs, units="mm")


def test_body_markers_by_name(tmp_path, markers_truth):
    """A body-marker table matched by name (with or without 'Subject:'), in any order, with a
    marker of the export that it does not list left out of the fit."""
    m, truth = markers_truth
    raw = tmp_path / "v.csv"
    jsphere.write_vicon_csv(raw, truth.t, m, NAMES)
    f = tmp_path / "body.csv"
    f.write_text(
        "# platform frame, m\nname,x,y,z\n"
        + "".join(f"{n},{b[0]},{b[1]},{b[2]}\n" for n, b in zip(NAMES[::-1], BODY[::-1]))
    )
    body = jsphere.read_body_markers(f)
    tr = jsphere.convert_raw(
        raw, _inputs_file(tmp_path, truth), format="vicon", options=jsphere.ConvertOptions(body_markers=body)
    )
    _check_recovery(tr, truth, pos=5e-4, ang=0.5)
    three = {k: body[k] for k in ("a", "b", "d")}
    tr3 = jsphere.convert_raw(
        raw, _inputs_file(tmp_path, truth), format="vicon", options=jsphere.ConvertOptions(body_markers=three)
    )
    _check_recovery(tr3, truth, pos=1e-3, ang=1.5)
    with pytest.raises(
        ValueError, match=r"fewer than 3 of the export's markers .* are among the body markers \['a', 'x', 'y'\]"
    ):
        jsphere.convert_raw(
            raw,
            _inputs_file(tmp_path, truth),
            format="vicon",
            options=jsphere.ConvertOptions(body_markers={"a": BODY[0], "x": BODY[1], "y": BODY[2]}),
        )
    f.write_text("marker,x,y,z\na,0,0,0\n")
    with pytest.raises(ValueError, match=r"body\.csv: the first line must be the header 'name,x,y,z'"):
        jsphere.read_body_markers(f)
    f.write_text("name,x,y,z\na,0,0,0\nb,0,,0\nc,1,1,1\n")
    with pytest.raises(ValueError, match=r"body\.csv, line 3: marker 'b' has a blank coordinate"):
        jsphere.read_body_markers(f)
