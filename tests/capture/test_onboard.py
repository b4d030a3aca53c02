"""Onboard-sensor trials: the CSV format read back as written, its errors naming file, line and
column, and synthetic trials whose readings are the measurement model's plus what was added."""

from __future__ import annotations

import math

import jax.numpy as jnp
import numpy as np
import pytest

import jsphere
from jsphere._runtime.errors import InputError
from jsphere.capture.onboard import (
    OnboardNoise,
    OnboardTrial,
    read_onboard_trial,
    synthetic_onboard_trial,
    write_onboard_trial,
)
from jsphere.model.sensors import Mounting, imu_readings

MOUNTING = Mounting((0.02, 0.01, -0.04), (np.cos(0.3), 0.0, np.sin(0.3), 0.0))


@pytest.fixture(scope="module")
def torques(paper):
    return jsphere.random_inputs(paper, 3.0, kind="torques", seed=4)


@pytest.fixture(scope="module")
def exact(paper, torques):
    """A trial without noise, bias or quantisation, and the motion it was made from."""
    tr = synthetic_onboard_trial(
        paper, torques, 3.0, mounting=MOUNTING, noise=OnboardNoise(0.0, 0.0, counts_per_turn=0), rate=50.0
    )
    motion = jsphere.simulate(
        paper, jsphere.State.at_rest(paper), torques, 3.0, ts=jnp.asarray(tr.t), rtol=1e-10, atol=1e-12
    )
    return tr, motion


def test_synthetic_readings_are_the_measurement_model_s(paper, exact):
    tr, motion = exact
    gyro, acc = imu_readings(paper, MOUNTING, motion.gamma, motion.omega, motion.Omega, motion.K)
    np.testing.assert_allclose(tr.gyro, gyro, atol=1e-12)
    np.testing.assert_allclose(tr.acc, acc, atol=1e-10)
    np.testing.assert_allclose(tr.chi, np.asarray(motion.chi) - np.asarray(motion.chi[0]), atol=1e-12)
    assert tr.kind == "torques" and tr.chi.shape == (tr.t.size, 3) and np.abs(tr.chi).max() > 0.1


def test_noise_biases_and_encoder_counts_are_what_was_asked(paper, torques, exact):
    clean, _ = exact
    noise = OnboardNoise(0.003, 0.03, (0.01, -0.02, 0.005), (0.1, 0.0, -0.2), counts_per_turn=4096)
    tr = synthetic_onboard_trial(paper, torques, 3.0, mounting=MOUNTING, noise=noise, rate=50.0, seed=2)
    dg, da = tr.gyro - clean.gyro, tr.acc - clean.acc
    np.testing.assert_allclose(dg.mean(0), noise.gyro_bias, atol=4 * 0.003 / math.sqrt(tr.t.size))
    np.testing.assert_allclose(da.mean(0), noise.acc_bias, atol=4 * 0.03 / math.sqrt(tr.t.size))
    assert 0.8 < dg.std(0).mean() / 0.003 < 1.2 and 0.8 < da.std(0).mean() / 0.03 < 1.2
    step = 2 * math.pi / 4096
    np.testing.assert_allclose(tr.chi / step, np.round(tr.chi / step), atol=1e-6)
    # counts from where each wheel stood: two roundings, the first a constant offset per wheel
    err = tr.chi - clean.chi
    assert np.abs(err).max() <= step + 1e-12 and np.abs(err - np.median(err, axis=0)).max() <= step + 1e-12


