"""The verdict on a fit: the capture's noise floor, the rules of `judge`, and what `jsphere fit`
writes and returns for a good fit (0), a misfit (6) and a fit stopped before convergence (5).

The fits share one small problem (2 wheel-speed trials of 1.5 s at 50 Hz, free `R_m, j`,
`m` fixed, one start), so the fit's functions are compiled once for the module; the misfit
gives each trial the inputs of the other.
"""

from __future__ import annotations

import json
import math
import types

import numpy as np
import pytest

import jsphere
from jsphere._runtime.errors import EXIT_CODES_HELP, ExitCode
from jsphere.cli.app import main
from jsphere.identify.data import pack_trials
from jsphere.identify.verdict import (
    CORRELATED,
    FAR,
    MODERATE,
    UNREACHABLE,
    headline,
    judge,
    lag1,
    missing_effects,
    noise_floor,
)
from jsphere.plots import worst_trial

TRUTH = jsphere.RobotParams.paper().replace(R_m=0.029, j=3.2e-4)
FLOOR = (1e-3, math.radians(0.5))


def synthetic(seeds, t1, rate, **kw):
    return [
        jsphere.synthetic_trial(
            TRUTH, jsphere.random_inputs(TRUTH, t1, seed=s), t1, rate=rate, seed=s, name=f"t{k}", **kw
        )
        for k, s in enumerate(seeds)
    ]


# ------------------------------------------------------------------ the noise floor


@pytest.mark.parametrize(
    "seeds, rate, t1, pos_sd, rot_sd_deg",
    # 8 trials of 76 frames, as the fits below (one compilation of the simulation): ~1000
    # differences per channel, a relative accuracy of ~3.5 %
    [(range(10, 18), 50.0, 1.5, 2e-3, 1.0), (range(20, 28), 100.0, 0.75, 0.5e-3, 0.3)],
)
def test_noise_floor_is_the_synthetic_noise(seeds, rate, t1, pos_sd, rot_sd_deg):
    trials = synthetic(seeds, t1, rate, pos_sd=pos_sd, rot_sd_deg=rot_sd_deg, dropout=0.05)
    data = pack_trials(trials, TRUTH)
    assert data.wpos.sum() < data.wpos.size and data.wrot.sum() < data.wrot.size  # gaps: runs across them are skipped
    sigma_pos, sigma_rot = noise_floor(data)
    print(
        f"noise floor / truth: {sigma_pos / pos_sd:.4f} (position), {math.degrees(sigma_rot) / rot_sd_deg:.4f} (orientation)"
    )
    assert sigma_pos == pytest.approx(pos_sd, rel=0.1)
    assert math.degrees(sigma_rot) == pytest.approx(rot_sd_deg, rel=0.1)


def test_noise_floor_of_a_capture_without_runs_of_four_frames_is_nan(trials):
    t = trials[0]
    holes = np.arange(len(t.t)) % 4 == 3  # every 4th frame lost: no 4 consecutive measured frames
    x, q = np.where(holes, np.nan, t.x), np.where(holes[:, None], np.nan, t.q)
    data = pack_trials([jsphere.Trial(t.t, x, t.y, q, t.inputs, t.kind, None, name="holes")], TRUTH)
    floor = noise_floor(data)
    assert all(math.isnan(f) for f in floor)
    rng = np.random.default_rng(0)
    v = judge([rng.normal(0, 1e-3, (76, 2))], [rng.normal(0, FLOOR[1], (76, 3))], floor, names=["holes"])
    assert v["status"] == "converged" and "noise floor cannot be estimated" in v["reason"]
    assert math.isnan(v["ratio_pos"]) and "n/a" in v["reason"]


# ------------------------------------------------------------------ the rules


def white(rng, m, scale=1.0):
    return rng.normal(0, scale * FLOOR[0], (m, 2)), rng.normal(0, scale * FLOOR[1], (m, 3))


