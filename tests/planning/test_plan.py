"""Gait families and planning: boundary conditions, the paper's gaits as special
cases, a rest-to-rest plan to a pose behind and beside the robot, the exported table replayed
through the plain simulator, infeasible requests, the full-stop braking of Section 5.2."""

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jsphere
from jsphere._runtime.errors import InputError
from jsphere.planning.rollout import rollout

# small search: 4 Fourier terms per tilt axis, 2 spin terms, 32 RK4 steps
SMALL = jsphere.PlanSettings(n_tilt=4, n_spin=2, n_steps=32, adam_steps=60, lm_steps=30)
FEW = jsphere.PlanOptions(restarts=2, rate=200.0)


@pytest.fixture(scope="module")
def planned(paper):
    """Behind and to the right of the robot, with a final heading: one target, 2 restarts."""
    return jsphere.plan(paper, (-0.5, -0.4), heading=0.8, settings=SMALL, plan_options=FEW)


def test_smooth_profile_vanishes_with_derivatives_at_the_ends():
    c = jnp.array([[0.1, -0.03, 0.02], [0.05, 0.01, -0.04]])
    for power, order in ((2, 1), (3, 2)):
        f = jsphere.Smooth(c, 3.0, power)
        derivs = [f]
        for _ in range(order + 1):
            prev = derivs[-1]
            derivs.append(lambda t, prev=prev: jax.jvp(prev, (t,), (jnp.ones_like(t),))[1])
        for t in (0.0, 3.0):
            for k in range(order + 1):
                assert np.max(np.abs(derivs[k](jnp.asarray(t)))) < 1e-12, (power, k, t)
            # the next derivative does not vanish in general
            assert np.max(np.abs(derivs[order + 1](jnp.asarray(t)))) > 1e-3


def test_tilt_to_gamma_is_smooth_through_upright_and_matches_euler_angles():
    th, ph = 0.23, -2.1
    g = jsphere.tilt_to_gamma(jnp.array([th * math.cos(ph), th * math.sin(ph)]))
    ref = np.array([math.sin(th) * math.cos(ph), math.sin(th) * math.sin(ph), math.cos(th)])
    np.testing.assert_allclose(g, ref, atol=1e-15)
    # second derivatives at u = 0 are finite and equal to the exact Hessian of (u1, u2, 1 - |u|^2/2)
    H = jax.jit(jax.hessian(jsphere.tilt_to_gamma))(jnp.zeros(2))
    np.testing.assert_allclose(H[2], -np.eye(2), atol=1e-12)
    np.testing.assert_allclose(H[:2], 0.0, atol=1e-12)
    assert np.all(np.isfinite(jax.jit(jax.jacfwd(jax.hessian(lambda u: jsphere.tilt_to_gamma(u)[2])))(jnp.zeros(2))))


def test_paper_gaits_are_special_cases(paper, straight):
    """Acceleration (5.1) and braking (5.3) written as members of the Smooth family (Fejer
    kernel, `paper_gait`) give the same motion and torques as the paper's sin^2 gaits."""
    fam = jsphere.simulate_gaits(paper, [jsphere.paper_gait(0.1), jsphere.paper_gait(-0.1)])
    np.testing.assert_allclose(fam.K, straight.K, atol=1e-12)
    np.testing.assert_allclose(fam.Omega, straight.Omega, atol=1e-10)
    np.testing.assert_allclose([fam.x[-1], fam.y[-1]], [straight.x[-1], straight.y[-1]], atol=1e-10)
    # and in any direction: a sin^2 turn at phi = pi/2 as a tilt vector along e2
    g = jsphere.paper_gait(0.1, math.pi / 2)
    ref = jsphere.turn()
    for t in (0.1, 0.5, 1.3):
        np.testing.assert_allclose(
            g.gamma(jnp.eye(3), jnp.asarray(t)), ref.gamma(jnp.eye(3), jnp.asarray(t)), atol=1e-15
        )


def test_rollout_matches_accurate_solver(paper, planned):
    """The search model (RK4, 32 steps) and simulate_gaits (Dopri8, rtol 1e-10) agree on the plan."""
    ro = eqx.filter_jit(rollout)(paper, planned.gaits[0], 32)
    tr = planned.trajectory
    assert abs(float(ro.x[-1]) - float(tr.x[-1])) < 2e-5
    assert abs(float(ro.y[-1]) - float(tr.y[-1])) < 2e-5
    np.testing.assert_allclose(ro.Omega[-1], tr.Omega[-1], atol=1e-4)


