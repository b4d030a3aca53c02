"""Feedback along a plan (`jsphere.track`): the Jacobians, the regulators, the table, the
closed loop on a robot that is not the model, the command line."""

import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.linalg

import jsphere
from jsphere.model.names import set_value
from jsphere.model.params import derive
from jsphere.model.state import State, state_error, state_plus
from jsphere.planning.tracking.flow import interval, linearise, reference
from jsphere.planning.tracking.lqr import (
    Weights,
    closed_loop_eigenvalues,
    complement,
    conserved_direction,
    terminal_regulator,
)
from jsphere.planning.tracking.table import read_track_csv
from jsphere.planning.tracking.track import gains

P = jsphere.RobotParams.paper()
H = 0.02  # 50 Hz: small tests


def _bump(T=1.0, rate=200.0):
    """A short torque table that rolls the robot a little and stops the torques."""
    t = np.arange(int(T * rate) + 1) / rate
    s = np.sin(np.pi * t / T) ** 2
    K = 0.01 * s[:, None] * np.array([1.0, -0.3, -0.7])
    return t, K


@pytest.fixture(scope="module")
def small():
    t, K = _bump()
    return gains(t, K, P, rate=1.0 / H, weights=Weights())


def test_state_error_is_the_inverse_of_state_plus():
    z = State.at_rest(P, x=0.1, y=-0.2, psi=0.7).flatten()
    e = jnp.asarray(np.random.default_rng(1).normal(size=11)) * 0.2
    np.testing.assert_allclose(state_error(state_plus(z, e), z), e, atol=1e-12)
    assert np.all(np.asarray(state_error(z, z)) == 0)


def test_jacobians_match_finite_differences(small):
    zs, Kz = jnp.asarray(small["reference"]), jnp.asarray(small["K_ff"])
    zs = zs.at[-1].set(reference(P, zs[0], Kz[:-1], H)[-1])  # the held reference's own end
    A, B = linearise(P, zs[:-1], Kz[:-1], zs[1:], H)  # the shapes `gains` compiled
    d = derive(P)
    k = 30  # mid-manoeuvre: the robot tilted and rolling
    z, u, zn = zs[k], Kz[k], zs[k + 1]

    @jax.jit
    def g(e, du):
        return state_error(interval(P, d, state_plus(z, e), u + du, H), zn)

    eps = 1e-6
    e0, u0 = jnp.zeros(11), jnp.zeros(3)
    A_fd = np.stack([(g(eps * v, u0) - g(-eps * v, u0)) / (2 * eps) for v in jnp.eye(11)], axis=1)
    B_fd = np.stack([(g(e0, eps * v) - g(e0, -eps * v)) / (2 * eps) for v in jnp.eye(3)], axis=1)
    np.testing.assert_allclose(A[k], A_fd, atol=2e-7 * np.abs(A_fd).max())
    np.testing.assert_allclose(B[k], B_fd, atol=2e-7 * np.abs(B_fd).max())
    assert np.abs(np.asarray(g(e0, u0))).max() < 1e-14  # the reference is the plan's torques held


def test_terminal_regulator_conserved_mode_and_dense_riccati(small):
    z = State.at_rest(P, x=0.4, y=0.2, psi=0.4).flatten()
    A, B = linearise(P, z[None], jnp.zeros((1, 3)), z[None], H)
    A, B = A[0], B[0]
    w, s = conserved_direction(A, B)
    # exactly one mode the torques cannot change: omega_3 + 0.58 Omega_3 (momentum about the vertical)
    assert s[-1] < 1e-12 * s[0] and s[-2] > 1e-4
    w = np.asarray(w) / float(w[7])
    np.testing.assert_allclose(w[10], 0.58, atol=0.01)
    assert np.abs(np.delete(w, [7, 10])).max() < 1e-9
    W = Weights()
    R = W.r * jnp.eye(3)
    G, Pm, w, V = terminal_regulator(A, B, W.Q(), R)
    Ay, By, Qy = (np.asarray(m) for m in (V.T @ A @ V, V.T @ B, V.T @ W.Q() @ V))
    P_dense = scipy.linalg.solve_discrete_are(Ay, By, Qy, np.asarray(R))
    np.testing.assert_allclose(np.asarray(V.T @ Pm @ V), P_dense, rtol=1e-8, atol=1e-8 * np.abs(P_dense).max())
    G_dense = np.linalg.solve(np.asarray(R) + By.T @ P_dense @ By, By.T @ P_dense @ Ay) @ np.asarray(V).T
    np.testing.assert_allclose(np.asarray(G), G_dense, rtol=1e-8, atol=1e-8 * np.abs(G_dense).max())
    ev = closed_loop_eigenvalues(A, B, G)
    np.testing.assert_allclose(abs(ev[0]), 1.0, atol=1e-9)  # the conserved mode stays at 1
    assert np.all(np.abs(ev[1:]) < 0.999)  # every other mode decays
    np.testing.assert_allclose(np.asarray(complement(jnp.asarray(w))).T @ np.asarray(w), 0.0, atol=1e-12)