def smooth(m, amp):
    """Slow sines (a period of 60 frames) of amplitude `amp` floors: residuals of a wrong model."""
    t = np.arange(m)[:, None] / 60.0
    return amp * FLOOR[0] * np.sin(2 * np.pi * t + [0.0, 1.0]), amp * FLOOR[1] * np.sin(2 * np.pi * t + [0.0, 1.0, 2.0])


def test_white_residuals_at_the_floor_are_converged():
    rng = np.random.default_rng(1)
    (p0, r0), (p1, r1) = white(rng, 300), white(rng, 300)
    p0[10:13] = np.nan  # a gap
    v = judge([p0, p1], [r0, r1], FLOOR, names=["a", "b"], n_params=20)
    assert v["status"] == "converged", v["reason"]
    assert v["ratio_pos"] == pytest.approx(1.0, abs=0.06) and v["ratio_rot"] == pytest.approx(1.0, abs=0.06)
    assert abs(v["autocorr_pos"]) < 0.1 and abs(v["autocorr_rot"]) < 0.1
    assert [t["name"] for t in v["trials"]] == ["a", "b"] and v["worst_trial"] in ("a", "b")
    rp, rr = v["ratio_pos"], v["ratio_rot"]
    assert (
        headline(v["status"], v["reason"], v)
        == f"converged (residual sigma {rp:.2f}x / {rr:.2f}x the capture's noise floor, position / orientation)"
    )


def test_smooth_residuals_far_above_the_floor_are_a_misfit():
    p, r = smooth(300, 10.0)
    v = judge([p], [r], FLOOR, names=["a"])
    assert v["status"] == "misfit"
    assert v["ratio_pos"] > FAR and v["autocorr_pos"] > 0.99
    assert "7.07x (position)" in v["reason"] and "--n-starts" in v["reason"]
    assert headline(v["status"], v["reason"], v) == f"misfit: {v['reason']}"


def test_an_unconverged_fit_far_beyond_reach_of_the_floor_is_a_misfit():
    """Out of iterations at 7x the floor: not converged (more iterations may reach it); at 14x,
    above `UNREACHABLE`: a misfit whose reason still says the optimiser stopped."""
    p, r = smooth(300, 10.0)
    v = judge([p], [r], FLOOR, names=["a"], converged=False, why_not="max_iter")
    assert FAR < v["ratio_pos"] < UNREACHABLE and v["status"] == "not_converged" and "--max-iter" in v["reason"]
    p, r = smooth(300, 20.0)
    v = judge([p], [r], FLOOR, names=["a"], converged=False, why_not="max_iter")
    assert v["ratio_pos"] > UNREACHABLE and v["status"] == "misfit"
    assert "did not converge (max_iter)" in v["reason"] and "--n-starts" in v["reason"]


def test_moderately_high_residuals_are_a_misfit_only_when_far_from_white():
    rng = np.random.default_rng(2)
    wp, wr = white(rng, 600, 0.5)
    sp, sr = smooth(600, 2.5)
    v = judge([wp + sp], [wr + sr], FLOOR, names=["a"])
    assert MODERATE < v["ratio_pos"] < FAR and v["autocorr_pos"] > CORRELATED
    assert v["status"] == "misfit" and v["diagnosis"] == "model error" and "correlated in time" in v["reason"]
    assert "check the capture" not in v["reason"] and "convert" not in v["reason"]
    wp, wr = white(rng, 600, 2.0)
    v = judge([wp], [wr], FLOOR, names=["a"])
    assert MODERATE < v["ratio_pos"] < FAR and abs(v["autocorr_pos"]) < 0.1
    assert v["status"] == "converged"


