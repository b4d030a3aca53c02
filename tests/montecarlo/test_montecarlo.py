"""Monte-Carlo runner: statistics against linear sensitivity, determinism, resume, devices."""

import json
import os
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import jax.numpy as jnp
import numpy as np
import pytest

import jsphere
from jsphere._runtime.errors import InputError
from jsphere.montecarlo.store import MonteCarloWarning

VARY = {"r_m[2]": ("normal", -0.0270146, 1e-4)}
GAITS = [jsphere.acceleration(), jsphere.braking()]


@pytest.fixture(scope="module")
def study(paper):
    return jsphere.monte_carlo(
        paper, GAITS, vary=VARY, n=256, options=jsphere.StudyOptions(seed=7, batch_size=128), progress=False
    )


@pytest.mark.slow
def test_stop_spread_equals_linear_sensitivity(paper):
    """R_m ~ N(27.0146 mm, 0.1 mm): the stop-distance sd is the linear sensitivity (~1.09 mm)."""
    res = jsphere.monte_carlo(
        paper, GAITS, vary=VARY, n=2048, options=jsphere.StudyOptions(seed=0, batch_size=1024), progress=False
    )
    sd = res.stats()["distance_m"]["sd"]

    def dist(Rm):
        tr = jsphere.simulate_gaits(paper.replace(R_m=Rm), GAITS)
        return float(np.hypot(tr.x[-1], tr.y[-1]))

    h = 1e-6
    slope = (dist(0.0270146 + h) - dist(0.0270146 - h)) / (2 * h)
    assert sd == pytest.approx(abs(slope) * 1e-4, rel=0.05)
    assert abs(slope) * 1e-4 == pytest.approx(1.09e-3, rel=0.03)  # docs/model.md: 0.036 (1/s)/mm * 2 s * R0
    assert res.stats()["n_failed"] == 0


def test_options_at_the_default_tolerance_are_the_study_without_options(paper, study):
    """`SolverOptions(rtol, atol)` at the default tolerances give the study without options, bit
    for bit (the same compiled batch)."""
    again = jsphere.monte_carlo(
        paper,
        GAITS,
        vary=VARY,
        n=256,
        options=jsphere.StudyOptions(seed=7, batch_size=128),
        progress=False,
        solver=jsphere.SolverOptions(rtol=1e-8, atol=1e-10),
    )
    np.testing.assert_array_equal(again.x_final, study.x_final)
    np.testing.assert_array_equal(again.status, study.status)


@pytest.mark.slow
def test_same_seed_same_study_whatever_the_batch_size(paper, study):
    other = jsphere.monte_carlo(
        paper, GAITS, vary=VARY, n=256, options=jsphere.StudyOptions(seed=7, batch_size=256), progress=False
    )
    assert np.array_equal(study.x_final, other.x_final) and np.array_equal(study.y_final, other.y_final)
    assert study.stats() == other.stats()
    third = jsphere.monte_carlo(
        paper, GAITS, vary=VARY, n=256, options=jsphere.StudyOptions(seed=8, batch_size=128), progress=False
    )
    assert not np.array_equal(study.x_final, third.x_final)


def test_resume_after_interruption(paper, study, tmp_path):
    out = tmp_path / "study"
    first = jsphere.monte_carlo(
        paper, GAITS, vary=VARY, n=256, options=jsphere.StudyOptions(seed=7, batch_size=128), out=out, progress=False
    )
    assert np.array_equal(first.x_final, study.x_final)
    (out / "batch_000001.npz").unlink()  # as if killed before the second batch was written
    mtime = (out / "batch_000000.npz").stat().st_mtime_ns
    again = jsphere.monte_carlo(
        paper, GAITS, vary=VARY, n=256, options=jsphere.StudyOptions(seed=7, batch_size=128), out=out, progress=False
    )
    assert np.array_equal(again.x_final, study.x_final)
    assert (out / "batch_000000.npz").stat().st_mtime_ns == mtime  # not recomputed
    assert (out / "stats.json").exists() and not list(out.glob(".*"))
    with pytest.raises(ValueError, match="different study"):
        jsphere.monte_carlo(
            paper,
            GAITS,
            vary=VARY,
            n=256,
            options=jsphere.StudyOptions(seed=99, batch_size=128),
            out=out,
            progress=False,
        )