def test_plan_reaches_pose_at_rest_within_limits(paper, planned):
    pl = planned
    assert pl.feasible, pl.summary()
    assert pl.errors["position_m"] < 1e-3
    assert pl.errors["speed_m_s"] < 1e-3
    assert pl.errors["heading_rad"] < 1e-3
    assert all(r["ok"] for r in pl.limits_report.values())
    # the accurate trajectory itself ends there, at rest, upright, with zero torques (C2 ends)
    tr = pl.trajectory
    assert math.hypot(float(tr.x[-1]) + 0.5, float(tr.y[-1]) + 0.4) < 1e-3
    np.testing.assert_allclose(tr.gamma[-1], [0, 0, 1], atol=1e-12)
    np.testing.assert_allclose(tr.K[0], 0.0, atol=1e-12)
    np.testing.assert_allclose(tr.K[-1], 0.0, atol=1e-12)
    assert 0 < pl.limits_report["torque_N_m"]["max"] < 0.1


def test_csv_table_and_torque_replay(paper, planned, tmp_path):
    path = tmp_path / "plan.csv"
    planned.to_csv(path)
    header = path.read_text().splitlines()[0].split(",")
    N = paper.n_wheels
    want = ["t"] + [f"K_{i + 1}" for i in range(N)] + [f"chi_dot_{i + 1}" for i in range(N)] + ["x", "y"]
    assert header[: len(want)] == want
    assert header[len(want) : len(want) + 3] == ["gamma_1", "gamma_2", "gamma_3"]
    data = np.loadtxt(path, delimiter=",", skiprows=1)
    t = data[:, 0]
    np.testing.assert_allclose(np.diff(t)[:-1], 1 / 200.0, rtol=1e-9)
    assert abs(t[-1] - planned.duration) < 1e-12
    # at rest at the last row: no torque (C2 ends), wheels stopped up to the small residual spin of the shell
    np.testing.assert_allclose(data[-1, 1 : 1 + N], 0.0, atol=1e-9)
    assert np.max(np.abs(data[-1, 1 + N : 1 + 2 * N])) < 5e-3
    rep = jsphere.replay_errors(planned, mode="torques")
    assert rep["target_error_m"] < 2e-3, rep
    assert rep["path_deviation_m"] < 1e-4


@pytest.mark.slow
def test_infeasible_request_says_how_far_and_which_limit(paper):
    lim = jsphere.Limits(max_time=3.0, max_tilt=0.05)
    with pytest.raises(jsphere.PlanInfeasibleError) as e:
        jsphere.plan(paper, (-0.5, -0.4), heading=0.8, settings=SMALL, plan_options=FEW, limits=lim)
    msg = str(e.value)
    assert "mm" in msg and "tilt" in msg
    best = e.value.plan
    assert isinstance(best, jsphere.Plan) and not best.feasible
    assert best.errors["position_m"] > 1e-3 or not all(r["ok"] for r in best.limits_report.values())


@pytest.mark.slow
def test_full_stop_braking_of_the_paper(paper):
    """The braking gait (theta_max, phi) that stops the robot after acceleration and turn (5.2):
    theta_max = 0.14162, phi = 0.78539 (docs/model.md, section 8), found through the simulator."""

    def build(x):
        return [jsphere.acceleration(), jsphere.turn(), jsphere.braking(theta_max=x[0], phi=x[1])]

    x, info = jsphere.optimise_gaits(paper, build, jnp.array([0.1, math.pi / 4]), lambda tr: tr.Omega[-1, :2])
    assert info["residual"] < 1e-10
    assert abs(x[0] - 0.14162) < 5e-5 and abs(x[1] - 0.78539) < 5e-5


@pytest.mark.slow
def test_replay_wheel_speeds(planned):
    rep = jsphere.replay_errors(planned, mode="wheel_speeds")
    assert rep["target_error_m"] < 2e-3, rep


