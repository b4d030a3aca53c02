"""Qualisys Track Manager (QTM) TSV exports: 3D marker data and 6DOF rigid-body data
(`read_qualisys_tsv`)."""

from __future__ import annotations

import re

import numpy as np
from scipy.spatial.transform import Rotation

from .._runtime.errors import InputError
from .markers import MarkerData, choose_body, fixed_markers, fixed_pose, open_export
from .text import _cut_short, _numbers
from .units import EXPORT_UNITS, resolve_units
from .validation import _check_times

#: a header line of a QTM TSV file: an upper-case variable name, a tab, its values
_KEY = re.compile(r"^[A-Z][A-Z0-9_]*$")
#: the fields of a 6DOF body's columns (`Rot[0]`..`Rot[8]`: its rotation matrix column by column)
_FIELDS_6D = ("X", "Y", "Z", "Roll", "Pitch", "Yaw", "Residual", *(f"Rot[{i}]" for i in range(9)))
#: the axis of each angle of a 6DOF body (QTM manual, "Rotation angles in QTM")
_AXIS = {"Roll": "X", "Pitch": "Y", "Yaw": "Z"}


def read_qualisys_tsv(
    path,
    *,
    rigid_body: str | None = None,
    units: str = "auto",
    up_axis: str = "z",
    allow_truncated: bool = False,
) -> MarkerData:
    """Read a Qualisys Track Manager TSV export with its TSV header (QTM manual, "Motion data
    (.tsv)"; the layouts read, QTM's and QTM 2.x's 3D and 6DOF exports with and without a
    column row: `docs/capture.md`).

    - **3D**: the markers of `MARKER_NAMES`; zeros (QTM's default) or blank cells are gaps.
    - **6DOF**: the pose of the body `rigid_body` (default: the only one) as `rb_q, rb_p`, no
      markers: its rotation `R` (`P_global = R P_local + P_origin`) from `Rot[0..8]` column by
      column, else from its angles (`_rotations`). A body not seen (NaN, blanks, an all-zero
      rotation, a residual of -1) is a gap.

    `units`: `"auto"` detects metres or millimetres from the marker spread (QTM writes
    millimetres: those where the spread cannot tell, and always for 6DOF), or `"m"` / `"mm"`.
    `up_axis`: `"z"` (QTM's default) or `"y"`. `allow_truncated`: as in `ConvertOptions`.
    """
    source, rows = open_export(path, up_axis, delimiter="\t")
    meta, k = _header(rows, source)
    kind = meta.get("DATA_INCLUDED", ["3D"])[0].strip().upper()
    if kind not in ("3D", "6D"):
        raise InputError(
            f"{source}: DATA_INCLUDED is {kind!r}; export 3D or 6DOF data to TSV (QTM: File > Export > To TSV)."
        )
    columns = None
    if k < len(rows) and _is_column_row(rows[k]):
        columns = [c.strip() for c in rows[k]]  # QTM 2.x starts its 6DOF column names with a space
        while columns and not columns[-1]:  # QTM ends the column row with a tab
            columns.pop()
        k += 1
    declared = meta.get("NO_OF_FRAMES", [""])[0].strip()
    first = _width(rows[k]) if k < len(rows) else 0
    ncol = first if columns is None else max(len(columns), first if kind == "6D" else 0)
    declared = int(declared) if declared.isdigit() else None
    end = _cut_short(rows, k, None, ncol, source, allow_truncated, declared=declared, field="NO_OF_FRAMES")
    if end <= k:
        raise InputError(f"{source}: no data rows after the header (line {k}).")
    read = _read_3d if kind == "3D" else _read_6d
    return read(rows[:end], k, columns, meta, rigid_body, units, up_axis, source)


def _is_column_row(row: list[str]) -> bool:
    """Whether `row` names the columns (`Frame`, `Time`, `<marker> X`, ...; QTM 2.x's 6DOF
    export: ` X`, ` Y`, ...) rather than holding a frame's numbers."""
    for cell in row:
        if cell.strip():
            try:
                float(cell)
            except ValueError:
                return True
    return False


def _width(row: list[str]) -> int:
    """The number of cells of `row` without the empty ones at its end."""
    n = len(row)
    while n and not row[n - 1].strip():
        n -= 1
    return n


def _header(rows: list[list[str]], source: str) -> tuple[dict[str, list[str]], int]:
    """The header variables `{NAME: values}` and the index of the first row after them."""
    meta: dict[str, list[str]] = {}
    k = 0
    while k < len(rows) and rows[k] and _KEY.match(rows[k][0].rstrip()):  # QTM 2.x's 6DOF columns: ' X', ...
        meta.setdefault(rows[k][0].rstrip(), rows[k][1:])
        k += 1
    if not meta:
        raise InputError(
            f"{source}, line 1: not a QTM TSV export with its header (expected lines like 'NO_OF_FRAMES<tab>...'); "
            "export again with Include TSV header checked."
        )
    return meta, k


