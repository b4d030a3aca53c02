"""Capture data on bad input: no input file overwritten, files cut short, unreadable C3D files,
encodings, units, and the plausibility warnings (`CaptureWarning`)."""

from __future__ import annotations

import codecs
import contextlib
import os
import struct
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest

import jsphere
from jsphere._runtime.errors import InputError
from jsphere._runtime.files import refuse_overwrite
from jsphere.capture.trial import trial_to_csv
from jsphere.capture.validation import CaptureWarning, implausible
from jsphere.cli.app import main

DATA = Path(__file__).resolve().parents[2] / "examples" / "data"
RAW = DATA / "raw"


def _cli(argv, capsys) -> tuple[int, str]:
    code = main([*map(str, argv), "--no-cache"])
    err = capsys.readouterr().err
    assert "Traceback" not in err, err
    return int(code), err


@contextlib.contextmanager
def _no_capture_warnings():
    with warnings.catch_warnings():
        warnings.simplefilter("error", CaptureWarning)
        yield


@pytest.fixture(scope="module")
def ws01():
    return jsphere.read_trial(DATA / "ws_01.csv")


def _convert_args(raw, out, fmt="motive", inputs=RAW / "inputs.csv", *extra):
    return ["convert", raw, "--format", fmt, "--inputs", inputs, "--out", out, *extra]


# --------------------------------------------------------------------------- no input overwritten


