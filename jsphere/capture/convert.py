"""One call from a raw export and an inputs table (or a ROS bag) to a `Trial` (`convert_raw`)."""

from __future__ import annotations

import dataclasses
from pathlib import Path

from .._runtime.errors import InputError
from .c3d import read_c3d
from .centre import check_centre_height
from .inputs import read_inputs_csv
from .motive import read_motive_csv
from .options import ConvertOptions, with_keywords
from .pose import markers_to_trial
from .qualisys import read_qualisys_tsv
from .rosbag import read_rosbag_inputs, read_rosbag_poses
from .trial import Trial
from .vicon import read_vicon_csv

RAW_FORMATS = ("motive", "vicon", "c3d", "qualisys", "rosbag")
#: the fields of `ConvertOptions` that `convert_raw` accepts as keywords (deprecated)
_KEYWORDS = tuple(f.name for f in dataclasses.fields(ConvertOptions) if f.name != "max_gap_fraction")


def convert_raw(path, inputs, *, format: str, options: ConvertOptions = ConvertOptions(), **kwargs) -> Trial:
    """Read a raw export (`format`: `"motive"`, `"vicon"`, `"c3d"`, `"qualisys"` or `"rosbag"`)
    and make a `Trial` with the inputs `inputs` (`markers_to_trial`): an inputs table, a tuple
    `(t, values, kind)`, a ROS bag read with `options.inputs_topic`, or None for the inputs of
    the bag `path` itself. `options` (`ConvertOptions`) says how; its fields given as keywords
    still work, with a `DeprecationWarning`.

    A ROS bag's poses are those on `options.pose_topic` (`read_rosbag_poses`). Times from two
    bags share the bag clock and start at the earlier first message; a bag beside another file
    starts at its own first message (align the clocks with `time_offset`).

    With `shell_radius` (the robot's `R0` [m]), the converted centre's height is checked
    (`check_centre_height`): a `CaptureWarning` naming the options of `format` that put the
    centre where it belongs."""
    o = with_keywords(options, kwargs, "convert_raw", _KEYWORDS)
    if format not in RAW_FORMATS:
        raise ValueError(f"convert_raw: format must be one of {RAW_FORMATS}; got {format!r}.")
    _check_bag_options(format, inputs, o)
    _check_body_options(format, o.rigid_body, o.subject)
    if format == "rosbag" and o.body_markers is not None:
        raise InputError(
            "--body-markers gives the markers of a marker export; a ROS bag's poses are those of the pose topic's "
            "frame: drop --body-markers (--body-offset X Y Z puts the shell centre in that frame)."
        )
    if o.child_frame is not None and format != "rosbag":
        raise InputError(f"--child-frame picks a frame of a ROS bag's /tf topic; --format {format} has none: drop it.")
    data = _read_poses(path, format, o)
    if o.inputs_topic is not None:
        t_in, u_in, kind, _ = read_rosbag_inputs(
            path if inputs is None else inputs,
            o.inputs_topic,
            input_kind=o.input_kind or "chi_dot",
            joints=o.joints,
            n_wheels=o.n_wheels,
        )
        t0 = min(float(data.t[0]), float(t_in[0])) if format == "rosbag" else float(t_in[0])
        inputs = (t_in - t0, u_in, kind)
    else:
        t0 = float(data.t[0])
        if not isinstance(inputs, tuple):  # an inputs table, or a plan's with both families (`input_kind`)
            inputs = read_inputs_csv(inputs, kind=o.input_kind, allow_truncated=o.allow_truncated)[:3]
    if format == "rosbag":
        data = dataclasses.replace(data, t=data.t - t0)
    trial = markers_to_trial(data, inputs, o, format=format)
    if o.shell_radius is not None:
        fix, example, floor = _centre_fix(format, data.rb_q is not None, o.body_markers is not None, o.body_offset)
        check_centre_height(trial, o.shell_radius, source=data.source, fix=fix, example=example, floor=floor)
    return trial


def _read_poses(path, format: str, o: ConvertOptions):
    """The `MarkerData` of the export `path` in `format`, read with the options `o`."""
    kw = {"units": o.units, "allow_truncated": o.allow_truncated}
    if format == "motive":
        return read_motive_csv(path, rigid_body=o.rigid_body, up_axis=o.up_axis or "y", **kw)
    if format == "vicon":
        return read_vicon_csv(path, subject=o.subject or o.rigid_body, up_axis=o.up_axis or "z", **kw)
    if format == "qualisys":
        return read_qualisys_tsv(path, rigid_body=o.rigid_body, up_axis=o.up_axis or "z", **kw)
    if format == "rosbag":
        return read_rosbag_poses(path, o.pose_topic, child_frame=o.child_frame)
    return read_c3d(path, up_axis=o.up_axis or "z", **kw)