def test_residuals_near_the_floor_but_correlated_in_time_are_a_model_error():
    """A smooth part of a third of the noise (residual sigma 1.05x the floor) is a model error
    that names what could be missing; white residuals 1.2x the floor are not; a noise-free
    capture (floor at the resolution) is not tested for whiteness."""
    rng = np.random.default_rng(5)
    missing = missing_effects(["r_m[2]", "j"], "torques", False, known=["k_tau"])
    for i in range(3):
        wp, wr = white(rng, 500)
        sp, sr = smooth(500, 0.45)
        v = judge([wp + sp], [wr + sr], FLOOR, names=["a"], missing=missing)
        assert v["ratio_pos"] < 1.2 and v["status"] == "misfit" and v["diagnosis"] == "model error", v["reason"]
        assert "--free c_roll,c_axle" in v["reason"] and "--fit-time-offset" in v["reason"] and "k_tau" in v["reason"]
        assert "capture" not in v["reason"].split("What it could be missing")[0].replace(
            "the capture's noise floor", ""
        )
    wp, wr = white(rng, 500, 1.2)
    v = judge([wp], [wr], FLOOR, names=["a"], missing=missing)
    assert v["status"] == "converged" and v["diagnosis"] is None
    sp, sr = smooth(500, 0.01)
    v = judge([sp * 1e-3], [sr * 1e-3], (0.0, 0.0), names=["a"])
    assert v["status"] == "converged" and math.isnan(v["trials"][0]["whiteness"]["x"])


def test_white_residuals_are_called_correlated_rarely():
    """The whiteness test over 3 trials x 5 series at its alpha: of 300 right-model verdicts on
    white residuals with gaps, at most 3 are model errors (measured: about 1 in 1,000)."""
    rng = np.random.default_rng(6)
    errors = 0
    for _ in range(300):
        pe, re = zip(*(white(rng, 400) for _ in range(3)))
        pe = [np.where(rng.random((400, 1)) < 0.03, np.nan, p) for p in pe]
        errors += judge(list(pe), list(re), FLOOR, names=["a", "b", "c"])["diagnosis"] == "model error"
    assert errors <= 3


def test_the_worst_trial_alone_can_make_a_misfit():
    rng = np.random.default_rng(3)
    good, bad = white(rng, 600), white(rng, 100, 4.0)
    v = judge([good[0], bad[0]], [good[1], bad[1]], FLOOR, names=["good", "bad"])
    assert v["ratio_pos"] < FAR and v["ratio_rot"] < FAR  # over all trials: not far above the floor
    assert v["status"] == "misfit" and v["worst_trial"] == "bad" and "'bad'" in v["reason"]


def test_the_optimisers_flag_comes_first_and_the_ratio_is_named():
    rng = np.random.default_rng(4)
    p, r = white(rng, 300)
    v = judge([p], [r], FLOOR, converged=False, why_not="Levenberg-Marquardt stopped at max_iter")
    assert v["status"] == "not_converged" and "stopped at max_iter" in v["reason"] and "x (position)" not in v["reason"]
    p, r = smooth(300, 10.0)
    v = judge([p], [r], FLOOR, converged=False, why_not="Levenberg-Marquardt stopped at max_iter")
    assert v["status"] == "not_converged" and "7.07x (position)" in v["reason"] and "--max-iter" in v["reason"]


def test_lag1_autocorrelation_skips_gaps():
    e = np.array([[1.0], [np.nan], [1.0], [np.nan], [1.0]])
    assert lag1(e) == (0.0, 0.0)  # no pair of consecutive measured frames
    e = np.array([[1.0], [1.0], [np.nan], [-1.0], [-1.0]])
    num, den = lag1(e)
    assert num / den == pytest.approx(1.0)  # the jump from 1 to -1 lies across the gap


def test_exit_codes_of_the_verdict():
    assert (ExitCode.NOT_CONVERGED, ExitCode.MISFIT) == (5, 6)
    assert (
        "\n  5    fit: the optimiser did not converge" in EXIT_CODES_HELP
        and "\n  6    fit, compare: the model does not explain the trials" in EXIT_CODES_HELP
    )


# ------------------------------------------------------------------ jsphere fit


@pytest.fixture(scope="module")
def trials():
    return synthetic((0, 2), 1.5, 50.0, dropout=0.05)


