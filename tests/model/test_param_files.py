"""Parameter files: TOML/JSON round trips, error messages, atomic writes, `from_dict` aliases."""

from __future__ import annotations

import dataclasses
import json
import os
import re
from pathlib import Path

import numpy as np
import pytest

import jsphere._runtime.files as jio
from jsphere import RobotParams
from jsphere._runtime.errors import InputError

FIELDS = tuple(f.name for f in dataclasses.fields(RobotParams))  # the class's own, in order
REFERENCE = Path(
    os.environ.get(
        "JSPHERE_REFERENCE", Path(__file__).resolve().parents[3] / "shared" / "reference" / "reference_cases.json"
    )
)


@pytest.fixture(scope="module")
def paper():
    return RobotParams.paper()


@pytest.fixture(scope="module")
def other():
    """A non-default parameter set (all fields differ from their defaults somewhere)."""
    return RobotParams.paper(R_m=0.0313, j=1.234567890123e-4, g=9.80665).replace(
        m=2.7182818284590451, I=[[0.0161, 0.0002, 0.0], [0.0002, 0.0159, 0.0], [0.0, 0.0, 0.0233]]
    )


def _assert_same(a: RobotParams, b: RobotParams):
    for f in FIELDS:
        x, y = np.asarray(getattr(a, f)), np.asarray(getattr(b, f))
        assert x.shape == y.shape, f
        np.testing.assert_array_equal(x, y, err_msg=f)  # bit-exact: floats are written with repr


def _files(d: Path):
    return sorted(p.name for p in d.iterdir())


def _write_json(path: Path, d):
    path.write_text(json.dumps(d))
    return path


# --------------------------------------------------------------------- round trips


@pytest.mark.parametrize("name", ["p.toml", "p.json", "P.TOML", "P.Json"])
@pytest.mark.parametrize("which", ["paper", "other"])
def test_round_trip(tmp_path, request, name, which):
    p = request.getfixturevalue(which)
    path = tmp_path / name
    p.save(path)
    q = RobotParams.load(path)
    _assert_same(p, q)
    assert q.R0.dtype == np.float64
    assert _files(tmp_path) == [name]


def test_round_trip_accepts_str_paths_and_creates_parents(tmp_path, paper):
    path = tmp_path / "a" / "b" / "params.toml"
    paper.save(str(path))
    _assert_same(paper, RobotParams.load(str(path)))


def test_toml_file_is_readable_toml(tmp_path, paper):
    import tomllib

    path = tmp_path / "p.toml"
    paper.save(path)
    text = path.read_text()
    assert text.startswith("#")  # header comment
    d = tomllib.loads(text)
    assert sorted(d) == sorted(FIELDS)
    assert d["R0"] == 0.15 and d["I"][2][2] == 0.023


def test_json_file_is_plain_json(tmp_path, paper):
    path = tmp_path / "p.json"
    paper.save(path)
    d = json.loads(path.read_text())
    assert sorted(d) == sorted(FIELDS)
    assert d == paper.to_dict()


def test_save_overwrites(tmp_path, paper, other):
    path = tmp_path / "p.json"
    paper.save(path)
    other.save(path)
    _assert_same(other, RobotParams.load(path))
    assert _files(tmp_path) == ["p.json"]


def test_to_dict_from_dict_round_trip(paper, other):
    for p in (paper, other):
        d = p.to_dict()
        json.dumps(d)  # plain Python values
        _assert_same(p, RobotParams.from_dict(d))


# ------------------------------------------------------------------------ errors


@pytest.mark.parametrize("name", ["p.yaml", "p.txt", "p"])
def test_save_bad_suffix(tmp_path, paper, name):
    path = tmp_path / name
    with pytest.raises(ValueError, match=r"\.toml or \.json") as ei:
        paper.save(path)
    assert name in str(ei.value)
    assert _files(tmp_path) == []  # nothing written, no temp file


def test_load_bad_suffix(tmp_path, paper):
    path = tmp_path / "p.yaml"
    path.write_text(json.dumps(paper.to_dict()))
    with pytest.raises(ValueError, match=r"\.toml or \.json") as ei:
        RobotParams.load(path)
    assert "p.yaml" in str(ei.value)


