"""The lab's loop: a plan's commands for the robot, the inputs table that reads them back, the
clock offset between capture and inputs (quick estimate and fitted), and `compare` on held-out
trials; the worked example end to end (slow)."""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import jsphere
from jsphere._runtime.errors import ExitCode, InputError
from jsphere.capture.synthetic import default_marker_set
from jsphere.cli.app import main
from jsphere.identify.compare import _ccf, _fit_percent, _norms
from jsphere.identify.whiteness import Z99
from jsphere.identify.whiteness import autocorrelation as _acf

ROOT = Path(__file__).resolve().parents[2]
RAW = ROOT / "examples" / "data" / "raw"
TRUTH = jsphere.RobotParams.paper().replace(R_m=0.029, j=3.2e-4)


def _shifted_trial(params, seed: int, offset: float, t1: float = 4.0, name: str | None = None) -> jsphere.Trial:
    """A wheel-speed trial of `t1` seconds whose capture clock runs `offset` behind its inputs'
    (capture frame `k` at stamp `t_k` shows the robot at `t_k + offset`); 2% dropped frames."""
    c = jsphere.random_inputs(params, t1 + 1.0, seed=seed)
    tr = jsphere.synthetic_trial(params, c, t1 + 1.0, seed=seed, dropout=0.02, name=name or f"trial_{seed}")
    k0, m = int(round(offset * 100)), int(round(t1 * 100)) + 1
    return jsphere.Trial(
        tr.t[:m], tr.x[k0 : k0 + m], tr.y[k0 : k0 + m], tr.q[k0 : k0 + m], tr.inputs[:m], tr.kind, name=tr.name
    )


# ----------------------------------------------------------------------------- inputs tables


def _plan_like_csv(path: Path) -> None:
    """A table with both input families and other columns, as `Plan.to_csv` writes."""
    t = np.arange(6) * 0.1
    cols = {"t": t}
    cols |= {f"K_{i + 1}": 0.01 * (i + 1) * t for i in range(3)}
    cols |= {f"chi_dot_{i + 1}": -(i + 1) * t for i in range(3)}
    cols |= {"x": t, "y": 0 * t}
    path.write_text(
        ",".join(cols) + "\n" + "".join(",".join(repr(float(v)) for v in row) + "\n" for row in zip(*cols.values()))
    )


def test_read_inputs_csv_chooses_the_family_of_a_plan_csv(tmp_path):
    p = tmp_path / "plan.csv"
    _plan_like_csv(p)
    with pytest.raises(ValueError, match="--input-kind chi_dot or --input-kind K"):
        jsphere.read_inputs_csv(p)
    t, u, kind, names = jsphere.read_inputs_csv(p, kind="K")
    assert kind == "torques" and names == ["K_1", "K_2", "K_3"]
    np.testing.assert_allclose(u[:, 2], 0.03 * t)
    t, u, kind, names = jsphere.read_inputs_csv(p, kind="chi_dot")
    assert kind == "wheel_speeds" and names == ["chi_dot_1", "chi_dot_2", "chi_dot_3"]
    np.testing.assert_allclose(u[:, 1], -2 * t)
    assert jsphere.read_inputs_csv(p, kind="wheel_speeds")[2] == "wheel_speeds"
    with pytest.raises(InputError, match="'chi_dot'"):
        jsphere.read_inputs_csv(p, kind="velocity")
    only = tmp_path / "ws.csv"
    jsphere.write_inputs_csv(only, t, u, "wheel_speeds")
    assert jsphere.read_inputs_csv(only, kind="chi_dot")[2] == "wheel_speeds"
    with pytest.raises(ValueError, match="no K_1..N columns"):
        jsphere.read_inputs_csv(only, kind="K")