@pytest.mark.slow
def test_four_host_devices_give_identical_results(study):
    script = textwrap.dedent(
        """
        import numpy as np, jax, jsphere
        jax.config.update("jax_enable_x64", True)
        assert len(jax.local_devices()) == 4
        p = jsphere.RobotParams.paper()
        r = jsphere.monte_carlo(p, [jsphere.acceleration(), jsphere.braking()],
                                vary={"r_m[2]": ("normal", -0.0270146, 1e-4)}, n=256, options=jsphere.StudyOptions(seed=7, batch_size=128), progress=False)
        np.save("OUT", np.stack([r.x_final, r.y_final]))
        """
    )
    out = Path(os.environ.get("TMPDIR", "/tmp")) / f"jsphere_mc_{os.getpid()}.npy"
    env = dict(os.environ, XLA_FLAGS="--xla_force_host_platform_device_count=4", JAX_PLATFORMS="cpu")
    subprocess.run([sys.executable, "-c", script.replace("OUT", str(out))], check=True, env=env, timeout=600)
    xy = np.load(out)
    out.unlink()
    assert np.array_equal(xy[0], study.x_final) and np.array_equal(xy[1], study.y_final)


def test_vary_validation(paper):
    with pytest.raises(ValueError, match="unknown parameter"):
        jsphere.monte_carlo(paper, GAITS, vary={"mass": ("normal", 1, 0.1)}, n=4)
    with pytest.raises(ValueError, match="normal"):
        jsphere.monte_carlo(paper, GAITS, vary={"j": ("gauss", 1, 0.1)}, n=4)
    with pytest.raises(ValueError, match="does not fit"):
        jsphere.monte_carlo(paper, GAITS, vary={"I[3,0]": ("normal", 0.016, 0.001)}, n=4)
    with pytest.raises(ValueError, match="scalar components"):
        jsphere.monte_carlo(paper, GAITS, vary={"I": ("normal", 0.016, 0.001)}, n=4)


def test_names_round_trip(paper):
    p = jsphere.set_value(paper, "I[0,1]", 1e-4)
    assert float(p.I[1, 0]) == 1e-4 and float(jsphere.get_value(p, "I[0,1]")) == 1e-4
    assert float(jsphere.get_value(jsphere.set_value(paper, "R_m", 0.03), "r_m[2]")) == pytest.approx(-0.03)
    assert jsphere.parse_name(" r_m [ 2 ] ") == ("r_m", (2,))


@pytest.mark.slow
def test_torque_replay_without_errors_reproduces_the_plan(paper):
    """The planned torques replayed open loop on the nominal robot stop where the gaits stop."""
    res = jsphere.monte_carlo(
        paper,
        GAITS,
        vary={},
        n=64,
        options=jsphere.StudyOptions(batch_size=64, mode="torques", settle=0.5),
        progress=False,
    )
    plan = jsphere.simulate_gaits(paper, GAITS)
    assert np.all(res.status == 0)
    assert np.max(np.abs(res.x_final - float(plan.x[-1]))) < 2e-5
    assert np.max(np.abs(res.y_final - float(plan.y[-1]))) < 2e-5
    assert np.max(res.speed_final) < 2e-4
    assert np.max(res.gamma3_sd_after) < 1e-4  # the platform stays upright after the plan ends


def test_cli_montecarlo(tmp_path, study, capsys):
    from jsphere.cli.app import main

    cfg = tmp_path / "study.toml"
    cfg.write_text(
        'trials = 256\nseed = 7\nbatch_size = 128\ngaits = [{kind = "acceleration"}, {kind = "braking"}]\n'
        '[vary]\n"r_m[2]" = ["normal", -0.0270146, 1e-4]\n'
    )
    out = tmp_path / "out"
    assert main(["montecarlo", str(cfg), "--out", str(out), "--no-cache"]) == 0
    stats = json.loads((out / "stats.json").read_text())
    assert stats["mean_xy_m"] == pytest.approx(study.stats()["mean_xy_m"], abs=1e-15)
    assert (out / "stop_points.png").stat().st_size > 10_000
    bad = tmp_path / "bad.toml"
    bad.write_text('[vary]\nj = ["gauss", 1, 2]\n')
    assert main(["montecarlo", str(bad), "--out", str(tmp_path / "o2"), "--no-cache"]) == 2
    assert "normal" in capsys.readouterr().err


