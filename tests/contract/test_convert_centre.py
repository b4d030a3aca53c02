"""`jsphere convert --params` checks the converted shell centre's height against the robot's
R0 and names the options that put the centre where it belongs: a Motive take converted
without its body offset tracks the markers' centroid, 3 cm above the centre; a ROS bag's pose
topic names no body markers."""

import re

import numpy as np
import pytest

import jsphere
from jsphere.capture.synthetic import default_marker_set
from jsphere.cli.app import main

T1 = 1.5
ABOVE = 0.03  # the markers' centroid above the shell centre [m]


@pytest.fixture(scope="module")
def take(paper, tmp_path_factory):
    """A synthetic wheel-speed trial, a Motive take of markers whose centroid lies `ABOVE` over
    the shell centre, its inputs table and the robot file."""
    folder = tmp_path_factory.mktemp("centre")
    c = jsphere.random_inputs(paper, T1, kind="wheel_speeds", seed=3)
    tr = jsphere.synthetic_trial(paper, c, T1, pos_sd=0.0, rot_sd_deg=0.0, name="truth")
    body = default_marker_set(float(paper.R0))
    body = body - body.mean(0) + np.array([0.0, 0.0, ABOVE])
    m = jsphere.synthetic_markers(tr, body, z=float(paper.R0), marker_sd=1e-4, seed=5)
    raw = folder / "take.csv"
    jsphere.write_motive_csv(raw, tr.t, m, ["m1", "m2", "m3", "m4"])
    inputs = folder / "inputs.csv"
    jsphere.write_inputs_csv(inputs, tr.t, tr.inputs, tr.kind)
    robot = folder / "robot.toml"
    paper.save(robot)
    return tr, raw, inputs, robot


def _convert(args, capsys):
    code = main(["convert", *map(str, args)])
    out, err = capsys.readouterr()
    return code, out, [ln for ln in err.splitlines() if ln.startswith("jsphere convert: warning:")]


def test_a_centroid_for_the_centre_is_named_with_its_height_and_fix(take, tmp_path, capsys):
    tr, raw, inputs, robot = take
    args = [raw, "--format", "motive", "--inputs", inputs, "--params", robot, "--out", tmp_path / "t.csv"]
    code, out, warned = _convert(args, capsys)
    assert code == 0, warned
    (line,) = [w for w in warned if "shell centre is" in w]
    height = float(line.split("shell centre is ")[1].split()[0])
    assert abs(height - (0.15 + ABOVE)) < 1e-3, line
    # the platform leans a little, so the centroid rises a little less than 3 cm above the centre
    above = re.search(r"([\d.]+) mm above the robot's shell radius R0 = 0\.1500 m", line)
    assert above and 28.0 < float(above[1]) <= 30.0, line
    suggested = re.search(r"--body-offset 0 0 (-0\.0\d+)\.$", line)
    assert "--body-markers FILE" in line and suggested and abs(float(suggested[1]) + float(above[1]) * 1e-3) < 1e-4
    assert f"shell centre height {height:.4f} m" in out, out  # the summary names it too

    code, out, warned = _convert([*args[:-1], tmp_path / "u.csv", "--body-offset", "0", "0", str(-ABOVE)], capsys)
    assert code == 0 and warned == [], warned
    assert "shell centre height 0.150" in out and "the robot's R0" in out, out
    z = jsphere.read_trial(tmp_path / "u.csv").z
    assert abs(np.nanmedian(z) - 0.15) < 5e-4


def test_without_params_the_check_is_skipped_once(take, tmp_path, capsys):
    _, raw, inputs, _ = take
    code, out, warned = _convert([raw, "--format", "motive", "--inputs", inputs, "--out", tmp_path / "t.csv"], capsys)
    assert code == 0 and warned == [], warned
    assert out.count("not checked against the shell radius: give --params ROBOT") == 1, out
    height = re.search(r"shell centre height ([\d.]+) m", out)
    assert height and 0.175 < float(height[1]) <= 0.18, out  # the centroid, unchecked


