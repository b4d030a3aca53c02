"""Real ROS bags (evo's test data, `rosbag/SOURCE.md`): `/tf` in ROS 1, ROS 2 sqlite3 and MCAP,
`geometry_msgs/PoseWithCovarianceStamped` and `nav_msgs/Odometry`, converted with `jsphere
convert --format rosbag` and compared with the messages decoded here byte by byte (the bag
containers opened with sqlite3 or rosbags' low-level readers, the messages parsed with `struct`)."""

import sqlite3
import struct
from pathlib import Path

import numpy as np
import pytest

import jsphere
from jsphere.cli.app import main

pytest.importorskip("rosbags")

HERE = Path(__file__).parent / "rosbag"
NAV2 = HERE / "nav2_turtlebot.mcap"


class _Cdr:
    """A cursor over a CDR (little-endian) message: alignment counted from after the 4-byte
    encapsulation header."""

    def __init__(self, raw: bytes):
        assert raw[:2] == b"\x00\x01", "little-endian CDR"
        self.buf, self.pos = raw[4:], 0

    def _take(self, fmt: str, size: int):
        self.pos += -self.pos % size
        (v,) = struct.unpack_from("<" + fmt, self.buf, self.pos)
        self.pos += size
        return v

    def u32(self) -> int:
        return self._take("I", 4)

    def f64s(self, n: int) -> list[float]:
        return [self._take("d", 8) for _ in range(n)]

    def text(self) -> str:
        n = self.u32()
        s = self.buf[self.pos : self.pos + n - 1].decode()
        self.pos += n
        return s

    def header(self) -> tuple[float, str]:
        sec, nsec = self.u32(), self.u32()
        return sec + 1e-9 * nsec, self.text()


class _Ros1:
    """A cursor over a ROS 1 message (little-endian, packed)."""

    def __init__(self, raw: bytes):
        self.buf, self.pos = raw, 0

    def _take(self, fmt: str):
        (v,) = struct.unpack_from("<" + fmt, self.buf, self.pos)
        self.pos += struct.calcsize(fmt)
        return v

    def u32(self) -> int:
        return self._take("I")

    def f64s(self, n: int) -> list[float]:
        return [self._take("d") for _ in range(n)]

    def text(self) -> str:
        n = self.u32()
        self.pos += n
        return self.buf[self.pos - n : self.pos].decode()

    def header(self) -> tuple[float, str]:
        self.u32()  # seq
        sec, nsec = self.u32(), self.u32()
        return sec + 1e-9 * nsec, self.text()


def _decode(c, msgtype: str):
    """`[(stamp [s], child frame, x, y, z, qx, qy, qz, qw), ...]`: the poses of one message."""
    if msgtype == "tf2_msgs/msg/TFMessage":
        out = []
        for _ in range(c.u32()):
            stamp, _parent = c.header()
            out.append((stamp, c.text(), *c.f64s(7)))
        return out
    stamp, _frame = c.header()
    child = c.text() if msgtype == "nav_msgs/msg/Odometry" else ""
    return [(stamp, child, *c.f64s(7))]  # Pose first in PoseWithCovariance (the covariance after it)


def _raw_messages(path: Path, topic: str):
    """`(cursor class, message type, [raw bytes])` of `topic`: ROS 1 through rosbags' rosbag1
    reader, sqlite3 storage through sqlite3, MCAP through rosbags' rosbag2 reader."""
    if path.suffix == ".bag":
        from rosbags.rosbag1 import Reader

        with Reader(path) as r:
            conns = [c for c in r.connections if c.topic == topic]
            return _Ros1, conns[0].msgtype, [raw for _, _, raw in r.messages(connections=conns)]
    if path.is_dir():
        [db] = path.glob("*.db3")
        with sqlite3.connect(db) as con:
            [(tid, msgtype)] = con.execute("SELECT id, type FROM topics WHERE name = ?", (topic,)).fetchall()
            rows = con.execute("SELECT data FROM messages WHERE topic_id = ? ORDER BY timestamp", (tid,)).fetchall()
        return _Cdr, msgtype, [bytes(d) for (d,) in rows]
    from rosbags.rosbag2 import Reader

    with Reader(path) as r:
        conns = [c for c in r.connections if c.topic == topic]
        return _Cdr, conns[0].msgtype, [raw for _, _, raw in r.messages(connections=conns)]