@pytest.mark.slow
@pytest.mark.parametrize("half", [0, 1])
def test_target_sweep_2m_square_and_replays(paper, half):
    """Targets over the 2 m x 2 m square around the start (behind and beside included), default
    settings, 1 kHz tables: < 1 mm, < 1 mm/s, limits respected; K and chi_dot replays < 2 mm."""
    xs = [-1.0, -0.35, 0.35, 1.0]
    targets = [(x, y) for x in xs for y in xs][8 * half : 8 * half + 8]
    plans = jsphere.plan_many(paper, targets, plan_options=jsphere.PlanOptions(restarts=4, rate=1000.0))
    for pl in plans:
        rep = {m: jsphere.replay_errors(pl, mode=m) for m in ("torques", "wheel_speeds")}
        print(
            f"target {pl.target[:2]}: T {pl.duration:.2f} s, error {1e3 * pl.errors['position_m']:.4f} mm, "
            f"speed {1e3 * pl.errors['speed_m_s']:.4f} mm/s, spin {pl.errors['spin_rad_s']:.1e} 1/s, "
            f"max |K| {pl.limits_report['torque_N_m']['max']:.4f} N m, max |chi_dot| "
            f"{pl.limits_report['wheel_speed_rad_s']['max']:.2f} rad/s, max tilt {pl.limits_report['tilt_rad']['max']:.3f}, "
            f"replay K {1e3 * rep['torques']['target_error_m']:.4f} mm, chi_dot {1e3 * rep['wheel_speeds']['target_error_m']:.4f} mm"
        )
        assert pl.feasible, pl.summary()
        assert pl.errors["position_m"] < 1e-3 and pl.errors["speed_m_s"] < 1e-3
        for m in rep:
            assert rep[m]["target_error_m"] < 2e-3


@pytest.mark.slow
def test_cli_plan(tmp_path):
    from jsphere.cli.app import main

    out = tmp_path / "plan.csv"
    rc = main(
        [
            "plan",
            "--to",
            "-0.3",
            "0.6",
            "--rate",
            "1000",
            "--out",
            str(out),
            "--no-plots",
            "--no-cache",
            "--restarts",
            "2",
        ]
    )
    assert rc == 0
    data = np.loadtxt(out, delimiter=",", skiprows=1)
    assert math.hypot(data[-1, 7] + 0.3, data[-1, 8] - 0.6) < 1e-3


# ------------------------------------------------------------------ bad requests (checked before any work)

NAN, INF = float("nan"), float("inf")


@pytest.mark.parametrize(
    "to, kwargs, match",
    [
        ((NAN, 0.0), {}, r"plan: target x must be a finite number \[m\]; got nan"),
        ((INF, 0.0), {}, r"plan: target x must be a finite number \[m\]; got inf"),
        ((0.5, -INF), {}, r"plan: target y must be a finite number"),
        ((0.5,), {}, r"plan: to must be the target \(x, y\)"),
        ((0.5, 0.0), {"heading": NAN}, r"plan: heading must be a finite number"),
        ((0.5, 0.0), {"heading": INF}, r"plan: heading must be a finite number"),
        (
            (0.5, 0.0),
            {"plan_options": jsphere.PlanOptions(rate=0.0)},
            r"plan: rate must be a finite number > 0 \[Hz\]; got 0.0",
        ),
        ((0.5, 0.0), {"plan_options": jsphere.PlanOptions(rate=-5.0)}, r"plan: rate must be a finite number > 0"),
        ((0.5, 0.0), {"plan_options": jsphere.PlanOptions(rate=1e9)}, r"rows over max_time"),
        (
            (0.5, 0.0),
            {"plan_options": jsphere.PlanOptions(restarts=0)},
            r"plan: restarts must be a whole number >= 1; got 0",
        ),
        (
            (0.5, 0.0),
            {"plan_options": jsphere.PlanOptions(restarts=2.5)},
            r"plan: restarts must be a whole number >= 1; got 2.5",
        ),
        ((0.5, 0.0), {"plan_options": jsphere.PlanOptions(restarts=True)}, r"plan: restarts must be a whole number"),
        ((0.5, 0.0), {"plan_options": jsphere.PlanOptions(seed=-1)}, r"plan: seed must be a whole number >= 0"),
        ((0.5, 0.0), {"limits": "fast"}, r"plan: limits must be a jsphere.Limits"),
    ],
)
def test_plan_request_is_checked_before_any_work(paper, to, kwargs, match):
    with pytest.raises(InputError, match=match):
        jsphere.plan(paper, to, **kwargs)


def test_moved_keywords_warn_and_keep_working(paper):
    """`restarts=`, `rate=`, ... moved into `PlanOptions`: they still reach it, with a warning
    naming the new spelling (the request is checked with their values)."""
    with pytest.warns(
        DeprecationWarning, match=r"plan: rate= is deprecated; pass plan_options=PlanOptions\(rate=...\)"
    ):
        with pytest.raises(InputError, match=r"plan: rate must be a finite number > 0"):
            jsphere.plan(paper, (0.5, 0.0), rate=0.0)
    with pytest.warns(DeprecationWarning, match=r"plan_route: restarts= is deprecated"):
        with pytest.raises(InputError, match=r"plan_route: restarts must be a whole number >= 1"):
            jsphere.plan_route(paper, [(0.5, 0.0)], restarts=0)
    with pytest.warns(DeprecationWarning, match=r"plan_many: tol_speed= is deprecated"):
        with pytest.raises(InputError, match=r"plan_many: tol_speed must be a finite number > 0"):
            jsphere.plan_many(paper, [(0.5, 0.0)], tol_speed=-1.0)
    with pytest.raises(TypeError, match="unexpected keyword argument 'restart'"):
        jsphere.plan(paper, (0.5, 0.0), restart=2)
    with pytest.raises(InputError, match=r"plan: plan_options must be a jsphere.PlanOptions"):
        jsphere.plan(paper, (0.5, 0.0), plan_options={"restarts": 2})


