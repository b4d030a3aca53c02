"""Excitation design (`jsphere.design`, `jsphere design`): the programmes, the criterion's
gradient, the search, the files, and (slow) the predicted standard errors against fits of
synthetic trials from another robot."""

import json
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jsphere
from jsphere.cli.app import main
from jsphere.design.excitation import design_excitation
from jsphere.design.information import Grid, Noise, problem
from jsphere.design.inputs import Spec, programmes, random_start, table
from jsphere.design.optimise import _value_and_grad, maximise
from jsphere.identify.free import FreeParams

#: tiny trials (1.5 s) with the command's defaults otherwise (6 frequencies up to 1.5 Hz, 0.5 s
#: ramps, max_torque 0.1 N m, a 20 Hz model grid with 2 RK4 steps per sample): the search's
#: gradient is compiled once for the tests that need it (slow: the compilation dominates), the
#: command's run included
SPEC = Spec(kind="K", trials=2, wheels=3, n_freqs=6, duration=1.5, f_max=1.5, ramp=0.5, limit=0.1)
GRID = Grid(rate=20.0, substeps=2)


@pytest.fixture(scope="module")
def small(paper):
    free = FreeParams(paper, "j,I[2,2]")
    return problem(paper, free, SPEC, Noise(), GRID)


def test_programmes_rest_at_both_ends_within_limit_and_round_trip(tmp_path):
    z = jnp.asarray(random_start(SPEC, np.random.default_rng(3), 5.0))  # strongly saturated
    for k, prog in enumerate(programmes(z, SPEC)):
        t, u = table(prog, 50.0)
        assert t[0] == 0.0 and t[-1] == pytest.approx(SPEC.duration)
        assert np.all(u[0] == 0.0) and np.allclose(u[-1], 0.0, atol=1e-12)
        assert np.max(np.abs(u)) < SPEC.limit
        assert np.max(np.abs(u)) > 0.3 * SPEC.limit
        for t_end in (0.0, SPEC.duration):  # zero slope at both ends: at rest
            rate = jax.jvp(prog, (jnp.asarray(t_end),), (jnp.asarray(1.0),))[1]
            np.testing.assert_allclose(rate, 0.0, atol=1e-12)
        path = tmp_path / f"p{k}.csv"
        jsphere.write_inputs_csv(path, t, u, "torques")
        t2, u2, kind, names = jsphere.read_inputs_csv(path)
        assert kind == "torques" and names == ["K_1", "K_2", "K_3"]
        np.testing.assert_allclose(t2, t, atol=1e-6)
        np.testing.assert_allclose(u2, u, rtol=1e-9, atol=1e-15)


@pytest.mark.slow  # compiles the criterion's gradient (about 30-40 s on 2 cores)
def test_criterion_gradient_matches_central_differences(small):
    # the search's own compiled gradient of the objective (criterion minus the limit penalty;
    # two rows, as the two starts of the search test): row 1 breaks the limits
    lim = jsphere.Limits()
    z = np.stack([random_start(SPEC, np.random.default_rng(s), a) for s, a in ((0, 0.05), (1, 0.5))])
    (obj, (phi, pen, _)), g = _value_and_grad(jnp.asarray(z), small, lim)
    assert np.all(np.isfinite(phi)) and float(pen[1]) > 0.0  # the penalty is checked too
    rng = np.random.default_rng(2)
    h = 1e-4
    for _ in range(2):
        d = rng.normal(size=z.shape[1])
        d /= np.linalg.norm(d)
        for r in range(2):
            (fd, _), _ = _value_and_grad(jnp.asarray(np.stack([z[r] + h * d, z[r] - h * d])), small, lim)
            want = float(fd[0] - fd[1]) / (2 * h)
            assert float(jnp.dot(g[r], d)) == pytest.approx(want, rel=1e-4, abs=1e-6 * (1 + abs(float(obj[r]))))


