"""Section 5 of the paper: the numbers `jsphere reproduce` reports, and the CLI."""

import json
import os
import subprocess
import sys

import numpy as np
import pytest

import jsphere
from jsphere.cli.app import main
from jsphere.model.params import PAPER_J, PAPER_R_M


@pytest.fixture(scope="module")
def rep():
    return jsphere.reproduce()


def test_omega1_and_straight_line(rep):
    v = rep.values
    assert f"{v['Omega_after_acceleration'][1]:.6f}" == "0.864000"
    x, y = v["straight_stop_m"]["continuation"]
    assert 1e3 * x == pytest.approx(259.199, abs=1e-3)
    assert 1e3 * y == pytest.approx(3.594, abs=1e-3)  # the sideways drift caused by j > 0
    x, y = v["straight_stop_m"]["reset_5.4"]
    assert 1e3 * x == pytest.approx(259.199, abs=1e-3) and 1e3 * y == pytest.approx(-0.006, abs=1e-3)


def test_turn(rep):
    np.testing.assert_allclose(rep.values["Omega_after_turn_reset"], [-0.864, 0.852, 0.000445], atol=5e-7)
    assert rep.values["turn_reset_residual_speed_m_s"] == pytest.approx(0.0524, abs=2e-4)
    # printed sign of (5.7): the "braking" speeds the robot up
    assert rep.values["turn_printed_residual_speed_m_s"] > 0.2
    fs = rep.values["full_stop_brake"]
    assert fs["theta_max"] == pytest.approx(0.1416, abs=2e-4)
    assert fs["phi"] == pytest.approx(np.pi / 4, abs=1e-4)


def test_figure2_sigmas(rep):
    s = rep.values["sigma_gamma3_t_gt_4"]
    assert 0.01 < s["kinematic"]["std"] < 0.03  # the experiment measured 0.018
    assert s["gait"]["std"] < 1e-6  # the gaits end on exact rest
    kin = rep.trajectories["kinematic"]
    assert np.ptp(np.asarray(jsphere.energy_along(jsphere.RobotParams.paper(), kin))[np.asarray(kin.ts) > 4.0]) < 1e-7
    # after 4 s the omniwheels are stopped in both runs ("after which the omniwheels stopped")
    gait = rep.trajectories["gait_8s"]
    late = np.asarray(gait.ts) > 4.0
    assert late.sum() == 400 and np.all(np.diff(np.asarray(gait.ts)[late]) > 0)
    np.testing.assert_allclose(np.asarray(gait.ts)[late], np.asarray(kin.ts)[np.asarray(kin.ts) > 4.0], atol=1e-12)
    for tr in (kin, gait):
        assert np.max(np.abs(np.asarray(tr.chi_dot)[np.asarray(tr.ts) > 4.0])) < 1e-12


def test_table_lists_every_paper_number(rep):
    table = rep.table()
    for number in ("0.864", "0.13", "0.018", "0.001", "344.6", "369.2", "0.852", "519.4", "482.4"):
        assert number in table, number


def test_figure_frame():
    xf, yf = jsphere.to_figure_frame(0.2592, 0.0036)
    assert float(xf) == pytest.approx(-0.0036) and float(yf) == pytest.approx(0.2592)


def test_paper_parameters_follow_from_paper_numbers(rep):
    """R_m and j solve Omega_1 = 0.864 after (5.1) and Omega_2 = 0.852 after the turn (5.6)."""
    base = jsphere.RobotParams.paper()

    def residual(u):
        p = base.replace(R_m=u[0] * 1e-3, j=u[1] * 1e-4)
        a = jsphere.simulate_gaits(p, [jsphere.acceleration(), jsphere.braking()])
        t = jsphere.simulate_gaits(
            p, [jsphere.acceleration(), jsphere.turn(), jsphere.braking(phi=np.pi / 4)], reset=[True, None]
        )
        i_a = np.nonzero(np.asarray(a.segment) == 0)[0][-1]
        i_t = np.nonzero(np.asarray(t.segment) == 1)[0][-1]
        return np.array([float(a.Omega[i_a, 1]) - 0.864, float(t.Omega[i_t, 1]) - 0.852])

    u = np.array([27.0, 2.7])
    for _ in range(6):
        r = residual(u)
        J = np.stack([(residual(u + h) - r) / 1e-6 for h in 1e-6 * np.eye(2)], axis=1)
        u = u - np.linalg.solve(J, r)
    assert u[0] * 1e-3 == pytest.approx(PAPER_R_M, rel=1e-6)
    assert u[1] * 1e-4 == pytest.approx(PAPER_J, rel=1e-5)


def test_cli_compile_for_one_run_leaves_a_running_backend_and_a_users_level_alone(monkeypatch):
    from jsphere.cli.compilation import compile_for_one_run

    jsphere.RobotParams.paper().R0.block_until_ready()  # the CPU client exists
    monkeypatch.setenv("XLA_FLAGS", "--xla_cpu_enable_fast_math=false")
    assert compile_for_one_run() is False
    assert os.environ["XLA_FLAGS"] == "--xla_cpu_enable_fast_math=false"
    monkeypatch.setenv("XLA_FLAGS", "--xla_backend_optimization_level=2")
    assert compile_for_one_run() is False  # the user's own level wins
    monkeypatch.setenv("XLA_FLAGS", "--xla_backend_optimization_level=0")
    assert compile_for_one_run() is True


def test_setting_up_the_paper_robot_and_gaits_compiles_nothing():
    """Python and NumPy values become device arrays without XLA programs: each one would be
    compiled in a first `jsphere reproduce` and loaded from the cache in every later one."""
    code = (
        "from jax._src.interpreters import pxla\n"
        "n = [0]\n"
        "orig = pxla.lower_sharding_computation\n"
        "def count(*a, **k):\n"
        "    n[0] += 1\n"
        "    return orig(*a, **k)\n"
        "pxla.lower_sharding_computation = count\n"
        "import jsphere\n"
        "jsphere.enable_x64()\n"
        "p = jsphere.RobotParams.paper()\n"
        "g = [jsphere.acceleration(), jsphere.turn(), jsphere.braking(theta_max=0.12, phi=0.7)]\n"
        "c = jsphere.kinematic_control(p, jsphere.straight_line(0.13), t_stop=4.0)\n"
        "print('programs', n[0])\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip().splitlines()[-1] == "programs 0", out


def test_cli_reproduce_writes_table_json_and_figures(tmp_path, capsys, rep):
    assert main(["reproduce", "--out", str(tmp_path), "--no-full-stop", "--no-cache"]) == 0
    out = capsys.readouterr().out
    assert "Omega_1 after acceleration" in out and "344.6" in out
    data = json.loads((tmp_path / "reproduce.json").read_text())
    assert data["values"]["Omega_after_acceleration"][1] == pytest.approx(0.864, abs=1e-6)
    for f in ("fig2_kinematic_vs_gaits.png", "fig3_trajectories.png", "straight_line_controls.png"):
        assert (tmp_path / f).stat().st_size > 10_000
    assert not list(tmp_path.glob(".*tmp*"))
