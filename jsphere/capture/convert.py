"""One call from a raw export and an inputs table to a `Trial` (`convert_raw`)."""

from __future__ import annotations

import numpy as np

from .c3d import read_c3d
from .motive import read_motive_csv
from .pose import markers_to_trial
from .trial import Trial
from .vicon import read_vicon_csv

RAW_FORMATS = ("motive", "vicon", "c3d")


def convert_raw(
    path,
    inputs,
    *,
    format: str,
    units: str = "auto",
    up_axis: str | None = None,
    body_markers: np.ndarray | None = None,
    alignment: np.ndarray | None = None,
    body_offset=(0.0, 0.0, 0.0),
    rigid_body: str | None = None,
    max_rms: float = 0.005,
    time_offset: float = 0.0,
    name: str | None = None,
    allow_truncated: bool = False,
) -> Trial:
    """Read a raw export (`format`: `"motive"`, `"vicon"` or `"c3d"`) and make a `Trial` with the
    inputs table `inputs` (`markers_to_trial`). `up_axis` defaults to the exporter's default
    (`"y"` for Motive, `"z"` otherwise); `rigid_body` selects a Motive asset or a Vicon subject.

    A file cut short (an export with fewer frames than its header declares, a last row cut off
    mid-row) is an `InputError` naming both counts; `allow_truncated=True` makes it a
    `CaptureWarning` and uses the complete frames. Implausible speeds, turn rates or time units
    in the result are `CaptureWarning`s naming the likely cause."""
    if format not in RAW_FORMATS:
        raise ValueError(f"convert_raw: format must be one of {RAW_FORMATS}; got {format!r}.")
    kw = {"units": units, "allow_truncated": allow_truncated}
    if format == "motive":
        data = read_motive_csv(path, rigid_body=rigid_body, up_axis=up_axis or "y", **kw)
    elif format == "vicon":
        data = read_vicon_csv(path, subject=rigid_body, up_axis=up_axis or "z", **kw)
    else:
        data = read_c3d(path, up_axis=up_axis or "z", **kw)
    return markers_to_trial(
        data,
        inputs,
        body_markers=body_markers,
        alignment=alignment,
        body_offset=body_offset,
        max_rms=max_rms,
        time_offset=time_offset,
        name=name,
        allow_truncated=allow_truncated,
    )