def test_load_missing_file(tmp_path):
    with pytest.raises(FileNotFoundError, match="nope.toml"):
        RobotParams.load(tmp_path / "nope.toml")


@pytest.mark.parametrize("suffix", [".json", ".toml"])
@pytest.mark.parametrize("field", ["m", "wheel_alpha", "R0"])
def test_load_missing_field(tmp_path, paper, suffix, field):
    d = paper.to_dict()
    del d[field]
    path = tmp_path / f"params{suffix}"
    path.write_text(json.dumps(d) if suffix == ".json" else jio.dumps_toml(d))
    with pytest.raises(InputError, match="missing required key") as ei:
        RobotParams.load(path)
    msg = str(ei.value)
    assert str(path) in msg
    assert f"'{field}'" in msg  # names exactly the missing field


def test_load_without_j_and_g_uses_defaults_and_says_so_once(tmp_path, paper, caplog):
    d = paper.to_dict()
    del d["j"], d["g"]
    path = _write_json(tmp_path / "p.json", d)
    with caplog.at_level("WARNING", logger="jsphere"):
        q = RobotParams.load(path)
        RobotParams.load(path)  # the same file again: no second line
    assert float(q.j) == 0.0
    assert float(q.g) == 9.81
    assert float(q.k_tau) == 1.0
    lines = [r.getMessage() for r in caplog.records]
    assert len(lines) == 1
    assert str(path) in lines[0] and "leaves out j, g" in lines[0]
    assert "j = 0 kg m^2" in lines[0] and "g = 9.81" in lines[0]


def test_load_complete_file_says_nothing(tmp_path, paper, caplog):
    with caplog.at_level("WARNING", logger="jsphere"):
        RobotParams.load(_write_json(tmp_path / "p.json", paper.to_dict()))
    assert caplog.records == []


def test_example_robot_loads_cleanly(caplog):
    path = Path(__file__).resolve().parents[2] / "examples" / "robot.toml"
    with caplog.at_level("WARNING", logger="jsphere"):
        p = RobotParams.load(path)
    assert caplog.records == []
    for f in FIELDS:  # the paper's robot, to the digits written
        np.testing.assert_allclose(
            np.asarray(getattr(p, f)), np.asarray(getattr(RobotParams.paper(), f)), rtol=1e-12, atol=1e-15
        )


def _fit_doc(p, values):
    return {"params": p.to_dict(), "free": list(values), "values": values}


def test_fit_result_copies_agree_within_rounding(tmp_path, paper):
    vals = {"j": float(paper.j) * (1 + 1e-12), "I": np.asarray(paper.I).tolist(), "R_m": float(paper.R_m)}
    vals["I"][0][1] = None  # an entry a whole free field does not hold (NaN in the fit, null in JSON)
    _assert_same(paper, RobotParams.load(_write_json(tmp_path / "fit.json", _fit_doc(paper, vals))))


@pytest.mark.parametrize(
    ("name", "value", "shown"), [("j", 3e-4, "values['j'] = 0.0003"), ("I", "edit", "values['I'][2,2] = 0.03")]
)
def test_fit_result_copies_that_disagree_are_refused(tmp_path, paper, name, value, shown):
    if value == "edit":
        value = np.asarray(paper.I).tolist()
        value[2][2] = 0.03
    path = _write_json(tmp_path / "fit.json", _fit_doc(paper, {name: value}))
    with pytest.raises(InputError, match=re.escape(shown)) as ei:
        RobotParams.load(path)
    assert str(path) in str(ei.value) and "params" in str(ei.value)


@pytest.mark.parametrize("suffix", [".json", ".toml"])
def test_load_unknown_field(tmp_path, paper, suffix):
    d = paper.to_dict()
    d["mass_of_platform"] = 2.5
    path = tmp_path / f"params{suffix}"
    path.write_text(json.dumps(d) if suffix == ".json" else jio.dumps_toml(d))
    with pytest.raises(ValueError, match="unknown") as ei:
        RobotParams.load(path)
    msg = str(ei.value)
    assert str(path) in msg
    assert "mass_of_platform" in msg


