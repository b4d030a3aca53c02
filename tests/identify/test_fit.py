"""System identification: transforms, the fit, its checks, errors and the CLI.

The default tests share one small problem (2 wheel-speed trials of 1.5 s at 50 Hz, free
`R_m, j`), so the compiled functions are built once. The full recovery studies (5 trials,
wheel speeds and torques), the 20-seed honesty study and the benchmark-size fit are marked
`slow`.
"""

import json
import math
import os
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

import jsphere
from jsphere._runtime.fast_start import FastStart
from jsphere._runtime.private import equinox_errors_as
from jsphere._runtime.quick_compile import programs_run_by
from jsphere.cli.app import main
from jsphere.identify.data import pack_trials
from jsphere.identify.fit import adam_start
from jsphere.identify.free import FreeParams, apply_fixes, expand
from jsphere.identify.identifiability import identifiability, symmetry_directions
from jsphere.identify.residuals import _functions
from jsphere.identify.starts import nuisance_guess
from jsphere.model.rotations import quat_exp, quat_log
from jsphere.plots import fit_figures

TRUTH = {"R_m": 0.029, "j": 3.2e-4, "m0": 0.9, "I0": 0.011, "I": np.diag([0.018, 0.015, 0.025])}
FREE = "R_m,j"
OPTS = {"n_starts": 1, "adam_steps": 2, "max_iter": 15}


def make_trials(truth, n, t1, kind="wheel_speeds", seed=0, rate=50.0, **kw):
    out = []
    for i in range(n):
        u = jsphere.random_inputs(truth, t1, kind=kind, seed=seed * 100 + i)
        out.append(jsphere.synthetic_trial(truth, u, t1, rate=rate, seed=seed * 100 + i, name=f"t{i}", **kw))
    return out


@pytest.fixture(scope="module")
def small_truth():
    # R_m and j differ from the start (the paper's values); the rest is known
    return jsphere.RobotParams.paper().replace(R_m=0.029, j=3.2e-4)


@pytest.fixture(scope="module")
def small_trials(small_truth):
    return make_trials(small_truth, 2, 1.5, dropout=0.05)


@pytest.fixture(scope="module")
def small_fit(small_trials, tmp_path_factory):
    ckpt = tmp_path_factory.mktemp("fit") / "fit.ckpt.npz"
    return jsphere.fit(small_trials, jsphere.RobotParams.paper(), FREE, fix={"m": 2.5}, checkpoint=ckpt, **OPTS), ckpt


# ------------------------------------------------------------------ transforms and names


def test_expand_whole_fields_and_components():
    p = jsphere.RobotParams.paper()
    given = expand(p, "r_m[2],j,I")
    assert [g for g, _ in given] == ["r_m[2]", "j", "I"]
    assert given[2][1] == ["I[0,0]", "I[0,1]", "I[0,2]", "I[1,1]", "I[1,2]", "I[2,2]"]
    assert expand(p, "r_m")[0][1] == ["r_m[0]", "r_m[1]", "r_m[2]"]
    assert expand(p, ["I[1,0]"])[0][1] == ["I[0,1]"]  # symmetric: one entry


def test_transforms_round_trip_and_keep_inertia_positive_definite():
    p = jsphere.RobotParams.paper().replace(
        I=np.array([[0.016, 0.001, 0.0], [0.001, 0.017, 0.0005], [0.0, 0.0005, 0.023]])
    )
    fp = FreeParams(p, "I,R_m,j,m0", bounds={"j": (1e-5, 1e-3)})
    assert [s.kind for s in fp.slots] == ["cholesky", "log", "interval", "log"]
    back = fp.to_params(jnp.asarray(fp.theta0))
    for f in ("I", "r_m", "j", "m0"):
        np.testing.assert_allclose(np.asarray(getattr(back, f)), np.asarray(getattr(p, f)), rtol=1e-12, atol=1e-15)
    rng = np.random.default_rng(0)
    for _ in range(20):
        th = fp.theta0 + rng.normal(0, 2.0, fp.size)
        q = fp.to_params(jnp.asarray(th))
        assert np.all(np.linalg.eigvalsh(np.asarray(q.I)) > 0)
        assert 1e-5 < float(q.j) < 1e-3 and float(q.m0) > 0 and float(q.R_m) > 0
    vals = np.asarray(fp.physical(jnp.asarray(fp.theta0)))
    assert vals[fp.names.index("I[0,1]")] == pytest.approx(0.001)
    assert vals[fp.names.index("R_m")] == pytest.approx(float(p.R_m))