@pytest.fixture(scope="module")
def files(trials, tmp_path_factory):
    """The trial files: `good` (as captured) and `swapped` (each trial with the other's inputs)."""
    d = tmp_path_factory.mktemp("trials")
    swapped = [
        jsphere.Trial(a.t, a.x, a.y, a.q, b.inputs, a.kind, None, name=a.name) for a, b in zip(trials, trials[::-1])
    ]
    out = {}
    for kind, group in (("good", trials), ("swapped", swapped)):
        out[kind] = []
        for t in group:
            path = d / f"{kind}_{t.name}.csv"
            jsphere.write_trial(path, t)
            out[kind].append(str(path))
    return out


def run_fit(paths, out, capsys, *extra):
    rc = main(
        [
            "fit",
            *paths,
            "--free",
            "R_m,j",
            "--fix",
            "m=2.5",
            "--n-starts",
            "1",
            "--out",
            str(out),
            "--quiet",
            "--no-cache",
            *extra,
        ]
    )
    lines = capsys.readouterr().out.strip().splitlines()
    doc = json.loads(out.read_text(), parse_constant=lambda c: pytest.fail(f"fit.json holds {c}"))
    assert not out.with_name(out.name + ".ckpt.npz").exists()
    return rc, lines, doc


def test_a_good_fit_is_converged_at_the_noise_floor(files, tmp_path, capsys):
    rc, lines, doc = run_fit(files["good"], tmp_path / "fit.json", capsys)
    assert rc == ExitCode.OK
    assert doc["converged"] is True and doc["status"] == "converged"
    v = doc["verdict"]
    assert 0.85 < v["ratio_pos"] < 1.15 and 0.85 < v["ratio_rot"] < 1.15, v
    assert abs(v["autocorr_pos"]) < 0.2 and abs(v["autocorr_rot"]) < 0.2
    assert v["noise_floor_pos_m"] == pytest.approx(1e-3, rel=0.15) and v["noise_floor_rot_deg"] == pytest.approx(
        0.5, rel=0.15
    )
    assert lines[-1].startswith("jsphere fit: converged (residual sigma ")
    assert lines[-2].startswith("wrote ") and lines[-3] == f"status: converged: {doc['status_reason']}"
    assert (tmp_path / "fit_overlay.png").exists() and (tmp_path / "fit_residuals.png").exists()


@pytest.mark.slow
def test_swapped_inputs_are_a_misfit(files, tmp_path, capsys):
    rc, lines, doc = run_fit(files["swapped"], tmp_path / "fit.json", capsys)
    assert rc == ExitCode.MISFIT == 6
    assert doc["status"] == "misfit" and doc["converged"] is True  # the optimiser is content; the verdict is not
    v = doc["verdict"]
    assert v["ratio_pos"] > FAR and v["ratio_rot"] > FAR and v["autocorr_pos"] > CORRELATED, v
    worst = v["worst_trial"]
    assert lines[-1] == f"jsphere fit: misfit: {doc['status_reason']}" and f"worst trial {worst!r}" in lines[-1]
    assert (tmp_path / "fit_residuals.png").exists()  # a misfit still writes its files
    # the figures put the worst trial first and name it with its ratios
    res = types.SimpleNamespace(trials=doc["trials"], verdict=v)
    k, text = worst_trial(res)
    assert doc["trials"][k]["name"] == worst and text.startswith(f"{worst}: residual sigma ") and "x / " in text


def test_a_fit_stopped_at_max_iter_is_not_converged(files, tmp_path, capsys):
    rc, lines, doc = run_fit(files["good"], tmp_path / "fit.json", capsys, "--max-iter", "1", "--no-plots")
    assert rc == ExitCode.NOT_CONVERGED == 5
    assert doc["converged"] is False and doc["status"] == "not_converged"
    assert lines[-1].startswith(
        "jsphere fit: not_converged: the optimiser did not converge (Levenberg-Marquardt reached max_iter"
    )
    assert "--max-iter" in doc["status_reason"]
