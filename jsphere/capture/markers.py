"""Marker data: what the raw-export readers return, their up-axis conventions, and the length units
of marker coordinates (declared by the file, or detected from the marker spread)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: Motive's default frame is Y-up; jsphere's fixed frame is Z-up. `UP_TO_Z["y"]` maps Motive
#: components to jsphere's: (X, Y, Z)_jsphere = (X, -Z, Y)_Motive (a +90 deg turn about X).
UP_TO_Z = {"z": np.eye(3), "y": np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])}


@dataclass(frozen=True)
class MarkerData:
    """Marker trajectories of one raw export, in jsphere's fixed frame (Z up) [m].

    - `t`: `(M,)` capture times [s]; `markers`: `(M, K, 3)` positions, NaN where a marker is
      missing; `names`: the K marker names; `source`: the file; `lines`: `(M,)` 1-based line of
      each frame in the file (None for binary files);
    - `rb_q`, `rb_p`: the exporter's own rigid-body pose, if the file has one (`(M, 4)` scalar-
      first quaternion body -> fixed, `(M, 3)` [m]), else None;
    - `marker_error`: `(M,)` the exporter's own marker error of each frame [m] (Motive's `Mean
      Marker Error` / `Error Per Marker`: the mean distance of the rigid body's markers from
      where its solved pose puts them), NaN where it reports none; None if the file has none.
      It floors the threshold of `suspect_frames`.
    """

    t: np.ndarray
    markers: np.ndarray
    names: tuple[str, ...]
    source: str
    lines: np.ndarray | None = None
    rb_q: np.ndarray | None = None
    rb_p: np.ndarray | None = None
    marker_error: np.ndarray | None = None


# --------------------------------------------------------------------------- units


def detect_marker_units(markers: np.ndarray) -> str | None:
    """`"m"`, `"mm"` or None from the spread of the markers about their centroid (a marker set on
    a ball of radius 0.1-0.3 m spreads 5 mm to 1 m): median over frames of the largest distance."""
    full = np.all(np.isfinite(markers), axis=(1, 2))
    if not np.any(full) or markers.shape[1] < 2:
        return None
    f = markers[full]
    r = np.median(np.max(np.linalg.norm(f - f.mean(1, keepdims=True), axis=2), axis=1))
    if 0.005 <= r <= 1.0:
        return "m"
    if 5.0 <= r <= 1000.0:
        return "mm"
    return None


#: metres per unit of the length units a raw export may declare
UNIT_SCALE = {"m": 1.0, "cm": 1e-2, "mm": 1e-3}
_UNIT_WORDS = {"m": "metres", "cm": "centimetres", "mm": "millimetres"}


def _scale(declared: str, file_units: str | None, detected: str | None, source: str) -> float:
    """Metres per unit of the marker coordinates: the file's own units (`file_units`), else the
    declared ones, else the detected ones. A declaration that contradicts the file, or a spread
    that contradicts the units, is an error. Centimetres come from the file or the declaration
    only: the spread of a marker set in centimetres (0.5-100) looks like metres or millimetres."""
    if declared not in ("auto", *UNIT_SCALE):
        raise ValueError(f"{source}: the units (--units) must be auto, m, cm or mm; got {declared!r}.")
    if file_units is not None and declared != "auto" and declared != file_units:
        raise ValueError(
            f"{source}: --units {declared} was given but the file says its lengths are in {file_units}; "
            "drop --units (the file's units are used) or re-export the file."
        )
    units = file_units if file_units is not None else declared
    if units == "cm":
        return UNIT_SCALE["cm"]
    if detected is not None and units != "auto" and detected != units:
        raise ValueError(
            f"{source}: the lengths are declared in {units!r} but the marker spread looks like "
            f"{_UNIT_WORDS[detected]}; pass --units {detected} if the file is wrong, "
            "or check the export scale."
        )
    if units == "auto":
        if detected is None:
            raise ValueError(f"{source}: cannot tell whether lengths are in m or mm; pass --units m or --units mm.")
        units = detected
    return UNIT_SCALE[units]


def _scale_rb(units: str, file_units: str | None, source: str) -> float:
    if units == "auto" and file_units is None:
        raise ValueError(f"{source}: cannot tell whether lengths are in m or mm; pass --units m or --units mm.")
    return _scale(units, file_units, None, source)
