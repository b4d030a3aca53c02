"""Robot logs in ROS bags: ROS 1 bags and ROS 2 bags (MCAP and sqlite3), written here with
`rosbags` as a robot would record them (poses from a motion-capture bridge, wheel states as
`sensor_msgs/JointState`), converted into trials and compared with the same data as CSV files."""

import numpy as np
import pytest

import jsphere
from jsphere.cli.app import main

pytest.importorskip("rosbags")
from rosbags.rosbag1 import Writer as Writer1  # noqa: E402
from rosbags.rosbag2 import StoragePlugin  # noqa: E402
from rosbags.rosbag2 import Writer as Writer2  # noqa: E402
from rosbags.typesys import Stores, get_types_from_msg, get_typestore  # noqa: E402

EPOCH_NS = 1_741_946_000_000_000_000  # the robot's clock: seconds since 1970
N = 120  # frames at 100 Hz
JOINTS = ["wheel_1", "wheel_2", "wheel_3"]


@pytest.fixture(scope="module")
def run():
    """Poses of a rolling ball (a smooth path, the platform turning and leaning a little) and
    the wheel rates and torques that drove it: `(t [s from 0], q (w, x, y, z), p, chi_dot, K)`."""
    t = np.arange(N) * 0.01
    p = np.stack([0.2 * np.sin(t), 0.1 * t**2, np.full(N, 0.15)], axis=1)
    half = 0.5 * np.stack([0.05 * np.sin(3 * t), 0.04 * np.cos(2 * t), 0.8 * t], axis=1)
    ang = np.linalg.norm(half, axis=1, keepdims=True)
    q = np.concatenate([np.cos(ang), np.sin(ang) * half / ang], axis=1)
    chi = np.stack([np.sin(t + k) for k in range(3)], axis=1)
    return t, q, p, chi, 0.01 * chi


def _typestore(ros1):
    ts = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
    if ros1:  # (noetic's store lacks tf2_msgs)
        ts.register(get_types_from_msg("geometry_msgs/TransformStamped[] transforms", "tf2_msgs/msg/TFMessage"))
    return ts


TOPICS = {"TFMessage": "/tf"}  # the pose topic of each `pose_type`; the others: /mocap/robot/pose