@pytest.mark.slow  # compiles the criterion's gradient (about 30-40 s on 2 cores)
def test_search_beats_its_start_and_a_random_multisine(small):
    from jsphere.design.inputs import match_rms, random_multisine

    lim = jsphere.Limits()
    z0 = np.stack([random_start(SPEC, np.random.default_rng(s), 0.1) for s in range(2)])
    zb, obj, phi, pen = maximise(z0, small, lim, steps=8, learning_rate=0.05)
    (obj0, _), _ = _value_and_grad(jnp.asarray(z0), small, lim)
    assert np.all(obj > np.asarray(obj0) + 0.1)
    again = maximise(z0, small, lim, steps=8, learning_rate=0.05)  # deterministic
    np.testing.assert_array_equal(again[0], zb)
    best = int(np.argmax(obj))
    rms_design = np.sqrt(
        np.mean(np.concatenate([table(p, 50.0)[1] for p in programmes(jnp.asarray(zb[best]), SPEC)]) ** 2)
    )
    zr, rms_base = match_rms(random_multisine(SPEC, np.random.default_rng(7)), SPEC, rms_design, 50.0)
    assert rms_base == pytest.approx(rms_design, rel=1e-4)
    # the objective (criterion less the limit penalty) of the design beats the baseline's
    (obj_base, _), _ = _value_and_grad(jnp.asarray(np.stack([zr, zr])), small, lim)
    assert obj[best] > float(obj_base[0])


@pytest.mark.slow  # compiles the criterion's gradient (about 30-40 s on 2 cores)
def test_cli_writes_one_table_per_trial_and_the_json(tmp_path, capsys):
    out = tmp_path / "design.csv"
    argv = ["design", "--free", "j,I[2,2]", "--duration", "1.5", "--kind", "K", "--trials", "2"]
    argv += ["--restarts", "2", "--steps", "2", "--capture-rate", "20", "--rate", "50", "--out", str(out), "-q"]
    assert main(argv) == 0
    tables = [tmp_path / "design_1.csv", tmp_path / "design_2.csv"]
    assert all(p.exists() for p in tables) and not out.exists()
    for p in tables:
        t, u, kind, names = jsphere.read_inputs_csv(p)
        assert kind == "torques" and u.shape == (76, 3) and t[-1] == pytest.approx(1.5)
        assert np.all(u[0] == 0) and np.allclose(u[-1], 0.0, atol=1e-9) and np.max(np.abs(u)) < 0.1
    doc = json.loads((tmp_path / "design.json").read_text())
    for key in ("stderr_predicted", "stderr_predicted_baseline"):
        assert set(doc[key]) == {"j", "I[2,2]"} and all(v > 0 and math.isfinite(v) for v in doc[key].values())
    assert set(doc["criterion"]) == {"design", "baseline"}
    assert 0 < doc["rms"]["baseline"] <= doc["rms"]["design"] * (1 + 1e-4)
    printed = capsys.readouterr().out
    assert "SE design" in printed and "I[2,2]" in printed
    # the criterion is printed in its natural sign and named as such, as design.json holds it
    line = next(x for x in printed.splitlines() if x.startswith("log det of the information matrix"))
    head = "log det of the information matrix (D-optimal criterion, larger is better): design "
    assert line.startswith(head)
    assert float(line[len(head) :].split(",")[0]) == pytest.approx(doc["criterion"]["design"], abs=5e-4)
    for r in doc["restarts"]:  # the search's objective is the criterion less the weighted penalty
        assert r["final"] == pytest.approx(r["criterion"] - 1e3 * r["penalty"])


@pytest.mark.parametrize(
    "extra, message",
    [
        (["--duration", "0"], "--duration must be a positive number of seconds"),
        (["--duration", "2", "--free", "nope"], "--free nope"),
        (["--duration", "2", "--trials", "0"], "--trials must be a whole number >= 1"),
        (["--duration", "2", "--max-torque", "none"], "max_torque (--max-torque)"),
        (["--duration", "0.6"], "ramp = 0.5 s needs a duration of at least 1 s"),
    ],
)
def test_cli_bad_input_is_one_line_and_exit_2(tmp_path, capsys, extra, message):
    argv = ["design", "--free", "j", "--kind", "K", "--out", str(tmp_path / "d.csv"), *extra]
    assert main(argv) == jsphere.ExitCode.BAD_INPUT
    err = capsys.readouterr().err.strip()
    assert err.startswith("jsphere design: error:") and message in err and "\n" not in err
    assert not list(tmp_path.iterdir())


