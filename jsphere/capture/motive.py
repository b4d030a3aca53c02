"""OptiTrack Motive CSV exports: the reader (`read_motive_csv`) and a writer for tests and examples."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .._runtime.errors import InputError
from .._runtime.files import atomic_write_text
from ..model.rotations import quat_from_rotmat_np, quat_mul_np
from .markers import UNIT_SCALE, UP_TO_Z, MarkerData, _scale, _scale_rb, detect_marker_units
from .text import _check_times, _cut_short, _data_end, _numbers, _read_lines, separator_hint
from .validation import sign_continuous


def read_motive_csv(
    path,
    *,
    rigid_body: str | None = None,
    use: str = "auto",
    units: str = "auto",
    up_axis: str = "y",
    allow_truncated: bool = False,
) -> MarkerData:
    """Read an OptiTrack Motive CSV export (Motive 2 and 3, format version 1.2x and later).

    Layout (https://docs.optitrack.com/motive/data-export/data-export-csv): line 1 `Format
    Version,...,Rotation Type,...,Length Units,Meters|Centimeters|Millimeters,...`; a blank
    line; rows `,Type,...` (`Rigid Body`, `Rigid Body Marker`, `Marker`, `Bone`, `Bone Marker`),
    `,Name,...`, `,ID,...`, in Motive 3 a `,Parent,...` row, a row naming each column's kind
    (`Rotation`, `Position`, `Mean Marker Error`, `Marker Quality`), then `Frame,Time
    (Seconds),X,Y,Z,...`, the columns in any order. Rigid-body rotations are quaternions in the
    order **X, Y, Z, W** (`Rotation Type,Quaternion`); Euler rotation types are read only where
    the rigid body's own pose is not needed (an `InputError` names the setting otherwise).
    Occluded markers are blank cells (gaps). The markers read are the labelled `Marker` columns
    (not the solved `Rigid Body Marker` / `Bone Marker` ones, nor `Unlabeled ...` markers); with
    a rigid body, those named `"<rigid body>:..."` if there are any.

    **Arguments:**
    - `rigid_body`: the asset name; selects that rigid body and the markers named `"<name>:..."`.
      Default: the only rigid body (if any), and every labelled `Marker` column.
    - `use`: `"markers"` (poses from the `Marker` columns by `rigid_body_pose`), `"rigid_body"`
      (Motive's own solved pose, kept in `MarkerData.rb_q/rb_p`), or `"auto"` (markers if there
      are at least 3 marker columns, else the rigid body). The markers are always returned.
    - `units`: `"auto"` (the file's `Length Units`, else detected), `"m"`, `"cm"` or `"mm"`.
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
    meta, file_units = _line_one(rows, source)
    head = _Header.find(rows, source)
    body = _rigid_body(head, rigid_body, source)
    mnames, cols, colnames = _marker_columns(head, body)
    want_rb = use == "rigid_body" or (use == "auto" and len(mnames) < 3)
    if want_rb:
        _check_rotation_type(meta, source)
        need, rb_cols = _rigid_body_columns(head, body, source)
        cols, colnames = cols + rb_cols, colnames + [f"{body} {k[0]} {k[1]}" for k in need]
    declared = int(meta["Total Exported Frames"]) if meta.get("Total Exported Frames", "").isdigit() else None
    end = _cut_short(
        rows,
        head.row + 1,
        _data_end(rows, head.row + 1),
        head.ncol,
        source,
        allow_truncated,
        declared=declared,
        field="Total Exported Frames",
    )
    data, lines = _numbers(rows[:end], head.row + 1, cols, source, colnames)
    if data.shape[0] == 0:
        raise InputError(f"{source}: no data rows after the header 'Frame,Time (Seconds),...' (line {head.row + 1}).")
    t = data[:, 1]
    _check_times(t, lines, source)
    K = len(mnames)
    C = UP_TO_Z[up_axis]
    raw = data[:, 2 : 2 + 3 * K].reshape(len(t), K, 3)
    scale = (
        _scale(units, file_units, detect_marker_units(raw), source) if K >= 2 else _scale_rb(units, file_units, source)
    )
    markers = np.einsum("ij,mkj->mki", C, raw) * scale
    rb_q, rb_p = _rigid_body_pose(data[:, 2 + 3 * K :], C, scale) if want_rb else (None, None)
    return MarkerData(t, markers, tuple(mnames), source, lines, rb_q, rb_p)


def _line_one(rows: list[list[str]], source: str) -> tuple[dict[str, str], str | None]:
    """The key-value pairs of line 1 (`Format Version,1.23,...`) and the length units it declares."""
    if not rows or not rows[0] or rows[0][0].strip() != "Format Version":
        raise ValueError(
            f"{source}, line 1: not a Motive CSV export (expected 'Format Version,...'); export with the header on"
            f"{separator_hint(rows[0][:1]) if rows and rows[0] else ''}."
        )
    meta = {rows[0][i].strip(): rows[0][i + 1].strip() for i in range(0, len(rows[0]) - 1, 2)}
    file_units = _LENGTH_UNITS.get(meta.get("Length Units", ""), None)
    if meta.get("Length Units") and file_units is None:
        raise InputError(
            f"{source}, line 1: Length Units {meta['Length Units']!r} not understood; export in Meters, Centimeters or "
            "Millimeters."
        )
    return meta, file_units


#: Motive's `Length Units` and jsphere's names for them
_LENGTH_UNITS = {"Meters": "m", "Centimeters": "cm", "Millimeters": "mm"}


def _check_rotation_type(meta: dict[str, str], source: str) -> None:
    """Raise `InputError` unless the rigid-body rotations are quaternions (Motive's Euler types
    `XYZ`, `XZY`, ... leave the convention of their angles to the reader)."""
    kind = meta.get("Rotation Type", "Quaternion")
    if kind != "Quaternion":
        raise InputError(
            f"{source}, line 1: Rotation Type is {kind!r} (Euler angles), and the rigid body's own pose is needed; "
            "export again with the CSV export option Rotation Type = Quaternion, or export at least 3 markers."
        )


@dataclass(frozen=True)
class _Header:
    """The header rows of a Motive export: per column its `Type`, `Name`, kind (`Rotation`,
    `Position`, ...) and axis; `row`: the index of the row `Frame,Time (Seconds),...`."""

    types: list[str]
    names: list[str]
    kinds: list[str]
    axes: list[str]
    row: int

    @classmethod
    def find(cls, rows: list[list[str]], source: str) -> _Header:
        def find(label: str, col: int = 1) -> int:
            for i, r in enumerate(rows):
                if len(r) > col and r[col].strip() == label:
                    return i
            raise ValueError(f"{source}: no '{label}' header row; is this a Motive CSV export with the header on?")

        i_type, i_name = find("Type"), find("Name")
        i_hdr = find("Frame", 0)
        if rows[i_hdr][1].strip() != "Time (Seconds)":
            raise ValueError(f"{source}, line {i_hdr + 1}: expected 'Frame,Time (Seconds),...'; got {rows[i_hdr][:2]}.")
        return cls(rows[i_type], rows[i_name], rows[i_hdr - 1], rows[i_hdr], i_hdr)

    @property
    def ncol(self) -> int:
        return len(self.axes)

    def cell(self, row: str, j: int) -> str:
        r = getattr(self, row)
        return r[j].strip() if j < len(r) else ""


def _rigid_body(head: _Header, rigid_body: str | None, source: str) -> str | None:
    """The rigid body to read: `rigid_body`, or the file's only one (None where it has none)."""
    bodies = sorted({head.cell("names", j) for j in range(2, head.ncol) if head.cell("types", j) == "Rigid Body"})
    if rigid_body is not None and bodies and rigid_body not in bodies:
        raise ValueError(f"{source}: no rigid body named {rigid_body!r}; the file has {bodies}.")
    if rigid_body is None and len(bodies) > 1:
        raise ValueError(f"{source}: the file has several rigid bodies {bodies}; pass rigid_body=<name>.")
    return rigid_body if rigid_body is not None else (bodies[0] if bodies else None)


def _marker_columns(head: _Header, body: str | None) -> tuple[list[str], list[int], list[str]]:
    """The labelled markers (raw positions, not the solved `Rigid Body Marker` columns) of `body`
    with X, Y and Z columns: their names, and the columns to read (frame, time, then X, Y, Z of
    each marker) with their names."""
    mk: dict[str, dict[str, int]] = {}
    for j in range(2, head.ncol):
        nm = head.cell("names", j)
        if head.cell("types", j) != "Marker" or head.cell("kinds", j) != "Position" or nm.startswith("Unlabeled"):
            continue
        if body is not None and ":" in nm and nm.split(":")[0] != body:
            continue
        mk.setdefault(nm, {})[head.cell("axes", j)] = j
    mk = {n: c for n, c in mk.items() if set(c) >= {"X", "Y", "Z"}}
    if body is not None and any(n.startswith(f"{body}:") for n in mk):  # the body's own markers, not stray ones
        mk = {n: c for n, c in mk.items() if n.startswith(f"{body}:")}
    mnames = list(mk)
    cols = [0, 1] + [mk[n][a] for n in mnames for a in "XYZ"]
    colnames = ["Frame", "Time (Seconds)"] + [f"{n} {a}" for n in mnames for a in "XYZ"]
    return mnames, cols, colnames


def _rigid_body_columns(head: _Header, body: str | None, source: str) -> tuple[list[tuple[str, str]], list[int]]:
    """The columns of the rigid body's Rotation X, Y, Z, W and Position X, Y, Z."""
    rb_cols = {}
    if body is not None:
        for j in range(2, head.ncol):
            if head.cell("types", j) == "Rigid Body" and head.cell("names", j) == body:
                rb_cols[(head.cell("kinds", j), head.cell("axes", j))] = j
    need = [("Rotation", a) for a in "XYZW"] + [("Position", a) for a in "XYZ"]
    if not all(k in rb_cols for k in need):
        raise ValueError(
            f"{source}: no complete rigid-body columns (Rotation X,Y,Z,W and Position X,Y,Z) and fewer than 3 "
            "marker columns; export the rigid body or its markers."
        )
    return need, [rb_cols[k] for k in need]


def _rigid_body_pose(rb: np.ndarray, C: np.ndarray, scale: float) -> tuple[np.ndarray, np.ndarray]:
    """Motive's solved pose (columns Rotation X, Y, Z, W, Position X, Y, Z) in jsphere's frame:
    `(q (M, 4), p (M, 3))`."""
    q_m = rb[:, [3, 0, 1, 2]]  # (X, Y, Z, W) -> (w, x, y, z)
    q_C = quat_from_rotmat_np(C)
    q = sign_continuous(quat_mul_np(np.broadcast_to(q_C, q_m.shape), q_m))  # C R_m
    return q, rb[:, 4:7] @ C.T * scale


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
    s = 1.0 / UNIT_SCALE[units]
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
            r=1.0 / float(np.median(np.diff(t))), u={v: k for k, v in _LENGTH_UNITS.items()}[units]
        ),
        "",
        ",Type," + ",".join(types),
        ",Name," + ",".join(nms),
        ",ID," + ",".join(ids),
        ",," + ",".join(kinds),
        "Frame,Time (Seconds)," + ",".join(axes),
    ]
    length_fmt = {"m": ".6f", "cm": ".4f", "mm": ".3f"}[units]
    fmts = [".6f" if k in ("Rotation", "Mean Marker Error") else length_fmt for k in kinds]
    data = np.concatenate(blocks, axis=1)
    for i in range(M):
        cells = ["" if not np.isfinite(v) else format(v + 0.0, f) for v, f in zip(data[i], fmts)]
        lines.append(",".join([str(i), f"{t[i]:.6f}", *cells]))
    atomic_write_text(path, "\n".join(lines) + "\n")