def write_bag(
    path,
    run,
    *,
    ros1=False,
    storage="mcap",
    pose_type="PoseStamped",
    stamps=True,
    names=None,
    effort=True,
    wand=False,
):
    """A bag with a pose topic `/mocap/robot/pose` (`pose_type`: PoseStamped as vrpn_client_ros and
    mocap4r2 publish, PoseWithCovarianceStamped as estimators do, TransformStamped, or Odometry)
    or `/tf` (`pose_type="TFMessage"`, as motion-capture bridges publish: the frame `robot` from
    `world`, and `camera` fixed on it; with `wand`, a second moving frame `wand`), and
    `/joint_states` (JointState: name, position, velocity, effort). The bag's receive times trail
    the header stamps by 3 ms; with `stamps=False` the header stamps are zero."""
    t, q, p, chi, K = run
    ts = _typestore(ros1)
    T = ts.types
    Time, Header = T["builtin_interfaces/msg/Time"], T["std_msgs/msg/Header"]
    Point, Vector3, Quat = (
        T["geometry_msgs/msg/Point"],
        T["geometry_msgs/msg/Vector3"],
        T["geometry_msgs/msg/Quaternion"],
    )
    Pose = T["geometry_msgs/msg/Pose"]
    msgtype = {
        "PoseStamped": "geometry_msgs/msg/PoseStamped",
        "PoseWithCovarianceStamped": "geometry_msgs/msg/PoseWithCovarianceStamped",
        "TransformStamped": "geometry_msgs/msg/TransformStamped",
        "Odometry": "nav_msgs/msg/Odometry",
        "TFMessage": "tf2_msgs/msg/TFMessage",
    }[pose_type]
    serialize = ts.serialize_ros1 if ros1 else ts.serialize_cdr
    names = JOINTS if names is None else names

    def header(i, ns):
        stamp = Time(sec=ns // 10**9, nanosec=ns % 10**9) if stamps else Time(sec=0, nanosec=0)
        return Header(seq=i, stamp=stamp, frame_id="world") if ros1 else Header(stamp=stamp, frame_id="world")

    def transform(h, child, qi, pi):
        (w, x, y, z), (px, py, pz) = qi, pi
        tf = T["geometry_msgs/msg/Transform"](translation=Vector3(x=px, y=py, z=pz), rotation=Quat(x=x, y=y, z=z, w=w))
        return T["geometry_msgs/msg/TransformStamped"](header=h, child_frame_id=child, transform=tf)

    def pose_msg(i, h):
        (w, x, y, z), (px, py, pz) = q[i], p[i]
        rot = Quat(x=x, y=y, z=z, w=w)
        if pose_type == "TransformStamped":
            return transform(h, "robot", q[i], p[i])
        if pose_type == "TFMessage":
            camera = Header(seq=i, stamp=h.stamp, frame_id="robot") if ros1 else Header(stamp=h.stamp, frame_id="robot")
            tfs = [transform(h, "robot", q[i], p[i]), transform(camera, "camera", (1.0, 0, 0, 0), (0.05, 0, 0.1))]
            if wand:
                tfs.insert(0, transform(h, "wand", q[-1 - i], p[-1 - i]))
            return T[msgtype](transforms=tfs)
        pose = Pose(position=Point(x=px, y=py, z=pz), orientation=rot)
        if pose_type == "PoseStamped":
            return T[msgtype](header=h, pose=pose)
        cov = np.zeros(36)
        if pose_type == "PoseWithCovarianceStamped":
            return T[msgtype](header=h, pose=T["geometry_msgs/msg/PoseWithCovariance"](pose=pose, covariance=cov))
        twist = T["geometry_msgs/msg/TwistWithCovariance"](
            twist=T["geometry_msgs/msg/Twist"](
                linear=Vector3(x=0.0, y=0.0, z=0.0), angular=Vector3(x=0.0, y=0.0, z=0.0)
            ),
            covariance=cov,
        )
        return T[msgtype](
            header=h,
            child_frame_id="robot",
            pose=T["geometry_msgs/msg/PoseWithCovariance"](pose=pose, covariance=cov),
            twist=twist,
        )

    if ros1:
        writer = Writer1(path)
    else:
        plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
        writer = Writer2(path, version=9, storage_plugin=plugin)
    with writer:
        c_pose = writer.add_connection(TOPICS.get(pose_type, "/mocap/robot/pose"), msgtype, typestore=ts)
        c_js = writer.add_connection("/joint_states", "sensor_msgs/msg/JointState", typestore=ts)
        c_other = writer.add_connection("/battery", "std_msgs/msg/Float32", typestore=ts)
        for i in range(N):
            ns = EPOCH_NS + i * 10_000_000
            js = T[
                "sensor_msgs/msg/JointState"
            ](
                header=header(i, ns + 2_000_000),  # the wheel states 2 ms after the pose
                name=list(names),
                position=np.zeros(len(names)),
                velocity=chi[i][: len(names)] if len(names) <= 3 else np.r_[chi[i], 0.0],
                effort=(K[i][: len(names)] if len(names) <= 3 else np.r_[K[i], 0.0]) if effort else np.zeros(0),
            )
            writer.write(c_js, ns + 5_000_000, serialize(js, "sensor_msgs/msg/JointState"))
            writer.write(c_pose, ns + 3_000_000, serialize(pose_msg(i, header(i, ns)), msgtype))
            writer.write(c_other, ns, serialize(T["std_msgs/msg/Float32"](data=12.0), "std_msgs/msg/Float32"))
    return path


def csv_files(tmp_path, run, kind="wheel_speeds"):
    """The same run as files a lab would write by hand: a Motive export of the rigid body (Y-up,
    metres) and an inputs table on the same clock (the wheel states 2 ms after the poses)."""
    t, q, p, chi, K = run
    take = tmp_path / "take.csv"
    jsphere.write_motive_csv(take, t, np.zeros((N, 0, 3)), [], rb_q=q, rb_p=p, units="m")
    inputs = tmp_path / "inputs.csv"
    jsphere.write_inputs_csv(inputs, t + 0.002, chi if kind == "wheel_speeds" else K, kind)
    return take, inputs


def _same(a, b, tol=2e-6):
    assert a.kind == b.kind and a.n_frames == b.n_frames and a.n_wheels == b.n_wheels
    np.testing.assert_allclose(a.t, b.t, atol=tol)
    np.testing.assert_allclose(a.x, b.x, atol=tol)
    np.testing.assert_allclose(a.y, b.y, atol=tol)
    np.testing.assert_allclose(a.q, b.q, atol=tol)
    np.testing.assert_allclose(a.inputs, b.inputs, atol=1e-6)


@pytest.mark.parametrize(
    ("ros1", "storage", "pose_type"),
    [
        (False, "mcap", "PoseStamped"),
        (True, None, "PoseStamped"),
        (False, "sqlite3", "TransformStamped"),
        (True, None, "Odometry"),
        (True, None, "TFMessage"),
        (False, "sqlite3", "TFMessage"),
        (False, "mcap", "TFMessage"),
        (True, None, "PoseWithCovarianceStamped"),
        (False, "sqlite3", "PoseWithCovarianceStamped"),
        (False, "mcap", "PoseWithCovarianceStamped"),
    ],
)
def test_bag_converts_into_the_trial_of_the_csv_files(tmp_path, run, ros1, storage, pose_type):
    """Each pose message type, in ROS 1, ROS 2 sqlite3 and MCAP bags; `/tf` with its one moving
    child frame (`robot`; `camera` is fixed on it) needs no `--child-frame`."""
    bag = write_bag(tmp_path / ("run.bag" if ros1 else "run"), run, ros1=ros1, storage=storage, pose_type=pose_type)
    take, inputs = csv_files(tmp_path, run)
    want = jsphere.convert_raw(take, inputs, format="motive")
    topic = TOPICS.get(pose_type, "/mocap/robot/pose")
    got = jsphere.convert_raw(
        bag,
        None,
        format="rosbag",
        options=jsphere.ConvertOptions(pose_topic=topic, inputs_topic="/joint_states", name="take"),
    )
    _same(got, want)
    # the clock starts at the first message, the pose at 0; that pose precedes the first wheel state (2 ms)
    assert got.t[0] == pytest.approx(0.01, abs=1e-6)


def test_cli_rosbag_equals_csv_files(tmp_path, run):
    """`jsphere convert BAG --format rosbag` writes the very trial file that the CSV files give,
    for wheel rates (velocity) and torques (effort), with the joints named in another order."""
    bag = write_bag(tmp_path / "run", run)
    t, q, p, chi, K = run
    for kind, flag in (("wheel_speeds", "chi_dot"), ("torques", "K")):
        take, inputs = csv_files(tmp_path, run, kind)
        a, b = tmp_path / f"csv_{flag}.csv", tmp_path / f"bag_{flag}.csv"
        assert main(["convert", str(take), "--format", "motive", "--inputs", str(inputs), "--out", str(a)]) == 0
        args = ["convert", str(bag), "--format", "rosbag", "--pose-topic", "/mocap/robot/pose"]
        args += ["--inputs-topic", "/joint_states", "--input-kind", flag, "--out", str(b)]
        assert main(args) == 0
        _same(jsphere.read_trial(b), jsphere.read_trial(a))
    rev = tmp_path / "rev.csv"
    args = ["convert", str(bag), "--format", "rosbag", "--pose-topic", "/mocap/robot/pose"]
    assert (
        main([*args, "--inputs-topic", "/joint_states", "--joints", "wheel_3,wheel_1,wheel_2", "--out", str(rev)]) == 0
    )
    np.testing.assert_allclose(
        jsphere.read_trial(rev).inputs, jsphere.read_trial(tmp_path / "bag_chi_dot.csv").inputs[:, [2, 0, 1]]
    )


def test_markers_from_a_capture_file_inputs_from_a_bag(tmp_path, run):
    """`--inputs BAG --inputs-topic U`: the poses from a Motive export, the inputs from the
    robot's bag (its clock starting at its first message)."""
    bag = write_bag(tmp_path / "run.bag", run, ros1=True)
    take, inputs = csv_files(tmp_path, run)
    want = jsphere.convert_raw(take, inputs, format="motive")
    got = jsphere.convert_raw(
        take, bag, format="motive", options=jsphere.ConvertOptions(inputs_topic="/joint_states", time_offset=-0.002)
    )
    np.testing.assert_allclose(got.inputs, want.inputs[: got.n_frames], atol=1e-6)
    out = tmp_path / "trial.csv"
    args = ["convert", str(take), "--format", "motive", "--inputs", str(bag), "--inputs-topic", "/joint_states"]
    assert main([*args, "--time-offset", "-0.002", "--out", str(out)]) == 0
    assert jsphere.read_trial(out).n_wheels == 3


def test_bag_time_when_the_stamps_are_missing(tmp_path, run):
    bag = write_bag(tmp_path / "run", run, stamps=False)
    with pytest.warns(jsphere.CaptureWarning, match="have no header stamp; using the times the bag recorded them"):
        data = jsphere.read_rosbag_poses(bag, "/mocap/robot/pose")
    np.testing.assert_allclose(data.t - data.t[0], run[0], atol=1e-6)
    assert data.t[0] == pytest.approx((EPOCH_NS + 3_000_000) * 1e-9)  # the bag's time of the first pose


def test_ros2_storage_file_reads_as_its_bag(tmp_path, run):
    bag = write_bag(tmp_path / "run", run)
    [mcap] = bag.glob("*.mcap")
    t, values, kind, names = jsphere.read_rosbag_inputs(mcap, "/joint_states", input_kind="K")
    assert kind == "torques" and names == JOINTS
    np.testing.assert_allclose(values, run[4], atol=1e-12)


def test_bag_errors(tmp_path, run, capsys):
    bag = write_bag(tmp_path / "run", run, effort=False)
    with pytest.raises(
        jsphere.InputError, match=r"no topic '/pose' in the bag; its topics: /battery \(std_msgs/msg/Float32\)"
    ):
        jsphere.read_rosbag_poses(bag, "/pose")
    with pytest.raises(jsphere.InputError, match="topic '/battery' holds std_msgs/msg/Float32, not poses"):
        jsphere.read_rosbag_poses(bag, "/battery")
    with pytest.raises(jsphere.InputError, match="holds geometry_msgs/msg/PoseStamped, not joint states"):
        jsphere.read_rosbag_inputs(bag, "/mocap/robot/pose")
    with pytest.raises(
        jsphere.InputError, match=r"0 effort values for its 3 joints .* --input-kind chi_dot reads velocity"
    ):
        jsphere.read_rosbag_inputs(bag, "/joint_states", input_kind="K")
    with pytest.raises(
        jsphere.InputError, match=r"has no joint 'wheel_4'; its joints: \['wheel_1', 'wheel_2', 'wheel_3'\]"
    ):
        jsphere.read_rosbag_inputs(bag, "/joint_states", joints="wheel_1,wheel_4")
    with pytest.raises(jsphere.InputError, match=r"gives 3 joints .* but the robot has 4 wheels; name its wheels"):
        jsphere.read_rosbag_inputs(bag, "/joint_states", n_wheels=4)
    four = write_bag(tmp_path / "four", run, names=[*JOINTS, "caster"])
    base = [
        "convert",
        str(four),
        "--format",
        "rosbag",
        "--pose-topic",
        "/mocap/robot/pose",
        "--out",
        str(tmp_path / "t.csv"),
    ]
    robot = tmp_path / "robot.toml"
    jsphere.RobotParams.paper().save(robot)
    assert main([*base, "--inputs-topic", "/joint_states", "--params", str(robot)]) == 2
    assert (
        "gives 4 joints ['wheel_1', 'wheel_2', 'wheel_3', 'caster'] but the robot has 3 wheels"
        in capsys.readouterr().err
    )
    assert main([*base, "--inputs-topic", "/joint_states", "--params", str(robot), "--joints", ",".join(JOINTS)]) == 0
    assert main(base) == 2
    assert "--inputs-topic TOPIC" in capsys.readouterr().err
    assert main([*base[:4], "--inputs-topic", "/joint_states", "--out", str(tmp_path / "t.csv")]) == 2
    assert "--format rosbag needs --pose-topic" in capsys.readouterr().err
    take, _ = csv_files(tmp_path, run)
    assert (
        main(["convert", str(take), "--format", "motive", "--inputs", str(four), "--out", str(tmp_path / "t.csv")]) == 2
    )
    assert "a ROS bag; name its JointState topic with --inputs-topic TOPIC" in capsys.readouterr().err
    (tmp_path / "junk.bag").write_bytes(b"not a bag at all")
    with pytest.raises(jsphere.InputError, match="not a readable ROS bag"):
        jsphere.read_rosbag_poses(tmp_path / "junk.bag", "/pose")


def test_tf_child_frame(tmp_path, run, capsys):
    """`/tf` with two moving child frames: refused without `--child-frame`, listing them;
    `--child-frame` picks one (a leading '/' as ROS 1 writes it reads the same); a frame that
    is not there, or `--child-frame` where it does not apply, is refused."""
    one = jsphere.read_rosbag_poses(write_bag(tmp_path / "one.bag", run, ros1=True, pose_type="TFMessage"), "/tf")
    bag = write_bag(tmp_path / "two", run, storage="sqlite3", pose_type="TFMessage", wand=True)
    with pytest.raises(
        jsphere.InputError,
        match=r"/tf holds 2 moving child frames: robot \(from world\), wand \(from world\); name the robot's frame "
        r"with --child-frame NAME\.$",
    ):
        jsphere.read_rosbag_poses(bag, "/tf")
    for name in ("robot", "/robot"):
        got = jsphere.read_rosbag_poses(bag, "/tf", child_frame=name)
        np.testing.assert_array_equal(got.t, one.t)
        np.testing.assert_allclose(got.rb_p, run[2], atol=1e-12)
        np.testing.assert_allclose(got.rb_q, run[1], atol=1e-12)
    wand = jsphere.read_rosbag_poses(bag, "/tf", child_frame="wand")
    np.testing.assert_allclose(wand.rb_p, run[2][::-1], atol=1e-12)
    with pytest.raises(
        jsphere.InputError,
        match=r"no child frame 'base_link' in /tf; its child frames: camera \(from robot\), robot \(from world\), "
        r"wand \(from world\)\.",
    ):
        jsphere.read_rosbag_poses(bag, "/tf", child_frame="base_link")
    out = tmp_path / "t.csv"
    args = ["convert", str(bag), "--format", "rosbag", "--pose-topic", "/tf", "--inputs-topic", "/joint_states"]
    assert main([*args, "--child-frame", "robot", "--out", str(out)]) == 0
    assert jsphere.read_trial(out).n_frames == N - 1  # (the first pose precedes the first wheel state)
    assert main([*args, "--out", str(out)]) == 2
    assert "--child-frame NAME" in capsys.readouterr().err
    pose_bag = write_bag(tmp_path / "pose", run)
    args = ["convert", str(pose_bag), "--format", "rosbag", "--pose-topic", "/mocap/robot/pose"]
    assert main([*args, "--inputs-topic", "/joint_states", "--child-frame", "robot", "--out", str(out)]) == 2
    assert "holds geometry_msgs/msg/PoseStamped, one pose per message: drop --child-frame" in capsys.readouterr().err
    take, inputs = csv_files(tmp_path, run)
    args = ["convert", str(take), "--format", "motive", "--inputs", str(inputs), "--child-frame", "robot"]
    assert main([*args, "--out", str(out)]) == 2
    assert "--child-frame picks a frame of a ROS bag's /tf topic; --format motive has none" in capsys.readouterr().err