def test_convert_reads_a_plan_csv_with_input_kind_and_estimates_the_clock_offset(tmp_path, capsys):
    """`jsphere convert --inputs PLAN.csv --input-kind chi_dot` reads the wheel speeds of a table
    with both families; without `--input-kind` it is bad input naming the option;
    `--time-offset auto` prints its estimate (the raw export shares the inputs' clock)."""
    t, u, _, _ = jsphere.read_inputs_csv(RAW / "inputs.csv")
    both = tmp_path / "plan.csv"
    cols = ["t", *(f"K_{i + 1}" for i in range(3)), *(f"chi_dot_{i + 1}" for i in range(3))]
    rows = np.column_stack([t, 0.5 * u, u])
    both.write_text(",".join(cols) + "\n" + "".join(",".join(repr(float(v)) for v in r) + "\n" for r in rows))
    common = ["convert", str(RAW / "motive.csv"), "--format", "motive", "--units", "mm"]
    common += ["--body-markers", str(RAW / "body_markers.csv"), "--inputs", str(both)]
    assert main([*common, "--out", str(tmp_path / "bad.csv")]) == ExitCode.BAD_INPUT
    assert "--input-kind chi_dot or --input-kind K" in capsys.readouterr().err
    assert main([*common, "--input-kind", "chi_dot", "--out", str(tmp_path / "a.csv")]) == 0
    tr = jsphere.read_trial(tmp_path / "a.csv")
    assert tr.kind == "wheel_speeds"
    np.testing.assert_allclose(tr.inputs, np.stack([np.interp(tr.t, t, u[:, i]) for i in range(3)], 1), atol=1e-9)
    capsys.readouterr()
    out = tmp_path / "b.csv"
    assert main([*common, "--input-kind", "chi_dot", "--time-offset", "auto", "--out", str(out)]) == 0
    line = next(ln for ln in capsys.readouterr().out.splitlines() if "time offset estimated" in ln)
    est = float(line.split("estimated:")[1].split()[0])
    assert abs(est) < 0.02, line
    assert main([*common, "--input-kind", "chi_dot", "--time-offset", "soon", "--out", str(tmp_path / "c.csv")]) == 2
    assert "'auto'" in capsys.readouterr().err


def test_the_commands_options_exist(capsys):
    for command, options in (
        ("plan", ("--commands", "--command-kind", "--rate")),
        ("fit", ("--fit-time-offset", "--max-time-offset")),
        ("compare", ("--params", "--out")),
        ("convert", ("--input-kind", "--time-offset")),
    ):
        with pytest.raises(SystemExit):
            main([command, "--help"])
        text = capsys.readouterr().out
        for o in options:
            assert o in text, (command, o)


# ----------------------------------------------------------------------------- clock offsets


@pytest.mark.parametrize("offset", [0.15, -0.08])
def test_quick_estimate_of_the_clock_offset(offset):
    """The capture clock 0.15 s behind the inputs' (frames shifted), or 0.08 s ahead (the
    inputs' stamps shifted): the estimate is within 5 ms."""
    tr = _shifted_trial(TRUTH, 3, max(offset, 0.0))
    t_in = tr.t + min(offset, 0.0)  # inputs stamped `offset` earlier than the capture's clock
    est, corr = jsphere.estimate_time_offset(
        tr.t, tr.x, tr.y, tr.q, t_in, tr.inputs, tr.kind, jsphere.RobotParams.paper()
    )
    assert abs(est - offset) < 0.005, (est, offset)
    assert corr > 0.9
    with pytest.raises(InputError, match="wheel-speed"):
        jsphere.estimate_time_offset(tr.t, tr.x, tr.y, tr.q, t_in, tr.inputs, "torques")
    with pytest.raises(InputError, match="max_offset"):
        jsphere.estimate_time_offset(tr.t, tr.x, tr.y, tr.q, t_in, tr.inputs, tr.kind, max_offset=0.0)


def test_fit_refuses_a_bad_max_time_offset():
    tr = _shifted_trial(TRUTH, 3, 0.0, t1=1.0)
    with pytest.raises(InputError, match="max_time_offset"):
        jsphere.fit([tr], TRUTH, "R_m", fit_time_offset=True, max_time_offset=-1.0)


# ----------------------------------------------------------------------------- the scores


def test_fit_percent_and_correlations_of_known_series():
    rng = np.random.default_rng(0)
    y = np.sin(np.linspace(0, 6, 500))
    assert _fit_percent(_norms(np.zeros(500), y)) == 100.0
    assert math.isclose(_fit_percent(_norms(y - y.mean(), y)), 0.0, abs_tol=1e-12)
    white, w = rng.normal(size=2000), np.ones(2000, bool)
    band = Z99 / math.sqrt(2000)
    assert np.mean(np.abs(_acf(white, w, 25)[1:]) > band) < 0.1
    walk = np.cumsum(white)
    assert np.all(np.abs(_acf(walk, w, 25)[1:]) > band)
    w[100:130] = False  # a gap leaves the white series white
    assert np.mean(np.abs(_acf(np.where(w, white, 1e3), w, 25)[1:]) > band) < 0.1
    ccf = _ccf(white, np.ones(2000, bool), np.roll(white, 3), 5)  # e(t) against u(t - k): peak at k = -3
    assert int(np.argmax(ccf)) == 5 - 3 and ccf.max() > 0.99