def test_load_invalid_value_names_field_and_file(tmp_path, paper):
    d = paper.to_dict()
    d["m0"] = -0.8
    path = _write_json(tmp_path / "bad.json", d)
    with pytest.raises(ValueError, match=r"RobotParams\.m0:") as ei:
        RobotParams.load(path)
    assert str(path) in str(ei.value)


def test_load_lengths_in_millimetres(tmp_path, paper):
    d = paper.to_dict()
    d["R0"] = 150.0
    path = _write_json(tmp_path / "mm.json", d)
    with pytest.raises(ValueError, match=r"RobotParams\.R0:.*millimetres"):
        RobotParams.load(path)


def test_load_malformed_toml_names_file(tmp_path):
    path = tmp_path / "broken.toml"
    path.write_text("R0 = [\n")
    with pytest.raises(ValueError, match=re.escape(str(path))):
        RobotParams.load(path)


def test_load_json_not_an_object(tmp_path):
    path = _write_json(tmp_path / "list.json", [1, 2, 3])
    with pytest.raises(ValueError, match=re.escape(str(path))):
        RobotParams.load(path)


# --------------------------------------------------------------- fit-result files


def test_load_fit_result_json(tmp_path, other):
    path = _write_json(tmp_path / "fit.json", {"params": other.to_dict(), "loss": 1.5e-7, "iterations": 40})
    _assert_same(other, RobotParams.load(path))


def test_load_fit_result_with_invalid_params_names_field(tmp_path, paper):
    d = paper.to_dict()
    del d["I"]
    path = _write_json(tmp_path / "fit.json", {"params": d, "loss": 0.0})
    with pytest.raises(InputError, match=r"missing required key 'I'") as ei:
        RobotParams.load(path)
    assert str(path) in str(ei.value)


# ---------------------------------------------------------------- atomic writes


def test_atomic_write_leaves_no_temp_files(tmp_path, paper):
    for name in ("a.toml", "b.json", "a.toml"):
        paper.save(tmp_path / name)
    assert _files(tmp_path) == ["a.toml", "b.json"]
    assert not any(n.endswith(".tmp") or n.startswith(".") for n in os.listdir(tmp_path))


def test_atomic_write_failure_keeps_old_file_and_cleans_up(tmp_path, monkeypatch, paper, other):
    path = tmp_path / "p.toml"
    paper.save(path)
    before = path.read_text()

    def boom(src, dst):
        raise OSError("disk full (simulated)")

    monkeypatch.setattr(jio.os, "replace", boom)
    with pytest.raises(OSError, match="simulated"):
        other.save(path)
    monkeypatch.undo()
    assert path.read_text() == before  # the old file is intact
    assert _files(tmp_path) == ["p.toml"]  # the temporary file was removed
    _assert_same(paper, RobotParams.load(path))


def test_atomic_write_text(tmp_path):
    path = tmp_path / "sub" / "x.txt"
    jio.atomic_write_text(path, "hello\n")
    jio.atomic_write_text(path, "world\n")
    assert path.read_text() == "world\n"
    assert _files(path.parent) == ["x.txt"]


def test_atomic_writes_get_the_usual_permissions(tmp_path):
    # mkstemp creates 0o600; a written file must get what open(path, "w") would give it
    text, binary = tmp_path / "a.json", tmp_path / "b.npz"
    jio.atomic_write_text(text, "{}\n")
    jio.atomic_write(binary, lambda tmp: np.savez(tmp, x=np.arange(3)))
    plain = tmp_path / "plain.txt"
    plain.write_text("x")
    for path in (text, binary):
        assert path.stat().st_mode & 0o777 == plain.stat().st_mode & 0o777, path
    os.chmod(text, 0o640)  # a file that exists keeps its mode
    jio.atomic_write_text(text, "[]\n")
    assert text.stat().st_mode & 0o777 == 0o640 and text.read_text() == "[]\n"
    assert _files(tmp_path) == ["a.json", "b.npz", "plain.txt"]


