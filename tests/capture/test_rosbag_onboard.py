"""Onboard-sensor trials from ROS bags, as a robot records them: `sensor_msgs/Imu` at 100 Hz and
the wheels' `sensor_msgs/JointState` (encoder angles wrapped to (-pi, pi], as a continuous
joint's state is published, from where each wheel stood, and the torques) on their own clock, 4 ms after the IMU's. Written
with `rosbags` from a synthetic onboard trial and converted back with `jsphere convert`."""

from __future__ import annotations

import math

import numpy as np
import pytest

import jsphere
from jsphere._runtime.errors import InputError
from jsphere.capture.onboard import OnboardNoise, read_onboard_trial, synthetic_onboard_trial
from jsphere.capture.rosbag import read_rosbag_onboard
from jsphere.cli.app import main

pytest.importorskip("rosbags")
from rosbags.rosbag2 import StoragePlugin  # noqa: E402
from rosbags.rosbag2 import Writer as Writer2  # noqa: E402
from rosbags.typesys import Stores, get_typestore  # noqa: E402

EPOCH_NS = 1_741_946_000_000_000_000
JOINTS = ["wheel_1", "wheel_2", "wheel_3"]
LAG_NS = 4_000_000  # the joint states' stamps trail the IMU's


@pytest.fixture(scope="module")
def truth(paper):
    K = jsphere.random_inputs(paper, 2.0, kind="torques", seed=3)
    noise = OnboardNoise(0.003, 0.03, (0.01, 0.0, -0.01), (0.05, 0.0, 0.1), counts_per_turn=0)
    return synthetic_onboard_trial(paper, K, 2.0, noise=noise, seed=3)


def write_bag(path, tr, *, imu_type="sensor_msgs/msg/Imu"):
    ts = get_typestore(Stores.ROS2_HUMBLE)
    T = ts.types
    Time, Header, Vector3 = T["builtin_interfaces/msg/Time"], T["std_msgs/msg/Header"], T["geometry_msgs/msg/Vector3"]
    # (-pi, pi], as a continuous joint's state is published, from where each wheel happened to stand
    wrapped = np.angle(np.exp(1j * (tr.chi + np.array([2.5, -3.0, 1.0]))))

    def header(ns):
        return Header(stamp=Time(sec=ns // 10**9, nanosec=ns % 10**9), frame_id="imu_link")

    with Writer2(path, version=9, storage_plugin=StoragePlugin.MCAP) as w:
        c_imu = w.add_connection("/imu/data", imu_type, typestore=ts)
        c_js = w.add_connection("/joint_states", "sensor_msgs/msg/JointState", typestore=ts)
        for i, t in enumerate(tr.t):
            ns = EPOCH_NS + round(t * 1e9)
            if imu_type.endswith("Imu"):
                msg = T[imu_type](
                    header=header(ns),
                    orientation=T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0),
                    orientation_covariance=np.full(9, -1.0),
                    angular_velocity=Vector3(x=tr.gyro[i, 0], y=tr.gyro[i, 1], z=tr.gyro[i, 2]),
                    angular_velocity_covariance=np.zeros(9),
                    linear_acceleration=Vector3(x=tr.acc[i, 0], y=tr.acc[i, 1], z=tr.acc[i, 2]),
                    linear_acceleration_covariance=np.zeros(9),
                )
            else:
                msg = T[imu_type](data=0.0)
            w.write(c_imu, ns + 1_000_000, ts.serialize_cdr(msg, imu_type))
            js = T["sensor_msgs/msg/JointState"](
                header=header(ns + LAG_NS),
                name=JOINTS,
                position=wrapped[i],
                velocity=np.zeros(3),
                effort=tr.inputs[i],
            )
            w.write(c_js, ns + LAG_NS + 1_000_000, ts.serialize_cdr(js, "sensor_msgs/msg/JointState"))


def test_a_bag_converts_into_the_onboard_trial_it_was_made_from(truth, tmp_path):
    write_bag(tmp_path / "run", truth)
    out = tmp_path / "run1.csv"
    argv = ["convert", str(tmp_path / "run"), "--format", "rosbag", "--imu-topic", "/imu/data"]
    assert main([*argv, "--inputs-topic", "/joint_states", "--input-kind", "K", "--out", str(out)]) == 0
    tr = read_onboard_trial(out)
    assert tr.kind == "torques" and not tr.hold and tr.name == "run1"
    # the samples are the IMU's within the joint states' span (which starts 4 ms later)
    np.testing.assert_allclose(tr.t, truth.t[1:] - truth.t[1], atol=1e-6)
    np.testing.assert_allclose(tr.gyro, truth.gyro[1:], atol=1e-9)
    np.testing.assert_allclose(tr.acc, truth.acc[1:], atol=1e-8)
    # encoders unwrapped, interpolated 4 ms back, from 0: the true angles to the interpolation's error
    step = np.abs(np.diff(truth.chi, axis=0)).max()
    expected = truth.chi[1:] - 0.4 * np.diff(truth.chi, axis=0)
    np.testing.assert_allclose(tr.chi, expected - expected[0], atol=0.05 * step + 1e-8)
    assert np.abs(np.diff(np.angle(np.exp(1j * (truth.chi + [2.5, -3.0, 1.0]))), axis=0)).max() > math.pi  # wrapped
    # (to the stamps as seconds since 1970 resolve: 0.24 us, 2.4e-5 of a sample)
    expected = truth.inputs[1:] - 0.4 * np.diff(truth.inputs, axis=0)
    np.testing.assert_allclose(tr.inputs, expected, atol=1e-4 * np.abs(np.diff(truth.inputs, axis=0)).max())


def test_held_inputs_and_wrong_topics(truth, tmp_path):
    write_bag(tmp_path / "run", truth)
    tr = read_rosbag_onboard(tmp_path / "run", "/imu/data", "/joint_states", hold=True)
    assert tr.hold
    np.testing.assert_allclose(tr.inputs, truth.inputs[:-1], atol=1e-12)  # the last torque sent before
    with pytest.raises(InputError, match="holds sensor_msgs/msg/JointState, not IMU readings"):
        read_rosbag_onboard(tmp_path / "run", "/joint_states", "/joint_states")
    with pytest.raises(InputError, match="no topic '/imu'"):
        read_rosbag_onboard(tmp_path / "run", "/imu", "/joint_states")
    code = main(["convert", str(tmp_path / "run"), "--format", "rosbag", "--imu-topic", "/imu/data", "--out", "x.csv"])
    assert code != 0
