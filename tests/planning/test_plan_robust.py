"""Plans robust to the robot's uncertainty: parameter draws from a fit's covariance or a vary
table, the RK4 replay of a table against the plain simulator, the robust search's Jacobian
against finite differences, and (slow) a robust plan whose tail miss beats the nominal plan's
on fresh draws, with the reported numbers checked by an independent replay."""

import json
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jsphere
from jsphere._runtime.errors import InputError
from jsphere.model.names import get_value
from jsphere.planning.problem import Limits, Objective, _vec_targets
from jsphere.planning.robust import _robust_residuals, replay_end
from jsphere.planning.uncertainty import Uncertainty

NAMES = ("r_m[2]", "j", "I[2,2]", "I0")
REL_SD = np.array([0.03, 0.2, 0.1, 0.05])


def _fit_json(p, corr=None):
    vals = np.array([float(get_value(p, n)) for n in NAMES])
    C = np.eye(4) if corr is None else corr
    return {
        "free": list(NAMES),
        "values": dict(zip(NAMES, vals.tolist())),
        "stderr": dict(zip(NAMES, (np.abs(vals) * REL_SD).tolist())),
        "correlation": C.tolist(),
    }


def test_draws_follow_the_fit_covariance(paper):
    C = np.eye(4)
    C[0, 1] = C[1, 0] = 0.6
    C[2, 3] = C[3, 2] = -0.4
    fit = _fit_json(paper, C)
    u = Uncertainty.from_fit(fit)
    vals, stacked = u.draw(paper, 20000, seed=3)
    sd = np.array([fit["stderr"][n] for n in NAMES])
    mean = np.array([fit["values"][n] for n in NAMES])
    assert np.all(np.abs(vals.mean(0) - mean) < 4 * sd / math.sqrt(20000))
    assert np.allclose(vals.std(0), sd, rtol=0.03)
    assert np.allclose(np.corrcoef(vals.T), C, atol=0.03)
    # the stacked parameter sets hold the drawn values
    assert np.allclose(np.asarray(stacked.j), vals[:, 1])
    assert np.allclose(np.asarray(stacked.I[:, 2, 2]), vals[:, 2])
    # the same seed draws the same sets
    assert np.array_equal(u.draw(paper, 5, seed=3)[0], u.draw(paper, 5, seed=3)[0])


def test_draws_that_are_no_robot_are_drawn_again(paper):
    # j normal about 0 with a large sd: half the draws would be negative
    u = Uncertainty(("j", "I0"), ("normal", "uniform"), np.array([0.0, 0.001]), np.array([1e-4, 0.002]))
    with pytest.warns(DeprecationWarning, match=r"from_vary\(entries\) is deprecated; pass Uncertainty\(names"):
        old = Uncertainty.from_vary([("j", "normal", 0.0, 1e-4), ("I0", "uniform", 0.001, 0.002)])
    assert old.names == u.names and np.array_equal(old.a, u.a) and np.array_equal(old.b, u.b)
    vals, _ = u.draw(paper, 500, seed=0)
    assert np.all(vals[:, 0] >= 0) and np.all((vals[:, 1] >= 0.001) & (vals[:, 1] <= 0.002))


@pytest.mark.parametrize(
    "change, match",
    [
        (lambda f: f["stderr"].update(j=None), r"stderr\['j'\] is None: the fit did not determine j"),
        (lambda f: f.pop("correlation"), r"a fit result needs 'correlation'"),
        (lambda f: f.update(correlation=[[1.0, 0.0], [0.0, 1.0]]), r"correlation must be a finite symmetric 4 x 4"),
        (lambda f: f["values"].update(j="x"), r"values\['j'\] must be a finite number"),
    ],
)
def test_bad_fit_results_are_refused(paper, change, match):
    fit = _fit_json(paper)
    change(fit)
    with pytest.raises(InputError, match=match):
        Uncertainty.from_fit(fit, source="fit.json")


def test_bad_robust_requests_are_refused_before_any_work(paper):
    u = Uncertainty.from_fit(_fit_json(paper))
    R = jsphere.RobustOptions
    with pytest.raises(InputError, match=r"^plan: quantile must be in \[0, 1\)"):
        jsphere.plan(paper, (0.5, 0.0), robust=R(u, quantile=1.0))
    with pytest.raises(InputError, match=r"^plan: samples must be a whole number >= 2"):
        jsphere.plan(paper, (0.5, 0.0), robust=R(u, samples=1))
    with pytest.raises(InputError, match=r"^plan: uncertainty must be a jsphere.Uncertainty"):
        jsphere.plan(paper, (0.5, 0.0), robust=R({"j": 1}))
    with pytest.raises(InputError, match=r"^plan: robust must be a jsphere.RobustOptions"):
        jsphere.plan(paper, (0.5, 0.0), robust=u)
    with pytest.raises(InputError, match=r"^plan: a route .* is not robust"):
        jsphere.plan(paper, [(0.5, 0.0)], robust=R(u))
    # the deprecated spelling maps its keywords and says the new one
    with pytest.warns(DeprecationWarning, match=r"robust=jsphere.RobustOptions"):
        with pytest.raises(InputError, match=r"^plan_robust: robust_steps must be a whole number >= 1"):
            jsphere.plan_robust(paper, (0.5, 0.0), u, robust_steps=0)
    with pytest.warns(DeprecationWarning), pytest.raises(TypeError, match="unexpected keyword argument 'sample'"):
        jsphere.plan_robust(paper, (0.5, 0.0), u, sample=3)
    with pytest.raises(InputError, match=r"kind must be 'normal' or 'uniform'"):
        Uncertainty(("j",), ("lognormal",), np.array([0.0]), np.array([1.0]))


