"""Raw motion-capture exports -> trials: marker readers, rigid-body poses, synthetic markers.

Pipeline: a reader (`read_motive_csv`, `read_vicon_csv`, `read_c3d`) parses a raw export into
`MarkerData` (times, marker trajectories in metres in jsphere's Z-up fixed frame, gaps as NaN),
`rigid_body_pose` turns the markers of each frame into the platform pose (Kabsch/Umeyama
without scale, with the reflection fix), and `markers_to_trial` adds the inputs (a separate
table, `read_inputs_csv`) to make a `Trial`. `docs/capture.md` explains every convention:

- `body_markers` `(K, 3)`: the markers' coordinates in the *body frame* [m]. Default: taken
  from the first frame in which every marker is seen, centred on their centroid, with the body
  frame's axes equal to the fixed axes at that frame.
- `alignment` `(3, 3)`: platform -> body-frame rotation (default identity), so the platform's
  rotation is `R_platform = R_body @ alignment`. With body markers given in the platform frame,
  leave it at the identity.
- `body_offset` `(3,)`: the shell centre in the platform frame relative to the body-frame
  origin [m] (default 0): `r_centre = p_body + R_platform @ body_offset`.
"""

from __future__ import annotations

import math
import struct
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .trial import (
    INPUT_PREFIX,
    KINDS,
    CaptureWarning,
    Trial,
    _check_increasing,
    _checked,
    _input_columns,
    _parse_cell,
    check_unique_columns,
    csv_rows,
    quat_mul_np,
    read_text,
    separator_hint,
    sign_continuous,
    warn_implausible,
)
from .._runtime.errors import InputError
from .._runtime.files import atomic_write_text

#: Motive's default frame is Y-up; jsphere's fixed frame is Z-up. `UP_TO_Z["y"]` maps Motive
#: components to jsphere's: (X, Y, Z)_jsphere = (X, -Z, Y)_Motive (a +90 deg turn about X).
UP_TO_Z = {"z": np.eye(3), "y": np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])}
#: smallest second singular value of the centred present markers [m] for a pose (not collinear)
MIN_SPREAD = 1e-3


@dataclass(frozen=True)
class MarkerData:
    """Marker trajectories of one raw export, in jsphere's fixed frame (Z up) [m].

    - `t`: `(M,)` capture times [s]; `markers`: `(M, K, 3)` positions, NaN where a marker is
      missing; `names`: the K marker names; `source`: the file; `lines`: `(M,)` 1-based line of
      each frame in the file (None for binary files);
    - `rb_q`, `rb_p`: the exporter's own rigid-body pose, if the file has one (`(M, 4)` scalar-
      first quaternion body -> fixed, `(M, 3)` [m]), else None.
    """

    t: np.ndarray
    markers: np.ndarray
    names: tuple[str, ...]
    source: str
    lines: np.ndarray | None = None
    rb_q: np.ndarray | None = None
    rb_p: np.ndarray | None = None


# --------------------------------------------------------------------------- poses from markers


def quat_from_rotmat_np(R: np.ndarray) -> np.ndarray:
    """Unit quaternions `(..., 4)` (w >= 0) of rotation matrices `(..., 3, 3)` (numpy)."""
    R = np.asarray(R, float)
    tr = R[..., 0, 0] + R[..., 1, 1] + R[..., 2, 2]
    c = np.stack(
        [
            np.stack([1 + tr, R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]], -1),
            np.stack([R[..., 2, 1] - R[..., 1, 2], 1 + 2 * R[..., 0, 0] - tr, R[..., 0, 1] + R[..., 1, 0], R[..., 0, 2] + R[..., 2, 0]], -1),
            np.stack([R[..., 0, 2] - R[..., 2, 0], R[..., 0, 1] + R[..., 1, 0], 1 + 2 * R[..., 1, 1] - tr, R[..., 1, 2] + R[..., 2, 1]], -1),
            np.stack([R[..., 1, 0] - R[..., 0, 1], R[..., 0, 2] + R[..., 2, 0], R[..., 1, 2] + R[..., 2, 1], 1 + 2 * R[..., 2, 2] - tr], -1),
        ],
        -2,
    )  # fmt: skip
    k = np.argmax(np.stack([tr, R[..., 0, 0], R[..., 1, 1], R[..., 2, 2]], -1), axis=-1)
    q = np.take_along_axis(c, k[..., None, None], axis=-2)[..., 0, :]
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    return np.where(q[..., :1] < 0, -q, q)


def rotmat_np(q: np.ndarray) -> np.ndarray:
    """Rotation matrices `(..., 3, 3)` of quaternions `(..., 4)` (w, x, y, z) (numpy)."""
    q = np.asarray(q, float)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    w, x, y, z = np.moveaxis(q, -1, 0)
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
            np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
            np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
        ],
        -2,
    )


