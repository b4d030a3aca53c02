"""The options of a conversion (`ConvertOptions`): how `convert_raw` reads a raw export and how
`markers_to_trial` turns its markers into a `Trial`."""

from __future__ import annotations

import dataclasses
from collections.abc import Iterable

import numpy as np

from .._runtime.moved_keywords import moved_into, no_other_keywords


@dataclasses.dataclass(frozen=True)
class ConvertOptions:
    """How a raw export becomes a trial (`convert_raw`, `markers_to_trial`). Each field is the
    `jsphere convert` flag of the same name (`up_axis`: `--up-axis`); the defaults are the
    command's.

    **Reading the export** (`convert_raw`):
    - `units`: the export's length units: `"auto"` (the file's own, else detected from the
      marker spread), `"m"`, `"cm"` or `"mm"`.
    - `up_axis`: the export's up axis, `"y"` or `"z"`; None: the exporter's default (`"y"` for
      Motive, `"z"` otherwise).
    - `rigid_body`: a Motive asset or a QTM 6DOF body (a Vicon subject too, when `subject` is
      None).
    - `subject`: a Vicon Nexus subject.
    - `allow_truncated`: a file cut short (an export with fewer frames than its header
      declares, a last row cut off mid-row; an inputs table too) is an `InputError` naming
      both counts; True makes it a `CaptureWarning` and uses the complete frames.

    **ROS bags** (`read_rosbag_poses`, `read_rosbag_inputs`):
    - `pose_topic`: the topic of the poses (`format="rosbag"`); on a `tf2_msgs/TFMessage`
      topic such as `/tf`, the transforms of `child_frame`, by default the topic's one moving
      child frame.
    - `inputs_topic`: a `sensor_msgs/JointState` topic of the inputs (of the bag `inputs`, or
      of the bag converted when `inputs` is None); the markers may then come from any format.
    - `input_kind`: `"chi_dot"` (a JointState's velocity, the default) or `"K"` (its effort);
      for an inputs table holding both input families (a plan's CSV), which columns to read.
    - `joints`: the wheels' joint names in wheel order (a list or a comma-separated string);
      default: every joint of the messages, in their order.
    - `n_wheels`: the robot's number of wheels, checked against the joints.

    **Markers to poses** (`jsphere.capture.pose`; `docs/capture.md` explains every convention):
    - `body_markers`: the markers' coordinates in the *body frame* [m], a `(K, 3)` array in the
      order of the export's markers or a dict `{name: (x, y, z)}` (`read_body_markers`),
      matched by full name or by the part after `Subject:` (markers of the export not in the
      dict are left out of the fit). Default: taken from the first frame in which every marker
      is seen, centred on their centroid, with the body frame's axes equal to the fixed axes
      at that frame. An exporter's own rigid-body pose, where the data carry one, is used
      instead of the markers.
    - `alignment`: `(3, 3)` platform -> body-frame rotation (default identity), so the
      platform's rotation is `R_platform = R_body @ alignment`. With body markers given in the
      platform frame, leave it at the identity.
    - `body_offset`: `(3,)` the shell centre in the platform frame relative to the body-frame
      origin [m]: `r_centre = p_body + R_platform @ body_offset`.
    - `max_rms`: frames whose marker fit has an RMS residual above this [m] are gaps, with a
      `CaptureWarning` saying how many.
    - `keep_suspect`: keep the frames whose marker fit residual stands out of the take's own
      noise (`suspect_frames`: a swapped or ghost marker); by default they are gaps, with a
      `CaptureWarning` saying how many and the threshold.

    **The trial:**
    - `time_offset`: added to the capture's times to match the inputs' clock [s]
      (`t_trial = t_capture + time_offset`).
    - `name`: the trial's name; default: the export's file stem.
    - `max_gap_fraction`: the largest fraction of gap frames accepted.
    - `shell_radius`: the robot's `R0` [m]; given, the converted centre's height is checked
      against it (`check_centre_height`).
    """

    units: str = "auto"
    up_axis: str | None = None
    rigid_body: str | None = None
    subject: str | None = None
    allow_truncated: bool = False
    pose_topic: str | None = None
    child_frame: str | None = None
    inputs_topic: str | None = None
    input_kind: str | None = None
    joints: Iterable[str] | str | None = None
    n_wheels: int | None = None
    body_markers: np.ndarray | dict[str, np.ndarray] | None = None
    alignment: np.ndarray | None = None
    body_offset: tuple[float, float, float] = (0.0, 0.0, 0.0)
    max_rms: float = 0.005
    keep_suspect: bool = False
    time_offset: float = 0.0
    name: str | None = None
    max_gap_fraction: float = 0.5
    shell_radius: float | None = None


def with_keywords(options: ConvertOptions, keywords: dict, func: str, known: Iterable[str]) -> ConvertOptions:
    """`options` with the fields `keywords` given to `func` as keywords (those it accepts:
    `known`), each with a `DeprecationWarning` naming its spelling in `ConvertOptions`
    (`moved_into`); another keyword is a `TypeError`, as Python raises it."""
    no_other_keywords(func, {k: v for k, v in keywords.items() if k not in known})
    return moved_into(func, keywords, options, ConvertOptions, "options")