def test_a_rigid_body_pivot_off_the_centre_names_the_pivot(take, tmp_path, capsys):
    """Motive's own rigid-body pose, its pivot point 3 cm above the centre: the warning names the
    pivot point and --body-offset, not the markers that were not used."""
    tr, _, inputs, robot = take
    raw = tmp_path / "rigid_body.csv"
    p = np.stack([tr.x, tr.y, np.full(tr.n_frames, 0.15 + ABOVE)], axis=1)
    jsphere.write_motive_csv(raw, tr.t, np.zeros((tr.n_frames, 0, 3)), [], rb_q=tr.q, rb_p=p)
    code, _, warned = _convert(
        [raw, "--format", "motive", "--inputs", inputs, "--params", robot, "--out", tmp_path / "t.csv"], capsys
    )
    assert code == 0, warned
    (line,) = warned
    assert "0.1800 m above the floor" in line and "the rigid body's pivot point is not the shell centre" in line, line
    assert "in Motive" in line and "--body-offset X Y Z" in line and "--body-markers" not in line, line


def test_a_pose_topic_off_the_centre_names_its_frame(take, tmp_path, capsys):
    """A ROS bag's poses of a frame 3 cm above the shell centre: the warning names the pose
    topic's frame and --body-offset, never the body markers a bag does not have; at the centre,
    no warning."""
    pytest.importorskip("rosbags")
    tr, _, _, robot = take
    for z, name in ((0.15 + ABOVE, "high"), (0.15, "centre")):
        bag = _write_bag(tmp_path / name, tr, z)
        args = [bag, "--format", "rosbag", "--pose-topic", "/mocap/robot/pose", "--inputs-topic", "/joint_states"]
        code, out, warned = _convert([*args, "--params", robot, "--out", tmp_path / f"{name}.csv"], capsys)
        assert code == 0, warned
        if name == "centre":
            assert warned == [], warned
            continue
        (line,) = warned
        assert "0.1800 m above the floor" in line and "the pose topic's frame is not at the shell centre" in line, line
        assert "--body-offset X Y Z" in line and "--body-markers" not in line, line


def _write_bag(path, tr, z):
    """A ROS 2 (MCAP) bag of `tr`'s poses at height `z` (PoseStamped) and its wheel speeds
    (JointState), stamped on one clock."""
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS2_HUMBLE)
    T = ts.types
    Time, Header = T["builtin_interfaces/msg/Time"], T["std_msgs/msg/Header"]
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as w:
        c_pose = w.add_connection("/mocap/robot/pose", "geometry_msgs/msg/PoseStamped", typestore=ts)
        c_js = w.add_connection("/joint_states", "sensor_msgs/msg/JointState", typestore=ts)
        for i, t in enumerate(tr.t):
            ns = 1_700_000_000_000_000_000 + int(round(t * 1e9))
            h = Header(stamp=Time(sec=ns // 10**9, nanosec=ns % 10**9), frame_id="world")
            (qw, qx, qy, qz) = tr.q[i]
            pose = T["geometry_msgs/msg/Pose"](
                position=T["geometry_msgs/msg/Point"](x=tr.x[i], y=tr.y[i], z=z),
                orientation=T["geometry_msgs/msg/Quaternion"](x=qx, y=qy, z=qz, w=qw),
            )
            msg = T["geometry_msgs/msg/PoseStamped"](header=h, pose=pose)
            w.write(c_pose, ns, ts.serialize_cdr(msg, "geometry_msgs/msg/PoseStamped"))
            js = T["sensor_msgs/msg/JointState"](
                header=h,
                name=["wheel_1", "wheel_2", "wheel_3"],
                position=np.zeros(3),
                velocity=np.asarray(tr.inputs[i], float),
                effort=np.zeros(3),
            )
            w.write(c_js, ns, ts.serialize_cdr(js, "sensor_msgs/msg/JointState"))
    return path