def test_a_finished_study_extends_to_more_trials(paper, study, tmp_path):
    """Run again with a larger n, a finished study computes only its new batches; its first trials
    are the smaller study's, bit for bit. A smaller n or any other change is refused."""
    out = tmp_path / "study"
    kw = dict(vary=VARY, options=jsphere.StudyOptions(seed=7, batch_size=128), out=out, progress=False)
    small = jsphere.monte_carlo(paper, GAITS, n=100, **kw)
    np.testing.assert_array_equal(small.x_final, study.x_final[:100])
    mtime = (out / "batch_000000.npz").stat().st_mtime_ns
    big = jsphere.monte_carlo(paper, GAITS, n=256, **kw)
    assert np.array_equal(big.x_final, study.x_final) and big.stats() == study.stats()
    assert (out / "batch_000000.npz").stat().st_mtime_ns == mtime  # not recomputed
    assert json.loads((out / "manifest.json").read_text())["n"] == 256
    assert json.loads((out / "stats.json").read_text())["n"] == 256
    with pytest.raises(InputError, match="with 256 trials; a study is extended to more trials but not cut to fewer"):
        jsphere.monte_carlo(paper, GAITS, n=100, **kw)
    with pytest.raises(InputError, match="different study"):
        jsphere.monte_carlo(paper, GAITS, n=512, **(kw | {"options": jsphere.StudyOptions(seed=8, batch_size=128)}))
    with pytest.raises(InputError, match="different study"):
        jsphere.monte_carlo(paper, GAITS, n=512, **(kw | {"vary": {"r_m[2]": ("normal", -0.0270146, 2e-4)}}))


@pytest.mark.slow
def test_kinematic_command_replay_matches_fig2(paper):
    """Replaying the kinematic control (2.9) as a command table (jump to zero at 4 s, an impulse)
    gives the rocking of `jsphere reproduce` (sd of gamma_3 over [4, 8] s about 0.020)."""
    u = np.asarray(jsphere.kinematic_wheel_speeds(paper, np.array([0.15 * 0.864, 0.0])))
    cmd = (np.array([0.0, 4.0]), np.stack([u, u]))
    res = jsphere.monte_carlo(
        paper,
        GAITS,
        vary={},
        n=64,
        options=jsphere.StudyOptions(batch_size=64, mode="wheel_speeds", commands=cmd, settle=4.0),
        progress=False,
    )
    assert np.all(res.status == 0)
    assert res.gamma3_sd_after[0] == pytest.approx(0.0201, abs=5e-4)
    assert res.x_final[0] == pytest.approx(0.49858, abs=1e-4)  # as the kinematic run of `reproduce` at t = 8 s


# ---------------------------------------------------------------- invalid draws, bad values, corrupt files
# (these reuse the compiled batch of `study`: one varied name, a normal distribution, 128 trials)

WIDE = {"r_m[2]": ("normal", -0.0270146, 0.1)}  # |r_m| >= R0 = 0.15 for about 1 draw in 8


@pytest.fixture(scope="module")
def wide(paper, study):
    return jsphere.monte_carlo(
        paper, GAITS, vary=WIDE, n=256, options=jsphere.StudyOptions(seed=7, batch_size=128), progress=False
    )