@pytest.mark.parametrize("mode", ["wheel_speeds", pytest.param("torques", marks=pytest.mark.slow)])
def test_rk4_replay_matches_the_plain_simulator(paper, mode):
    """`replay_end` (RK4 on the table's rows) against `simulate` (adaptive Dopri) on a smooth
    rest-to-rest table sampled at 100 Hz, for the paper's robot and a perturbed one."""
    T = 3.0
    ts = np.linspace(0.0, T, 301)
    s3 = np.sin(np.pi * ts / T) ** 3
    amp = np.array([4.0, -2.0, 1.0]) if mode == "wheel_speeds" else np.array([0.004, -0.002, 0.001])
    table = s3[:, None] * np.cos(np.pi * ts / T)[:, None] * amp[None, :]
    other = jsphere.set_value(jsphere.set_value(paper, "j", 4e-4), "I0", float(paper.I0) * 1.1)
    end = jax.jit(replay_end, static_argnums=3)
    for p in (paper, other):
        x, y, Om, g = end(p, ts, table, mode)
        ctrl = (jsphere.WheelSpeeds if mode == "wheel_speeds" else jsphere.Torques).from_samples(ts, table)
        tr = jsphere.simulate(p, jsphere.State.at_rest(p), ctrl, T, ts=ts, rtol=1e-10, atol=1e-12, max_steps=65536)
        assert abs(float(x) - float(tr.x[-1])) < 1e-7 and abs(float(y) - float(tr.y[-1])) < 1e-7
        assert np.allclose(np.asarray(Om), np.asarray(tr.Omega[-1]), atol=1e-7)
        assert abs(float(tr.x[-1])) > 1e-3  # the table moves the robot


@pytest.mark.slow
def test_replay_gradient_matches_finite_differences(paper):
    """The derivative of the replayed end position with respect to the table's amplitude, its
    duration and a parameter (`j`), by forward mode, against central differences."""
    n = 41

    def end(a):
        T = 2.0 + a[1]
        ts = jnp.linspace(0.0, 1.0, n) * T
        prof = jnp.sin(jnp.pi * ts / T) ** 3 * jnp.cos(jnp.pi * ts / T)
        table = a[0] * prof[:, None] * jnp.array([3.0, -1.0, 0.5])
        p = jsphere.set_value(paper, "j", a[2])
        x, y, Om, _ = replay_end(p, ts, table, "wheel_speeds")
        return jnp.concatenate([jnp.stack([x, y]), Om])

    a = jnp.array([1.5, 0.3, 3e-4])
    h = jnp.array([1e-5, 1e-5, 1e-8])
    E = jnp.diag(h)
    both = jax.jit(lambda a: (jax.jacfwd(end)(a), jax.vmap(end)(a + E), jax.vmap(end)(a - E)))
    J, up, down = (np.asarray(v) for v in both(a))
    for i in range(3):
        fd = (up[i] - down[i]) / (2 * float(h[i]))
        assert np.allclose(J[:, i], fd, rtol=1e-5, atol=1e-8 * np.max(np.abs(fd))), (i, J[:, i], fd)
        assert np.max(np.abs(fd)) > 0


@pytest.mark.slow
def test_robust_jacobian_matches_finite_differences(paper):
    """The forward-mode Jacobian of the robust residuals (all samples: quantile 0) through the
    nominal rollout and the vmapped wheel-speed replays, against central differences."""
    s = jsphere.PlanSettings(n_tilt=2, n_spin=1, n_steps=8)
    lim, obj = Limits(), Objective()
    u = Uncertainty.from_fit(_fit_json(paper))
    _, samples = u.draw(paper, 2, seed=1)
    target = jnp.asarray(_vec_targets([(0.3, 0.1, None)])[0])
    z = jnp.array([0.0, 0.06, 0.0, 0.02, 0.05, 0.3])

    def r(z):
        return _robust_residuals(z, target, paper, samples, lim, obj, s, 2)

    eps = 1e-6
    E = eps * jnp.eye(z.shape[0])
    both = jax.jit(lambda z: (jax.jacfwd(r)(z), jax.vmap(r)(z + E), jax.vmap(r)(z - E)))
    J, up, down = (np.asarray(a) for a in both(z))
    for i in range(z.shape[0]):
        fd = (up[i] - down[i]) / (2 * eps)
        scale = max(1.0, float(np.max(np.abs(fd))))
        assert np.max(np.abs(J[:, i] - fd)) < 1e-5 * scale, i
    assert np.max(np.abs(J[:10])) > 1.0  # the terminal rows depend on the plan


