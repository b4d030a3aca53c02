"""Marker data: what the raw-export readers return, and their up-axis conventions."""

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


def to_fixed_frame(raw: np.ndarray, up_axis: str, scale: float) -> np.ndarray:
    """Marker positions `raw (M, K, 3)` of an export with the up axis `up_axis` in jsphere's
    Z-up fixed frame (`UP_TO_Z`), times `scale` [m per unit]."""
    return np.einsum("ij,mkj->mki", UP_TO_Z[up_axis], raw) * scale