def test_invalid_draws_are_rejected_not_simulated(wide):
    """A draw that breaks a rule of RobotParams (here the centre of mass outside the shell) gets
    the status REJECTED and NaN outcomes, and `stats()` counts it apart from solver failures."""
    r = wide
    outside = np.abs(r.samples["r_m[2]"]) >= 0.15
    assert 10 < outside.sum() < 80
    np.testing.assert_array_equal(r.status == jsphere.MonteCarloResult.REJECTED, outside)
    assert np.all(np.isnan(r.x_final[outside])) and np.all(np.isfinite(r.x_final[r.status == 0]))
    assert jsphere.MonteCarloResult.REASONS[r.reject_code[outside][0]] == "|r_m| >= R0"
    st = r.stats()
    assert st["n_rejected"] == outside.sum() and st["rejected"] == {"|r_m| >= R0": int(outside.sum())}
    assert st["n_ok"] + st["n_failed"] + st["n_rejected"] == 256
    assert st["n_failed"] == int(np.sum((r.status != 0) & ~outside))


def test_truncate_draws_again_until_valid(paper, wide):
    """With "truncate" an invalid draw is drawn again: no rejections, every value inside the valid
    range, distributed as the truncated normal; draws valid at the first try are unchanged."""
    from scipy import stats

    r = jsphere.monte_carlo(
        paper,
        GAITS,
        vary={"r_m[2]": (*WIDE["r_m[2]"], "truncate")},
        n=256,
        options=jsphere.StudyOptions(seed=7, batch_size=128),
        progress=False,
    )
    assert r.stats()["n_rejected"] == 0 and np.all(r.reject_code == 0)
    v = r.samples["r_m[2]"]
    assert np.all(np.abs(v) < 0.15)
    first = wide.status != jsphere.MonteCarloResult.REJECTED
    np.testing.assert_array_equal(v[first], wide.samples["r_m[2]"][first])
    np.testing.assert_array_equal(r.x_final[first], wide.x_final[first])
    mean, sd = WIDE["r_m[2]"][1:]
    tn = stats.truncnorm((-0.15 - mean) / sd, (0.15 - mean) / sd, loc=mean, scale=sd)
    assert stats.kstest(v, tn.cdf).pvalue > 1e-3


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"n": 10.9}, r"n must be a whole number >= 1; got 10.9"),
        ({"n": 0}, r"n must be a whole number >= 1; got 0"),
        ({"n": True}, r"n must be a whole number"),
        ({"seed": 1.7}, r"seed must be a whole number in \[0, 4294967295\]; got 1.7"),
        ({"seed": -1}, r"seed must be a whole number in \[0, 4294967295\]"),
        ({"seed": 2**32}, r"seed must be a whole number in \[0, 4294967295\]"),
        ({"batch_size": 0}, r"batch_size must be a whole number >= 1"),
        ({"batch_size": 64.5}, r"batch_size must be a whole number >= 1"),
        ({"settle": -1.0, "mode": "torques"}, r"settle must be a finite number >= 0"),
        ({"settle": float("nan")}, r"settle must be a finite number >= 0"),
        ({"Omega0_sd": float("inf")}, r"Omega0_sd must be a finite number >= 0"),
        ({"plan_rate": 0.0, "mode": "torques"}, r"plan_rate must be a finite number > 0"),
        ({"max_steps": 0}, r"max_steps must be a whole number >= 1"),
        ({"rtol": -1e-8}, r"rtol must be a finite number > 0"),
        ({"vary": 3}, r"vary must be a table"),
        ({"vary": {"j": ("normal", 2.7e-4, float("inf"))}}, r"vary\['j'\]: the sd must be a finite number; got inf"),
        ({"vary": {"j": ("normal", float("nan"), 1e-5)}}, r"vary\['j'\]: the mean must be a finite number; got nan"),
        ({"vary": {"j": ("uniform", 3e-4, 2e-4)}}, r"uniform needs low <= high"),
        ({"vary": {"j": ("uniform", float("-inf"), 2e-4)}}, r"the low must be a finite number"),
        ({"vary": {"j": ("normal", True, 1e-5)}}, r"the mean must be a finite number; got True"),
        ({"vary": {"j": ("normal", 2.7e-4, 1e-5, "clip")}}, r"got 'clip' as its last entry"),
        ({"vary": {"j": ("normal", 2.7e-4)}}, r"vary\['j'\] must be \['normal', mean, sd\]"),
        (
            {"vary": {"I[0,1]": ("normal", 0, 1e-4), "I[1,0]": ("normal", 0, 1e-4)}},
            r"'I\[0,1\]' and 'I\[1,0\]' set the same value",
        ),
        ({"vary": {"R_m": ("normal", 0.027, 1e-4), "r_m[2]": ("normal", -0.027, 1e-4)}}, r"set the same value"),
        ({"gaits": []}, r"gaits must be a non-empty list"),
        ({"actuators": jsphere.Actuators(gain_sd=0.01)}, r"actuators apply to replayed commands"),
    ],
)
def test_study_values_are_checked_before_any_work(paper, kwargs, match):
    kw = {"vary": VARY, "n": 64, "progress": False, **kwargs}
    gaits = kw.pop("gaits", GAITS)
    with pytest.raises(InputError, match=match):
        jsphere.monte_carlo(paper, gaits, **kw)