def test_cli_refuses_to_write_over_its_parameter_file(tmp_path, capsys):
    params = tmp_path / "robot.json"
    params.write_text(json.dumps({"params": jsphere.RobotParams.paper().to_dict()}))
    before = params.read_text()
    argv = ["design", "--free", "j", "--duration", "2", "--kind", "K", "--params", str(params)]
    assert main([*argv, "--out", str(tmp_path / "robot.csv")]) == jsphere.ExitCode.BAD_INPUT
    assert "would write over the parameter file" in capsys.readouterr().err
    assert params.read_text() == before


@pytest.mark.slow
def test_predicted_standard_errors_match_fits_of_another_robot(paper):
    """Design for the paper's robot, run the design and the baseline on a robot 6-8 % away with
    capture noise, fit: the fitted standard errors agree with the predicted ones within a
    factor 1.6, and the design's beat the baseline's."""
    from jsphere.controls import Sampled, Torques

    free = "r_m[2],j,I[2,2]"
    res = design_excitation(
        paper, free, 4.0, "K", options=jsphere.DesignOptions(trials=2, restarts=2, steps=40), progress=False
    )
    truth = paper
    for name, f in (("r_m[2]", 1.06), ("j", 0.93), ("I[2,2]", 1.08)):
        truth = jsphere.set_value(truth, name, jsphere.get_value(paper, name) * f)
    fitted = {}
    for which, tables in (("design", res.tables), ("baseline", res.baseline_tables)):
        trials = [
            jsphere.synthetic_trial(
                truth,
                Torques(Sampled(jnp.asarray(t), jnp.asarray(u), "cubic")),
                4.0,
                rate=100.0,
                seed=k,
                name=f"{which}{k}",
            )
            for k, (t, u) in enumerate(tables)
        ]
        fr = jsphere.fit(trials, paper, free, sigma_pos=1e-3, sigma_rot=math.radians(0.5), progress=False)
        fitted[which] = fr.stderr
        for n in res.free:
            assert abs(fr.values[n] - jsphere.get_value(truth, n)) < 5 * fr.stderr[n]
    for n in res.free:
        for which, pred in (("design", res.stderr_predicted), ("baseline", res.stderr_predicted_baseline)):
            ratio = fitted[which][n] / pred[n]
            assert 1 / 1.6 < ratio < 1.6, (n, which, ratio)
    assert all(fitted["design"][n] < fitted["baseline"][n] for n in res.free)


def test_file_names_one_table_or_one_per_trial(tmp_path):
    from jsphere.design.result import json_path, table_paths

    assert table_paths(tmp_path / "design.csv", 1) == [tmp_path / "design.csv"]
    assert table_paths(tmp_path / "d.csv", 3) == [tmp_path / f"d_{k}.csv" for k in (1, 2, 3)]
    assert json_path(tmp_path / "design.csv") == tmp_path / "design.json"


def test_options_are_checked_and_moved_keywords_warn(paper):
    """`design_excitation` takes its options as a `DesignOptions`; a field given as a keyword
    still reaches it, with a warning naming the new spelling. Bad values are refused before any
    work."""
    from jsphere._runtime.errors import InputError

    with pytest.raises(InputError, match=r"^design_excitation: restarts must be a whole number >= 1"):
        design_excitation(paper, "j", 4.0, "K", options=jsphere.DesignOptions(restarts=0))
    with pytest.warns(DeprecationWarning, match=r"design_excitation: ramp= is deprecated; pass options=DesignOptions"):
        with pytest.raises(InputError, match=r"ramp = 3 s needs a duration of at least 6 s"):
            design_excitation(paper, "j", 4.0, "K", ramp=3.0)
    with pytest.raises(TypeError, match="unexpected keyword argument 'step'"):
        design_excitation(paper, "j", 4.0, "K", step=3)
    with pytest.raises(InputError, match=r"options must be a jsphere.DesignOptions"):
        design_excitation(paper, "j", 4.0, "K", options={"steps": 3})