def test_read_trials_skips_hidden_temporary_files(tmp_path):
    from jsphere import read_trials, write_trial
    from jsphere.capture.trial import Trial

    t = np.linspace(0.0, 1.0, 11)
    trial = Trial(t, 0.01 * t, 0.0 * t, np.tile([1.0, 0.0, 0.0, 0.0], (11, 1)), np.zeros((11, 3)), "torques", name="a")
    write_trial(tmp_path / "a.csv", trial)
    (tmp_path / ".a.k2j3.csv").write_text("half a file")  # what a killed writer might leave
    [got] = read_trials([tmp_path])
    np.testing.assert_allclose(got.x, trial.x)


# ------------------------------------------------------------------ aliases


def test_from_dict_aliases(paper):
    d = paper.to_dict()
    d["r"], d["n"], d["alpha"] = d.pop("wheel_r"), d.pop("wheel_n"), d.pop("wheel_alpha")
    _assert_same(paper, RobotParams.from_dict(d))


def test_from_dict_alias_and_field_together_is_rejected(paper):
    d = paper.to_dict()
    d["r"] = d["wheel_r"]
    with pytest.raises(InputError, match=r"unknown key 'r'"):
        RobotParams.from_dict(d)


def test_load_aliases_from_file(tmp_path, paper):
    d = paper.to_dict()
    d["r"], d["n"], d["alpha"] = d.pop("wheel_r"), d.pop("wheel_n"), d.pop("wheel_alpha")
    _assert_same(paper, RobotParams.load(_write_json(tmp_path / "alias.json", d)))


@pytest.fixture(scope="module")
def reference_param_sets():
    if not REFERENCE.exists():
        pytest.skip(f"reference file {REFERENCE} not present")
    return json.loads(REFERENCE.read_text())["param_sets"]


def test_reference_param_sets_use_aliases(reference_param_sets):
    for name, d in reference_param_sets.items():
        assert {"r", "n", "alpha"} <= set(d), name
        p = RobotParams.from_dict(d)
        assert p.n_wheels == 3
        np.testing.assert_array_equal(np.asarray(p.wheel_r), np.asarray(d["r"]))
        np.testing.assert_array_equal(np.asarray(p.wheel_n), np.asarray(d["n"]))
        np.testing.assert_array_equal(np.asarray(p.wheel_alpha), np.asarray(d["alpha"]))


def test_reference_param_sets_match_paper(reference_param_sets):
    p1 = RobotParams.from_dict(reference_param_sets["P1_fit"])
    ref1 = RobotParams.paper()
    p0 = RobotParams.from_dict(reference_param_sets["P0_j0"])
    ref0 = RobotParams.paper(R_m=float(p0.R_m), j=0.0)
    assert float(p0.R_m) == pytest.approx(26.8727e-3, abs=1e-7)
    for p, ref in ((p1, ref1), (p0, ref0)):
        for f in FIELDS:
            np.testing.assert_allclose(
                np.asarray(getattr(p, f)), np.asarray(getattr(ref, f)), rtol=1e-14, atol=1e-16, err_msg=f
            )


def test_json_is_strict():
    """Every JSON jsphere writes parses with a parser that refuses NaN and infinities: a
    non-finite value is written as null."""
    import json
    import math

    import numpy as np

    from jsphere._runtime.files import dumps_json

    def strict(text):
        return json.loads(text, parse_constant=lambda c: (_ for _ in ()).throw(ValueError(c)))

    obj = {
        "a": float("nan"),
        "b": [1.0, float("inf"), -math.inf],
        "c": np.array([np.nan, 2.0]),
        "d": np.float64("nan"),
        "e": 3,
    }
    assert strict(dumps_json(obj)) == {"a": None, "b": [1.0, None, None], "c": [None, 2.0], "d": None, "e": 3}
    with pytest.raises(ValueError):
        strict(json.dumps(obj["a"]))  # the check itself: Python's default output is refused