def test_a_negative_R_m_draw_is_rejected(paper):
    """`R_m` is a distance: a negative draw (which would flip r_m) is rejected with its own reason."""
    from jsphere.montecarlo.sampling import REASONS, draw_code

    codes = [int(draw_code(paper, ("R_m",), jnp.array([v]))) for v in (0.02, -0.02, 0.2)]
    assert [REASONS[c] for c in codes] == ["valid", "R_m <= 0", "|r_m| >= R0"]


def test_actuators_values_are_checked():
    for kw, match in (
        ({"gain_sd": -0.1}, "gain_sd must be a finite number >= 0"),
        ({"delay_s": float("nan")}, "delay_s"),
        ({"band_hz": 0.0}, "band_hz must be a finite number > 0"),
        ({"white_sd": "0.1"}, "white_sd"),
    ):
        with pytest.raises(InputError, match=match):
            jsphere.Actuators(**kw)


def _corrupt(path: Path, how: str) -> None:
    data = path.read_bytes()
    if how == "truncated":
        path.write_bytes(data[: len(data) // 2])
    elif how == "random":
        path.write_bytes(np.random.default_rng(0).bytes(len(data)))
    else:
        path.write_bytes(b"")


def test_corrupt_batches_are_recomputed_and_temporary_files_removed(paper, tmp_path):
    """A batch file cut short, overwritten with random bytes or empty is recomputed with a warning
    naming it; the temporary files of a killed run are removed; every file ends up byte-identical
    to an uninterrupted run's."""
    out = tmp_path / "study"
    kw = dict(vary=VARY, n=384, options=jsphere.StudyOptions(seed=7, batch_size=128), out=out, progress=False)
    first = jsphere.monte_carlo(paper, GAITS, **kw)
    times = [f"time_{k:06d}.json" for k in range(3)]  # when each batch was computed: not compared
    files = {f.name: f.read_bytes() for f in out.iterdir() if f.name not in times}
    assert sorted(files) == ["batch_000000.npz", "batch_000001.npz", "batch_000002.npz", "manifest.json", "stats.json"]
    assert all((out / name).exists() for name in times)
    for k, how in enumerate(("truncated", "random", "empty")):
        _corrupt(out / f"batch_{k:06d}.npz", how)
    (out / "stats.json").unlink()
    for name in (".batch_000001.k2v_9x0q.npz", ".stats.abcd1234.tmp", ".manifest.zz_00001.tmp", ".time_000002.q1.tmp"):
        (out / name).write_bytes(b"partial")
    with pytest.warns(MonteCarloWarning) as record:
        again = jsphere.monte_carlo(paper, GAITS, **kw)
    messages = sorted(str(w.message) for w in record)
    assert len(messages) == 3 and all("corrupt or incomplete" in m and "recomputing" in m for m in messages)
    assert [f"batch_{k:06d}.npz" in m for k, m in enumerate(messages)] == [True] * 3
    assert {f.name: f.read_bytes() for f in out.iterdir() if f.name not in times} == files
    assert sorted(f.name for f in out.iterdir()) == sorted([*files, *times])  # no temporary file left
    np.testing.assert_array_equal(again.x_final, first.x_final)


def test_corrupt_manifest_and_orphan_batches_are_refused(paper, tmp_path):
    (tmp_path / "a").mkdir()
    (tmp_path / "a" / "manifest.json").write_text("{not json")
    with pytest.raises(InputError, match="not a valid study manifest"):
        jsphere.monte_carlo(paper, GAITS, vary=VARY, n=64, out=tmp_path / "a", progress=False)
    (tmp_path / "b").mkdir()
    (tmp_path / "b" / "batch_000000.npz").write_bytes(b"")
    with pytest.raises(InputError, match="no manifest.json"):
        jsphere.monte_carlo(paper, GAITS, vary=VARY, n=64, out=tmp_path / "b", progress=False)
    assert sorted(f.name for f in (tmp_path / "b").iterdir()) == ["batch_000000.npz"]


def test_cli_reports_rejected_draws(tmp_path, wide, capsys):
    """The command line says how many draws were rejected and why; a study whose every draw is
    rejected is bad input (exit 2)."""
    from jsphere.cli.app import main

    cfg = tmp_path / "wide.toml"
    cfg.write_text('trials = 256\nseed = 7\nbatch_size = 128\n[vary]\n"r_m[2]" = ["normal", -0.0270146, 0.1]\n')
    out = tmp_path / "out"
    assert main(["montecarlo", str(cfg), "--out", str(out), "--no-cache", "--no-plots"]) == 0
    err = capsys.readouterr().err
    k = wide.stats()["n_rejected"]
    assert f"{k} of 256 draws rejected" in err and f"|r_m| >= R0: {k}" in err
    assert json.loads((out / "stats.json").read_text())["rejected"] == {"|r_m| >= R0": k}
    cfg.write_text('trials = 128\nbatch_size = 128\n[vary]\n"r_m[2]" = ["normal", 0.5, 0.01]\n')
    assert main(["montecarlo", str(cfg), "--out", str(tmp_path / "out2"), "--no-cache", "--no-plots"]) == 2
    assert "every draw was rejected (|r_m| >= R0: 128)" in capsys.readouterr().err


def _cli(folder: Path, study: Path, env: dict) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, "-m", "jsphere.cli.app", "montecarlo", str(study), "--out", str(folder), "--no-plots"],
        env=env,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
    )