def vendor_poses(path: Path, topic: str, child: str | None = None):
    """`(t [s], p (n, 3) [m], q (n, 4) w, x, y, z)` of `topic` (of `child` on a TF topic)."""
    cursor, msgtype, raws = _raw_messages(path, topic)
    rows = [row for raw in raws for row in _decode(cursor(raw), msgtype)]
    rows = np.array([row[:1] + row[2:] for row in rows if child is None or row[1] == child], float)
    return rows[:, 0], rows[:, 1:4], rows[:, [7, 4, 5, 6]]


CASES = [  # (bag, topic, --child-frame, frames)
    (HERE / "tf_example.bag", "/tf", None, 517),
    (HERE / "tf_example", "/tf", None, 517),
    (NAV2, "/amcl_pose", None, 135),
    (NAV2, "/odom", None, 2639),
    (NAV2, "/tf", "base_link", 2639),
]


@pytest.mark.parametrize(("bag", "topic", "child", "frames"), CASES, ids=lambda v: getattr(v, "name", v))
def test_real_bag_converts_to_its_poses(tmp_path, bag, topic, child, frames):
    t, p, q = vendor_poses(bag, topic, child or ("base_footprint" if topic == "/tf" else None))
    assert len(t) == frames
    inputs = tmp_path / "inputs.csv"
    jsphere.write_inputs_csv(inputs, np.linspace(-1.0, t[-1] - t[0] + 1.0, 50), np.zeros((50, 3)), "wheel_speeds")
    out = tmp_path / "trial.csv"
    args = ["convert", str(bag), "--format", "rosbag", "--pose-topic", topic, "--inputs", str(inputs)]
    assert main([*args, *(["--child-frame", child] if child else []), "--out", str(out)]) == 0
    trial = jsphere.read_trial(out)
    assert trial.n_frames == frames
    np.testing.assert_allclose(trial.t, t - t[0], atol=1e-6)
    np.testing.assert_allclose(np.stack([trial.x, trial.y, trial.z], axis=1), p, atol=1e-6)
    q = q * np.sign(np.sum(q * trial.q, axis=1))[:, None]  # q and -q: the same orientation
    np.testing.assert_allclose(trial.q, q, atol=1e-6)


def test_real_tf_with_several_moving_frames_is_refused(tmp_path, capsys):
    """Nav2's `/tf` moves `base_link` (from `odom`), `odom` (from `map`) and the two wheels: the
    conversion asks which, listing them; `/tf_static` moves none; `--child-frame` on a pose topic
    is refused."""
    inputs = tmp_path / "inputs.csv"
    jsphere.write_inputs_csv(inputs, np.linspace(0.0, 100.0, 50), np.zeros((50, 3)), "wheel_speeds")
    base = ["convert", str(NAV2), "--format", "rosbag", "--inputs", str(inputs), "--out", str(tmp_path / "t.csv")]
    assert main([*base, "--pose-topic", "/tf"]) == 2
    err = capsys.readouterr().err
    assert "/tf holds 4 moving child frames: base_link (from odom), left_wheel (from base_link), odom (from map)" in err
    assert err.rstrip().endswith("name the robot's frame with --child-frame NAME.")
    assert main([*base, "--pose-topic", "/tf_static"]) == 2
    err = capsys.readouterr().err
    assert "no child frame of /tf_static moves (29 fixed ones: base_footprint (from base_link)" in err
    assert "and 17 more); give the topic where the robot's frame moves (such as /tf) with --pose-topic." in err
    assert main([*base, "--pose-topic", "/amcl_pose", "--child-frame", "base_link"]) == 2
    err = capsys.readouterr().err
    assert "--child-frame picks a frame of a tf2_msgs/msg/TFMessage topic" in err
    assert (
        "/amcl_pose holds geometry_msgs/msg/PoseWithCovarianceStamped, one pose per message: drop --child-frame" in err
    )
