"""Robot logs in ROS bags (ROS 1 `*.bag`; ROS 2 folders with `metadata.yaml` and sqlite3 or
MCAP storage, or the storage file itself), read through `rosbags` (no ROS install): poses
(`read_rosbag_poses`), wheel inputs (`read_rosbag_inputs`) and onboard-sensor trials
(`read_rosbag_onboard`). A message's time is its header stamp, else (stamps of zero) the time
the bag recorded it, with a `CaptureWarning`; times are seconds since the epoch, as in the bag.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .._runtime.errors import InputError
from .inputs import interpolate_inputs
from .markers import MarkerData
from .onboard import OnboardTrial
from .validation import sign_continuous, warn

#: message types that carry one pose (REP 103: metres, X forward, Y left, Z up)
POSE_TYPES = (
    "geometry_msgs/msg/PoseStamped",
    "geometry_msgs/msg/PoseWithCovarianceStamped",
    "geometry_msgs/msg/TransformStamped",
    "nav_msgs/msg/Odometry",
)
#: message types that carry the transforms of several frames (`/tf`; `tf/tfMessage` of ROS 1's tf)
TF_TYPES = ("tf2_msgs/msg/TFMessage", "tf/msg/tfMessage")
JOINT_STATE = "sensor_msgs/msg/JointState"
IMU = "sensor_msgs/msg/Imu"
#: `--input-kind`: the JointState field it reads and the trial's kind of inputs
INPUT_FIELDS = {"chi_dot": ("velocity", "wheel_speeds"), "K": ("effort", "torques")}


def _messages(path, topic: str, types: tuple[str, ...], what: str) -> tuple[list, np.ndarray, str]:
    """The messages of `topic` (deserialised), the bag's receive times [s] and the message type.
    A topic that is not in the bag, or of another type, is an `InputError` naming what there is."""
    try:
        from rosbags.highlevel import AnyReader, AnyReaderError
    except ImportError:
        raise ImportError(
            'reading ROS bags needs rosbags: pip install rosbags (or pip install -e ".[ros]" in the jsphere source folder).'
        ) from None
    bag = Path(path)
    if not bag.exists():
        raise FileNotFoundError(f"ROS bag {bag} does not exist.")
    if bag.is_file() and bag.suffix in (".db3", ".mcap") and (bag.parent / "metadata.yaml").exists():
        bag = bag.parent  # a ROS 2 bag is its folder
    source = str(path)
    try:
        with AnyReader([bag]) as reader:
            topics = {name: info.msgtype for name, info in reader.topics.items()}
            if topic not in topics:
                listing = ", ".join(f"{n} ({t})" for n, t in sorted(topics.items())) or "none"
                raise InputError(f"{source}: no topic {topic!r} in the bag; its topics: {listing}.")
            if topics[topic] not in types:
                raise InputError(
                    f"{source}: topic {topic!r} holds {topics[topic]}, not {what} ({' or '.join(types)}); "
                    f"choose a topic of that type."
                )
            conns = [c for c in reader.connections if c.topic == topic]
            msgs, times = [], []
            for conn, stamp, raw in reader.messages(connections=conns):
                msgs.append(reader.deserialize(raw, conn.msgtype))
                times.append(stamp * 1e-9)
    except AnyReaderError as e:
        raise InputError(f"{source}: not a readable ROS bag (rosbags: {e}).") from None
    if not msgs:
        raise InputError(f"{source}: topic {topic!r} holds no messages.")
    return msgs, np.asarray(times), topics[topic]


def _clock(headers: list, bag_times: np.ndarray, source: str, topic: str) -> np.ndarray:
    """The message times [s]: their header stamps, or the bag's receive times (with a
    `CaptureWarning`) where any stamp is zero; times that do not increase strictly are an
    `InputError`."""
    t = np.array([h.stamp.sec + 1e-9 * h.stamp.nanosec for h in headers])
    zero = t == 0.0
    if np.any(zero):
        warn(
            f"{source}: {int(zero.sum())} of the {len(t)} messages of {topic} have no header stamp; using the times "
            "the bag recorded them (they include the transport delay)."
        )
        t = bag_times
    bad = np.nonzero(np.diff(t) <= 0)[0]
    if bad.size:
        i = int(bad[0]) + 1
        raise InputError(
            f"{source}: the stamps of {topic} are not strictly increasing (message {i + 1} at {t[i]:.9f} s follows "
            f"{t[i - 1]:.9f} s); record the topic with distinct stamps, in order."
        )
    return t


def read_rosbag_poses(path, topic: str, *, child_frame: str | None = None) -> MarkerData:
    """The poses on `topic` of a ROS bag, in metres in a Z-up frame (REP 103).

    `topic` holds `geometry_msgs/PoseStamped` (vrpn_client_ros, mocap4r2),
    `PoseWithCovarianceStamped` (an estimator such as amcl or robot_localization),
    `TransformStamped` or `nav_msgs/Odometry`: its pose in its header's frame. Or it holds
    `tf2_msgs/TFMessage` (`/tf`, as motion-capture bridges publish): the transforms of
    `child_frame` from its parent frame (the parent's own motion is not composed in). Without
    `child_frame`, the topic's one moving child frame; several moving child frames are an
    `InputError` listing them.

    Returns `MarkerData` without markers, the pose in `rb_q` (scalar first, body -> fixed) and
    `rb_p`; a quaternion of zeros or a non-finite value is a gap. Times: header stamps [s since
    the epoch, or since the simulation's start], else the bag's times with a `CaptureWarning`.
    """
    source = str(path)
    msgs, bag_t, msgtype = _messages(path, topic, POSE_TYPES + TF_TYPES, "poses")
    if child_frame is not None and msgtype not in TF_TYPES:
        raise InputError(
            f"{source}: --child-frame picks a frame of a tf2_msgs/msg/TFMessage topic such as /tf; {topic} holds "
            f"{msgtype}, one pose per message: drop --child-frame."
        )
    if msgtype in TF_TYPES:
        msgs, bag_t = _frame_transforms(msgs, bag_t, source, topic, child_frame)
        topic = f"{topic} ({msgs[0].child_frame_id})"
    if msgtype.endswith("Odometry") or msgtype.endswith("WithCovarianceStamped"):
        poses = [(m.pose.pose.position, m.pose.pose.orientation) for m in msgs]
    elif msgtype.endswith("PoseStamped"):
        poses = [(m.pose.position, m.pose.orientation) for m in msgs]
    else:
        poses = [(m.transform.translation, m.transform.rotation) for m in msgs]
    t = _clock([m.header for m in msgs], bag_t, source, topic)
    p = np.array([_xyz(v) for v, _ in poses], float)
    q = np.array([[r.w, r.x, r.y, r.z] for _, r in poses], float)
    norm = np.linalg.norm(q, axis=1)
    gap = ~np.all(np.isfinite(p), axis=1) | ~np.isfinite(norm) | (norm < 0.5)
    q[gap], p[gap] = np.nan, np.nan
    q[~gap] /= norm[~gap, None]
    return MarkerData(t, np.zeros((len(t), 0, 3)), (), source, None, sign_continuous(q), p)


def _frame_transforms(msgs: list, bag_t: np.ndarray, source: str, topic: str, child_frame: str | None):
    """The `TransformStamped`s of one child frame in the `TFMessage`s `msgs`, and the bag's times
    of the messages that hold them: `child_frame` (a leading '/' ignored), else the one child
    frame whose transform changes. `InputError` naming the child frames where there is none,
    several moving ones, or one with several parents."""
    frames: dict[str, list] = {}
    for m, tb in zip(msgs, bag_t):
        for tf in m.transforms:
            frames.setdefault(tf.child_frame_id.lstrip("/"), []).append((tf, tb))
    if not frames:
        raise InputError(f"{source}: the messages of {topic} hold no transforms.")

    def parents(name):
        return sorted({tf.header.frame_id for tf, _ in frames[name]})

    def listing(names, most=12):
        shown = ", ".join(f"{n} (from {' and '.join(parents(n))})" for n in names[:most])
        return shown + (f" and {len(names) - most} more" if len(names) > most else "")

    if child_frame is not None:
        name = child_frame.strip().lstrip("/")
        if name not in frames:
            raise InputError(
                f"{source}: no child frame {child_frame!r} in {topic}; its child frames: {listing(sorted(frames))}."
            )
    else:
        moving = sorted(n for n in frames if _moves([tf.transform for tf, _ in frames[n]]))
        if len(moving) > 1:
            raise InputError(
                f"{source}: {topic} holds {len(moving)} moving child frames: {listing(moving)}; name the robot's frame "
                "with --child-frame NAME."
            )
        if not moving and len(frames) > 1:
            raise InputError(
                f"{source}: no child frame of {topic} moves ({len(frames)} fixed ones: {listing(sorted(frames))}); "
                "give the topic where the robot's frame moves (such as /tf) with --pose-topic."
            )
        [name] = moving or list(frames)
    if len(parents(name)) > 1:
        raise InputError(
            f"{source}: the transforms of child frame {name!r} on {topic} come from {len(parents(name))} parent "
            f"frames ({', '.join(parents(name))}); a pose needs one: record the robot's frame from one parent."
        )
    return [tf for tf, _ in frames[name]], np.array([tb for _, tb in frames[name]])


def _moves(transforms: list) -> bool:
    """Whether the `geometry_msgs/Transform`s `transforms` are not all the same."""
    v = np.array([[*_xyz(t.translation), t.rotation.w, *_xyz(t.rotation)] for t in transforms])
    return bool(np.any(v != v[0]))


def _xyz(v) -> list[float]:
    """The components `x, y, z` of a message's vector (or of a quaternion's vector part)."""
    return [v.x, v.y, v.z]


def read_rosbag_inputs(
    path, topic: str, *, input_kind: str = "chi_dot", joints=None, n_wheels: int | None = None
) -> tuple[np.ndarray, np.ndarray, str, list[str]]:
    """The wheel inputs on `topic` (`sensor_msgs/JointState`) of a ROS bag.

    `input_kind`: `"chi_dot"` reads `velocity` (wheel rates relative to the platform [rad/s],
    encoder readings or commands), `"K"` reads `effort` (axle torques [N m]). `joints`: the
    wheels' joint names in wheel order (a list or a comma-separated string); default: every
    joint of the messages, in their order. `n_wheels`: the robot's number of wheels, checked.

    Returns `(t, values (T, N), kind, joint names)` like `read_inputs_csv`, `t` in seconds since
    the epoch (header stamps, else the bag's times with a `CaptureWarning`). A missing topic, a
    topic of another type, a joint that is not in a message, an empty `velocity`/`effort`, or a
    joint count other than `n_wheels` is an `InputError` saying what there is.
    """
    field, kind = _input_field(path, input_kind)
    t, values, names = _joint_values(path, topic, field, joints, n_wheels)
    return t, values, kind, names


def _input_field(path, input_kind: str) -> tuple[str, str]:
    """The JointState field and the trial's kind of inputs of `input_kind` (`INPUT_FIELDS`)."""
    if input_kind not in INPUT_FIELDS:
        raise InputError(f"{path}: input kind must be one of {list(INPUT_FIELDS)}; got {input_kind!r}.")
    return INPUT_FIELDS[input_kind]


def _joint_values(
    path, topic: str, field: str, joints, n_wheels: int | None
) -> tuple[np.ndarray, np.ndarray, list[str]]:
    """`(t, values (T, N), joint names)`: the `field` (`position`, `velocity` or `effort`) of
    the wheels' joints on the `sensor_msgs/JointState` topic (`read_rosbag_inputs`)."""
    source = str(path)
    if isinstance(joints, str):
        joints = [j.strip() for j in joints.split(",") if j.strip()]
    msgs, bag_t, _ = _messages(path, topic, (JOINT_STATE,), "joint states")
    first = list(msgs[0].name)
    names = list(joints) if joints else first
    values = np.empty((len(msgs), len(names)))
    for i, m in enumerate(msgs):
        have = list(m.name)
        vals = np.asarray(getattr(m, field), float)
        if len(vals) != len(have):
            filled = [f for f in ("position", "velocity", "effort") if len(getattr(m, f)) == len(have) and have]
            other = {"velocity": "K", "effort": "chi_dot"}.get(field)
            raise InputError(
                f"{source}: message {i + 1} of {topic} has {len(vals)} {field} values for its {len(have)} joints "
                f"{have} (it fills {', '.join(filled) or 'none of position, velocity, effort'}); "
                + (
                    f"--input-kind {other} reads {INPUT_FIELDS[other][0]}."
                    if other is not None and INPUT_FIELDS[other][0] in filled
                    else f"record the joint states with {field} filled."
                )
            )
        if not joints and have != first:
            raise InputError(
                f"{source}: the joints of {topic} change at message {i + 1} ({have}, first {first}); name the wheels "
                f"in wheel order with --joints, e.g. --joints {','.join(first)}."
            )
        missing = [j for j in names if j not in have]
        if missing:
            raise InputError(f"{source}: message {i + 1} of {topic} has no joint {missing[0]!r}; its joints: {have}.")
        values[i] = vals[[have.index(j) for j in names]]
    if n_wheels is not None and len(names) != n_wheels:
        raise InputError(
            f"{source}: {topic} gives {len(names)} joints {names} but the robot has {n_wheels} wheels; name its wheels in "
            f"wheel order with --joints, e.g. --joints {','.join(names[:n_wheels])}."
        )
    bad = np.argwhere(~np.isfinite(values))
    if bad.size:
        i, j = int(bad[0, 0]), int(bad[0, 1])
        raise InputError(f"{source}: message {i + 1} of {topic}: {field} of joint {names[j]!r} is not finite.")
    t = _clock([m.header for m in msgs], bag_t, source, topic)
    if len(t) < 2:
        raise InputError(f"{source}: {topic} holds {len(t)} message; the inputs need at least 2.")
    return t, values, names


def read_rosbag_onboard(
    path,
    imu_topic: str,
    inputs_topic: str,
    *,
    input_kind: str = "K",
    encoder_topic: str | None = None,
    joints=None,
    n_wheels: int | None = None,
    hold: bool = False,
    name: str | None = None,
) -> OnboardTrial:
    """An onboard-sensor trial from a ROS bag: the IMU's `sensor_msgs/Imu` on `imu_topic`
    (`angular_velocity` as the gyro, `linear_acceleration` as the accelerometer: the specific
    force, +9.81 up at rest, as REP 145 has it; in the IMU's frame), the wheels' encoders as the
    `position` of the `JointState` on `encoder_topic` (default: `inputs_topic`), and the inputs
    as its `effort` (`input_kind="K"`) or `velocity` (`"chi_dot"`) on `inputs_topic`.

    The trial's samples are the IMU's messages within the span every topic covers, its times
    from the first of them; the encoder angles are unwrapped, interpolated linearly at the IMU's
    times and taken from 0; the inputs are interpolated linearly, or held (`hold`: a digital
    controller's torques, the trial says `# hold: zero-order`). `joints`, `n_wheels` as for
    `read_rosbag_inputs`. `InputError` for topics of other types, spans that do not overlap, or
    fewer than 4 IMU samples in the overlap."""
    source = str(path)
    field, kind = _input_field(path, input_kind)
    msgs, bag_t, _ = _messages(path, imu_topic, (IMU,), "IMU readings")
    t = _clock([m.header for m in msgs], bag_t, source, imu_topic)
    gyro = np.array([_xyz(m.angular_velocity) for m in msgs], float)
    acc = np.array([_xyz(m.linear_acceleration) for m in msgs], float)
    enc_topic = encoder_topic or inputs_topic
    t_chi, chi, names = _joint_values(path, enc_topic, "position", joints, n_wheels)
    t_in, u, _ = _joint_values(path, inputs_topic, field, joints or names, n_wheels)
    lo, hi = max(t[0], t_chi[0], t_in[0]), min(t[-1], t_chi[-1], t_in[-1])
    keep = (t >= lo) & (t <= hi)
    if keep.sum() < 4:
        raise InputError(
            f"{source}: {imu_topic} ({t[0]:.3f}-{t[-1]:.3f} s), {enc_topic} ({t_chi[0]:.3f}-{t_chi[-1]:.3f} s) and "
            f"{inputs_topic} ({t_in[0]:.3f}-{t_in[-1]:.3f} s) overlap in {int(keep.sum())} IMU samples; an onboard "
            "trial needs at least 4: record the topics together."
        )
    t, gyro, acc = t[keep], gyro[keep], acc[keep]
    chi = interpolate_inputs(t_chi, np.unwrap(chi, axis=0), t)
    if hold:
        inputs = u[np.clip(np.searchsorted(t_in, t, side="right") - 1, 0, len(t_in) - 1)]
    else:
        inputs = interpolate_inputs(t_in, u, t)
    stem = Path(path).stem if Path(path).is_file() else Path(path).name
    return OnboardTrial(t - t[0], gyro, acc, chi - chi[0], inputs, kind, hold, name or stem, source)