def rigid_body_pose(
    markers: np.ndarray, body_markers: np.ndarray, *, max_rms: float = np.inf
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The rigid motion that best maps `body_markers` onto each frame's markers.

    For each frame, over the markers present (finite), finds the rotation `R` and translation
    `p` minimising `sum_k |R b_k + p - m_k|^2` (Kabsch/Umeyama without scale: SVD of the
    cross-covariance, with the determinant fixed to +1 so that a reflection is never returned).

    **Arguments:**
    - `markers`: `(M, K, 3)` marker positions [m], NaN where missing.
    - `body_markers`: `(K, 3)` marker coordinates in the body frame [m].
    - `max_rms`: frames whose RMS fit residual exceeds this [m] (e.g. a swapped marker) are gaps.

    **Returns:** `(q, p, rms)`: `(M, 4)` quaternions (w, x, y, z) body -> fixed, sign-continuous;
    `(M, 3)` positions of the body-frame origin; `(M,)` RMS residuals [m]. Frames with fewer
    than 3 markers, or markers (nearly) collinear (second singular value of the centred body
    markers below `MIN_SPREAD`), or a residual above `max_rms`, are NaN (gaps).
    """
    m = np.asarray(markers, float)
    b = np.asarray(body_markers, float)
    if m.ndim != 3 or m.shape[2] != 3 or b.shape != (m.shape[1], 3):
        raise ValueError(f"rigid_body_pose: markers must be (M, K, 3) and body_markers (K, 3); got {m.shape} and {b.shape}.")
    if not np.all(np.isfinite(b)):
        raise ValueError("rigid_body_pose: body_markers must be finite.")
    w = np.all(np.isfinite(m), axis=2).astype(float)  # (M, K)
    n = w.sum(1)
    mz = np.where(w[..., None] > 0, m, 0.0)
    nn = np.maximum(n, 1.0)[:, None]
    mc = (w[..., None] * mz).sum(1) / nn  # (M, 3) centroid of present markers
    bc = (w[..., None] * b[None]).sum(1) / nn  # (M, 3) centroid of their body coordinates
    db = w[..., None] * (b[None] - bc[:, None])  # (M, K, 3), zero where missing
    dm = w[..., None] * (mz - mc[:, None])
    H = np.einsum("mki,mkj->mij", db, dm)  # sum_k b_k m_k^T
    U, _, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(np.swapaxes(Vt, 1, 2) @ np.swapaxes(U, 1, 2)))
    d = np.where(d == 0, 1.0, d)
    D = np.zeros((m.shape[0], 3, 3))
    D[:, 0, 0] = D[:, 1, 1] = 1.0
    D[:, 2, 2] = d
    R = np.swapaxes(Vt, 1, 2) @ D @ np.swapaxes(U, 1, 2)
    p = mc - np.einsum("mij,mj->mi", R, bc)
    fit = np.einsum("mij,kj->mki", R, b) + p[:, None]
    res2 = np.where(w > 0, np.sum((fit - mz) ** 2, axis=2), 0.0)
    rms = np.sqrt(res2.sum(1) / nn[:, 0])
    spread = np.linalg.svd(db, compute_uv=False)[:, 1]
    ok = (n >= 3) & (spread >= MIN_SPREAD) & (rms <= max_rms)
    q = quat_from_rotmat_np(R)
    q[~ok], p[~ok], rms[~ok] = np.nan, np.nan, np.nan
    return sign_continuous(q), p, rms


def read_body_markers(path, *, units: str = "auto") -> dict[str, np.ndarray]:
    """Read marker coordinates in the platform frame: a CSV with columns `name, x, y, z` (`#`
    lines are comments; a comment `# units: mm` declares millimetres). Returns `{name: (3,)
    array}` in metres for `markers_to_trial`.

    `units`: `"auto"` (the `# units:` line, else detected), `"m"` or `"mm"`. Detected from the
    largest distance of a marker from their centroid: 5 mm-1 m on a robot of this kind, so
    5-1000 means millimetres (converted, with a `CaptureWarning` saying so); anything else, or
    a declaration that contradicts the numbers, is an `InputError`.
    """
    if units not in ("auto", "m", "mm"):
        raise InputError(f"read_body_markers: units must be 'auto', 'm' or 'mm'; got {units!r}.")
    path, rows = _read_lines(path)
    source = str(path)
    file_units = None
    for r in rows:
        if r and r[0].lstrip().startswith("#"):
            key, _, value = ",".join(r).lstrip("# ").partition(":")
            if key.strip().lower() == "units":
                file_units = value.strip().strip(",").strip()
                if file_units not in ("m", "mm"):
                    raise InputError(f"{source}: the '# units:' line says {file_units!r}; it must be 'm' or 'mm'.")
    if file_units is not None and units != "auto" and units != file_units:
        raise InputError(f"{source}: units={units!r} was declared but the file's '# units:' line says {file_units!r}.")
    rows = [(i + 1, r) for i, r in enumerate(rows) if r and any(c.strip() for c in r) and not r[0].lstrip().startswith("#")]
    if not rows or [c.strip() for c in rows[0][1]] != ["name", "x", "y", "z"]:
        raise ValueError(
            f"{source}: the first line must be the header 'name,x,y,z' (marker coordinates in the platform frame, m)"
            f"{separator_hint(rows[0][1]) if rows else ''}."
        )
    out = {}
    for line, r in rows[1:]:
        if len(r) != 4:
            raise ValueError(f"{source}, line {line}: expected 4 cells (name, x, y, z); got {len(r)}.")
        xyz = np.array([_parse_cell(c, source, line, k) for c, k in zip(r[1:], "xyz")])
        if not np.all(np.isfinite(xyz)):
            raise ValueError(f"{source}, line {line}: marker {r[0].strip()!r} has a blank coordinate.")
        if r[0].strip() in out:
            raise InputError(f"{source}, line {line}: marker {r[0].strip()!r} is listed twice; keep one row per marker.")
        out[r[0].strip()] = xyz
    if len(out) < 3:
        raise ValueError(f"{source}: {len(out)} marker(s); a pose needs at least 3.")
    b = np.stack(list(out.values()))
    spread = float(np.max(np.linalg.norm(b - b.mean(0), axis=1)))
    detected = detect_marker_units(b[None])
    declared = file_units or (units if units != "auto" else None)
    if declared is not None:
        if detected is not None and detected != declared:
            raise InputError(
                f"{source}: the coordinates are declared in {declared!r} but the markers lie up to {spread:.4g} from their "
                f"centroid, which looks like {'millimetres' if detected == 'mm' else 'metres'}; fix the numbers or the units."
            )
        scale = 1.0 if declared == "m" else 1e-3
    elif detected is None:
        raise InputError(
            f"{source}: the markers lie up to {spread:.4g} from their centroid: neither metres (5 mm-1 m on a robot of this "
            "kind) nor millimetres (5-1000); check the coordinates (platform frame, metres)."
        )
    else:
        scale = 1.0 if detected == "m" else 1e-3
        if detected == "mm":
            warnings.warn(
                f"{source}: the marker coordinates look like millimetres (the markers lie up to {spread:.4g} from their "
                "centroid; metres would make the robot metres wide): read as mm. Add a line '# units: mm' to the file "
                "to say so, or give metres.",
                CaptureWarning, stacklevel=2,
            )  # fmt: skip
    return {k: v * scale for k, v in out.items()}


def _match_body_markers(body: dict, names: tuple[str, ...], source: str) -> np.ndarray:
    """Rows of `body` in the order of `names` (full name, or the part after `Subject:`); NaN rows
    for markers that `body` does not list (they are then left out of the fit)."""
    out = np.full((len(names), 3), np.nan)
    for k, n in enumerate(names):
        for key in (n, n.split(":", 1)[-1]):
            if key in body:
                out[k] = np.asarray(body[key], float)
                break
    if np.sum(np.all(np.isfinite(out), axis=1)) < 3:
        raise ValueError(
            f"{source}: fewer than 3 of the export's markers {list(names)} are in body_markers {sorted(body)}; "
            "name them as in the export (with or without the 'Subject:' prefix)."
        )
    return out


def estimate_body_markers(markers: np.ndarray, source: str = "markers") -> tuple[np.ndarray, int]:
    """Body-frame marker coordinates from the first frame where every marker is seen: the
    positions minus their centroid, in the fixed axes of that frame. Returns `(body, frame)`."""
    full = np.nonzero(np.all(np.isfinite(markers), axis=(1, 2)))[0]
    if full.size == 0:
        raise ValueError(
            f"{source}: no frame shows all {markers.shape[1]} markers, so the body cannot be estimated; "
            "pass body_markers (their coordinates in the platform frame) or drop a marker that is never seen."
        )
    k = int(full[0])
    return markers[k] - markers[k].mean(0), k


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


def _scale(declared: str, file_units: str | None, detected: str | None, source: str) -> float:
    if declared not in ("auto", "m", "mm"):
        raise ValueError(f"{source}: units must be 'auto', 'm' or 'mm'; got {declared!r}.")
    if file_units is not None and declared != "auto" and declared != file_units:
        raise ValueError(
            f"{source}: units={declared!r} was declared but the file says its lengths are in {file_units!r}; "
            "drop the argument (the file's units are used) or re-export the file."
        )
    units = file_units if file_units is not None else declared
    if detected is not None and units != "auto" and detected != units:
        raise ValueError(
            f"{source}: the lengths are declared in {units!r} but the marker spread looks like "
            f"{'millimetres' if detected == 'mm' else 'metres'}; pass units={detected!r} if the file is wrong, "
            "or check the export scale."
        )
    if units == "auto":
        if detected is None:
            raise ValueError(f"{source}: cannot tell whether lengths are in m or mm; pass units='m' or units='mm'.")
        units = detected
    return 1.0 if units == "m" else 1e-3


# --------------------------------------------------------------------------- readers


def _read_lines(path) -> tuple[Path, list[list[str]]]:
    """The CSV rows of a text file (`read_text`: UTF-8 with or without a BOM, or UTF-16)."""
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"capture file {path} does not exist.")
    return path, csv_rows(read_text(path), str(path))


def _data_end(rows, start: int, end: int | None = None) -> int:
    """The end of the data rows `rows[start:end]` without the trailing empty rows."""
    end = len(rows) if end is None else end
    while end > start and not any(c.strip() for c in rows[end - 1]):
        end -= 1
    return end


def _cut_short(
    rows, start: int, end: int, ncols: int, source: str, allow: bool, *, declared: int | None = None, field: str = "",
    noun: str = "frames",
) -> int:  # fmt: skip
    """Check the data rows `rows[start:end]` of an export for a file that was cut short: a last
    row with fewer cells than the header row (`ncols`: the copy or the export broke off
    mid-row), or fewer rows than the header declares (`declared`, from its `field`). Raises an
    `InputError` naming the file and both counts; with `allow`, issues a `CaptureWarning`
    instead. Returns the end of the complete rows (the cut row is dropped)."""
    cut_row = end > start and len(rows[end - 1]) < ncols
    n = end - start - int(cut_row)
    parts = []
    if declared is not None and n < declared:
        parts.append(f"the header declares {declared} {noun} ({field}) but the file holds {n}")
    if cut_row:
        parts.append(f"its last row (line {end}) has {len(rows[end - 1])} of {ncols} cells, cut off mid-row")
    if not parts:
        return end
    what = "; ".join(parts)
    if not allow:
        raise InputError(
            f"{source}: the file is cut short: {what} (the copy or the export broke off). Export or copy it again, or "
            f"pass --allow-truncated (allow_truncated=True) to use the {n} complete {noun}."
        )
    warnings.warn(f"{source}: the file is cut short: {what}; using the {n} complete {noun}.", CaptureWarning, stacklevel=3)
    return end - int(cut_row)


def _numbers(rows, start: int, cols: list[int], source: str, names: list[str]) -> tuple[np.ndarray, np.ndarray]:
    """Parse `rows[start:]` at `cols` into floats (blank -> NaN); trailing empty rows dropped.
    Returns `(data, lines)` with 1-based file lines."""
    body = rows[start : _data_end(rows, start)]
    data = np.full((len(body), len(cols)), np.nan)
    lines = np.arange(len(body)) + start + 1
    for i, row in enumerate(body):
        for jj, j in enumerate(cols):
            if j < len(row):
                data[i, jj] = _parse_cell(row[j], source, int(lines[i]), names[jj])
    return data, lines


def _check_times(t: np.ndarray, lines: np.ndarray, source: str) -> None:
    bad = np.nonzero(~np.isfinite(t))[0]
    if bad.size:
        raise ValueError(f"{source}, line {lines[bad[0]]}: the time (or frame number) is blank; every row needs one.")
    _check_increasing(t, source, lines)


def read_motive_csv(
    path, *, rigid_body: str | None = None, use: str = "auto", units: str = "auto", up_axis: str = "y",
    allow_truncated: bool = False,
) -> MarkerData:  # fmt: skip
    """Read an OptiTrack Motive CSV export (format version 1.2x and later).

    Layout (https://docs.optitrack.com/motive/data-export/data-export-csv): line 1 `Format
    Version,...,Length Units,Meters|Millimeters,...`; a blank line; rows `,Type,...` (`Rigid
    Body`, `Rigid Body Marker`, `Marker`), `,Name,...`, `,ID,...`, a row naming `Rotation` /
    `Position` / `Mean Marker Error`, then `Frame,Time (Seconds),X,Y,Z,...`; rigid-body rotations
    are quaternions in the order **X, Y, Z, W**. Occluded markers are blank cells (gaps).

    **Arguments:**
    - `rigid_body`: the asset name; selects that rigid body and the markers named `"<name>:..."`.
      Default: the only rigid body (if any), and every labelled `Marker` column.
    - `use`: `"markers"` (poses from the `Marker` columns by `rigid_body_pose`), `"rigid_body"`
      (Motive's own solved pose, kept in `MarkerData.rb_q/rb_p`), or `"auto"` (markers if there
      are at least 3 marker columns, else the rigid body). The markers are always returned.
    - `units`: `"auto"` (the file's `Length Units`, else detected), `"m"` or `"mm"`.
    - `up_axis`: `"y"` (Motive's default) or `"z"`; Y-up data are turned into jsphere's Z-up frame
      by `UP_TO_Z["y"]`: `(X, Y, Z) = (X_m, -Z_m, Y_m)`.
    - `allow_truncated`: a file cut short (fewer data rows than line 1's `Total Exported
      Frames`, or a last row with fewer cells than the header) is an `InputError` naming both
      counts; with `True` it is a `CaptureWarning` and the complete rows are used.
    """
    path, rows = _read_lines(path)
    source = str(path)
    if up_axis not in UP_TO_Z:
        raise ValueError(f"{source}: up_axis must be 'y' or 'z'; got {up_axis!r}.")
    if use not in ("auto", "markers", "rigid_body"):
        raise ValueError(f"{source}: use must be 'auto', 'markers' or 'rigid_body'; got {use!r}.")
    if not rows or not rows[0] or rows[0][0].strip() != "Format Version":
        raise ValueError(
            f"{source}, line 1: not a Motive CSV export (expected 'Format Version,...'); export with the header on"
            f"{separator_hint(rows[0][:1]) if rows and rows[0] else ''}."
        )
    meta = {rows[0][i].strip(): rows[0][i + 1].strip() for i in range(0, len(rows[0]) - 1, 2)}
    if meta.get("Rotation Type", "Quaternion") != "Quaternion":
        raise ValueError(f"{source}, line 1: Rotation Type is {meta['Rotation Type']!r}; export with Rotation Type = Quaternion.")
    file_units = {"Meters": "m", "Millimeters": "mm"}.get(meta.get("Length Units", ""), None)
    if meta.get("Length Units") and file_units is None:
        raise ValueError(
            f"{source}, line 1: Length Units {meta['Length Units']!r} not supported; export in Meters or Millimeters."
        )

    def find(label: str, col: int = 1) -> int:
        for i, r in enumerate(rows):
            if len(r) > col and r[col].strip() == label:
                return i
        raise ValueError(f"{source}: no '{label}' header row; is this a Motive CSV export with the header on?")

    i_type, i_name = find("Type"), find("Name")
    i_hdr = find("Frame", 0)
    if rows[i_hdr][1].strip() != "Time (Seconds)":
        raise ValueError(f"{source}, line {i_hdr + 1}: expected 'Frame,Time (Seconds),...'; got {rows[i_hdr][:2]}.")
    types, names, kinds, axes = rows[i_type], rows[i_name], rows[i_hdr - 1], rows[i_hdr]
    ncol = len(axes)

    def cell(r, j):
        return r[j].strip() if j < len(r) else ""

    # rigid bodies: Rotation X,Y,Z,W + Position X,Y,Z
    bodies = sorted({cell(names, j) for j in range(2, ncol) if cell(types, j) == "Rigid Body"})
    if rigid_body is not None and bodies and rigid_body not in bodies:
        raise ValueError(f"{source}: no rigid body named {rigid_body!r}; the file has {bodies}.")
    if rigid_body is None and len(bodies) > 1:
        raise ValueError(f"{source}: the file has several rigid bodies {bodies}; pass rigid_body=<name>.")
    body = rigid_body if rigid_body is not None else (bodies[0] if bodies else None)
    rb_cols = {}
    if body is not None and body in bodies:
        for j in range(2, ncol):
            if cell(types, j) == "Rigid Body" and cell(names, j) == body:
                rb_cols[(cell(kinds, j), cell(axes, j))] = j
    # labelled markers (raw positions, not the solved "Rigid Body Marker" columns)
    mk: dict[str, dict[str, int]] = {}
    for j in range(2, ncol):
        nm = cell(names, j)
        if cell(types, j) != "Marker" or cell(kinds, j) != "Position" or nm.startswith("Unlabeled"):
            continue
        if body is not None and ":" in nm and nm.split(":")[0] != body:
            continue
        mk.setdefault(nm, {})[cell(axes, j)] = j
    mk = {n: c for n, c in mk.items() if set(c) >= {"X", "Y", "Z"}}
    mnames = list(mk)
    cols = [0, 1] + [mk[n][a] for n in mnames for a in "XYZ"]
    colnames = ["Frame", "Time (Seconds)"] + [f"{n} {a}" for n in mnames for a in "XYZ"]
    want_rb = use == "rigid_body" or (use == "auto" and len(mnames) < 3)
    if want_rb:
        need = [("Rotation", a) for a in "XYZW"] + [("Position", a) for a in "XYZ"]
        if not all(k in rb_cols for k in need):
            raise ValueError(
                f"{source}: no complete rigid-body columns (Rotation X,Y,Z,W and Position X,Y,Z) and fewer than 3 "
                "marker columns; export the rigid body or its markers."
            )
        cols += [rb_cols[k] for k in need]
        colnames += [f"{body} {k[0]} {k[1]}" for k in need]
    declared = None
    if meta.get("Total Exported Frames", "").isdigit():
        declared = int(meta["Total Exported Frames"])
    end = _cut_short(rows, i_hdr + 1, _data_end(rows, i_hdr + 1), ncol, source, allow_truncated, declared=declared,
                     field="Total Exported Frames")  # fmt: skip
    data, lines = _numbers(rows[:end], i_hdr + 1, cols, source, colnames)
    if data.shape[0] == 0:
        raise InputError(f"{source}: no data rows after the header 'Frame,Time (Seconds),...' (line {i_hdr + 1}).")
    t = data[:, 1]
    _check_times(t, lines, source)
    K = len(mnames)
    C = UP_TO_Z[up_axis]
    raw = data[:, 2 : 2 + 3 * K].reshape(-1, K, 3)
    scale = _scale(units, file_units, detect_marker_units(raw), source) if K >= 2 else _scale_rb(units, file_units, source)
    markers = np.einsum("ij,mkj->mki", C, raw) * scale
    rb_q = rb_p = None
    if want_rb:
        rb = data[:, 2 + 3 * K :]
        q_m = rb[:, [3, 0, 1, 2]]  # (X, Y, Z, W) -> (w, x, y, z)
        q_C = quat_from_rotmat_np(C)
        rb_q = sign_continuous(quat_mul_np(np.broadcast_to(q_C, q_m.shape), q_m))  # C R_m
        rb_p = rb[:, 4:7] @ C.T * scale
    return MarkerData(t, markers, tuple(mnames), source, lines, rb_q, rb_p)


def _scale_rb(units: str, file_units: str | None, source: str) -> float:
    if units == "auto" and file_units is None:
        raise ValueError(f"{source}: cannot tell whether lengths are in m or mm; pass units='m' or units='mm'.")
    return _scale(units, file_units, None, source)


def read_vicon_csv(
    path, *, subject: str | None = None, units: str = "auto", up_axis: str = "z", allow_truncated: bool = False
) -> MarkerData:
    """Read a Vicon Nexus "Trajectories" CSV export.

    Layout (e.g. https://ccu.uni-konstanz.de/wiki/ , Vicon Nexus reference guide): a line
    `Trajectories`, the frame rate [Hz], a row with each marker's name `Subject:Marker` in the
    column of its X, then `Frame,Sub Frame,X,Y,Z,...`, a units row (`mm`), then one row per
    frame, up to a blank line (other sections, e.g. `Devices`, may come before or after). Blank
    cells are gaps. Time is `(Frame - first Frame) / rate` [s] (`Sub Frame` is 0
    in trajectory exports; other values are an error).

    `subject` keeps the markers named `"<subject>:..."` (default: all). `units`: `"auto"` (the
    units row), `"m"` or `"mm"`. `up_axis`: Vicon is Z-up by default. A file cut short (the
    section runs to the end of the file and its last row has fewer cells than the header) is an
    `InputError` naming both counts; `allow_truncated=True` makes it a `CaptureWarning` and
    drops that row.
    """
    path, rows = _read_lines(path)
    source = str(path)
    if up_axis not in UP_TO_Z:
        raise ValueError(f"{source}: up_axis must be 'y' or 'z'; got {up_axis!r}.")
    i0 = next((i for i, r in enumerate(rows) if r and r[0].strip() == "Trajectories"), None)
    if i0 is None:
        hint = next((separator_hint(r[:1]) for r in rows if r and r[0].strip().startswith("Trajectories")), "")
        raise ValueError(f"{source}: no 'Trajectories' section; export the marker trajectories from Nexus as CSV{hint}.")
    try:
        rate = float(rows[i0 + 1][0])
    except (IndexError, ValueError):
        raise ValueError(f"{source}, line {i0 + 2}: expected the frame rate [Hz] after 'Trajectories'.") from None
    if not rate > 0:
        raise ValueError(f"{source}, line {i0 + 2}: the frame rate must be positive; got {rate}.")
    names, hdr = rows[i0 + 2], rows[i0 + 3]
    if len(hdr) < 2 or hdr[0].strip() != "Frame" or hdr[1].strip() != "Sub Frame":
        raise ValueError(f"{source}, line {i0 + 4}: expected 'Frame,Sub Frame,X,Y,Z,...'{separator_hint(hdr[:1])}.")
    unit_row = rows[i0 + 4] if len(rows) > i0 + 4 else []
    found_units = {c.strip() for c in unit_row[2:] if c.strip()}
    if not found_units <= {"mm", "m"} or len(found_units) > 1:
        raise ValueError(f"{source}, line {i0 + 5}: units row {sorted(found_units)} not understood; expected mm or m.")
    file_units = found_units.pop() if found_units else None
    mk = []
    for j in range(2, len(hdr) - 2):
        nm = names[j].strip() if j < len(names) else ""
        if nm and hdr[j].strip() == "X" and (subject is None or nm.split(":")[0] == subject):
            mk.append((nm, j))
    if not mk:
        raise ValueError(f"{source}, line {i0 + 3}: no marker trajectories" + (f" of subject {subject!r}." if subject else "."))
    cols = [0, 1] + [j + a for _, j in mk for a in range(3)]
    colnames = ["Frame", "Sub Frame"] + [f"{n} {a}" for n, _ in mk for a in "XYZ"]
    end = next((i for i in range(i0 + 5, len(rows)) if not any(c.strip() for c in rows[i])), len(rows))
    if _data_end(rows, end) == end:  # the section runs to the end of the file: it may have been cut off
        end = _cut_short(rows, i0 + 5, end, len(hdr), source, allow_truncated)
    data, lines = _numbers(rows[:end], i0 + 5, cols, source, colnames)  # the section ends at a blank line
    if data.shape[0] == 0:
        raise InputError(f"{source}: no data rows after the units row (line {i0 + 5}).")
    sub = np.nonzero(np.nan_to_num(data[:, 1]) != 0)[0]
    if sub.size:
        raise ValueError(f"{source}, line {lines[sub[0]]}: Sub Frame is not 0; export the trajectories at the camera rate.")
    t = (data[:, 0] - data[0, 0]) / rate
    _check_times(t, lines, source)
    raw = data[:, 2:].reshape(len(t), len(mk), 3)
    scale = _scale(units, file_units, detect_marker_units(raw), source)
    markers = np.einsum("ij,mkj->mki", UP_TO_Z[up_axis], raw) * scale
    return MarkerData(t, markers, tuple(n for n, _ in mk), source, lines)


#: C3D processor types (byte 4 of the parameter section): 84 Intel, 85 DEC (both little-endian
#: integers), 86 MIPS/SGI (big-endian)
_C3D_PROCESSORS = {84: "<", 85: "<", 86: ">"}


def c3d_layout(path) -> dict:
    """Check the structure of a C3D file before `ezc3d` reads it, and return what its header
    declares: `{"frames": declared frame count or None (a header that saturates at 65535),
    "frames_in_file": whole frames the file holds, "points": ..., "data_start": byte offset}`.

    ezc3d reads a truncated or corrupt file without a word (it shortens the frame count to what
    it finds, even in `POINT:FRAMES`), raises assorted errors, and on some corrupt parameter
    sections crashes the process or never returns. So the header (512 bytes: key byte 0x50,
    the parameter block, points, analog samples, first and last frame, scale, data start) and
    every record of the parameter section (names, types, dimensions, offsets inside the
    section) are checked here; any problem is an `InputError` naming the file.
    """
    path = Path(path)
    source = str(path)
    size = path.stat().st_size
    with open(path, "rb") as f:
        raw = f.read(512)
    if size == 0:
        raise InputError(f"{source}: the file is empty (0 bytes), not a C3D file; export or copy it again.")
    if size < 512 or raw[1] != 0x50:
        what = f"{size} bytes, shorter than the 512-byte header" if size < 512 else f"its second byte is 0x{raw[1]:02x}, not 0x50"
        raise InputError(f"{source}: not a C3D file ({what}); check the file (and --format: motive, vicon or c3d).")
    p0 = (raw[0] - 1) * 512
    if raw[0] < 2 or size < p0 + 4:
        raise InputError(
            f"{source}: the C3D file is cut short or corrupt: its parameter section (block {raw[0]}) is not in the "
            f"file ({size} bytes); export or copy it again."
        )
    with open(path, "rb") as f:
        f.seek(p0)
        head = f.read(4)
    endian = _C3D_PROCESSORS.get(head[3])
    if endian is None:
        raise InputError(f"{source}: not a C3D file, or a corrupt one (processor type {head[3]}, not 84, 85 or 86).")
    n_points, n_analog, first, last = struct.unpack(endian + "4H", raw[2:10])
    data_start = struct.unpack(endian + "H", raw[16:18])[0]
    sign_byte = {">": 12, "<": 15}[endian] if head[3] != 85 else 13  # the sign bit of the scale factor
    float_data = bool(raw[sign_byte] & 0x80)
    p_end = p0 + 512 * head[2]
    if head[2] == 0 or data_start - 1 < raw[0] or size < p_end:
        raise InputError(
            f"{source}: the C3D file is cut short or corrupt: {size} bytes, but its parameters end at byte {p_end} and its "
            f"data start at byte {512 * (data_start - 1)}; export or copy it again."
        )
    with open(path, "rb") as f:
        f.seek(p0)
        params = f.read(p_end - p0)
    _check_c3d_parameters(params, endian, source)
    frame_bytes = (4 * n_points + n_analog) * (4 if float_data else 2)
    start = 512 * (data_start - 1)
    if size < start:
        raise InputError(f"{source}: the C3D file is cut short before its data (byte {start}; the file has {size}).")
    frames = last - first + 1 if (last >= first and last < 65535) else None
    in_file = (size - start) // frame_bytes if frame_bytes else (frames or 0)
    return {"frames": frames, "frames_in_file": int(in_file), "points": n_points, "data_start": start}


def _check_c3d_parameters(params: bytes, endian: str, source: str) -> None:
    """Walk the records of a C3D parameter section (`params`: the whole section, from its 4-byte
    head); raise `InputError` at the first that runs out of the section or makes no sense."""
    pos, n_records = 4, 0
    end = len(params)

    def bad(why: str):
        return InputError(f"{source}: the C3D file is corrupt: parameter record {n_records + 1} ({why}); export or copy it again.")

    while pos + 2 <= end:
        n_name = abs(struct.unpack("b", params[pos : pos + 1])[0])
        if n_name == 0:
            return  # the end of the records
        name = params[pos + 2 : pos + 2 + n_name]
        if len(name) < n_name or not all(32 < c < 127 for c in name):
            raise bad("its name is not printable")
        group = struct.unpack("b", params[pos + 1 : pos + 2])[0] < 0
        at = pos + 2 + n_name  # the offset to the next record counts from here
        if at + 2 > end:
            raise bad("it runs past the section")
        nxt = struct.unpack(endian + "h", params[at : at + 2])[0]
        q = at + 2
        if not group:
            if q + 2 > end:
                raise bad("it runs past the section")
            typ, ndim = struct.unpack("b", params[q : q + 1])[0], params[q + 1]
            if typ not in (-1, 1, 2, 4) or ndim > 7:
                raise bad(f"type {typ}, {ndim} dimensions")
            dims = params[q + 2 : q + 2 + ndim]
            q += 2 + ndim + abs(typ) * int(np.prod(list(dims), dtype=np.int64))
        if q + 1 > end or q + 1 + params[q] > end:
            raise bad("it runs past the section")
        if nxt == 0:
            return  # the last record
        if nxt < 0 or at + nxt <= pos or at + nxt > end:
            raise bad(f"its link to the next record ({nxt}) leaves the section")
        pos = at + nxt
        n_records += 1
        if n_records > 100_000:
            raise bad("too many records")


def read_c3d(path, *, units: str = "auto", up_axis: str = "z", allow_truncated: bool = False) -> MarkerData:
    """Read marker trajectories from a C3D file through `ezc3d` (`pip install jsphere[c3d]`).

    Uses `POINT:LABELS`, `POINT:RATE`, `POINT:UNITS` and `data.points` `(4, K, M)`; a point whose
    residual (`data.meta_points.residuals`) is negative is a gap. Times are frame / rate from 0.

    The file's structure is checked first (`c3d_layout`): an empty, random or corrupt file is
    an `InputError` naming it. A file with fewer frames than its header declares (a copy or an
    export that broke off) is an `InputError` naming both counts; with `allow_truncated=True`
    it is a `CaptureWarning` and the frames present are used.
    """
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"capture file {path} does not exist.")
    source = str(path)
    layout = c3d_layout(path)
    declared, present = layout["frames"], layout["frames_in_file"]
    if declared is not None and present < declared:
        what = f"the header declares {declared} frames but the file holds {present}"
        if not allow_truncated or present == 0:
            raise InputError(
                f"{source}: the file is cut short: {what} (the copy or the export broke off). Export or copy it again"
                + (", or pass --allow-truncated (allow_truncated=True) to use the frames present." if present else ".")
            )
        warnings.warn(f"{source}: the file is cut short: {what}; using the {present} frames present.", CaptureWarning, stacklevel=2)
    try:  # after the checks of the file's structure, which need no ezc3d
        import ezc3d
    except ImportError:
        raise ImportError(
            "read_c3d needs the optional dependency ezc3d: pip install jsphere[c3d] (or pip install ezc3d)."
        ) from None
    try:
        c = ezc3d.c3d(str(path))
        point = c["parameters"]["POINT"]
        labels = tuple(str(s).strip() for s in point["LABELS"]["value"])
        rate = float(point["RATE"]["value"][0])
        file_units = str(point["UNITS"]["value"][0]).strip() if "UNITS" in point else None
        pts = np.asarray(c["data"]["points"], float)
        res = np.asarray(c["data"]["meta_points"]["residuals"], float)
    except (RuntimeError, OSError, ValueError, KeyError, IndexError, TypeError) as e:
        raise InputError(f"{source}: not a readable C3D file (ezc3d: {str(e).strip() or type(e).__name__}); export it again.") from None
    if not (math.isfinite(rate) and rate > 0):
        raise InputError(f"{source}: POINT:RATE is {rate:g}; the frame rate must be a positive number of Hz.")
    if file_units not in (None, "m", "mm"):
        raise ValueError(f"{source}: POINT:UNITS is {file_units!r}; only 'm' and 'mm' are supported.")
    if pts.ndim != 3 or pts.shape[0] < 3 or pts.shape[1] != len(labels) or res.ndim != 3 or res.shape[1:] != pts.shape[1:]:
        raise ValueError(f"{source}: data.points has shape {pts.shape}; expected (4, {len(labels)}, frames).")
    if pts.shape[2] == 0:
        raise InputError(f"{source}: the C3D file holds no frames.")
    raw = np.transpose(pts[:3], (2, 1, 0)).copy()  # (M, K, 3)
    raw[res[0].T < 0] = np.nan
    t = np.arange(raw.shape[0]) / rate
    scale = _scale(units, file_units, detect_marker_units(raw), source)
    markers = np.einsum("ij,mkj->mki", UP_TO_Z[up_axis], raw) * scale
    return MarkerData(t, markers, labels, source, None)


# --------------------------------------------------------------------------- inputs table


def read_inputs_csv(path, *, allow_truncated: bool = False) -> tuple[np.ndarray, np.ndarray, str, list[str]]:
    """Read an inputs table: columns `t` [s] and `chi_dot_1..N` [rad/s] or `K_1..N` [N m] (lines
    starting with `#` before the header are comments). Returns `(t, values, kind, names)`.
    Blank cells, NaN and non-increasing times are errors naming the line. A last row with fewer
    cells than the header (a file cut off mid-row) is an `InputError` naming both counts; with
    `allow_truncated=True` it is a `CaptureWarning` and the row is dropped."""
    path, rows = _read_lines(path)
    source = str(path)
    k = 0
    while k < len(rows) and (not rows[k] or rows[k][0].lstrip().startswith("#") or not any(c.strip() for c in rows[k])):
        k += 1
    if k == len(rows):
        raise ValueError(f"{source}: no header line; the inputs table needs columns t and chi_dot_1..N or K_1..N.")
    header = [h.strip() for h in rows[k]]
    if "t" not in header:
        raise ValueError(f"{source}, line {k + 1}: missing required column t (time [s]){separator_hint(rows[k])}.")
    kind, in_cols = _input_columns(header, f"{source}, line {k + 1}")
    names = [header[j] for j in in_cols]
    check_unique_columns(header, f"{source}, line {k + 1}", ["t", *names])
    end = _cut_short(rows, k + 1, _data_end(rows, k + 1), len(header), source, allow_truncated, noun="rows")
    data, lines = _numbers(rows[:end], k + 1, [header.index("t")] + in_cols, source, ["t"] + names)
    if data.shape[0] < 2:
        raise ValueError(f"{source}: the inputs table needs at least 2 rows.")
    _check_times(data[:, 0], lines, source)
    bad = np.argwhere(~np.isfinite(data[:, 1:]))
    if bad.size:
        i, c = int(bad[0, 0]), int(bad[0, 1])
        raise ValueError(f"{source}, line {lines[i]}: input column {names[c]} is blank or not finite; inputs may not have gaps.")
    return data[:, 0], data[:, 1:], kind, names


def write_inputs_csv(path, t: np.ndarray, values: np.ndarray, kind: str) -> None:
    """Write an inputs table (see `read_inputs_csv`) atomically."""
    if kind not in KINDS:
        raise ValueError(f"write_inputs_csv: kind must be one of {KINDS}; got {kind!r}.")
    values = np.asarray(values, float).reshape(len(t), -1)
    cols = ["t"] + [f"{INPUT_PREFIX[kind]}{i + 1}" for i in range(values.shape[1])]
    lines = [",".join(cols)] + [",".join([f"{tt:.6f}"] + [f"{v + 0.0:.10g}" for v in row]) for tt, row in zip(t, values)]
    atomic_write_text(path, "\n".join(lines) + "\n")


def interpolate_inputs(t_in: np.ndarray, values: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Inputs at times `t`, linearly interpolated from the table `(t_in, values)` (`(T, N)`)."""
    return np.stack([np.interp(t, t_in, values[:, i]) for i in range(values.shape[1])], axis=1)


# --------------------------------------------------------------------------- markers -> trial


def markers_to_trial(
    data: MarkerData,
    inputs,
    *,
    body_markers: np.ndarray | dict[str, np.ndarray] | None = None,
    alignment: np.ndarray | None = None,
    body_offset=(0.0, 0.0, 0.0),
    max_rms: float = 0.005,
    time_offset: float = 0.0,
    name: str | None = None,
    max_gap_fraction: float = 0.5,
    allow_truncated: bool = False,
) -> Trial:
    """A `Trial` from raw marker data and an inputs table.

    **Arguments:**
    - `data`: from `read_motive_csv`, `read_vicon_csv` or `read_c3d`.
    - `inputs`: the path of an inputs table (`read_inputs_csv`) or a tuple `(t, values, kind)`.
      The inputs are interpolated linearly to the capture times; capture frames outside the
      table's time range are dropped (the two must share a clock: `t_trial = t_capture +
      time_offset`).
    - `body_markers`, `alignment`, `body_offset`: see the module docstring. `body_markers` may
      be a `(K, 3)` array in the order of `data.names`, or a dict `{name: (x, y, z)}` (e.g. from
      `read_body_markers`), matched by full name or by the part after `Subject:`; markers of
      the export not in the dict are ignored. If the data carry
      the exporter's rigid-body pose (`rb_q`), it is used instead of the markers, as the body
      frame.
    - `max_rms`: frames whose marker fit has an RMS residual above this [m] are gaps.
    - `allow_truncated`: passed to `read_inputs_csv`.

    Given body markers whose distances from each other disagree with the export's (by more than
    10%: markers in millimetres, or of another robot) are an `InputError`. The trial is checked
    for plausibility (`jsphere.capture.trial.implausible`: speeds, turn rates, time units), each
    finding a `CaptureWarning`.
    """
    source = data.source
    off = np.asarray(body_offset, float)
    if off.size != 3 or not np.all(np.isfinite(off)):
        raise InputError(f"{source}: body_offset must be 3 finite numbers (x, y, z in the platform frame, m); got {body_offset!r}.")
    if not math.isfinite(time_offset):
        raise InputError(f"{source}: time_offset must be a finite number of seconds; got {time_offset!r}.")
    if not max_rms > 0:  # NaN too
        raise InputError(f"{source}: max_rms must be positive (metres); got {max_rms!r}.")
    if isinstance(inputs, (str, Path)):
        t_in, u_in, kind, _ = read_inputs_csv(inputs, allow_truncated=allow_truncated)
    else:
        t_in, u_in, kind = inputs
        t_in, u_in = np.asarray(t_in, float), np.asarray(u_in, float).reshape(len(t_in), -1)
    A = np.eye(3) if alignment is None else np.asarray(alignment, float)
    if A.shape != (3, 3) or not np.allclose(A @ A.T, np.eye(3), atol=1e-6) or np.linalg.det(A) < 0:
        raise ValueError(f"{source}: alignment must be a 3x3 rotation matrix (platform -> body frame).")
    off = np.asarray(body_offset, float).reshape(3)
    if data.rb_q is not None:
        q_body, p_body = data.rb_q, data.rb_p
    else:
        if len(data.names) < 3:
            raise ValueError(f"{source}: {len(data.names)} marker(s) {list(data.names)}; a pose needs at least 3 markers.")
        if body_markers is None:
            body_markers, _ = estimate_body_markers(data.markers, source)
        elif isinstance(body_markers, dict):
            body_markers = _match_body_markers(body_markers, data.names, source)
        body_markers = np.asarray(body_markers, float)
        if body_markers.shape != (len(data.names), 3):
            raise ValueError(f"{source}: body_markers must be ({len(data.names)}, 3), one row per marker {list(data.names)}.")
        known = np.all(np.isfinite(body_markers), axis=1)  # markers left out of a body_markers dict
        _check_body_scale(data.markers[:, known], body_markers[known], source)
        q_body, p_body, _ = rigid_body_pose(data.markers[:, known], body_markers[known], max_rms=max_rms)
    R_body = rotmat_np(np.where(np.isfinite(q_body), q_body, 1.0))
    R = R_body @ A  # platform -> fixed
    centre = p_body + np.einsum("mij,j->mi", R, off)
    q = quat_from_rotmat_np(R)
    q[~np.all(np.isfinite(q_body), axis=1)] = np.nan
    t = data.t + time_offset
    keep = (t >= t_in[0] - 1e-9) & (t <= t_in[-1] + 1e-9)
    if not np.any(keep):
        raise ValueError(
            f"{source}: the capture times [{t[0]:g}, {t[-1]:g}] s do not overlap the inputs' [{t_in[0]:g}, {t_in[-1]:g}] s; "
            "the two must share a clock (use time_offset)."
        )
    span_in, span = float(t_in[-1] - t_in[0]), float(t[keep][-1] - t[keep][0])
    if span_in >= 100.0 * max(span, 1e-9) and float(np.median(np.diff(t_in))) >= 100.0 * float(np.median(np.diff(t))):
        warnings.warn(
            f"{source}: the inputs table spans {span_in:g} s with steps of {float(np.median(np.diff(t_in))):g} s, the capture "
            f"{span:g} s with steps of {float(np.median(np.diff(t))):g} s: are the inputs' times in milliseconds? Give them in "
            "seconds.",
            CaptureWarning, stacklevel=2,
        )  # fmt: skip
    u = interpolate_inputs(t_in, u_in, t[keep])
    lines = None if data.lines is None else data.lines[keep]
    tt, x, y, qq, uu, z = _checked(
        t[keep], centre[keep, 0], centre[keep, 1], q[keep], u, kind, centre[keep, 2], source=source, lines=lines,
        max_gap_fraction=max_gap_fraction,
    )  # fmt: skip
    warn_implausible(
        tt, x, y, qq, source, z, from_markers=True, units_hint="pass units='mm' (--units mm)",
        up_hint="is the export's up axis right? (up_axis / --up-axis: 'y' is Motive's default, 'z' Vicon's and C3D's)",
    )  # fmt: skip
    return Trial(tt, x, y, qq, uu, kind, z, name=name or Path(source).stem)


def _check_body_scale(markers: np.ndarray, body: np.ndarray, source: str) -> None:
    """Raise `InputError` if the distances between the body markers differ from those between
    the export's markers by more than 10% (median over marker pairs of the ratio of the body's
    distance to the export's median over frames): body markers in millimetres, or another
    marker set, would give no pose at all ("too few valid frames")."""
    K = body.shape[0]
    i, j = np.triu_indices(K, 1)
    d_data = np.linalg.norm(markers[:, i] - markers[:, j], axis=2)  # (M, pairs), NaN where missing
    seen = np.sum(np.isfinite(d_data), axis=0) > 0
    if not np.any(seen):
        return
    d_data = np.nanmedian(d_data[:, seen], axis=0)
    d_body = np.linalg.norm(body[i] - body[j], axis=1)[seen]
    ok = d_data > 0
    if not np.any(ok):
        return
    ratio = float(np.median(d_body[ok] / d_data[ok]))
    if abs(ratio - 1.0) <= 0.1:
        return
    hint = (
        "the body markers look like millimetres: give them in metres (or add '# units: mm' to their file)"
        if 500.0 <= ratio <= 2000.0
        else "the body markers look like metres while the export is read in millimetres" if 5e-4 <= ratio <= 2e-3
        else "check that they belong to this marker set, and their units (metres)"
    )  # fmt: skip
    raise InputError(
        f"{source}: the body markers are {ratio:.4g} times as far apart as the markers in the export (median over "
        f"marker pairs); {hint}."
    )


# --------------------------------------------------------------------------- synthetic markers and writers


def default_marker_set(R0: float = 0.15) -> np.ndarray:
    """Four non-coplanar markers (platform frame, relative to the shell centre) [m] on a
    platform inside a shell of radius `R0`: a stand of about `R0/2`."""
    a = 0.5 * R0
    return np.array([[a, 0.0, 0.1 * a], [-0.5 * a, 0.8 * a, 0.0], [-0.5 * a, -0.8 * a, 0.0], [0.0, 0.2 * a, 0.7 * a]])


def synthetic_markers(
    trial: Trial,
    body_markers: np.ndarray,
    *,
    z: float = 0.15,
    body_offset=(0.0, 0.0, 0.0),
    alignment: np.ndarray | None = None,
    marker_sd: float = 2e-4,
    dropout: float = 0.0,
    seed: int = 0,
) -> np.ndarray:
    """Marker positions `(M, K, 3)` [m] that a capture system would see for `trial`'s poses.

    The shell centre is at `(x, y, z)` (`trial.z` if it has one, else `z`, the shell radius);
    marker k is at `centre - R body_offset + R alignment^T body_markers[k]` with `R` the platform
    rotation; Gaussian noise of `marker_sd` [m] per coordinate; each marker independently
    missing (NaN) with probability `dropout`; gap frames of `trial` give NaN markers.
    """
    rng = np.random.default_rng(seed)
    A = np.eye(3) if alignment is None else np.asarray(alignment, float)
    R = rotmat_np(np.where(np.isfinite(trial.q), trial.q, 1.0))
    zz = trial.z if trial.z is not None else np.full(trial.n_frames, float(z))
    centre = np.stack([trial.x, trial.y, zz], axis=1)
    off = np.asarray(body_offset, float)
    b_pl = np.asarray(body_markers, float) @ A  # rows: A^T b_k
    m = centre[:, None] - np.einsum("mij,j->mi", R, off)[:, None] + np.einsum("mij,kj->mki", R, b_pl)
    m = m + rng.normal(0.0, marker_sd, m.shape)
    m[rng.random(m.shape[:2]) < dropout] = np.nan
    m[~trial.valid] = np.nan
    return m


def _cells(v: np.ndarray, fmt: str) -> list[str]:
    return ["" if not np.isfinite(x) else format(x + 0.0, fmt) for x in v]


def write_motive_csv(
    path,
    t,
    markers,
    names,
    *,
    rigid_body: str = "robot",
    rb_q: np.ndarray | None = None,
    rb_p: np.ndarray | None = None,
    units: str = "m",
    up_axis: str = "y",
) -> None:
    """Write markers `(M, K, 3)` [m, jsphere Z-up frame] as a Motive-style CSV (format 1.23,
    `Marker` columns named `<rigid_body>:<name>`, blank cells for gaps), for tests and examples.
    With `rb_q (M, 4)` (w, x, y, z; body -> fixed) and `rb_p (M, 3)` [m], a `Rigid Body` block is
    written first: Rotation X, Y, Z, W, Position X, Y, Z, Mean Marker Error."""
    C = UP_TO_Z[up_axis]
    s = 1.0 if units == "m" else 1000.0
    raw = np.einsum("ji,mkj->mki", C, np.asarray(markers, float)) * s  # C^T: jsphere -> Motive
    M, K = raw.shape[:2]
    full = [f"{rigid_body}:{n}" for n in names]
    types, nms, ids, kinds, axes = [], [], [], [], []
    blocks = []
    if rb_q is not None:
        q_Ci = quat_from_rotmat_np(C.T)
        q_m = quat_mul_np(np.broadcast_to(q_Ci, np.shape(rb_q)), np.asarray(rb_q, float))  # C^T R
        p_m = np.asarray(rb_p, float) @ C * s
        blocks.append(np.concatenate([q_m[:, [1, 2, 3, 0]], p_m, np.zeros((M, 1))], axis=1))
        types += ["Rigid Body"] * 8
        nms += [rigid_body] * 8
        ids += ["1"] * 8
        kinds += ["Rotation"] * 4 + ["Position"] * 3 + ["Mean Marker Error"]
        axes += ["X", "Y", "Z", "W", "X", "Y", "Z", ""]
    blocks.append(raw.reshape(M, -1))
    types += ["Marker"] * 3 * K
    nms += [n for n in full for _ in range(3)]
    ids += [f"{i + 2}" for i in range(K) for _ in range(3)]
    kinds += ["Position"] * 3 * K
    axes += ["X", "Y", "Z"] * K
    lines = [
        "Format Version,1.23,Take Name,jsphere-synthetic,Capture Frame Rate,{r:.6f},Export Frame Rate,{r:.6f},"
        "Rotation Type,Quaternion,Length Units,{u},Coordinate Space,Global".format(
            r=1.0 / float(np.median(np.diff(t))), u="Meters" if units == "m" else "Millimeters"
        ),
        "",
        ",Type," + ",".join(types),
        ",Name," + ",".join(nms),
        ",ID," + ",".join(ids),
        ",," + ",".join(kinds),
        "Frame,Time (Seconds)," + ",".join(axes),
    ]
    length_fmt = ".6f" if units == "m" else ".3f"
    fmts = [".6f" if k in ("Rotation", "Mean Marker Error") else length_fmt for k in kinds]
    data = np.concatenate(blocks, axis=1)
    for i in range(M):
        cells = ["" if not np.isfinite(v) else format(v + 0.0, f) for v, f in zip(data[i], fmts)]
        lines.append(",".join([str(i), f"{t[i]:.6f}", *cells]))
    atomic_write_text(path, "\n".join(lines) + "\n")


def write_vicon_csv(path, t, markers, names, *, subject: str = "robot", units: str = "mm") -> None:
    """Write markers `(M, K, 3)` [m] as a Vicon Nexus-style Trajectories CSV (frame numbers from
    1 at the rate `1 / median(diff(t))`; blank cells for gaps), for tests and examples."""
    rate = 1.0 / float(np.median(np.diff(t)))
    s = 1.0 if units == "m" else 1000.0
    raw = np.asarray(markers, float) * s
    K = raw.shape[1]
    lines = [
        "Trajectories",
        f"{rate:g}",
        ",," + ",".join(f"{subject}:{n},," for n in names).rstrip(","),
        "Frame,Sub Frame," + ",".join(["X", "Y", "Z"] * K),
        ",," + ",".join([units] * 3 * K),
    ]
    fmt = ".6f" if units == "m" else ".3f"
    for i in range(raw.shape[0]):
        frame = round(float(t[i] - t[0]) * rate) + 1
        lines.append(",".join([str(frame), "0"] + _cells(raw[i].reshape(-1), fmt)))
    atomic_write_text(path, "\n".join(lines) + "\n")


# --------------------------------------------------------------------------- one call

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
        data, inputs, body_markers=body_markers, alignment=alignment, body_offset=body_offset, max_rms=max_rms,
        time_offset=time_offset, name=name, allow_truncated=allow_truncated,
    )  # fmt: skip