# ----------------------------------------------------------------------------- slow


@pytest.mark.slow
def test_compare_scores_true_parameters_high_and_a_wrong_R_m_lower(tmp_path, capsys):
    """Held-out trials of a robot: `compare` with its true parameters gives > 95 % on x and y
    and white residuals (verdict "consistent"); with R_m 5 % off it is visibly lower and a model
    error. The CLI writes compare.json with the documented keys and a figure per trial, exit
    code 0 for the right model."""
    held = [
        jsphere.synthetic_trial(
            TRUTH, jsphere.random_inputs(TRUTH, 4.0, seed=s), 4.0, seed=s, dropout=0.02, name=f"held_{s}"
        )
        for s in (7, 8)
    ]
    right = jsphere.compare(TRUTH, held)
    wrong = jsphere.compare(TRUTH.replace(R_m=TRUTH.R_m * 1.05), held)
    for t in right.trials:
        assert t["fit_percent"]["x"] > 95 and t["fit_percent"]["y"] > 95, t["fit_percent"]
        assert t["whiteness"]["acf_outside_99"] < 0.1
    r, w = right.overall["fit_percent"], wrong.overall["fit_percent"]
    assert min(r["x"], r["y"]) > 95
    assert min(w["x"], w["y"]) < min(r["x"], r["y"]) - 3, (r, w)
    assert wrong.overall["whiteness"]["acf_outside_99"] > 0.3
    assert right.verdict == "consistent" and wrong.verdict == "model error", (right.reason, wrong.reason)
    # the predicted trials hold the simulated path
    s = right.trials[0]["series"]
    np.testing.assert_allclose(right.predicted[0].x, s["x_sim"])
    # the CLI
    for tr in held:
        jsphere.write_trial(tmp_path / f"{tr.name}.csv", tr)
    TRUTH.save(tmp_path / "truth.toml")
    out = tmp_path / "cmp" / "compare.json"
    rc = main(
        [
            "compare",
            str(tmp_path / "held_7.csv"),
            str(tmp_path / "held_8.csv"),
            "--params",
            str(tmp_path / "truth.toml"),
            "--out",
            str(out),
        ]
    )
    assert rc == 0
    doc = json.loads(out.read_text())
    assert [t["name"] for t in doc["trials"]] == ["held_7", "held_8"]
    for t in [*doc["trials"], doc["overall"]]:
        assert set(t["fit_percent"]) == {"x", "y", "rot"} and "acf_outside_99" in t["whiteness"]
    assert doc["overall"]["name"] == "overall" and doc["verdict"] == "consistent"
    assert (out.parent / "compare_held_7.png").stat().st_size > 10_000
    assert "overall" in capsys.readouterr().out


@pytest.mark.slow
def test_fit_recovers_a_clock_offset_and_the_parameters(tmp_path):
    """A trial whose capture clock runs 0.15 s behind its inputs (and one without an offset),
    fitted with `fit_time_offset=True` from the paper's values: the offsets come back within
    5 ms, R_m and j within 3 standard errors; fit.json lists them in trial order; `predict`
    runs the fitted model on a held-out trial."""
    trials = [_shifted_trial(TRUTH, 0, 0.15), _shifted_trial(TRUTH, 1, 0.0)]
    res = jsphere.fit(trials, jsphere.RobotParams.paper(), "R_m,j", fit_time_offset=True, progress=False)
    assert abs(res.time_offset[0] - 0.15) < 0.005 and abs(res.time_offset[1]) < 0.005, res.time_offset
    assert all(0 < s < 0.005 for s in res.time_offset_stderr)
    for name in ("R_m", "j"):
        err = (res.values[name] - float(getattr(TRUTH, name))) / res.stderr[name]
        assert abs(err) < 3, (name, res.values[name], res.stderr[name])
    doc = res.to_json()
    assert doc["time_offset"] == pytest.approx(res.time_offset) and len(doc["time_offset_stderr"]) == 2
    assert res.trials[0]["nuisance"]["time_offset"] == pytest.approx(res.time_offset[0])
    held = jsphere.synthetic_trial(TRUTH, jsphere.random_inputs(TRUTH, 3.0, seed=9), 3.0, seed=9, name="held")
    pred = res.predict([held])
    assert pred.trials[0]["fit_percent"]["x"] > 95
    assert pred.predicted[0].name == "held_predicted"