@pytest.mark.slow  # compiles the RK4 information and the fit's onboard Jacobian (about 50 s on 2 cores)
def test_onboard_information_matches_the_fits_onboard_jacobian(paper):
    """The search model's information of onboard readings (RK4, biases and encoder offsets
    eliminated) against the fit's own onboard Jacobian (adaptive solver) of noise-free trials
    at the model's sample times: the same matrix within 0.1 %."""
    import equinox as eqx

    from jsphere.design.inputs import values_at
    from jsphere.design.prediction import fit_information

    spec = Spec(kind="K", trials=1, wheels=3, n_freqs=6, duration=1.5, f_max=1.5, ramp=0.5, limit=0.1)
    grid = Grid(rate=50.0, substeps=2)
    free = FreeParams(paper, "r_m[2],j,I[2,2]")
    noise = Noise(mounting=jsphere.Mounting((0.02, -0.01, -0.04), (0.9, 0.1, 0.0, 0.3)))
    pr = problem(paper, free, spec, noise, grid)
    z = jnp.asarray(random_start(spec, np.random.default_rng(0), 0.1))
    Fs = np.asarray(eqx.filter_jit(lambda pr, z: pr.information(z)[0])(pr, z))
    t = grid.times(spec.duration)
    values, Fv, _, se, _ = fit_information(
        paper, free, "torques", t, [values_at(p, t) for p in programmes(z, spec)], noise
    )
    S = np.maximum(np.abs(values), 0.1 * free.scales())
    np.testing.assert_allclose(Fs, S[:, None] * Fv * S[None, :], rtol=1e-3, atol=1e-3 * np.abs(Fs).max())
    assert np.all(np.isfinite(se)) and np.all(se > 0)


@pytest.mark.slow  # compiles the criterion's gradient and the fit's onboard Jacobian (about 2 min on 2 cores)
def test_cli_onboard_writes_the_tables_and_the_json_and_beats_the_baseline(tmp_path, capsys):
    out = tmp_path / "design.csv"
    argv = ["design", "--free", "j,I[2,2]", "--duration", "1.5", "--kind", "K", "--onboard", "--sigma-gyro", "0.005"]
    argv += ["--imu-position", "0.02", "-0.01", "-0.04", "--restarts", "2", "--steps", "6", "--capture-rate", "20"]
    assert main([*argv, "--rate", "50", "--out", str(out), "-q"]) == 0
    t, u, kind, _ = jsphere.read_inputs_csv(out)
    assert kind == "torques" and u.shape == (76, 3) and np.max(np.abs(u)) < 0.1
    doc = json.loads((tmp_path / "design.json").read_text())
    s = doc["settings"]
    assert s["sensors"] == "onboard" and s["sigma_gyro_rad_s"] == 0.005 and s["sigma_acc_m_s2"] == 0.03
    assert s["imu_position_m"] == [0.02, -0.01, -0.04] and "sigma_pos_m" not in s
    assert s["sigma_encoder_rad"] == pytest.approx(2 * math.pi / 4096 / math.sqrt(12))
    se, base = doc["stderr_predicted"], doc["stderr_predicted_baseline"]
    assert set(se) == set(base) == {"j", "I[2,2]"} and all(
        v > 0 and math.isfinite(v) for v in [*se.values(), *base.values()]
    )
    gmean = lambda d: math.exp(np.mean(np.log(list(d.values()))))
    assert gmean(se) <= gmean(base)
    assert "SE design" in capsys.readouterr().out


@pytest.mark.parametrize(
    "extra, message",
    [
        (["--sigma-pos", "1e-3"], "--sigma-pos is the motion capture's noise; with --onboard give --sigma-gyro"),
        (["--sigma-rot-deg", "0.5"], "--sigma-rot-deg is the motion capture's noise"),
        (["--sigma-encoder", "0"], "--sigma-encoder must be a number > 0 (rad)"),
        (["--free", "m,m0,r_m[2]"], "leave m out of --free"),
    ],
)
def test_cli_onboard_bad_input_is_one_line_and_exit_2(tmp_path, capsys, extra, message):
    argv = ["design", "--free", "j", "--kind", "K", "--duration", "2", "--onboard", "--out", str(tmp_path / "d.csv")]
    assert main([*argv, *extra]) == jsphere.ExitCode.BAD_INPUT
    err = capsys.readouterr().err.strip()
    assert err.startswith("jsphere design: error:") and message in err and "\n" not in err
    assert not list(tmp_path.iterdir())