def _centre_fix(format: str, exporter_pose: bool, body_given: bool, body_offset):
    """`(fix, example, floor)` for `check_centre_height`: what puts the converted point at the
    shell centre in the options of `format` (ROS bag: the pose topic's frame; an exporter's
    rigid-body pose: its pivot point or `--body-offset`; markers: `--body-markers` or
    `--body-offset`), the `--body-offset` that raises the centre by `dz` where the body frame is
    upright (markers: estimated at the first full frame, or given in the platform frame), and
    where height 0 is."""
    offset = "--body-offset X Y Z"
    if format == "rosbag":
        fix = (
            "the pose topic's frame is not at the shell centre: publish the shell centre's pose (a motion-capture "
            f"rigid body with its pivot point there), or give {offset}, the shell centre in the poses' frame [m]"
        )
        return fix, None, "the floor at height 0 of the poses' world frame: an origin off the floor shifts it too"
    floor = "the floor at height 0, where the capture's ground plane is set"
    if exporter_pose:
        tool = {"motive": "Motive", "qualisys": "QTM"}.get(format, "the capture software")
        fix = (
            f"the rigid body's pivot point is not the shell centre: move it there in {tool} before exporting, or give "
            f"{offset}, the shell centre in the rigid body's frame [m]"
        )
        return fix, None, floor
    if body_given:
        fix = (
            "the body markers are not measured from the shell centre: give them from it (--body-markers FILE, "
            f"platform frame), or give {offset}, the shell centre in their frame [m]"
        )
    else:
        fix = (
            "the markers' centroid was taken for the shell centre: give --body-markers FILE (the markers measured "
            f"from the shell centre, platform frame) or {offset}, the shell centre from the markers' centroid in the "
            "platform frame [m]"
        )
    x, y, z = (float(v) for v in body_offset)

    def example(dz: float) -> str:
        side = "below" if dz < 0 else "above"
        return f"if the shell centre lies straight {side} it: --body-offset {x:.4g} {y:.4g} {z + dz:.4f}"

    return fix, example, floor


#: the formats whose files name bodies: `rigid_body` (a Vicon subject too) and `subject`
RIGID_BODY_FORMATS = ("motive", "qualisys", "vicon")
SUBJECT_FORMATS = ("vicon",)


def _check_body_options(format, rigid_body, subject) -> None:
    """`InputError` for a body named in a format whose files name none (a C3D file holds points,
    a ROS bag a pose topic)."""
    if rigid_body is not None and format not in RIGID_BODY_FORMATS:
        raise InputError(
            f"--rigid-body selects a body of a Motive, Qualisys or Vicon export; --format {format} has "
            "none: drop it (C3D: the markers are the points; ROS bag: --pose-topic)."
        )
    if subject is not None and format not in SUBJECT_FORMATS:
        raise InputError(
            f"--subject selects a Vicon Nexus subject; --format {format} has none: drop it"
            + (" (use --rigid-body)." if format in RIGID_BODY_FORMATS else ".")
        )


def _check_bag_options(format, inputs, o: ConvertOptions) -> None:
    """`InputError` for options that do not fit the format: a ROS bag without its topics, topics
    without a bag, lengths or axes declared for a bag (REP 103: metres, Z up)."""
    units, up_axis, pose_topic, inputs_topic = o.units, o.up_axis, o.pose_topic, o.inputs_topic
    if format == "rosbag":
        if pose_topic is None:
            raise InputError("--format rosbag needs --pose-topic TOPIC: the topic of the poses.")
        if units not in ("auto", "m") or up_axis not in (None, "z"):
            raise InputError("a ROS bag's poses are in metres with Z up (REP 103); drop --units and --up-axis.")
        if inputs is None and inputs_topic is None:
            raise InputError(
                "the inputs: --inputs-topic TOPIC (a sensor_msgs/JointState topic of the bag) or --inputs TABLE."
            )
    elif pose_topic is not None:
        raise InputError(f"--pose-topic is for --format rosbag; the poses of --format {format} come from its file.")
    elif inputs is None:
        raise InputError("--inputs is needed: the inputs table, or a ROS bag with --inputs-topic TOPIC.")
    if o.joints is not None and inputs_topic is None:
        raise InputError("--joints names the wheels of a JointState topic; give --inputs-topic TOPIC too.")
    if inputs is not None and inputs_topic is None and not isinstance(inputs, tuple):
        where = Path(inputs)
        if where.suffix in (".bag", ".db3", ".mcap") or (where / "metadata.yaml").exists():
            raise InputError(f"{where}: a ROS bag; name its JointState topic with --inputs-topic TOPIC.")
