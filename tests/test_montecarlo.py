"""Monte-Carlo runner: statistics against linear sensitivity, determinism, resume, devices."""

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

import jsphere

VARY = {"r_m[2]": ("normal", -0.0270146, 1e-4)}
GAITS = [jsphere.acceleration(), jsphere.braking()]


@pytest.fixture(scope="module")
def study(paper):
    return jsphere.monte_carlo(paper, GAITS, vary=VARY, n=256, seed=7, batch_size=128, progress=False)


def test_stop_spread_equals_linear_sensitivity(paper):
    """R_m ~ N(27.0146 mm, 0.1 mm): the stop-distance sd is the linear sensitivity (~1.09 mm)."""
    res = jsphere.monte_carlo(paper, GAITS, vary=VARY, n=2048, seed=0, batch_size=1024, progress=False)
    sd = res.stats()["distance_m"]["sd"]

    def dist(Rm):
        tr = jsphere.simulate_gaits(paper.replace(R_m=Rm), GAITS)
        return float(np.hypot(tr.x[-1], tr.y[-1]))

    h = 1e-6
    slope = (dist(0.0270146 + h) - dist(0.0270146 - h)) / (2 * h)
    assert sd == pytest.approx(abs(slope) * 1e-4, rel=0.05)
    assert abs(slope) * 1e-4 == pytest.approx(1.09e-3, rel=0.03)  # MODEL-NOTES: 0.036 (1/s)/mm * 2 s * R0
    assert res.stats()["n_failed"] == 0


def test_same_seed_same_study_whatever_the_batch_size(paper, study):
    other = jsphere.monte_carlo(paper, GAITS, vary=VARY, n=256, seed=7, batch_size=256, progress=False)
    assert np.array_equal(study.x_final, other.x_final) and np.array_equal(study.y_final, other.y_final)
    assert study.stats() == other.stats()
    third = jsphere.monte_carlo(paper, GAITS, vary=VARY, n=256, seed=8, batch_size=128, progress=False)
    assert not np.array_equal(study.x_final, third.x_final)


def test_resume_after_interruption(paper, study, tmp_path):
    out = tmp_path / "study"
    first = jsphere.monte_carlo(paper, GAITS, vary=VARY, n=256, seed=7, batch_size=128, out=out, progress=False)
    assert np.array_equal(first.x_final, study.x_final)
    (out / "batch_000001.npz").unlink()  # as if killed before the second batch was written
    mtime = (out / "batch_000000.npz").stat().st_mtime_ns
    again = jsphere.monte_carlo(paper, GAITS, vary=VARY, n=256, seed=7, batch_size=128, out=out, progress=False)
    assert np.array_equal(again.x_final, study.x_final)
    assert (out / "batch_000000.npz").stat().st_mtime_ns == mtime  # not recomputed
    assert (out / "stats.json").exists() and not list(out.glob(".*"))
    with pytest.raises(ValueError, match="different study"):
        jsphere.monte_carlo(paper, GAITS, vary=VARY, n=256, seed=99, batch_size=128, out=out, progress=False)


def test_four_host_devices_give_identical_results(study):
    script = textwrap.dedent(
        """
        import numpy as np, jax, jsphere
        assert len(jax.local_devices()) == 4
        p = jsphere.RobotParams.paper()
        r = jsphere.monte_carlo(p, [jsphere.acceleration(), jsphere.braking()],
                                vary={"r_m[2]": ("normal", -0.0270146, 1e-4)}, n=256, seed=7, batch_size=128, progress=False)
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


def test_torque_replay_without_errors_reproduces_the_plan(paper):
    """The planned torques replayed open loop on the nominal robot stop where the gaits stop."""
    res = jsphere.monte_carlo(paper, GAITS, vary={}, n=64, batch_size=64, mode="torques", settle=0.5, progress=False)
    plan = jsphere.simulate_gaits(paper, GAITS)
    assert np.all(res.status == 0)
    assert np.max(np.abs(res.x_final - float(plan.x[-1]))) < 2e-5
    assert np.max(np.abs(res.y_final - float(plan.y[-1]))) < 2e-5
    assert np.max(res.speed_final) < 2e-4
    assert np.max(res.gamma3_sd_after) < 1e-4  # the platform stays upright after the plan ends


def test_cli_montecarlo(tmp_path, study, capsys):
    from jsphere.cli import main

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


def test_two_processes_share_one_study(study, tmp_path):
    """Two processes (as on two hosts) split the batches through a shared folder; both return the
    whole study, identical to a single process."""
    script = textwrap.dedent(
        """
        import sys, numpy as np, jsphere
        p = jsphere.RobotParams.paper()
        r = jsphere.monte_carlo(p, [jsphere.acceleration(), jsphere.braking()],
                                vary={"r_m[2]": ("normal", -0.0270146, 1e-4)}, n=256, seed=7, batch_size=128,
                                progress=False, out=sys.argv[1], process_index=int(sys.argv[2]), process_count=2,
                                wait_timeout=600)
        np.save(sys.argv[3], np.stack([r.x_final, r.y_final]))
        """
    )
    folder = tmp_path / "shared"
    procs = [
        subprocess.Popen([sys.executable, "-c", script, str(folder), str(i), str(tmp_path / f"r{i}.npy")])
        for i in range(2)
    ]
    assert all(p.wait(timeout=900) == 0 for p in procs)
    for i in range(2):
        xy = np.load(tmp_path / f"r{i}.npy")
        assert np.array_equal(xy[0], study.x_final) and np.array_equal(xy[1], study.y_final)
    with pytest.raises(ValueError, match="shared|every process"):
        jsphere.monte_carlo(jsphere.RobotParams.paper(), GAITS, vary=VARY, n=8, process_index=0, process_count=2)


def test_kinematic_command_replay_matches_fig2(paper):
    """Replaying the kinematic control (2.9) as a command table (jump to zero at 4 s, an impulse)
    gives the rocking of `jsphere reproduce` (sd of gamma_3 over [4, 8] s about 0.020)."""
    u = np.asarray(jsphere.kinematic_wheel_speeds(paper, np.array([0.15 * 0.864, 0.0])))
    cmd = (np.array([0.0, 4.0]), np.stack([u, u]))
    res = jsphere.monte_carlo(paper, GAITS, vary={}, n=64, batch_size=64, mode="wheel_speeds", commands=cmd,
                              settle=4.0, progress=False)  # fmt: skip
    assert np.all(res.status == 0)
    assert res.gamma3_sd_after[0] == pytest.approx(0.0201, abs=5e-4)
    assert res.x_final[0] == pytest.approx(0.49858, abs=1e-4)  # as the kinematic run of `reproduce` at t = 8 s