def _times(data: np.ndarray, lead: list[str], meta: dict[str, list[str]], lines, source: str) -> np.ndarray:
    """The frame times [s] from the leading columns `lead` of `data` (`Frame`, `Time`): the
    `Time` column, else `(Frame - first Frame) / FREQUENCY`, else `row / FREQUENCY`."""
    if "Time" in lead:
        t = data[:, lead.index("Time")]
    else:
        try:
            rate = float(meta["FREQUENCY"][0])
        except (KeyError, IndexError, ValueError):
            rate = float("nan")
        if not rate > 0:
            raise InputError(f"{source}: no Time column and no positive FREQUENCY in the header; export the time data.")
        t = (data[:, 0] - data[0, 0]) / rate if "Frame" in lead else np.arange(data.shape[0]) / rate
    _check_times(t, source, lines)
    return t


def _read_3d(rows, k, columns, meta, rigid_body, units, up_axis, source) -> MarkerData:
    """The markers of a 3D export (`rigid_body` unused: a 3D export holds no bodies)."""
    names = [n.strip() for n in meta.get("MARKER_NAMES", []) if n.strip()]
    if not names:
        count = meta.get("NO_OF_MARKERS", [""])[0].strip()
        raise InputError(
            f"{source}: the take holds no labelled markers (NO_OF_MARKERS {count}, no names in MARKER_NAMES): "
            "label the robot's trajectories in QTM, or define its 6DOF body, and export again."
            if "MARKER_NAMES" in meta or count == "0"
            else f"{source}: no MARKER_NAMES line in the header; export with the TSV header included."
        )
    K = len(names)
    if columns is not None:
        where = {c: j for j, c in enumerate(columns)}
        missing = [f"{n} {a}" for n in names for a in "XYZ" if f"{n} {a}" not in where]
        if missing:
            raise InputError(f"{source}, line {k}: no column {missing[0]!r} for a marker of MARKER_NAMES.")
        lead = [c for c in ("Frame", "Time") if c in where]
        cols = [where[c] for c in lead] + [where[f"{n} {a}"] for n in names for a in "XYZ"]
    else:
        lead = ["Frame", "Time"] if len(rows[k]) >= 3 * K + 2 else []
        cols = list(range(len(lead) + 3 * K))
    data, lines = _numbers(rows, k, cols, source, lead + [f"{n} {a}" for n in names for a in "XYZ"])
    t = _times(data, lead, meta, lines, source)
    raw = data[:, len(lead) :].reshape(-1, K, 3)
    raw[np.all(raw == 0.0, axis=2)] = np.nan  # QTM writes a marker that is not seen as zeros
    markers, _ = fixed_markers(raw, source, units, None, up_axis, fallback="mm")
    return MarkerData(t, markers, tuple(names), source, lines)


def _body_columns(columns: list[str], bodies: list[str], source: str, line: int) -> dict[str, dict[str, int]]:
    """The columns of each body: `{body: {field: column}}`. A column is `<body> <field>` or a bare
    `<field>`. A named column starts that body's group and the bare fields after it belong to it
    (QTM names a body in its `X` column only); a bare `X` outside a group starts the next body of
    `BODY_NAMES`."""
    out: dict[str, dict[str, int]] = {}
    turn, current = -1, None
    for j, c in enumerate(columns):
        head, _, field = c.rpartition(" ")
        if field not in _FIELDS_6D:
            continue
        if head:
            current = head
            turn = bodies.index(head) if head in bodies else turn
        elif current is None or field in out[current]:
            turn += 1
            if turn >= len(bodies):
                raise InputError(f"{source}, line {line}: more 6DOF column groups than BODY_NAMES {bodies}.")
            current = bodies[turn]
        if field in out.get(current, {}):
            raise InputError(f"{source}, line {line}: column {c!r} of body {current!r} appears twice.")
        out.setdefault(current, {})[field] = j
    return out