def test_refuse_overwrite_compares_resolved_paths(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    a = tmp_path / "take.csv"
    a.write_text("raw data\n")
    (tmp_path / "sub").mkdir()
    os.symlink(a, tmp_path / "link.csv")
    os.link(a, tmp_path / "hard.csv")
    for out in ("take.csv", "./take.csv", str(a), "sub/../take.csv", "link.csv", "hard.csv"):
        with pytest.raises(
            InputError, match=r"--out .* would write over the raw export .*take\.csv.*give --out another path"
        ):
            refuse_overwrite(out, {"the raw export": "take.csv"})
    with pytest.raises(
        InputError,
        match=r"--to x would write over the input file x: a command never replaces its own input; give --to another path",
    ):
        refuse_overwrite([None, "other.csv", "x"], ["take.csv", None, "x"], option="--to")
    refuse_overwrite(["other.csv", "sub/take.csv"], {"the raw export": "take.csv", "unused": None})  # no error
    assert a.read_text() == "raw data\n"


@pytest.mark.parametrize("which", ["raw", "inputs", "body", "symlink"])
def test_convert_never_writes_over_its_inputs(tmp_path, capsys, monkeypatch, which):
    monkeypatch.chdir(tmp_path)
    for f in ("motive.csv", "inputs.csv", "body_markers.csv"):
        (tmp_path / f).write_bytes((RAW / f).read_bytes())
    os.symlink("motive.csv", tmp_path / "take_link.csv")
    out = {
        "raw": "./motive.csv",
        "inputs": "inputs.csv",
        "body": str(tmp_path / "body_markers.csv"),
        "symlink": "take_link.csv",
    }
    before = {f: (tmp_path / f).read_bytes() for f in ("motive.csv", "inputs.csv", "body_markers.csv")}
    code, err = _cli(
        _convert_args("motive.csv", out[which], "motive", "inputs.csv", "--body-markers", "body_markers.csv"), capsys
    )
    assert code == 2 and "would write over the" in err and "give --out another path" in err, err
    assert {f: (tmp_path / f).read_bytes() for f in before} == before


def test_synth_never_writes_over_its_parameter_file(tmp_path, capsys):
    params = tmp_path / "robot.toml"
    jsphere.RobotParams.paper().save(params)
    (tmp_path / "trials").mkdir()
    os.symlink(params, tmp_path / "trials" / "torques_00.csv")
    before = params.read_bytes()
    code, err = _cli(
        ["synth", "--out", tmp_path / "trials", "--kind", "torques", "--trials", "1", "--params", params], capsys
    )
    assert code == 2 and "would write over the parameter file" in err, err
    assert params.read_bytes() == before


def test_synth_and_convert_check_their_options_first(tmp_path, capsys):
    for opts, msg in (
        (["--trials", "0"], "--trials must be at least 1"),
        (["--duration", "nan"], "--duration must be a positive number of seconds; got nan"),
        (["--pos-sd", "-1"], "--pos-sd must be a finite number >= 0"),
        (["--rot-sd-deg", "inf"], "--rot-sd-deg must be a finite number >= 0"),
        (["--dropout", "1"], "--dropout must be a fraction in [0, 1)"),
        (["--seed", "-3"], "--seed must be an integer >= 0; got -3"),
    ):
        code, err = _cli(["synth", "--out", tmp_path / "s", *opts], capsys)
        assert code == 2 and msg in err, (opts, err)
    (tmp_path / "file").write_text("x")
    code, err = _cli(["synth", "--out", tmp_path / "file"], capsys)
    assert code == 2 and "is a file; give the folder" in err
    code, err = _cli(
        _convert_args(RAW / "motive.csv", tmp_path, "motive", RAW / "inputs.csv", "--body-offset", "0", "nan", "0"),
        capsys,
    )
    assert code == 2 and "--body-offset X Y Z must be finite numbers [m]; got 0 nan 0" in err, err
    code, err = _cli(
        _convert_args(RAW / "motive.csv", tmp_path / "t.csv", "motive", RAW / "inputs.csv", "--time-offset", "inf"),
        capsys,
    )
    assert code == 2 and "--time-offset must be a finite number of seconds" in err, err
    code, err = _cli(_convert_args(RAW / "motive.csv", tmp_path, "motive"), capsys)
    assert code == 2 and "is a folder; give the file to write" in err, err
    code, err = _cli(_convert_args(RAW / "motive.csv", tmp_path / "file" / "t.csv", "motive"), capsys)
    assert code == 2 and f"{tmp_path / 'file'} is a file, not a folder" in err, err
    code, err = _cli(["synth", "--out", tmp_path / "file" / "trials"], capsys)
    assert code == 2 and f"{tmp_path / 'file'} is a file, not a folder" in err, err
    with pytest.raises(
        InputError, match=r"body offset \(--body-offset X Y Z\) must be 3 finite numbers.* got \(0\.0, nan, 0\.0\)"
    ):
        jsphere.convert_raw(
            RAW / "motive.csv",
            RAW / "inputs.csv",
            format="motive",
            options=jsphere.ConvertOptions(body_offset=(0.0, np.nan, 0.0)),
        )


# --------------------------------------------------------------------------- files cut short


def _cut_mid_row(path: Path, keep_chars: int = 12) -> None:
    """Cut the file `keep_chars` characters into its last line (as a broken copy would)."""
    text = path.read_text()
    start = text.rindex("\n", 0, len(text) - 1) + 1
    path.write_text(text[: start + keep_chars])


def test_motive_cut_mid_row_and_short_of_its_declared_frames(tmp_path):
    raw = tmp_path / "take.csv"
    raw.write_text((RAW / "motive.csv").read_text())
    _cut_mid_row(raw)
    with pytest.raises(
        InputError,
        match=r"take\.csv: the file is cut short: its last row \(line 158\) has 2 of 14 cells, cut off "
        r"mid-row .* pass --allow-truncated to use the 150 complete frames",
    ):
        jsphere.read_motive_csv(raw)
    with pytest.warns(CaptureWarning, match=r"take\.csv: the file is cut short: .*; using the 150 complete frames"):
        data = jsphere.read_motive_csv(raw, allow_truncated=True)
    assert data.t.shape == (150,) and np.isfinite(data.markers).any(axis=(1, 2)).all()

    lines = (RAW / "motive.csv").read_text().splitlines()
    lines[0] = lines[0].replace("Rotation Type", "Total Frames in Take,151,Total Exported Frames,151,Rotation Type")
    raw.write_text("\n".join(lines) + "\n")
    assert jsphere.read_motive_csv(raw).t.shape == (151,)  # the declared count, no warning
    raw.write_text("\n".join(lines[:-87]) + "\n")  # whole rows lost: 64 of 151
    with pytest.raises(InputError, match=r"declares 151 frames \(Total Exported Frames\) but the file holds 64"):
        jsphere.read_motive_csv(raw)
    with pytest.warns(CaptureWarning, match=r"declares 151 frames .* holds 64; using the 64 complete frames"):
        tr = jsphere.convert_raw(
            raw, RAW / "inputs.csv", format="motive", options=jsphere.ConvertOptions(allow_truncated=True)
        )
    assert tr.n_frames == 64


def test_vicon_and_inputs_cut_mid_row(tmp_path):
    raw = tmp_path / "v.csv"
    raw.write_text((RAW / "vicon.csv").read_text())
    _cut_mid_row(raw, 9)
    with pytest.raises(InputError, match=r"v\.csv: the file is cut short: its last row \(line 156\) has 3 of 14 cells"):
        jsphere.read_vicon_csv(raw)
    with pytest.warns(CaptureWarning, match="using the 150 complete frames"):
        assert jsphere.read_vicon_csv(raw, allow_truncated=True).t.shape == (150,)
    # a section followed by another is not cut short, whatever its last row
    inputs = tmp_path / "in.csv"
    inputs.write_text((RAW / "inputs.csv").read_text())
    _cut_mid_row(inputs, 14)
    with pytest.raises(
        InputError, match=r"in\.csv: the file is cut short: its last row \(line 152\) has 2 of 4 cells.* complete rows"
    ):
        jsphere.read_inputs_csv(inputs)
    with pytest.raises(InputError, match=r"in\.csv: the file is cut short"):
        jsphere.convert_raw(RAW / "motive.csv", inputs, format="motive")
    with pytest.warns(CaptureWarning, match=r"in\.csv: the file is cut short"):
        t, u, _, _ = jsphere.read_inputs_csv(inputs, allow_truncated=True)
    assert t.shape == (150,)


def test_trial_cut_mid_row_says_so(tmp_path):
    p = tmp_path / "trial.csv"
    p.write_text((DATA / "ws_01.csv").read_text())
    _cut_mid_row(p, 20)
    with pytest.raises(
        ValueError, match=r"trial\.csv, line 506: 3 cells but the header has 10 columns \(the file looks cut off"
    ):
        jsphere.read_trial(p)


# --------------------------------------------------------------------------- C3D files


@pytest.fixture(scope="module")
def c3d_file(tmp_path_factory):
    """A C3D file of the example markers (151 frames, mm), written by ezc3d."""
    ezc3d = pytest.importorskip("ezc3d")
    data = jsphere.read_vicon_csv(RAW / "vicon.csv")
    M, K = data.markers.shape[:2]
    c = ezc3d.c3d()
    c["parameters"]["POINT"]["RATE"]["value"] = [100.0]
    c["parameters"]["POINT"]["LABELS"]["value"] = list(data.names)
    pts = np.ones((4, K, M))
    pts[:3] = np.transpose(np.nan_to_num(data.markers) * 1000.0, (2, 1, 0))
    c["data"]["points"] = pts
    c.add_parameter("POINT", "UNITS", ["mm"])
    path = tmp_path_factory.mktemp("c3d") / "take.c3d"
    c.write(str(path))
    return path, data


def test_c3d_cut_short_names_both_counts(tmp_path, c3d_file, capsys):
    full, data = c3d_file
    assert jsphere.read_c3d(full).t.shape == (151,)
    cut = tmp_path / "cut.c3d"
    cut.write_bytes(full.read_bytes()[: 1536 + 64 * 64 + 30])  # 64 whole frames of 4 float points
    with pytest.raises(
        InputError,
        match=r"cut\.c3d: the file is cut short: the header declares 151 frames but the file holds 64 "
        r".* --allow-truncated",
    ):
        jsphere.read_c3d(cut)
    with pytest.warns(CaptureWarning, match=r"declares 151 frames but the file holds 64; using the 64 frames present"):
        got = jsphere.read_c3d(cut, allow_truncated=True)
    np.testing.assert_allclose(got.markers, np.nan_to_num(data.markers[:64]), atol=1e-6)
    out = tmp_path / "t.csv"
    code, err = _cli(_convert_args(cut, out, "c3d"), capsys)
    assert code == 2 and "declares 151 frames but the file holds 64" in err and not out.exists()
    code, err = _cli(_convert_args(cut, out, "c3d", RAW / "inputs.csv", "--allow-truncated"), capsys)
    assert code == 0 and err.startswith("jsphere convert: warning: ") and "holds 64" in err, err
    assert jsphere.read_trial(out).n_frames == 64


class _MustNotRead:
    """An `ezc3d` stand-in that fails the test if the reader hands it the file."""

    def c3d(self, path):
        raise AssertionError(f"ezc3d was given {path}")


def _corrupt_parameter(raw: bytes) -> bytes:
    """`raw` with the dimension count of its first parameter record set to 200."""
    b = bytearray(raw)
    p0 = (b[0] - 1) * 512
    pos = p0 + 4
    while True:  # skip the groups (negative id) to the first parameter
        n, gid = abs(struct.unpack("b", b[pos : pos + 1])[0]), struct.unpack("b", b[pos + 1 : pos + 2])[0]
        at = pos + 2 + n
        if gid > 0:
            b[at + 3] = 200  # after the link (2 bytes) and the type (1 byte)
            return bytes(b)
        pos = at + struct.unpack("<h", b[at : at + 2])[0]


def test_broken_c3d_files_are_one_line_before_ezc3d_reads_them(tmp_path, c3d_file, monkeypatch, capsys):
    """Empty, random, cut inside the parameters (ezc3d hangs on it), corrupt parameters (ezc3d
    can crash on those): each an `InputError` naming the file, ezc3d never called."""
    full, _ = c3d_file
    good = full.read_bytes()
    cases = {
        "empty.c3d": (b"", r"the file is empty \(0 bytes\), not a C3D file"),
        "random.c3d": (np.random.default_rng(0).bytes(4096), r"not a C3D file \(its second byte is 0x"),
        "short.c3d": (good[:100], r"not a C3D file \(100 bytes, shorter than the 512-byte header\)"),
        "params_cut.c3d": (good[:789], r"cut short or corrupt: 789 bytes, but its parameters end at byte 1536"),
        "params_bad.c3d": (
            _corrupt_parameter(good),
            r"the C3D file is corrupt: parameter record \d+ \(type -?\d, 200 dimensions\)",
        ),
        "no_processor.c3d": (good[:515] + b"\x00" + good[516:], r"processor type 0, not 84, 85 or 86"),
    }
    monkeypatch.setitem(sys.modules, "ezc3d", _MustNotRead())
    for name, (content, msg) in cases.items():
        p = tmp_path / name
        p.write_bytes(content)
        with pytest.raises(InputError, match=rf"{name}: .*{msg}"):
            jsphere.read_c3d(p)
        code, err = _cli(_convert_args(p, tmp_path / "t.csv", "c3d"), capsys)
        assert code == 2 and err.count("\n") == 1 and name in err, err


def test_c3d_layout_counts_frames_of_either_storage(tmp_path):
    from test_capture import c3d_shell

    from jsphere.capture.c3d import c3d_layout

    p = tmp_path / "x.c3d"
    for integers in (False, True):
        p.write_bytes(c3d_shell(4, 30, 30, integers=integers))
        assert c3d_layout(p)["frames"] == 30 and c3d_layout(p)["frames_in_file"] == 30
        p.write_bytes(c3d_shell(4, 30, 50, integers=integers))
        assert (c3d_layout(p)["frames"], c3d_layout(p)["frames_in_file"]) == (50, 30)


def test_ezc3d_errors_become_one_line(tmp_path, monkeypatch):
    class Raises:
        def c3d(self, path):
            raise RuntimeError("Could not read the processor type")

    p = tmp_path / "x.c3d"
    from test_capture import c3d_shell  # a header the structure check accepts

    p.write_bytes(c3d_shell(4, 10))
    monkeypatch.setitem(sys.modules, "ezc3d", Raises())
    with pytest.raises(
        InputError, match=r"x\.c3d: not a readable C3D file \(ezc3d: Could not read the processor type\)"
    ):
        jsphere.read_c3d(p)


# --------------------------------------------------------------------------- encodings and separators


def test_bom_and_utf16_files_read_as_utf8(tmp_path, ws01):
    text = (DATA / "ws_01.csv").read_text()
    for name, content in (("bom.csv", codecs.BOM_UTF8 + text.encode()), ("u16.csv", text.encode("utf-16"))):
        (tmp_path / name).write_bytes(content)
        tr = jsphere.read_trial(tmp_path / name)
        np.testing.assert_array_equal(tr.x, ws01.x)
        assert tr.name == "ws_01"
    inputs = tmp_path / "in.csv"
    inputs.write_bytes(codecs.BOM_UTF8 + (RAW / "inputs.csv").read_bytes())
    np.testing.assert_array_equal(jsphere.read_inputs_csv(inputs)[1], jsphere.read_inputs_csv(RAW / "inputs.csv")[1])
    body = tmp_path / "body.csv"
    body.write_bytes(codecs.BOM_UTF8 + (RAW / "body_markers.csv").read_bytes())
    assert sorted(jsphere.read_body_markers(body)) == ["m1", "m2", "m3", "m4"]


def test_non_utf8_and_binary_files_name_the_file_and_line(tmp_path):
    latin = (DATA / "ws_01.csv").read_text().replace("# name: ws_01", "# name: ws_01, 21 \u00b0C")
    cases = [
        (jsphere.read_trial, "trial.csv", latin.encode("latin-1"), r"trial\.csv, line 2: not UTF-8 text \(byte 0xb0"),
        (
            jsphere.read_inputs_csv,
            "in.csv",
            b"# \xe9t\xe9\nt,K_1\n0,1\n1,1\n",
            r"in\.csv, line 1: not UTF-8 text .* save it as UTF-8",
        ),
        (jsphere.read_body_markers, "b.csv", b"name,x,y,z\nm\xfc,0,0,0\n", r"b\.csv, line 2: not UTF-8 text"),
        (
            jsphere.read_motive_csv,
            "m.csv",
            b"Format Version,1.23\n\x00\x01",
            r"m\.csv, line 2: a binary file, not CSV text",
        ),
    ]
    for fn, name, content, msg in cases:
        (tmp_path / name).write_bytes(content)
        with pytest.raises(InputError, match=msg):
            fn(tmp_path / name)


def test_semicolon_separated_files_say_so(tmp_path):
    p = tmp_path / "trial.csv"
    p.write_text((DATA / "ws_01.csv").read_text().replace(",", ";"))
    with pytest.raises(ValueError, match=r"missing required column\(s\) t, x, .*separated by semicolons, not commas"):
        jsphere.read_trial(p)
    p.write_text("t\tK_1\n0\t1\n")
    with pytest.raises(ValueError, match=r"missing required column t .*separated by tabs"):
        jsphere.read_inputs_csv(p)


def test_duplicated_columns_and_markers(tmp_path):
    p = tmp_path / "trial.csv"
    p.write_text(
        (DATA / "ws_01.csv")
        .read_text()
        .replace("t,x,y,qw,qx,qy,qz,chi_dot_1", "t,x,y,qw,qx,qy,qz,x,chi_dot_1", 1)
        .replace("\n0.000000,", "\n0.000000,0,", 1)
    )
    with pytest.raises(
        InputError, match=r"trial\.csv, line 5: column 'x' appears 2 times \(columns \[2, 8\]\); keep one"
    ):
        jsphere.read_trial(p)
    p.write_text("t,K_1,K_1\n0,1,2\n1,1,2\n")
    with pytest.raises(InputError, match=r"column 'K_1' appears 2 times"):
        jsphere.read_inputs_csv(p)
    p.write_text("name,x,y,z\na,0.05,0,0\nb,0,0.05,0\na,0,0,0.05\nc,0,0,0\n")
    with pytest.raises(InputError, match=r"trial\.csv, line 4: marker 'a' is listed twice"):
        jsphere.read_body_markers(p)


def test_raw_exports_separated_by_semicolons(tmp_path):
    for fmt, reader in (("motive", jsphere.read_motive_csv), ("vicon", jsphere.read_vicon_csv)):
        p = tmp_path / f"{fmt}.csv"
        p.write_text((RAW / f"{fmt}.csv").read_text().replace(",", ";"))
        with pytest.raises(ValueError, match=r"separated by semicolons, not commas"):
            reader(p)


def test_inputs_in_milliseconds_warn(tmp_path):
    t, u, kind, _ = jsphere.read_inputs_csv(RAW / "inputs.csv")
    with pytest.warns(CaptureWarning, match=r"the inputs table spans 1500 s .* are the inputs' times in milliseconds"):
        jsphere.convert_raw(RAW / "motive.csv", (t * 1000.0, u, kind), format="motive")
    long = np.arange(0.0, 600.0, 0.01)  # a long session logged at the capture's rate: no warning
    with _no_capture_warnings():
        jsphere.convert_raw(RAW / "motive.csv", (long, np.zeros((long.size, 3)), kind), format="motive")


# --------------------------------------------------------------------------- units of body markers, empty folders


def test_body_markers_in_millimetres(tmp_path):
    metres = jsphere.read_body_markers(RAW / "body_markers.csv")
    mm = "".join(f"{k},{v[0] * 1000:.3f},{v[1] * 1000:.3f},{v[2] * 1000:.3f}\n" for k, v in metres.items())
    p = tmp_path / "body.csv"
    p.write_text("name,x,y,z\n" + mm)
    with pytest.warns(CaptureWarning, match=r"body\.csv: the marker coordinates look like millimetres .* read as mm"):
        got = jsphere.read_body_markers(p)
    for k in metres:
        np.testing.assert_allclose(got[k], metres[k], atol=1e-9)
    p.write_text("# units: mm\nname,x,y,z\n" + mm)
    with _no_capture_warnings():
        got = jsphere.read_body_markers(p)
    np.testing.assert_allclose(got["m1"], metres["m1"], atol=1e-9)
    p.write_text("# units: m\nname,x,y,z\n" + mm)
    with pytest.raises(
        InputError,
        match=r"declared in 'm' but the markers lie up to 75\.47 from their centroid, which looks like millimetres",
    ):
        jsphere.read_body_markers(p)
    p.write_text("name,x,y,z\na,0,0,0\nb,3,0,0\nc,0,3,0\n")
    with pytest.raises(InputError, match=r"neither metres .* nor millimetres"):
        jsphere.read_body_markers(p)
    # an array in millimetres through the API: the distances disagree with the export's
    body_mm = np.stack([metres[k] for k in ("m1", "m2", "m3", "m4")]) * 1000.0
    with pytest.raises(
        InputError, match=r"1000 times as far apart as the markers in the export .* look like millimetres"
    ):
        jsphere.convert_raw(
            RAW / "motive.csv",
            RAW / "inputs.csv",
            format="motive",
            options=jsphere.ConvertOptions(body_markers=body_mm),
        )


def test_empty_trial_folder_says_so(tmp_path, capsys):
    (tmp_path / "notes.txt").write_text("no trials here\n")
    with pytest.raises(InputError, match=rf"{tmp_path} holds no trial CSV files \(\*\.csv\)"):
        jsphere.read_trials([tmp_path])
    code, err = _cli(["fit", tmp_path, "--free", "j", "--out", tmp_path / "fit.json", "--no-plots"], capsys)
    assert code == 2 and "holds no trial CSV files (*.csv)" in err


# --------------------------------------------------------------------------- plausibility


def test_example_data_raise_no_warning():
    with _no_capture_warnings():
        jsphere.read_trials([DATA])
        body = jsphere.read_body_markers(RAW / "body_markers.csv")
        for fmt in ("motive", "vicon"):
            jsphere.convert_raw(
                RAW / f"{fmt}.csv", RAW / "inputs.csv", format=fmt, options=jsphere.ConvertOptions(body_markers=body)
            )


def _rewrite(tmp_path, trial, name="trial.csv", *, units=True):
    text = trial_to_csv(trial)
    if not units:
        text = text.replace("# units: m\n", "")
    p = tmp_path / name
    p.write_text(text)
    return p


def test_centimetres_read_as_metres_warn(tmp_path, ws01):
    cm = ws01.replace(x=ws01.x * 100.0, y=ws01.y * 100.0)  # 12 "m" at most: not detected as millimetres
    p = _rewrite(tmp_path, cm, units=False)
    with pytest.warns(
        CaptureWarning,
        match=r"trial\.csv: the shell centre moves at 2\d\.\d m/s .*beyond any rolling robot .*"
        r"millimetres or centimetres read as metres",
    ):
        jsphere.read_trial(p)


def test_milliseconds_and_fast_turns_warn(tmp_path, ws01):
    with pytest.warns(
        CaptureWarning, match=r"the median time step is 10 s \(0\.1 Hz\): the times look like milliseconds"
    ):
        jsphere.read_trial(_rewrite(tmp_path, ws01.replace(t=ws01.t * 1000.0)))
    t = np.arange(501) * 1e-3  # a platform spinning at 60 rad/s, half a second at 1 kHz
    q = np.stack([np.cos(30.0 * t), 0 * t, 0 * t, np.sin(30.0 * t)], axis=1)
    spin = jsphere.Trial(t, 0 * t, 0 * t, q, np.ones((t.size, 3)), "wheel_speeds", name="spin")
    with pytest.warns(
        CaptureWarning, match=r"the platform turns at 60 rad/s .*beyond any rolling robot .*wrong frame rate"
    ):
        jsphere.read_trial(_rewrite(tmp_path, spin))


def test_xyzw_quaternion_order_warns(tmp_path, ws01):
    lines = trial_to_csv(ws01).splitlines()
    k = lines.index(next(ln for ln in lines if ln.startswith("t,")))
    for i in range(k + 1, len(lines)):
        c = lines[i].split(",")
        c[3:7] = c[4:7] + c[3:4]  # written x, y, z, w under the header qw, qx, qy, qz
        lines[i] = ",".join(c)
    p = tmp_path / "xyzw.csv"
    p.write_text("\n".join(lines) + "\n")
    with pytest.warns(
        CaptureWarning,
        match=r"xyzw\.csv: read as x, y, z, w the platform leans with the ball's acceleration .*"
        r"the quaternion columns look like x, y, z, w order; reorder them to qw, qx, qy, qz",
    ):
        jsphere.read_trial(p)


def test_xyzw_detection_at_any_heading(ws01):
    """The platform turned to other headings (the trial rotated about Z): the true order never
    warns; `x, y, z, w` is caught by the lean, the upside-down tilt or the rest pose."""
    from jsphere.model.rotations import quat_mul_np

    for deg in (0, 90, 180, 250):
        a = np.radians(deg)
        qz = np.array([np.cos(a / 2), 0.0, 0.0, np.sin(a / 2)])
        q = quat_mul_np(np.broadcast_to(qz, ws01.q.shape), ws01.q)
        x, y = np.cos(a) * ws01.x - np.sin(a) * ws01.y, np.sin(a) * ws01.x + np.cos(a) * ws01.y
        assert implausible(ws01.t, x, y, q) == [], deg
        assert [k for k, _ in implausible(ws01.t, x, y, q[:, [1, 2, 3, 0]])] == ["xyzw"], deg
    # at rest: no acceleration to judge by, the first pose decides
    n = 200
    t, z = np.arange(n) * 0.01, np.zeros(n)
    rest = np.tile([1.0, 0.0, 0.0, 0.0], (n, 1))
    assert implausible(t, z, z, rest) == []
    assert [k for k, _ in implausible(t, z, z, rest[:, [1, 2, 3, 0]])] == ["xyzw"]


def test_wrong_up_axis_warns(capsys, tmp_path):
    """Motive's Y-up export read as Z-up: with body markers the platform lies on its side;
    without, the shell centre's height follows the motion."""
    body = jsphere.read_body_markers(RAW / "body_markers.csv")
    with pytest.warns(
        CaptureWarning, match=r"motive\.csv: the platform tilts 9\d deg from upright .*is the export's up axis right"
    ):
        jsphere.convert_raw(
            RAW / "motive.csv",
            RAW / "inputs.csv",
            format="motive",
            options=jsphere.ConvertOptions(up_axis="z", body_markers=body),
        )
    with pytest.warns(
        CaptureWarning, match=r"the shell centre's height z varies by 3\.\d+ cm while it moves 7\.\d+ cm horizontally"
    ):
        jsphere.convert_raw(
            RAW / "motive.csv", RAW / "inputs.csv", format="motive", options=jsphere.ConvertOptions(up_axis="z")
        )
    code, err = _cli(
        _convert_args(RAW / "motive.csv", tmp_path / "t.csv", "motive", RAW / "inputs.csv", "--up-axis", "z"), capsys
    )
    assert code == 0 and err.startswith("jsphere convert: warning: ") and "--up-axis" in err, err


def test_convert_prints_warnings_as_one_line_each(tmp_path, capsys):
    body = tmp_path / "body.csv"
    metres = jsphere.read_body_markers(RAW / "body_markers.csv")
    body.write_text(
        "name,x,y,z\n" + "".join(f"{k},{v[0] * 1e3:.3f},{v[1] * 1e3:.3f},{v[2] * 1e3:.3f}\n" for k, v in metres.items())
    )
    out = tmp_path / "t.csv"
    code, err = _cli(
        _convert_args(RAW / "motive.csv", out, "motive", RAW / "inputs.csv", "--body-markers", body), capsys
    )
    assert (
        code == 0 and err.count("\n") == 1 and err.startswith("jsphere convert: warning: ") and "millimetres" in err
    ), err
    assert jsphere.read_trial(out).valid.mean() > 0.95
