"""Direct plans (free torque profiles, multiple shooting with IPOPT): the transcription's
derivatives against JAX's own, the default plan to (0.4, 0.2) as short as direct optimal control
allows and within every limit on the accurate replay, its table replayed with linear torques, a
final heading, requests that cannot be met, and float32 refused."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jsphere
from jsphere._runtime.errors import InputError
from jsphere.planning import direct

#: the minimum-time manoeuvre to (0.4, 0.2) at the default limits that CasADi + IPOPT finds by
#: multiple shooting (`benchmarks/tasks.py plan`): a direct plan is no longer than 1.02 x it
CASADI_T = 2.34


@pytest.fixture(scope="module")
def planned(paper):
    return jsphere.plan(paper, (0.4, 0.2), plan_options=jsphere.PlanOptions(rate=200.0))


def _small(paper, heading=True, n=3):
    lay = direct._Layout(n, paper.n_wheels, heading)
    a = direct._args(paper, [0.3, 0.1, 0.4], np.zeros(6), jsphere.Objective(effort=0.5), jsphere.Limits())
    rest = np.asarray(jsphere.State.at_rest(paper).flatten())[direct.REDUCED]
    z = direct._start(lay, rest, [0.3, 0.1, 0.4], jsphere.Limits())
    rng = np.random.default_rng(0)
    z[:-1] += 1e-3 * rng.normal(size=z.size - 1)  # off the start's symmetries
    return lay, a, z, direct._Transcription(lay, a, 1)


def _dense(lay, a, z):
    """The constraints and objective of `z` as dense JAX functions of the whole vector."""

    def g(z):
        c = jax.vmap(lambda w: direct._block(w, a, lay.n, 1))(z[lay.blocks]).reshape(-1)
        return jnp.concatenate([c, direct._terminal(z[lay.end], a, lay.heading)])

    def f(z):
        return a.weights[0] * z[-1] + jnp.sum(jax.vmap(lambda w: direct._block_cost(w, a, lay.n))(z[lay.blocks]))

    return g, f


@pytest.mark.slow  # the dense Hessian of the whole problem compiles for tens of seconds
def test_sparse_derivatives_match_dense_ones(paper):
    """Every callable IPOPT is given against `jax.jacfwd` / `jax.hessian` of the whole problem:
    Jacobian and gradient exact, the Hessian of the Lagrangian to its differences' accuracy."""
    lay, a, z, tr = _small(paper)
    g, f = _dense(lay, a, z)
    zj = jnp.asarray(z)
    np.testing.assert_allclose(tr.constraints(z), g(zj), rtol=0, atol=1e-13)
    assert tr.objective(z) == pytest.approx(float(f(zj)), rel=1e-13)
    np.testing.assert_allclose(tr.gradient(z), jax.grad(f)(zj), rtol=0, atol=1e-12)
    J = np.zeros((len(g(zj)), z.size))
    rows, cols = lay.jacobian_structure
    np.add.at(J, (rows, cols), tr.jacobian(z))
    np.testing.assert_allclose(J, jax.jacfwd(g)(zj), rtol=0, atol=1e-11)
    lam = np.random.default_rng(1).normal(size=J.shape[0])
    sigma = 0.7
    H = np.zeros((z.size, z.size))
    rows, cols = lay.hessian_structure
    assert np.all(rows >= cols) and len(set(zip(rows, cols))) == len(rows)  # lower triangle, each once
    H[rows, cols] = tr.hessian(z, lam, sigma)
    exact = np.tril(jax.hessian(lambda z: sigma * f(z) + jnp.asarray(lam) @ g(z))(zj))
    scale = np.max(np.abs(exact))
    assert np.max(np.abs(H - exact)) < 1e-4 * scale  # forward differences: O(step) relative


def test_default_plan_is_direct_short_and_within_every_limit(planned):
    """The default family: no longer than the direct method's manoeuvre, on the target at rest,
    and every limit kept on the accurate replay (between knots too)."""
    pl = planned
    assert pl.family == "direct" and pl.feasible and pl.at_rest, pl.summary()
    assert pl.duration <= 1.02 * CASADI_T, pl.summary()
    assert pl.errors["position_m"] < 5e-4 and pl.errors["speed_m_s"] < 5e-4
    assert all(r["ok"] for r in pl.limits_report.values()), pl.limits_report
    # a minimum-time manoeuvre presses its limits: torque, wheel speed and tilt within 1 %
    for name in ("torque_N_m", "wheel_speed_rad_s", "tilt_rad"):
        r = pl.limits_report[name]
        assert r["max"] > 0.99 * r["limit"], (name, r)
    ts, K = pl.profile
    assert K.shape == (ts.size, 3) and np.all(K[[0, -1]] == 0.0)