def _kill_when(proc: subprocess.Popen, ready, timeout: float = 300.0) -> None:
    """SIGKILL `proc` as soon as `ready()` holds (or when it ends by itself)."""
    deadline = time.monotonic() + timeout
    while not ready() and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.002)
    proc.kill()
    proc.wait()


@pytest.mark.slow
def test_cli_killed_anywhere_resumes_to_the_same_files(tmp_path):
    """`jsphere montecarlo` killed with SIGKILL during start-up, as its first batch file appears
    and between later batches, then run again, leaves the same bytes as an uninterrupted run
    (batches, manifest, stats.json) and no temporary file. ~1-2 min on 2 cores."""
    import signal  # noqa: F401 - Popen.kill sends SIGKILL

    study = tmp_path / "study.toml"
    study.write_text(
        'trials = 320\nseed = 3\nbatch_size = 64\ngaits = [{kind = "acceleration", T = 1.0}, {kind = "braking", T = 1.0}]\n'
        '[vary]\n"r_m[2]" = ["normal", -0.0270146, 0.05, "truncate"]\nm0 = ["normal", 0.8, 0.4]\n'
    )
    env = dict(
        os.environ,
        JSPHERE_CACHE_DIR=str(tmp_path / "cache"),
        JAX_PLATFORMS="cpu",
        PYTHONPATH=str(Path(__file__).resolve().parents[2]),
    )
    ref, res = tmp_path / "ref", tmp_path / "res"
    p = _cli(ref, study, env)
    assert p.wait(timeout=900) == 0, p.stderr.read().decode()
    expected = {f.name: f.read_bytes() for f in ref.iterdir()}
    assert [n[:5] for n in sorted(expected) if n.startswith(("batch_", "time_"))] == ["batch"] * 5 + ["time_"] * 5
    assert json.loads(expected["stats.json"])["n_rejected"] > 0  # m0 < 0 for ~1 draw in 40

    def batches():
        return len(list(res.glob("batch_*.npz")))

    t0 = time.monotonic()
    kills = [lambda: time.monotonic() - t0 > 1.5, lambda: batches() >= 1, lambda: batches() >= 3]
    left = []
    for ready in kills:
        t0 = time.monotonic()
        _kill_when(_cli(res, study, env), ready)
        left.append(sorted(f.name for f in res.iterdir()) if res.exists() else [])
    print("files after each kill:", left)
    assert batches() < 5  # the last kill came before the end
    p = _cli(res, study, env)
    assert p.wait(timeout=900) == 0, p.stderr.read().decode()
    got = {f.name: f.read_bytes() for f in res.iterdir()}
    assert sorted(got) == sorted(expected)  # no hidden temporary file left; a time record per batch
    for name in expected:
        if not name.startswith("time_"):  # when each batch was computed differs from run to run
            assert got[name] == expected[name], name