def test_plan_many_and_route_requests_are_checked(paper):
    with pytest.raises(InputError, match=r"plan_many: target 1 x must be a finite number"):
        jsphere.plan_many(paper, [(0.5, 0.0), (NAN, 0.0)])
    with pytest.raises(InputError, match=r"plan_many: tol_position must be a finite number > 0"):
        jsphere.plan_many(paper, [(0.5, 0.0)], plan_options=jsphere.PlanOptions(tol_position=0.0))
    with pytest.raises(InputError, match=r"plan_many: targets must be a non-empty list"):
        jsphere.plan_many(paper, [])
    with pytest.raises(InputError, match=r"plan_route: target 0 heading must be a finite number"):
        jsphere.plan_route(paper, [(0.5, 0.0, NAN), (1.0, 0.0)])
    # `plan` with waypoints is a route
    with pytest.raises(InputError, match=r"^plan: target 0 heading must be a finite number"):
        jsphere.plan(paper, [(0.5, 0.0, NAN), (1.0, 0.0)])
    with pytest.raises(InputError, match=r"^plan: a route gives each waypoint's heading"):
        jsphere.plan(paper, [(0.5, 0.0), (1.0, 0.0)], heading=1.0)


@pytest.mark.parametrize(
    "make, match",
    [
        (lambda: jsphere.Limits(max_torque=-1.0), r"Limits.max_torque must be a positive number"),
        (lambda: jsphere.Limits(max_wheel_speed=NAN), r"Limits.max_wheel_speed must be a positive number"),
        (lambda: jsphere.Limits(max_tilt=True), r"Limits.max_tilt must be a positive number"),
        (lambda: jsphere.Limits(max_time=INF), r"Limits.max_time must be a finite number of seconds"),
        (lambda: jsphere.Limits(min_time=NAN), r"Limits.min_time must be a finite number of seconds"),
        (lambda: jsphere.Limits(max_time=0.5), r"need 0 < min_time < max_time"),
        (lambda: jsphere.Objective(energy=NAN), r"Objective: energy must be a finite number >= 0"),
        (lambda: jsphere.Objective(time=-1.0), r"Objective: time must be a finite number >= 0"),
        (lambda: jsphere.Objective(position_scale=0.0), r"Objective: position_scale must be a finite number > 0"),
        (lambda: jsphere.Objective(margin=1.0), r"Objective.margin must be a number in \[0, 1\)"),
        (lambda: jsphere.PlanSettings(n_steps=0), r"PlanSettings: n_steps must be a whole number >= 1"),
        (lambda: jsphere.PlanSettings(learning_rate=NAN), r"PlanSettings: learning_rate must be a finite number > 0"),
    ],
)
def test_limits_objective_settings_are_checked(make, match):
    with pytest.raises(InputError, match=match):
        make()


@pytest.mark.parametrize(
    "make, match",
    [
        (
            lambda: jsphere.acceleration(theta_max=NAN),
            r"acceleration: theta_max must be a finite number \[rad\]; got nan",
        ),
        (lambda: jsphere.braking(phi=INF), r"braking: phi must be a finite number \[rad\]; got inf"),
        (lambda: jsphere.turn(T=NAN), r"turn: T must be a finite number \[s\]; got nan"),
        (lambda: jsphere.acceleration(theta_max="0.1"), r"acceleration: theta_max must be a finite number"),
        (lambda: jsphere.acceleration(period=0.0), r"acceleration: period must be a positive number"),
        (lambda: jsphere.Gait(theta=jsphere.SinSquared(0.1), T=INF), r"Gait.T must be a positive duration"),
        (lambda: jsphere.paper_gait(NAN), r"paper_gait: theta_max must be a finite number"),
        (lambda: jsphere.smooth_gait([[0.1, NAN], [0.0, 0.0]]), r"smooth_gait: tilt_coeffs must be a finite number"),
        (lambda: jsphere.smooth_gait([[0.1, 0.0], [0.0, 0.0]], T=INF), r"smooth_gait: T must be a positive number"),
    ],
)
def test_gait_constructors_reject_non_finite_parameters(make, match):
    with pytest.raises(InputError, match=match):
        make()