def _read_6d(rows, k, columns, meta, rigid_body, units, up_axis, source) -> MarkerData:
    """The pose of the 6DOF body `rigid_body` (default: the only one)."""
    bodies = [n.strip() for n in meta.get("BODY_NAMES", []) if n.strip()]
    if not bodies and ("BODY_NAMES" in meta or meta.get("NO_OF_BODIES", [""])[0].strip() == "0"):
        raise InputError(
            f"{source}: the 6DOF export holds no rigid body (no names in BODY_NAMES): define the robot's 6DOF body in "
            "QTM and export again, or export its labelled markers as 3D data."
        )
    if columns is None:
        if len(bodies) != 1:
            raise InputError(f"{source}: 6DOF data without a column row; export again with Include TSV header checked.")
        columns = ["Frame", "Time", *_FIELDS_6D]
    groups = _body_columns(columns, bodies or ["body"], source, k)
    if columns is not None and len(groups) < len(bodies) and not any(" " in c for c in columns):
        groups = _repeated_groups(groups, bodies, rows[k])
    body = choose_body(rigid_body, sorted(groups), source, "6DOF body")
    if body not in groups:
        raise InputError(f"{source}: no 6DOF body named {body!r}; the file has no 6DOF body columns.")
    g = groups[body]
    rot = [f"Rot[{i}]" for i in range(9)]
    euler = ("Roll", "Pitch", "Yaw")
    if not all(f in g for f in "XYZ") or not (all(f in g for f in rot) or all(f in g for f in euler)):
        raise InputError(
            f"{source}, line {k}: the columns of body {body!r} lack X, Y, Z and Rot[0..8] or Roll, Pitch, Yaw."
        )
    angles = sorted(euler, key=g.get) if all(f in g for f in euler) else []  # in the file's order
    fields = ["X", "Y", "Z", *(rot if all(f in g for f in rot) else angles), *(["Residual"] if "Residual" in g else [])]
    lead = [c for c in ("Frame", "Time") if c in columns]
    data, lines = _numbers(rows, k, [columns.index(c) for c in lead] + [g[f] for f in fields], source, lead + fields)
    t = _times(data, lead, meta, lines, source)
    val = {f: data[:, len(lead) + i] for i, f in enumerate(fields)}
    p = np.stack([val[a] for a in "XYZ"], axis=1)
    R = _rotations(val, rot, angles)
    gap = ~np.all(np.isfinite(p), axis=1) | ~np.all(np.isfinite(R), axis=(1, 2)) | np.all(R == 0.0, axis=(1, 2))
    if "Residual" in val:  # QTM writes a body it does not see as zeros with residual -1
        gap |= val["Residual"] < 0
    scale = resolve_units(units, None, None if units != "auto" else "mm", source, EXPORT_UNITS)
    q, p = fixed_pose(R, p, gap, up_axis, scale)
    return MarkerData(t, np.zeros((len(t), 0, 3)), (), source, lines, q, p)


def _rotations(val: dict[str, np.ndarray], rot: list[str], angles: list[str]) -> np.ndarray:
    """The `(M, 3, 3)` body -> global rotations of a 6DOF body from its `Rot[0..8]` (column by
    column), else from its angles `angles` (`Roll`, `Pitch`, `Yaw` in the file's column order),
    applied in that order about the rotated axes: `R_x(roll) R_y(pitch) R_z(yaw)` in QTM's
    standard order, `R_z(yaw) R_y(pitch) R_x(roll)` in QTM 2.x's Yaw, Pitch, Roll columns."""
    if all(f in val for f in rot):
        flat = np.stack([val[f] for f in rot], axis=1)
        return np.swapaxes(flat.reshape(-1, 3, 3), 1, 2)  # Rot[0..2] is the first column
    ang = np.stack([val[f] for f in angles], axis=1)
    ok = np.all(np.isfinite(ang), axis=1)
    R = np.full((ang.shape[0], 3, 3), np.nan)
    if np.any(ok):
        seq = "".join(_AXIS[f] for f in angles)  # upper case: intrinsic, about the rotated axes
        R[ok] = Rotation.from_euler(seq, ang[ok], degrees=True).as_matrix()
    return R


def _repeated_groups(
    groups: dict[str, dict[str, int]], bodies: list[str], first_row: list[str]
) -> dict[str, dict[str, int]]:
    """QTM 2.x's 6DOF export names the fields of one body (` X`, ` Y`, ..., ` Rot[8]`, no body
    name); each body of `BODY_NAMES` has those fields in turn, followed by one blank cell. The
    columns of every body, where the first data row `first_row` is wide enough for them."""
    if len(groups) != 1:
        return groups
    (g,) = groups.values()
    lo, span = min(g.values()), max(g.values()) - min(g.values()) + 1
    stride = span + 1 if lo + span < len(first_row) and not first_row[lo + span].strip() else span
    if _width(first_row) < lo + stride * (len(bodies) - 1) + span:
        return groups
    return {b: {f: j + i * stride for f, j in g.items()} for i, b in enumerate(bodies)}