def test_gains_table_round_trip_and_limits(small, tmp_path):
    tr = jsphere.Tracker(**small)
    assert tr.ts.shape == (51,) and tr.G.shape == (51, 3, 11) and tr.K_ff.shape == (51, 3)
    assert np.all(tr.K_ff[-1] == 0)  # the terminal row: at rest at the target
    assert tr.eigenvalues[0] == pytest.approx(1.0, abs=1e-9) and tr.eigenvalues[1] < 1.0
    # the gains respect the torque limit under the expected errors
    ask = np.abs(tr.K_ff) + np.linalg.norm(tr.G * np.asarray(tr.weights.sigma()), axis=-1)
    assert ask.max() <= 0.1
    path = tmp_path / "track.csv"
    tr.to_csv(path)
    back = read_track_csv(path)
    np.testing.assert_array_equal(back["t"], tr.ts)
    np.testing.assert_array_equal(back["K_ff"], tr.K_ff)
    np.testing.assert_array_equal(back["G"], tr.G)
    np.testing.assert_array_equal(back["q"], tr.reference[:, 0:4])
    np.testing.assert_array_equal(back["Omega"], tr.reference[:, 11:14])
    header = path.read_text().splitlines()[0].split(",")
    assert header[:16] == "t K_1 K_2 K_3 x y qw qx qy qz omega_1 omega_2 omega_3 Omega_1 Omega_2 Omega_3".split()
    assert header[16] == "G_1_1" and header[-1] == "G_3_11" and len(header) == 16 + 33
    js = tr.to_json()
    assert js["rate_hz"] == 50.0 and js["weights"]["q_pos"] == Weights().q_pos


def test_a_tight_torque_limit_raises_r(small):
    t, K = _bump()
    tight = gains(t, K, P, rate=1.0 / H, weights=Weights(), max_torque=0.02)
    sigma = np.asarray(Weights().sigma())
    assert (np.abs(small["K_ff"]) + np.linalg.norm(small["G"] * sigma, axis=-1)).max() > 0.02
    assert tight["r_scale"] > 1
    assert (np.abs(tight["K_ff"]) + np.linalg.norm(tight["G"] * sigma, axis=-1)).max() <= 0.02


def test_weights_file_and_flags(tmp_path):
    import argparse

    from jsphere.cli.track import _weights

    f = tmp_path / "weights.toml"
    f.write_text("q_pos = 1e6\nr = 1e4\nexpected = [0.002, 0.01, 0.05]\n")
    ns = argparse.Namespace(weights=str(f), q_pos=None, q_att=100.0, q_rate=None, r=None)
    w = _weights(ns)
    assert (w.q_pos, w.q_att, w.r, w.expected) == (1e6, 100.0, 1e4, (0.002, 0.01, 0.05))
    f.write_text("q_position = 1\n")
    with pytest.raises(jsphere.InputError, match="q_position"):
        _weights(ns)


def test_a_table_that_is_not_a_track_table_is_refused(tmp_path):
    t, K = _bump(rate=20.0)
    plan = tmp_path / "plan.csv"
    jsphere.write_inputs_csv(plan, t, K, "torques")
    with pytest.raises(jsphere.InputError, match="not a track table"):
        read_track_csv(plan)


@pytest.mark.slow
def test_a_trial_that_is_not_finite_is_an_error_not_a_nan(small):
    from jsphere.planning.tracking.track import evaluate

    tr = jsphere.Tracker(**small)
    bad = set_value(P, "I[0,0]", float("nan"))
    robots = jax.tree_util.tree_map(lambda a, b: jnp.stack([a, b]), P, bad)
    with pytest.raises(jsphere.SolverFailure, match="1 of 2 open loop trials are not finite"):
        evaluate(tr, robots, conditions=jsphere.TrackConditions(settle=0.1))


@pytest.mark.parametrize(
    "argv, message",
    [
        (["track", "missing.csv"], "no such plan"),
        (["track", "PLAN", "--out", "track.txt"], ".csv"),
        (["track", "PLAN", "--rate", "0"], "rate"),
        (["track", "PLAN", "--q-pos", "-1"], "q_pos"),
        (["track", "PLAN", "--samples", "-3"], "samples"),
        (["track", "PLAN", "--vary", "study.json"], ".toml"),
    ],
)
def test_cli_bad_input_is_one_line_and_exit_2(tmp_path, capsys, argv, message):
    from jsphere.cli.app import main

    t, K = _bump(rate=20.0)
    plan = tmp_path / "plan.csv"
    jsphere.write_inputs_csv(plan, t, K, "torques")
    argv = [str(plan) if a == "PLAN" else a for a in argv]
    argv = [str(tmp_path / a) if a.endswith((".txt",)) else a for a in argv]
    code = main(argv + ([] if "--out" in argv else ["--out", str(tmp_path / "track.csv")]))
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and message in err[0]


# ----------------------------------------------------------------------------- the paper's robot, a real plan

TARGET = (0.4, 0.2)


@pytest.fixture(scope="module")
def planned(tmp_path_factory):
    pl = jsphere.plan(P, TARGET, plan_options=jsphere.PlanOptions(restarts=4, family="gait"))  # torque to spare
    folder = tmp_path_factory.mktemp("plan")
    pl.to_csv(folder / "plan.csv")
    (folder / "plan.json").write_text(json.dumps({"target": [*TARGET, None]}))
    return pl, folder