def test_quaternion_log_exp_are_inverse_and_smooth_at_zero():
    v = jnp.array([[0.3, -0.2, 0.1], [1e-10, 0.0, 0.0], [0.0, 0.0, 0.0]])
    np.testing.assert_allclose(np.asarray(quat_log(quat_exp(v))), np.asarray(v), atol=1e-14)
    import jax

    J = jax.jacfwd(lambda x: quat_log(quat_exp(x)))(jnp.zeros(3))
    np.testing.assert_allclose(np.asarray(J), np.eye(3), atol=1e-12)


# ------------------------------------------------------------------ the fit


@pytest.mark.slow
def test_small_fit_recovers_truth_within_standard_errors(small_fit, small_truth):
    res, _ = small_fit
    assert res.converged
    assert res.free == ["R_m", "j"]
    for name in res.free:
        truth = float(jsphere.get_value(small_truth, name))
        se = res.stderr[name]
        assert 0 < se < 0.2 * abs(truth)
        assert abs(res.values[name] - truth) < 4 * se, (name, res.values[name], truth, se)
    # the noise levels of synthetic_trial (1 mm per coordinate, 0.5 deg per axis) are recovered
    assert res.sigma_pos == pytest.approx(1e-3, rel=0.15)
    assert math.degrees(res.sigma_rot) == pytest.approx(0.5, rel=0.15)
    assert float(res.params.m) == 2.5 and float(res.params.R_m) == pytest.approx(res.values["R_m"])
    # the correlation is the covariance scaled by the standard errors, which are its diagonal's roots
    se = np.array([res.stderr[n] for n in res.free])
    np.testing.assert_allclose(se, np.sqrt(np.diag(res.covariance)), rtol=1e-12)
    np.testing.assert_allclose(res.correlation, res.covariance / np.outer(se, se), rtol=1e-10, atol=1e-14)
    assert all(t["rms_pos_m"] < 2e-3 for t in res.trials)


SPLIT_FIT = """
import json, jax, jsphere
jsphere.enable_x64()
jsphere.use_cpu_cores(2)
from jsphere.identify import residuals
meshes = []
mesh = residuals.trial_mesh
residuals.trial_mesh = lambda devices: meshes.append(len(devices)) or mesh(devices)
truth = jsphere.RobotParams.paper().replace(R_m=0.029, j=3.2e-4)
trials = []
for i in range(2):
    u = jsphere.random_inputs(truth, 1.5, kind="wheel_speeds", seed=i)
    trials.append(jsphere.synthetic_trial(truth, u, 1.5, rate=50.0, seed=i, name=f"t{i}", dropout=0.05))
res = jsphere.fit(trials, jsphere.RobotParams.paper(), "R_m,j", fix={"m": 2.5}, progress=False, **OPTS)
print(json.dumps({"values": res.values, "devices": sorted(set(meshes))}))
"""


