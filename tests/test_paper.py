"""Section 5 of the paper: the numbers `jsphere reproduce` reports, and the CLI."""

import json

import numpy as np
import pytest

import jsphere
from jsphere._params import PAPER_J, PAPER_R_M
from jsphere.cli import main


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
        t = jsphere.simulate_gaits(p, [jsphere.acceleration(), jsphere.turn(), jsphere.braking(phi=np.pi / 4)], reset=[True, None])
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


def test_cli_reproduce_writes_table_json_and_figures(tmp_path, capsys, rep):
    assert main(["reproduce", "--out", str(tmp_path), "--no-full-stop", "--no-cache"]) == 0
    out = capsys.readouterr().out
    assert "Omega_1 after acceleration" in out and "344.6" in out
    data = json.loads((tmp_path / "reproduce.json").read_text())
    assert data["values"]["Omega_after_acceleration"][1] == pytest.approx(0.864, abs=1e-6)
    for f in ("fig2_kinematic_vs_gaits.png", "fig3_trajectories.png", "straight_line_controls.png"):
        assert (tmp_path / f).stat().st_size > 10_000
    assert not list(tmp_path.glob(".*tmp*"))