def test_the_csv_reads_back_as_written(paper, exact, tmp_path):
    tr, _ = exact
    path = tmp_path / "run1.csv"
    write_onboard_trial(path, tr)
    header = path.read_text().splitlines()[3]
    assert header == "t,gyro_x,gyro_y,gyro_z,acc_x,acc_y,acc_z,chi_1,chi_2,chi_3,K_1,K_2,K_3"
    back = read_onboard_trial(path)
    assert back.kind == "torques" and back.name == tr.name and not back.hold and back.source == str(path)
    np.testing.assert_allclose(back.t, tr.t, atol=1e-6)
    for a, b in ((back.gyro, tr.gyro), (back.acc, tr.acc), (back.inputs, tr.inputs)):
        np.testing.assert_allclose(a, b, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(back.chi, tr.chi, atol=1e-9)


def _write(tmp_path, lines: list[str]):
    path = tmp_path / "bad.csv"
    path.write_text("\n".join(lines) + "\n")
    return path


HEADER = "t,gyro_x,gyro_y,gyro_z,acc_x,acc_y,acc_z,chi_1,chi_2,chi_3,K_1,K_2,K_3"


def _row(t, chi=(0.0, 0.0, 0.0), k=(0.0, 0.0, 0.0)):
    return ",".join(map(str, [t, 0, 0, 0, 0, 0, 9.81, *chi, *k]))


@pytest.mark.parametrize(
    "lines, message",
    [
        (["t,gyro_x,gyro_y,gyro_z,acc_x,acc_y,chi_1,K_1", "0,0,0,0,0,0,0,0"], r"bad\.csv, line 1: missing column\(s\) acc_z"),
        ([HEADER, _row(0.0), _row(0.01, chi=(0.1, 0.0, 0.0)), _row(0.02, chi=(4.0, 0.0, 0.0))],
         r"bad\.csv, line 4, column chi_1: .*jumps by more than half a turn"),
        ([HEADER, _row(0.0, chi=(0.0, 0.3, 0.0)), _row(0.01)], r"bad\.csv, line 2, column chi_2: .*start at 0"),
        ([HEADER, _row(0.0), _row(0.01).replace(",9.81,", ",,", 1)], r"bad\.csv, line 3, column acc_z: blank"),
        ([HEADER, _row(0.0), _row(0.0)], r"bad\.csv, line 3: time stamps are duplicated"),
        (["# hold: sometimes", HEADER, _row(0.0), _row(0.01)], r"'# hold: sometimes' is not one of"),
        (["t,gyro_x,gyro_y,gyro_z,acc_x,acc_y,acc_z,chi_1,chi_3,K_1,K_2", _row(0.0)[:-4]],
         r"line 1: the encoder columns must be chi_1\.\.chi_2"),
    ],
)  # fmt: skip
def test_a_bad_file_is_one_line_naming_file_line_and_column(tmp_path, lines, message):
    with pytest.raises(ValueError, match=message):
        read_onboard_trial(_write(tmp_path, lines))


def test_a_held_torque_trial_replays_its_samples_held(tmp_path):
    path = _write(tmp_path, ["# hold: zero-order", HEADER, _row(0.0, k=(0.1, 0, 0)), _row(0.5, k=(0.3, 0, 0))])
    tr = read_onboard_trial(path)
    assert tr.hold
    K = tr.controls().fn(jnp.asarray(0.25))
    assert float(K[0]) == pytest.approx(0.1)
    with pytest.raises(InputError, match="wheel-speed"):
        OnboardTrial(tr.t, tr.gyro, tr.acc, tr.chi, tr.inputs, "wheel_speeds", hold=True)


def test_arrays_are_checked_as_a_file_is_naming_the_sample(exact):
    tr, _ = exact
    chi = tr.chi.copy()
    chi[5:, 1] += 2 * np.pi
    with pytest.raises(InputError, match=r"trial 'synthetic', sample 6, column chi_2: .*half a turn"):
        OnboardTrial(tr.t, tr.gyro, tr.acc, chi, tr.inputs, tr.kind, name=tr.name)
    acc = tr.acc.copy()
    acc[3, 0] = np.nan
    with pytest.raises(InputError, match=r"sample 4, column acc_x: blank or not finite"):
        OnboardTrial(tr.t, tr.gyro, acc, tr.chi, tr.inputs, tr.kind, name=tr.name)


def test_synth_writes_onboard_trials_for_rehearsal(tmp_path, capsys):
    from jsphere.cli.app import main

    argv = ["synth", "--onboard", "--kind", "torques", "--trials", "2", "--duration", "1", "--out", str(tmp_path)]
    assert main([*argv, "--imu-position", "0.02", "-0.01", "-0.04", "--counts-per-turn", "1024"]) == 0
    printed = capsys.readouterr().out
    for i in range(2):
        tr = read_onboard_trial(tmp_path / f"onboard_torques_0{i}.csv")
        assert tr.kind == "torques" and tr.t.size == 101 and tr.name == f"onboard_torques_0{i}"
        steps = tr.chi / (2 * math.pi / 1024)
        np.testing.assert_allclose(steps, np.round(steps), atol=1e-5)  # whole counts
        bias = [
            float(v)
            for v in printed.splitlines()[i].split("biases (gyro rad/s, acc m/s^2) ")[1].split(" ->")[0].split(", ")
        ]
        assert abs(tr.gyro[:5, 0].mean() - bias[0]) < 0.01  # at rest at first: the reading is the bias
    assert main([*argv[:-2], "--out", str(tmp_path / "x"), "--imu-rotation", "0", "0", "0", "0"]) != 0