def test_a_fit_split_over_two_cpu_devices_finds_the_one_device_values(small_fit):
    """With one CPU device per core, the residuals and Jacobians of the two trials are
    computed one per device: the fit ends within a hundredth of a standard error of the
    one-device fit (the solves' steps differ within their tolerance with the batch's size)."""
    env = dict(os.environ, JAX_PLATFORMS="cpu")
    env.pop("XLA_FLAGS", None)
    script = SPLIT_FIT.replace("**OPTS", ", ".join(f"{k}={v!r}" for k, v in OPTS.items()))
    out = subprocess.run([sys.executable, "-c", script], env=env, capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr[-3000:]
    got = json.loads(out.stdout.strip().splitlines()[-1])
    assert got["devices"] == [2]
    res = small_fit[0]
    for name, value in res.values.items():
        assert abs(got["values"][name] - value) < 0.01 * res.stderr[name], (name, got["values"][name], value)


@pytest.mark.slow
def test_result_json_loads_as_params_and_plots_are_written(small_fit, tmp_path):
    res, _ = small_fit
    written = res.save(tmp_path / "fit.json") + fit_figures(res, tmp_path, stem="fit")
    doc = json.loads((tmp_path / "fit.json").read_text())
    for key in (
        "params",
        "stderr",
        "correlation",
        "free",
        "cost",
        "iterations",
        "identifiability",
        "converged",
        "rms_pos_m",
        "rms_rot_deg",
    ):
        assert key in doc
    assert set(doc["stderr"]) == {"R_m", "j"}
    p = jsphere.RobotParams.load(tmp_path / "fit.json")
    assert float(p.j) == pytest.approx(res.values["j"])
    assert [w.name for w in written] == ["fit.json", "fit_overlay.png", "fit_residuals.png"]
    assert all(w.stat().st_size > 5000 for w in written[1:])
    assert not list(tmp_path.glob(".*tmp*"))


@pytest.mark.slow
def test_gradient_of_the_loss_agrees_with_finite_differences(small_trials):
    """`J^T r` (forward mode through diffrax) against central differences of the cost, with
    respect to the free parameters and one nuisance parameter. At the fit's `rtol = 1e-6` the
    cost has jumps of ~0.01-0.3 from the adaptive step control (central differences with steps
    of 1e-2 then disagree by 0.3-7 %, depending on the processor's rounding), so this check
    solves at `rtol = 1e-10`, where they agree to ~1e-5 with steps of 1e-3."""
    p = jsphere.RobotParams.paper()
    fp = FreeParams(p, FREE)
    data = pack_trials(small_trials, p)
    fns = _functions(fp, data.kind, 1e-10, 1e-12, 16384)
    d = data.arrays()
    sig = jnp.array([1e-3, math.radians(0.5)])
    th = fp.theta0[None]
    nu = nuisance_guess(data, p)[None]

    def cost_and_grad(th, nu):
        res, ok, J, _ = fns.jacobian(p, jnp.asarray(th), jnp.asarray(nu), d, sig)
        assert bool(np.all(ok))
        res, J = np.asarray(res), np.asarray(J)
        return (
            0.5 * float((res * res).sum()),
            np.einsum("stkp,stk->sp", J[..., : fp.size], res),
            np.einsum("stkn,stk->stn", J[..., fp.size :], res),
        )

    _, g, g_nu = cost_and_grad(th, nu)
    for k in range(fp.size):
        e = np.zeros_like(th)
        e[0, k] = 1e-3
        fd = (cost_and_grad(th + e, nu)[0] - cost_and_grad(th - e, nu)[0]) / 2e-3
        assert fd == pytest.approx(g[0, k], rel=1e-3)
    assert abs(g[0, 0]) > 100 and abs(g[0, 1]) > 10  # far from the optimum: a real test
    e = np.zeros_like(nu)
    e[0, 0, 1] = 1e-3  # Omega0_y of trial 0 [1/s]
    fd = (cost_and_grad(th, nu + e)[0] - cost_and_grad(th, nu - e)[0]) / 2e-3
    assert fd == pytest.approx(g_nu[0, 0, 1], rel=1e-2)


@pytest.mark.slow
def test_killed_fit_resumes_from_checkpoint(small_trials, small_fit, tmp_path):
    res_full, _ = small_fit
    ckpt = tmp_path / "c.npz"

    def kill_at_second_step(line):
        if "LM stage 1 it   2" in line:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        jsphere.fit(
            small_trials,
            jsphere.RobotParams.paper(),
            FREE,
            fix={"m": 2.5},
            checkpoint=ckpt,
            progress=kill_at_second_step,
            **OPTS,
        )
    assert ckpt.exists()
    lines = []
    res = jsphere.fit(
        small_trials, jsphere.RobotParams.paper(), FREE, fix={"m": 2.5}, checkpoint=ckpt, progress=lines.append, **OPTS
    )
    assert any("resuming" in s and "stage 1, iteration 2" in s for s in lines)
    assert not any("adam" in s or "LM stage 1 it   1 " in s for s in lines)  # nothing is repeated
    assert res.converged
    for n in res.free:
        assert res.values[n] == pytest.approx(res_full.values[n], abs=0.2 * res_full.stderr[n])
    # another configuration does not pick up this checkpoint, and says so
    lines = []
    with pytest.raises(KeyboardInterrupt), pytest.warns(UserWarning, match="is from another fit"):
        jsphere.fit(
            small_trials,
            jsphere.RobotParams.paper(),
            FREE,
            fix={"m": 2.5},
            checkpoint=ckpt,
            seed=1,
            progress=lambda s: lines.append(s) or kill_at_second_step(s),
            **{k: v for k, v in OPTS.items()},
        )
    assert not any("resuming" in s for s in lines)


def test_wheel_speed_motion_does_not_depend_on_the_mass_scale(small_truth, small_trials):
    """The invariance `identifiability` names: inertias, m0 + m and m r_m scaled together."""
    p = small_truth
    s = 1.3
    q = p.replace(I=p.I * s, I0=p.I0 * s, j=p.j * s, m0=s * (p.m0 + p.m) - p.m, R_m=p.R_m * s)
    u = jsphere.random_inputs(p, 1.5, seed=0)
    ts = np.linspace(0, 1.5, 31)
    a = jsphere.simulate(p, jsphere.State.at_rest(p), u, 1.5, ts=ts, rtol=1e-10, atol=1e-12)
    b = jsphere.simulate(q, jsphere.State.at_rest(q), u, 1.5, ts=ts, rtol=1e-10, atol=1e-12)
    assert float(jnp.max(jnp.abs(a.x - b.x))) < 1e-8 and float(jnp.max(jnp.abs(a.q - b.q))) < 1e-8
    assert float(jnp.max(jnp.abs(a.x))) > 1e-2


def test_identifiability_names_the_mass_scale_and_what_to_fix():
    p = jsphere.RobotParams.paper()
    fp = FreeParams(p, "R_m,j,I0,m0,I[2,2]")
    vals = np.asarray(fp.physical(jnp.asarray(fp.theta0)))
    e = symmetry_directions(fp.names, vals, p)["mass_scale"]
    rng = np.random.default_rng(0)
    es = e / vals / np.linalg.norm(e / vals)  # the direction in relative units
    Js = 100.0 * rng.normal(size=(50, fp.size))  # residuals per relative change: well determined ...
    Js -= np.outer(Js @ es, es)  # ... except along the mass scale

    def F(Js):  # information in physical units
        return (Js / vals).T @ (Js / vals)

    rep = identifiability(fp, vals, F(Js), 1.0, p)
    assert rep["symmetries"]["mass_scale"]["relative_sd"] > 1e3
    assert any("scaling every inertia" in w and "--fix m0=" in w for w in rep["warnings"])
    assert len(rep["warnings"]) == 1 and rep["condition_number"] > 1e10
    full = identifiability(fp, vals, F(Js) + np.outer(es / vals, es / vals) * 1e4, 1.0, p)
    assert not full["warnings"]


# ------------------------------------------------------------------ bad inputs


@pytest.mark.parametrize(
    "free, fix, bounds, match",
    [
        ("R_m,bogus", None, None, "unknown parameter 'bogus'"),
        ("R_m", {"mass": 2.0}, None, "unknown parameter 'mass'"),
        ("R_m,j", {"j": 1e-4}, None, "'j' is both free"),
        ("I", {"I[0,0]": 0.02}, None, "both free"),
        ("r_m[2]", {"R_m": 0.02}, None, "both free"),
        ("R_m,j", None, {"j": (5e-4, 1e-3)}, r"exclude the start value"),
        ("R_m,j", None, {"j": (1e-3, 1e-4)}, "lower bound must be below"),
        ("R_m", None, {"j": (0, 1)}, "not a free parameter"),
        ("R_m,r_m[2]", None, None, "overlap"),
        ("j,j", None, None, "named twice"),
        ("wheel_n", None, None, "unit vectors"),
        ("I[3,0]", None, None, "does not fit I"),
        ("R_m", {"m": "heavy"}, None, "must be a number"),
        ("R_m", {"m": -1.0}, None, "RobotParams.m: must be > 0"),
        ("R_m", {"I": [1, 2]}, None, "expected a value of shape"),
        ("", None, None, "no free parameters"),
    ],
)
def test_bad_fit_configuration_is_reported(small_trials, free, fix, bounds, match):
    with pytest.raises(ValueError, match=match):
        jsphere.fit(small_trials, jsphere.RobotParams.paper(), free, fix=fix, bounds=bounds)


def test_trials_that_do_not_fit_the_robot_are_reported(small_trials):
    p = jsphere.RobotParams.paper()
    t = small_trials[0]
    four = jsphere.Trial(
        t.t, t.x, t.y, t.q, np.concatenate([np.asarray(t.inputs), np.zeros((len(t.t), 1))], 1), t.kind, name="four"
    )
    with pytest.raises(ValueError, match="inputs for 4 wheels .* the robot has 3"):
        jsphere.fit([four], p, "R_m")
    torq = jsphere.Trial(t.t, t.x, t.y, t.q, t.inputs, "torques", name="tq")
    with pytest.raises(ValueError, match="same input kind"):
        jsphere.fit([t, torq], p, "R_m")
    with pytest.raises(ValueError, match="no trials"):
        jsphere.fit([], p, "R_m")
    with pytest.raises(ValueError, match="n_starts must be a whole number >= 1"):
        jsphere.fit([t], p, "R_m", n_starts=0)


def test_whole_field_and_alias_entries_of_stderr():
    from jsphere.identify.report import _assemble_named

    p = jsphere.RobotParams.paper()
    fp = FreeParams(p, ["I", "r_m[2]", "j"])
    se = {n: float(k + 1) for k, n in enumerate(fp.names)}
    out = _assemble_named(fp, se, p, 0.0)
    assert np.asarray(out["I"]).shape == (3, 3) and out["I"][1][0] == out["I"][0][1] == se["I[0,1]"]
    assert out["r_m[2]"] == se["r_m[2]"] and out["j"] == se["j"]
    fp2 = FreeParams(p, ["I[1,0]", "I[0, 0]"])
    out2 = _assemble_named(fp2, {"I[0,1]": 1.0, "I[0,0]": 2.0}, p, 0.0)
    assert out2["I[1,0]"] == 1.0 and out2["I[0, 0]"] == 2.0


def test_apply_fixes_accepts_json_lists():
    p = apply_fixes(jsphere.RobotParams.paper(), {"m": "2.0", "I": "[[0.02,0,0],[0,0.02,0],[0,0,0.03]]", "R_m": 0.03})
    assert float(p.m) == 2.0 and float(p.I[2, 2]) == 0.03 and float(p.R_m) == pytest.approx(0.03)


# ------------------------------------------------------------------ CLI


@pytest.mark.slow
def test_cli_fit_writes_json_plots_and_loadable_params(small_trials, small_fit, tmp_path, capsys):
    paths = []
    for t in small_trials:
        jsphere.write_trial(tmp_path / f"{t.name}.csv", t)
        paths.append(str(tmp_path / f"{t.name}.csv"))
    out = tmp_path / "res" / "fit.json"
    rc = main(
        ["fit", *paths, "--free", FREE, "--fix", "m=2.5", "--out", str(out), "--n-starts", "1", "--quiet", "--no-cache"]
    )
    assert rc == 0
    doc = json.loads(out.read_text())
    res, _ = small_fit
    assert doc["free"] == ["R_m", "j"] and set(doc["stderr"]) == {"R_m", "j"}
    assert doc["params"]["R_m" if "R_m" in doc["params"] else "r_m"]
    assert doc["values"]["R_m"] == pytest.approx(res.values["R_m"], abs=0.2 * res.stderr["R_m"])
    assert (out.parent / "fit_overlay.png").exists() and (out.parent / "fit_residuals.png").exists()
    assert not (out.parent / "fit.json.ckpt.npz").exists()
    assert jsphere.RobotParams.load(out).n_wheels == 3
    assert "R_m" in capsys.readouterr().out
    # the flags as the fit's options, recorded to replay it
    options = jsphere.FitOptions.from_json(doc["options"])
    assert (options.n_starts, options.loss, options.solver.rtol) == (1, "cauchy", 1e-6)


@pytest.mark.slow
def test_fit_through_fast_start_is_the_fit_and_its_programs_are_kept(small_truth, tmp_path, capsys):
    """Programs run by a `FastStart`, as `jsphere fit` runs them through its cache's: the same
    fit; the residual and step programs exported once, and a new `FastStart` (the next
    process) runs them from the files without exporting again. (Trials of their own length: a
    program this process traced before with equinox's checks raising cannot be exported.)"""
    trials = make_trials(small_truth, 2, 1.2, seed=3)
    paper = jsphere.RobotParams.paper()
    with equinox_errors_as("nan"):  # as the command line traces (host callbacks cannot be exported)
        with programs_run_by(FastStart(tmp_path)):
            a = jsphere.fit(trials, paper, FREE, fix={"m": 2.5}, **OPTS)
        files = sorted((tmp_path / "aot").glob("*.jaxexport"))
        again = FastStart(tmp_path)
        with programs_run_by(again):
            b = jsphere.fit(trials, paper, FREE, fix={"m": 2.5}, **OPTS)
    direct = jsphere.fit(trials, paper, FREE, fix={"m": 2.5}, **OPTS)
    assert a.values == pytest.approx(direct.values, rel=1e-12) and a.cost == pytest.approx(direct.cost, rel=1e-12)
    assert b.values == a.values and b.cost == a.cost
    assert len(files) == 2  # the residuals with their Jacobian, and the Levenberg-Marquardt step
    assert sorted((tmp_path / "aot").glob("*.jaxexport")) == files
    assert "not exporting" not in capsys.readouterr().err
    assert len(again._loaded) == 2


@pytest.mark.parametrize(
    "extra, match",
    [
        (["--free", "R_m", "--fix", "m"], "--fix expects NAME=VALUE"),
        (["--free", "R_m", "--fix", "m=abc"], "must be a number"),
        (["--free", "R_m", "--fix", "zz=1"], "unknown parameter 'zz'"),
        (["--free", "R_m,j", "--fix", "j=1e-4"], "both free"),
        (["--free", "R_m", "--bound", "R_m=0.03"], "expected LO:HI"),
        (["--free", "R_m", "--bound", "R_m=0.03:0.04"], "exclude the start"),
        (["--free", "R_m", "--out", "fit.txt"], "ending in .json"),
    ],
)
def test_cli_fit_errors(small_trials, tmp_path, capsys, extra, match):
    jsphere.write_trial(tmp_path / "a.csv", small_trials[0])
    rc = main(
        ["fit", str(tmp_path / "a.csv"), "--no-cache", *extra]
        + ([] if "--out" in extra else ["--out", str(tmp_path / "f.json")])
    )
    assert rc == 2
    assert match in capsys.readouterr().err


# ------------------------------------------------------------------ slow: recovery studies


def _study(kind, free, fix_names, n=5, seed=0, durations=(4.0, 8.0), **kw):
    truth = jsphere.RobotParams.paper().replace(**TRUTH)
    rng = np.random.default_rng(seed)
    trials = []
    for i in range(n):
        t1 = float(np.round(rng.uniform(*durations) * 100) / 100)
        u = jsphere.random_inputs(truth, t1, kind=kind, seed=seed * 1000 + i)
        trials.append(jsphere.synthetic_trial(truth, u, t1, seed=seed * 1000 + i, name=f"t{i}"))
    fix = {k: np.asarray(jsphere.get_value(truth, k)).tolist() for k in fix_names}
    res = jsphere.fit(trials, jsphere.RobotParams.paper(), free, fix=fix, seed=seed, **kw)
    z = {n: (res.values[n] - float(jsphere.get_value(truth, n))) / res.stderr[n] for n in res.free}
    print(
        f"\n{kind} seed {seed}: {n} trials, {res.elapsed_s:.0f} s, {res.iterations} iterations, errors in SE:",
        {k: round(v, 2) for k, v in z.items()},
    )
    return res, z


@pytest.mark.slow
def test_recovery_wheel_speeds_five_trials():
    """Wheel speeds: the mass scale is invisible (see identifiability), so m0 is fixed with m."""
    res, z = _study("wheel_speeds", "R_m,j,I[0,0],I[1,1],I[2,2],I0", ["m", "m0"])
    assert res.converged and not res.identifiability["warnings"]
    assert all(abs(v) < 3 for v in z.values()), z


@pytest.mark.slow
def test_recovery_torques_five_trials():
    res, z = _study("torques", "R_m,j,I[0,0],I[1,1],I[2,2],m0,I0", ["m"])
    assert res.converged and not res.identifiability["warnings"]
    assert all(abs(v) < 3 for v in z.values()), z


@pytest.mark.slow
def test_wheel_speeds_with_only_m_fixed_reports_the_mass_scale():
    res, _ = _study("wheel_speeds", "R_m,j,I[0,0],I[1,1],I[2,2],m0,I0", ["m"], n=2, durations=(4.0, 4.0), n_starts=1)
    assert any("scaling every inertia" in w for w in res.identifiability["warnings"])


@pytest.mark.slow
def test_standard_errors_are_honest_over_20_seeds():
    """Truth within 2 SE for most of 20 seeds (expected 95%; at least 80% of all (seed, name))."""
    inside, total = 0, 0
    for seed in range(20):
        _, z = _study(
            "wheel_speeds",
            "R_m,j,I[2,2],I0",
            ["m", "m0", "I[0,0]", "I[1,1]"],
            n=3,
            durations=(4.0, 4.0),
            n_starts=1,
            adam_steps=0,
            seed=seed,
        )
        inside += sum(abs(v) < 2 for v in z.values())
        total += len(z)
    print(f"truth within 2 SE: {inside}/{total}")
    assert inside >= 0.8 * total, (inside, total)


@pytest.mark.slow
def test_benchmark_size_fit_finishes_in_minutes():
    import time

    t = time.perf_counter()
    res, z = _study(
        "wheel_speeds", "R_m,j,I[0,0],I[1,1],I[2,2],I0", ["m", "m0"], n=20, durations=(6.0, 6.0), n_starts=1
    )
    assert time.perf_counter() - t < 15 * 60
    assert res.converged and all(abs(v) < 4 for v in z.values()), z


def test_adams_start_is_optax_init_made_on_the_host(programs_compiled):
    """The fit's Adam starts from `opt.init(w)` (zeros), made without an XLA program."""
    opt = optax.chain(optax.scale_by_adam(), optax.scale(-0.01))
    w = {"theta": jax.device_put(np.ones((3, 7))), "nu": jax.device_put(np.ones((3, 2, 11)))}
    state = adam_start(opt, w)
    assert programs_compiled == []
    reference = opt.init(w)
    assert jax.tree_util.tree_structure(state) == jax.tree_util.tree_structure(reference)
    for a, b in zip(jax.tree_util.tree_leaves(state), jax.tree_util.tree_leaves(reference)):
        assert a.dtype == b.dtype and a.shape == b.shape
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