def test_the_table_replayed_with_linear_torques_lands(paper, planned, tmp_path):
    """plan.csv's `K_i` at its rate, interpolated linearly, reach the target within 0.5 mm and
    0.5 mm/s in the plain simulator."""
    planned.to_csv(tmp_path / "plan.csv")
    data = np.genfromtxt(tmp_path / "plan.csv", delimiter=",", names=True)
    K = np.stack([data[f"K_{i}"] for i in (1, 2, 3)], axis=1)
    assert np.all(np.diff(data["t"]) > 0) and data["t"][1] == pytest.approx(1 / 200.0)
    ctrl = jsphere.Torques.from_samples(data["t"], K, kind="linear")
    tr = jsphere.simulate(paper, jsphere.State.at_rest(paper), ctrl, float(data["t"][-1]))
    miss = np.hypot(float(tr.x[-1]) - 0.4, float(tr.y[-1]) - 0.2)
    speed = float(paper.R0) * np.linalg.norm(np.cross(np.asarray(tr.Omega[-1]), np.asarray(tr.gamma[-1])))
    assert miss < 5e-4 and speed < 5e-4, (miss, speed)


@pytest.mark.slow
def test_a_final_heading_is_reached(paper):
    pl = jsphere.plan(paper, (0.3, -0.2), heading=0.8, plan_options=jsphere.PlanOptions(rate=100.0))
    assert pl.feasible and pl.errors["heading_rad"] < 1e-3, pl.summary()


@pytest.mark.slow
def test_a_request_out_of_reach_names_what_it_misses(paper):
    """0.4 m in at most 1.5 s is beyond the limits: the error says the search found no feasible
    point and holds the best plan."""
    lim = jsphere.Limits(max_time=1.5)
    with pytest.raises(jsphere.PlanInfeasibleError, match="direct search ended infeasible") as e:
        jsphere.plan(paper, (0.4, 0.2), limits=lim, plan_options=jsphere.PlanOptions(rate=100.0))
    assert e.value.plan is not None and not e.value.plan.feasible


def test_gaits_on_request_and_float32_refused(paper):
    with pytest.raises(InputError, match="family must be one of direct, gait"):
        jsphere.plan(paper, (0.4, 0.2), plan_options=jsphere.PlanOptions(family="spline"))
    p32 = jax.tree_util.tree_map(lambda v: jnp.asarray(v, jnp.float32) if jnp.ndim(v) >= 0 else v, paper)
    with pytest.raises(InputError, match="direct plan needs float64"):
        jsphere.plan(p32, (0.4, 0.2))
    with pytest.raises(InputError, match="settings must be a PlanSettings"):
        jsphere.plan_many(paper, [(0.4, 0.2)], settings=jsphere.DirectSettings())
    assert dataclasses.replace(jsphere.PlanOptions(), family="gait").family == "gait"


def test_a_robust_plan_refuses_a_direct_nominal(paper, planned):
    """A robust plan perturbs a gait plan: a direct plan given as its nominal is named."""
    u = jsphere.planning.uncertainty.Uncertainty(("j",), ("normal",), np.array([4e-4]), np.array([2e-5]))
    robust = jsphere.RobustOptions(u, nominal=planned)
    with pytest.raises(InputError, match="nominal is a direct plan; a robust plan starts from a gait plan"):
        jsphere.plan(paper, (0.4, 0.2), robust=robust)


@pytest.mark.slow
@pytest.mark.parametrize("to, heading", [((-1.0, -1.0), None), ((1.0, 1.0), 1.0), ((-1.0, 0.35), -2.0)])
def test_far_targets_behind_and_turned_are_met(paper, to, heading):
    """Up to 1.41 m away, behind the robot, with and without a final heading: feasible, on the
    target at rest on the accurate replay (its end moved by the replay's miss, solve by solve)."""
    pl = jsphere.plan(paper, to, heading=heading, plan_options=jsphere.PlanOptions(rate=100.0))
    assert pl.feasible and pl.errors["position_m"] < 1e-4 and pl.errors["speed_m_s"] < 1e-4, pl.summary()