@pytest.fixture(scope="module")
def robust(paper):
    u = Uncertainty.from_fit(_fit_json(paper), source="fit.json")
    s = jsphere.PlanSettings(n_tilt=4, n_spin=2, n_steps=32, adam_steps=60, lm_steps=30)
    return jsphere.plan(
        paper,
        (0.5, 0.3),
        settings=s,
        plan_options=jsphere.PlanOptions(restarts=3, rate=200.0),
        robust=jsphere.RobustOptions(u, samples=32, quantile=0.9, restarts=3, steps=20, check_samples=1000),
        progress=False,
    )


@pytest.mark.slow
def test_robust_plan_lands_better_and_its_numbers_replay(paper, robust):
    mc = robust.miss_mc
    assert mc["samples"] >= 1000
    assert mc["robust"]["p95"] <= mc["nominal"]["p95"]
    assert mc["robust"]["p95"] < 0.5 * mc["nominal"]["p95"]  # a clear gain for this uncertainty
    assert robust.plan.feasible, robust.plan.shortfall
    # an independent replay: a fresh draw with another seed, the plain simulator on a few sets
    u = robust.uncertainty
    vals, fresh = u.draw(paper, 1000, seed=12345)
    for key, pl in (("nominal", robust.nominal), ("robust", robust.plan)):
        d = jsphere.miss_distribution(pl, fresh)
        p95 = float(np.percentile(d["miss_m"], 95))
        assert abs(p95 - mc[key]["p95"]) < 0.2 * mc[key]["p95"], (key, p95, mc[key]["p95"])
        assert abs(float(np.mean(d["miss_m"])) - mc[key]["mean"]) < 0.15 * mc[key]["mean"]
        cols = pl.table()
        ctrl = jsphere.WheelSpeeds.from_samples(cols["t"], np.stack([cols[f"chi_dot_{i}"] for i in (1, 2, 3)], 1))
        for k in range(3):
            p = jax.tree_util.tree_map(lambda v, k=k: v[k], fresh)
            tr = jsphere.simulate(p, jsphere.State.at_rest(p), ctrl, float(cols["t"][-1]), max_steps=65536)
            miss = math.hypot(float(tr.x[-1]) - pl.target[0], float(tr.y[-1]) - pl.target[1])
            assert abs(miss - d["miss_m"][k]) < 2e-6, (key, k, miss, d["miss_m"][k])


@pytest.mark.slow
def test_cli_plan_robust_writes_miss_mc(paper, tmp_path):
    from jsphere.cli.app import main

    fit = tmp_path / "fit.json"
    fit.write_text(json.dumps(_fit_json(paper) | {"params": paper.to_dict()}))
    out = tmp_path / "robust.csv"
    rc = main(
        ["plan", "--to", "0.4", "0.0", "--robust", str(fit), "--samples", "8", "--rate", "100"]
        + ["--restarts", "2", "--no-plots", "--no-cache", "--out", str(out)]
    )
    assert rc == 0
    info = json.loads(out.with_suffix(".json").read_text())
    for key in ("nominal", "robust"):
        assert set(info["miss_mc"][key]) >= {"mean", "p95"}
    assert info["miss_mc"]["samples"] == 1000
    assert info["robust"]["names"] == list(NAMES)
    assert info["miss_mc"]["robust"]["p95"] <= info["miss_mc"]["nominal"]["p95"] * 1.0001


def test_cli_reads_a_fit_result_or_a_study_as_uncertainty(paper, tmp_path):
    from jsphere.cli.plan import uncertainty_of

    fit = tmp_path / "fit.json"
    fj = _fit_json(paper)
    fj["values"]["j"] = 3e-4
    fit.write_text(json.dumps(fj | {"params": paper.replace(j=3e-4).to_dict()}))
    u, p = uncertainty_of(fit)
    assert u.names == NAMES and u.kinds == ("normal",) * 4
    assert float(p.j) == 3e-4  # the nominal robot is the fit's estimate
    study = tmp_path / "study.toml"
    study.write_text('[vary]\nj = ["uniform", 2.0e-4, 3.5e-4]\n"r_m[2]" = ["normal", -0.0271, 1e-4]\n')
    u, p = uncertainty_of(study)
    assert u.names == ("j", "r_m[2]") and u.kinds == ("uniform", "normal")
    assert float(p.r_m[2]) == -0.0271
    with pytest.raises(InputError, match=r"expected a fit result \(.json\) or a Monte-Carlo study \(.toml\)"):
        uncertainty_of(tmp_path / "x.csv")