def test_options_object_and_moved_keywords_give_the_same_study(paper, study):
    """`options=StudyOptions(...)` is the study of the keywords it replaces; each moved keyword
    warns with its new spelling, and `options=SolverOptions(...)` means `solver=`."""
    new = jsphere.monte_carlo(
        paper, GAITS, vary=VARY, n=256, options=jsphere.StudyOptions(seed=7, batch_size=128), progress=False
    )
    np.testing.assert_array_equal(new.x_final, study.x_final)
    with pytest.warns(DeprecationWarning, match=r"seed= is deprecated; pass options=StudyOptions\(seed=\.\.\.\)"):
        jsphere.monte_carlo(paper, GAITS, vary=VARY, n=64, seed=1, progress=False)
    with pytest.warns(DeprecationWarning, match=r"rtol= is deprecated; pass solver=SolverOptions\(rtol=\.\.\.\)"):
        jsphere.monte_carlo(paper, GAITS, vary=VARY, n=64, rtol=1e-8, progress=False)
    with pytest.warns(DeprecationWarning, match=r"options=SolverOptions\(\.\.\.\) is deprecated; pass solver="):
        jsphere.monte_carlo(paper, GAITS, vary=VARY, n=64, options=jsphere.SolverOptions(), progress=False)
    with pytest.raises(TypeError, match=r"unexpected keyword argument\(s\) \['sed'\]"):
        jsphere.monte_carlo(paper, GAITS, vary=VARY, n=64, sed=1)
    with pytest.raises(InputError, match=r"monte_carlo: seed must be a whole number"):
        jsphere.monte_carlo(paper, GAITS, vary=VARY, n=64, options=jsphere.StudyOptions(seed=-1))


def test_a_study_folder_reads_back_as_its_result(paper, study, tmp_path):
    """`read_result` of a finished study's folder is the study, bitwise; of a folder with a batch
    missing, the trials of the others with their indices; a folder without a study is refused."""
    from jsphere.montecarlo import read_result

    out = tmp_path / "study"
    options = jsphere.StudyOptions(seed=7, batch_size=128)
    jsphere.monte_carlo(paper, GAITS, vary=VARY, n=256, options=options, out=out, progress=False)
    back = read_result(out)
    assert back.n == 256 and back.seed == 7 and back.trials is None and back.compute_time.recorded == 2
    for name in ("x_final", "y_final", "speed_final", "status", "gamma3_sd_after", "reject_code"):
        np.testing.assert_array_equal(getattr(back, name), getattr(study, name))
    np.testing.assert_array_equal(back.samples["r_m[2]"], study.samples["r_m[2]"])
    assert back.stats() == json.loads((out / "stats.json").read_text())
    (out / "batch_000000.npz").unlink()
    part = read_result(out)
    np.testing.assert_array_equal(part.trials, np.arange(128, 256))
    np.testing.assert_array_equal(part.x_final, study.x_final[128:])
    (out / "batch_000001.npz").write_bytes(b"")
    with pytest.raises(InputError, match=r"batch_000001.npz is corrupt or incomplete"):
        read_result(out)
    with pytest.raises(InputError, match=r"not a Monte-Carlo study \(no manifest.json\)"):
        read_result(tmp_path)