def _robot_off_the_model():
    """A robot several per cent off the paper's (the size of a fit's uncertainty)."""
    p = P
    for name, f in (("r_m[2]", 1.05), ("j", 1.10), ("I[0,0]", 1.03), ("I[1,1]", 0.96), ("I[2,2]", 1.04)):
        p = set_value(p, name, f * float(jsphere.get_value(P, name)))
    return p


def _replay(table, robot, gain, start, closed, settle=2.0, max_torque=0.1):
    """The rule of track.csv applied by hand: `K = K_ff - G e` from the row of the moment, held
    for one period (zero-order hold), the last row held; the robot integrated by `simulate`
    (the adaptive solver) one period at a time. Returns the end state and the largest |K|."""
    t = table["t"]
    h = float(t[1] - t[0])
    refs = np.concatenate(
        [
            table["q"],
            np.zeros((len(t), 4)),
            table["omega"],
            table["Omega"],
            table["x"][:, None],
            table["y"][:, None],
            np.zeros((len(t), 3)),
        ],
        axis=1,
    )

    @jax.jit
    def period(state, u):
        ctl = jsphere.Torques.from_samples(np.array([0.0, h]), jnp.stack([u, u]), kind="linear")
        return jsphere.simulate(robot, state, ctl, h).state(-1)

    state, umax = start, 0.0
    for k in range(len(t) - 1 + int(round(settle / h))):
        row = min(k, len(t) - 1)
        u = table["K_ff"][row]
        if closed:
            e = np.asarray(state_error(state.flatten(), jnp.asarray(refs[row])))
            u = u - table["G"][row] @ e
        umax = max(umax, float(np.max(np.abs(u))))
        state = period(state, jnp.asarray(gain * np.clip(u, -max_torque, max_torque)))
    return state, umax


@pytest.mark.slow
def test_closed_loop_lands_where_the_open_loop_misses(planned, tmp_path):
    pl, _ = planned
    tr = jsphere.track(pl, samples=0)
    tr.to_csv(tmp_path / "track.csv")
    table = read_track_csv(tmp_path / "track.csv")
    robot = _robot_off_the_model()
    gain = np.array([1.05, 0.95, 1.03])  # motor torque constants off by up to 5 %
    start = State.at_rest(robot, x=0.0024, y=-0.0018)  # 3 mm from the plan's start
    result = {}
    for closed in (False, True):
        s, umax = _replay(table, robot, gain, start, closed)
        miss = float(np.hypot(s.x - TARGET[0], s.y - TARGET[1]))
        speed = float(robot.R0 * np.linalg.norm(np.cross(np.asarray(s.Omega), np.asarray(s.gamma))))
        result[closed] = (miss, speed, umax)
    (m_open, _, _), (m_closed, v_closed, u_closed) = result[False], result[True]
    assert m_closed < 0.005 and m_closed * 5 < m_open
    assert v_closed < 0.005  # at rest
    assert u_closed <= 0.1  # within the torque limit, unsaturated


@pytest.mark.slow
def test_cli_end_to_end_with_its_defaults(planned, tmp_path):
    from jsphere.cli.app import main

    _, folder = planned
    out = tmp_path / "track.csv"
    assert main(["track", str(folder / "plan.json"), "--out", str(out)]) == 0
    info = json.loads(out.with_suffix(".json").read_text())
    mc = info["miss_mc"]
    assert mc["samples"] == 1000
    for loop in ("open_loop", "closed_loop"):
        assert all(np.isfinite(mc[loop][k]) for k in ("mean", "p95", "speed_p95", "max_torque_N_m"))
    assert mc["closed_loop"]["p95"] < 0.005 and 5 * mc["closed_loop"]["mean"] < mc["open_loop"]["mean"]
    assert info["target"] == list(TARGET)
    table = read_track_csv(out)
    assert table["G"].shape == (len(table["t"]), 3, 11)
    # robots drawn from a fit's estimate and covariance, as `plan --robust`
    names = ("r_m[2]", "j", "I[2,2]")
    vals = [float(jsphere.get_value(P, n)) for n in names]
    fit = tmp_path / "fit.json"
    fit.write_text(
        json.dumps(
            {
                "free": list(names),
                "values": dict(zip(names, vals)),
                "stderr": {n: 0.03 * abs(v) for n, v in zip(names, vals)},
                "correlation": np.eye(3).tolist(),
            }
        )
    )
    P.save(tmp_path / "robot.toml")
    argv = ["track", str(folder / "plan.csv"), "--robust", str(fit), "--params", str(tmp_path / "robot.toml")]
    assert main([*argv, "--samples", "64", "--out", str(tmp_path / "fit_track.csv")]) == 0
    mc = json.loads((tmp_path / "fit_track.json").read_text())["miss_mc"]
    assert mc["source"] == str(fit) and mc["samples"] == 64
    assert mc["closed_loop"]["p95"] < 0.005 < mc["open_loop"]["mean"]