@pytest.mark.slow
def test_plan_commands_convert_chain(tmp_path):
    """`jsphere plan --commands` writes the table that `jsphere convert --inputs` reads, and the
    plan's own CSV serves as well with `--input-kind`: no file is edited on the way."""
    cmd, plan_csv = tmp_path / "commands.csv", tmp_path / "plan.csv"
    args = ["plan", "--to", "0.2", "0", "--rate", "100", "--restarts", "2", "--max-time", "5", "--no-plots"]
    assert main([*args, "--commands", str(cmd), "--command-kind", "chi_dot", "--out", str(plan_csv)]) == 0
    t, u, kind, names = jsphere.read_inputs_csv(cmd)
    assert kind == "wheel_speeds" and names == ["chi_dot_1", "chi_dot_2", "chi_dot_3"]
    assert np.allclose(np.diff(t)[:-1], 0.01)
    tp, up, _, _ = jsphere.read_inputs_csv(plan_csv, kind="chi_dot")
    # the rows before the end agree; the end is rest, exactly 0 in both (the commands' last time
    # is written to the microsecond, where a direct plan's wheel speeds still change by ~1e-7)
    np.testing.assert_allclose(np.stack([np.interp(t[:-1], tp, up[:, i]) for i in range(3)], 1), u[:-1], atol=1e-7)
    assert np.all(u[-1] == 0.0) and np.all(up[-1] == 0.0) and abs(t[-1] - tp[-1]) <= 5e-7
    # the robot runs the commands; the capture sees it
    p = jsphere.RobotParams.paper()
    traj = jsphere.simulate(p, jsphere.State.at_rest(p), jsphere.WheelSpeeds.from_samples(t, u), float(t[-1]), ts=t)
    tr = jsphere.Trial(t, np.asarray(traj.x), np.asarray(traj.y), np.asarray(traj.q), u, kind)
    markers = jsphere.synthetic_markers(tr, default_marker_set(float(p.R0)), z=float(p.R0), seed=1)
    jsphere.write_motive_csv(tmp_path / "capture.csv", t, markers, ["m1", "m2", "m3", "m4"], units="mm")
    body = tmp_path / "body.csv"
    body.write_text(
        "name,x,y,z\n"
        + "".join(f"m{k + 1},{b[0]},{b[1]},{b[2]}\n" for k, b in enumerate(default_marker_set(float(p.R0))))
    )
    for inputs, extra in ((cmd, []), (plan_csv, ["--input-kind", "chi_dot"])):
        out = tmp_path / f"trial_{inputs.stem}.csv"
        rc = main(
            [
                "convert",
                str(tmp_path / "capture.csv"),
                "--format",
                "motive",
                "--inputs",
                str(inputs),
                *extra,
                "--body-markers",
                str(body),
                "--out",
                str(out),
            ]
        )
        assert rc == 0
        got = jsphere.read_trial(out)
        np.testing.assert_allclose(got.inputs, np.stack([np.interp(got.t, t, u[:, i]) for i in range(3)], 1), atol=1e-6)
        np.testing.assert_allclose(got.x[got.valid], np.interp(got.t, t, tr.x)[got.valid], atol=2e-3)
    tk, uk = jsphere.read_inputs_csv(plan_csv, kind="K")[:2]
    assert uk.shape == (len(tk), 3)


@pytest.mark.slow
def test_the_lab_loop_lands_closer_the_second_time(tmp_path):
    """examples/lab_loop.py end to end: the plan made with the fitted robot stops closer to its
    target than the plan made with the starting model; convert's estimate of the clock offset
    and what the fit finds left over add up to the truth."""
    env = {k: v for k, v in os.environ.items() if k != "JAX_ENABLE_X64"}
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT), env.get("PYTHONPATH", "")])
    env["MPLBACKEND"] = "Agg"
    run = subprocess.run(
        [sys.executable, str(ROOT / "examples" / "lab_loop.py"), "--out", str(tmp_path / "loop")],
        capture_output=True,
        text=True,
        env=env,
        timeout=3000,
    )
    assert run.returncode == 0, run.stdout[-3000:] + run.stderr[-3000:]
    assert "PrecisionWarning" not in run.stderr, run.stderr[-2000:]  # as every example (tests/project/test_docs.py)
    s = json.loads((tmp_path / "loop" / "loop.json").read_text())
    assert s["second_plan_miss_m"] < s["first_plan_miss_m"], s
    total = [a + b for a, b in zip(s["convert_time_offset"], s["fit_time_offset"])]
    assert all(abs(v - 0.15) < 0.005 for v in total), s
    f, m = s["held_out_fit_percent"]["fitted"], s["held_out_fit_percent"]["model"]
    assert min(f["x"], f["y"]) > min(m["x"], m["y"])
