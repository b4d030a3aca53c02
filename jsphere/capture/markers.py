"""Marker data: what the raw-export readers return, their up-axis conventions, and the steps
every reader ends with (`check_up_axis`, `fixed_markers`, `fixed_pose`): the vendor's header and
columns parsed by its own reader, the lengths resolved (`jsphere.capture.units`) and turned into
jsphere's fixed frame here."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .._runtime.errors import InputError
from ..model.rotations import quat_from_rotmat_np
from .text import _read_lines
from .units import EXPORT_UNITS, detect_marker_units, resolve_units
from .validation import sign_continuous

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


def check_up_axis(up_axis: str, source: str, quote: str = "") -> None:
    """`ValueError` unless `up_axis` is one of `UP_TO_Z` (`quote` around the choices in the message)."""
    if up_axis not in UP_TO_Z:
        raise ValueError(
            f"{source}: the up axis (--up-axis) must be {quote}y{quote} or {quote}z{quote}; got {up_axis!r}."
        )


def choose_body(name: str | None, bodies: list[str], source: str, what: str = "rigid body") -> str | None:
    """The body to read: `name`, else the only one of `bodies` (None where there is none). A
    `name` not among `bodies`, or several bodies and no `name`, is an `InputError` listing them."""
    if name is not None and bodies and name not in bodies:
        raise InputError(f"{source}: no {what} named {name!r}; the file has {bodies}.")
    if name is None and len(bodies) > 1:
        plural = what.removesuffix("body") + "bodies"
        raise InputError(f"{source}: the file has several {plural} {bodies}; choose one with --rigid-body NAME.")
    return name if name is not None else (bodies[0] if bodies else None)


def open_export(path, up_axis: str, quote: str = "", delimiter: str = ",") -> tuple[str, list[list[str]]]:
    """`(source, rows)` of a text export (`_read_lines`), its `up_axis` checked (`check_up_axis`)."""
    path, rows = _read_lines(path, delimiter=delimiter)
    check_up_axis(up_axis, str(path), quote)
    return str(path), rows


def fixed_markers(
    raw: np.ndarray, source: str, units: str, file_units: str | None, up_axis: str, fallback: str | None = None
) -> tuple[np.ndarray, float]:
    """The last step of every raw-export reader: markers `raw (M, K, 3)` in the file's units and
    axes turned into metres in jsphere's Z-up fixed frame (`UP_TO_Z`), with the units
    resolved (`resolve_units`) from the caller's `units`, the file's own `file_units` and those
    detected from the marker spread (`fallback` where the spread cannot tell and `units` is
    `"auto"`). Returns `(markers, scale)`, `scale` [m per unit] for the export's other lengths."""
    detected = detect_marker_units(raw) or (fallback if units == "auto" else None)
    scale = resolve_units(units, file_units, detected, source, EXPORT_UNITS)
    return np.einsum("ij,mkj->mki", UP_TO_Z[up_axis], raw) * scale, scale


def fixed_pose(R: np.ndarray, p: np.ndarray, gap: np.ndarray, up_axis: str, scale: float):
    """An exporter's rigid-body pose in jsphere's fixed frame: `(q (M, 4), p (M, 3))` [m] from the
    rotations `R (M, 3, 3)` (body -> the export's frame) and positions `p (M, 3)` of an export
    with the up axis `up_axis`, times `scale` [m per unit]; NaN at the frames `gap` (`(M,)`
    bool), quaternions scalar first and sign-continuous."""
    C = UP_TO_Z[up_axis]
    q = quat_from_rotmat_np(C @ np.where(gap[:, None, None], np.eye(3), R))
    p = p @ C.T * scale
    q[gap], p[gap] = np.nan, np.nan
    return sign_continuous(q), p
