"""OptiTrack Motive CSV exports: the reader (`read_motive_csv`) and a writer for tests and examples."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .._runtime.errors import InputError
from .._runtime.files import atomic_write_text
from ..model.rotations import quat_from_rotmat_np, quat_mul_np, rotmat_np
from .markers import UP_TO_Z, MarkerData, choose_body, fixed_markers, fixed_pose, open_export
from .text import _cut_short, _numbers, cells, separator_hint
from .units import UNIT_SCALE
from .validation import _check_times


def read_motive_csv(
    path,
    *,
    rigid_body: str | None = None,
    use: str = "auto",
    units: str = "auto",
    up_axis: str = "y",
    allow_truncated: bool = False,
) -> MarkerData:
    """Read an OptiTrack Motive CSV export (Motive 2 and 3: CSV format 1.21 and later; layout:
    `docs/capture.md`, after https://docs.optitrack.com/motive/data-export/data-export-csv).
    Older layouts (Motive 1.x) are an `InputError` naming the version.

    The markers read are the labelled `Marker` columns (not the solved `Rigid Body Marker` /
    `Bone Marker` ones, nor `Unlabeled ...`), blank cells gaps; with a rigid body, those named
    `"<rigid body>:..."` if there are any. The rigid body's `Mean Marker Error` (`Error Per
    Marker`) is kept in `MarkerData.marker_error`. A take with neither labelled markers nor a
    rigid body is an `InputError`.

    - `rigid_body`: the asset to read (default: the only one, if any).
    - `use`: `"markers"`, `"rigid_body"` (Motive's solved pose, as quaternions X, Y, Z, W, kept
      in `MarkerData.rb_q/rb_p`) or `"auto"` (markers if there are at least 3, else the rigid
      body). The markers are always returned.
    - `units`, `allow_truncated`: as in `ConvertOptions` (`"auto"`: line 1's `Length Units`,
      else detected; cut short: fewer rows than line 1's `Total Exported Frames`).
    - `up_axis`: `"y"` (Motive's default: turned Z-up by `UP_TO_Z["y"]`) or `"z"`.
    """
    source, rows = open_export(path, up_axis, quote="'")
    if use not in ("auto", "markers", "rigid_body"):
        raise ValueError(
            f"read_motive_csv: use must be 'auto', 'markers' or 'rigid_body' (what to read of {source}); got {use!r}."
        )
    meta, file_units = _line_one(rows, source)
    head = _Header.find(rows, source)
    body = choose_body(rigid_body, sorted({head.cell("names", j) for j in head.columns("Rigid Body")}), source)
    mnames, cols, colnames = _marker_columns(head, body)
    _check_has_data(head, body, mnames, source)
    want_rb = use == "rigid_body" or (use == "auto" and len(mnames) < 3)
    if want_rb:
        need, rb_cols = _rigid_body_columns(head, body, len(mnames), meta, source)
        cols, colnames = cols + rb_cols, colnames + [f"{body} {k[0]} {k[1]}" for k in need]
    errors = ("Mean Marker Error", "Error Per Marker")  # the rigid body's own marker error (format 1.21: the second)
    err = [j for j in head.columns("Rigid Body", body) if head.cell("kinds", j) in errors][:1] if body else []
    cols, colnames = cols + err, colnames + [f"{body} {head.cell('kinds', j)}" for j in err]
    declared = int(meta["Total Exported Frames"]) if meta.get("Total Exported Frames", "").isdigit() else None
    end = _cut_short(
        rows, head.row + 1, None, head.ncol, source, allow_truncated, declared=declared, field="Total Exported Frames"
    )
    data, lines = _numbers(rows[:end], head.row + 1, cols, source, colnames)
    if data.shape[0] == 0:
        raise InputError(f"{source}: no data rows after the header 'Frame,{head.time},...' (line {head.row + 1}).")
    t = data[:, 1]
    _check_times(t, source, lines)
    K = len(mnames)
    markers, scale = fixed_markers(data[:, 2 : 2 + 3 * K].reshape(len(t), K, 3), source, units, file_units, up_axis)
    rb_q = rb_p = None
    if want_rb:  # Motive's solved pose: Rotation X, Y, Z, W (scalar last), Position X, Y, Z
        rb = data[:, 2 + 3 * K : 9 + 3 * K]
        q = rb[:, [3, 0, 1, 2]]
        gap = ~np.all(np.isfinite(rb), axis=1) | ~(np.linalg.norm(q, axis=1) > 0)
        R = rotmat_np(np.where(gap[:, None], [1.0, 0.0, 0.0, 0.0], q))
        rb_q, rb_p = fixed_pose(R, rb[:, 4:7], gap, up_axis, scale)
    error = data[:, -1] * scale if err else None
    return MarkerData(t, markers, tuple(mnames), source, lines, rb_q, rb_p, error)


def _line_one(rows: list[list[str]], source: str) -> tuple[dict[str, str], str | None]:
    """The key-value pairs of line 1 (`Format Version,1.23,...`) and the length units it declares."""
    if rows and rows[0] and rows[0][0].strip().lower() in ("comment", "info"):
        version = next(
            (r[2].strip() for r in rows[:20] if len(r) > 2 and [c.strip() for c in r[:2]] == ["info", "version"]), ""
        )
        raise InputError(
            f"{source}: a Motive CSV export of format version {version or '1.1 or older'} (Motive 1.x), an older layout "
            "that jsphere does not read; export the take again from Motive 2 or later (CSV format 1.21 or later)."
        )
    if not rows or not rows[0] or rows[0][0].strip() != "Format Version":
        raise ValueError(
            f"{source}, line 1: not a Motive CSV export (expected 'Format Version,...'); export with the header on"
            f"{separator_hint(rows[0][:1]) if rows and rows[0] else ''}."
        )
    meta = {rows[0][i].strip(): rows[0][i + 1].strip() for i in range(0, len(rows[0]) - 1, 2)}
    version = meta.get("Format Version", "")
    try:
        old = float(version) < MIN_FORMAT_VERSION
    except ValueError:
        old = False
    if old:
        raise InputError(
            f"{source}, line 1: Motive CSV format version {version}, an older layout that jsphere does not read "
            f"(it reads {MIN_FORMAT_VERSION:g} and later); export the take again from Motive 2 or later."
        )
    file_units = _LENGTH_UNITS.get(meta.get("Length Units", ""), None)
    if meta.get("Length Units") and file_units is None:
        raise InputError(
            f"{source}, line 1: Length Units {meta['Length Units']!r} not understood; export in Meters, Centimeters or "
            "Millimeters."
        )
    return meta, file_units


#: the oldest Motive CSV format version read (Motive 1.9 / 2.0); older layouts are refused
MIN_FORMAT_VERSION = 1.21
#: Motive's `Length Units` and jsphere's names for them
_LENGTH_UNITS = {"Meters": "m", "Centimeters": "cm", "Millimeters": "mm"}


@dataclass(frozen=True)
class _Header:
    """The header rows of a Motive export: per column its `Type`, `Name`, kind (`Rotation`,
    `Position`, ...) and axis; `row`: the index of the row `Frame,Time (Seconds),...`; `time`:
    the time column's name (`Time (Seconds)`, or `Time` in format 1.21)."""

    types: list[str]
    names: list[str]
    kinds: list[str]
    axes: list[str]
    row: int
    time: str

    @classmethod
    def find(cls, rows: list[list[str]], source: str) -> _Header:
        i_hdr = next((i for i, r in enumerate(rows) if r and r[0].strip() == "Frame"), None)
        if i_hdr is None:
            raise InputError(
                f"{source}: no 'Frame,Time (Seconds),...' header row; export the take from Motive as CSV with the "
                "header on."
            )
        time = rows[i_hdr][1].strip() if len(rows[i_hdr]) > 1 else ""
        if time not in ("Time (Seconds)", "Time"):
            raise InputError(
                f"{source}, line {i_hdr + 1}: expected 'Frame,Time (Seconds),...'; got {rows[i_hdr][:2]}; export the "
                "take from Motive as CSV with the header on."
            )

        def labelled(label: str) -> int | None:
            return next((i for i, r in enumerate(rows[:i_hdr]) if len(r) > 1 and r[1].strip() == label), None)

        i_type, i_name = labelled("Type"), labelled("Name")
        if i_type is None:  # format 1.21: the rows after line 1's blank line, their first two cells blank
            head = [i for i in range(1, i_hdr) if any(c.strip() for c in rows[i])]
            if len(head) < 4:
                raise InputError(
                    f"{source}: {len(head)} header row(s) between line 1 and the 'Frame' row (line {i_hdr + 1}); a "
                    "Motive export has its type, name, ID and kind rows there: export the take again with the header on."
                )
            i_type, i_name = head[0], head[1]
        return cls(rows[i_type], rows[i_name] if i_name is not None else [], rows[i_hdr - 1], rows[i_hdr], i_hdr, time)

    @property
    def ncol(self) -> int:
        return len(self.axes)

    def columns(self, kind: str, name: str | None = None) -> list[int]:
        """The data columns of the `Type` `kind` (`Marker`, `Rigid Body`, ...), of `name` where given."""
        return [
            j
            for j in range(2, self.ncol)
            if self.cell("types", j) == kind and (name is None or self.cell("names", j) == name)
        ]

    def cell(self, row: str, j: int) -> str:
        r = getattr(self, row)
        return r[j].strip() if j < len(r) else ""


def _marker_columns(head: _Header, body: str | None) -> tuple[list[str], list[int], list[str]]:
    """The labelled markers (raw positions, not the solved `Rigid Body Marker` columns) of `body`
    with X, Y and Z columns: their names, and the columns to read (frame, time, then X, Y, Z of
    each marker) with their names."""
    mk: dict[str, dict[str, int]] = {}
    for j in head.columns("Marker"):
        nm = head.cell("names", j)
        if head.cell("kinds", j) != "Position" or nm.startswith("Unlabeled"):
            continue
        if body is not None and ":" in nm and nm.split(":")[0] != body:
            continue
        mk.setdefault(nm, {})[head.cell("axes", j)] = j
    mk = {n: c for n, c in mk.items() if set(c) >= {"X", "Y", "Z"}}
    if body is not None and any(n.startswith(f"{body}:") for n in mk):  # the body's own markers, not stray ones
        mk = {n: c for n, c in mk.items() if n.startswith(f"{body}:")}
    mnames = list(mk)
    cols = [0, 1] + [mk[n][a] for n in mnames for a in "XYZ"]
    colnames = ["Frame", head.time] + [f"{n} {a}" for n in mnames for a in "XYZ"]
    return mnames, cols, colnames


def _check_has_data(head: _Header, body: str | None, mnames: list[str], source: str) -> None:
    """`InputError` for a take with neither labelled markers nor a rigid body (only `Unlabeled`
    markers, or no columns at all): nothing in it follows the robot."""
    if mnames or body is not None:
        return
    unlabelled = {head.cell("names", j) for j in range(2, head.ncol) if head.cell("names", j).startswith("Unlabeled")}
    what = f"only {len(unlabelled)} unlabelled marker(s)" if unlabelled else "no marker or rigid-body columns"
    raise InputError(
        f"{source}: the take holds no labelled markers or rigid body ({what}); in Motive, define a rigid body on "
        "the robot's markers (or label them), then export the take again with its markers or rigid body."
    )


def _rigid_body_columns(
    head: _Header, body: str | None, n_markers: int, meta: dict[str, str], source: str
) -> tuple[list[tuple[str, str]], list[int]]:
    """The columns of the rigid body's Rotation X, Y, Z, W and Position X, Y, Z; `InputError`
    unless its rotations are quaternions (line 1's `Rotation Type`: Motive's Euler types `XYZ`,
    `XZY`, ... leave the convention of their angles to the reader)."""
    kind = meta.get("Rotation Type", "Quaternion")
    if kind != "Quaternion":
        raise InputError(
            f"{source}, line 1: Rotation Type is {kind!r} (Euler angles), and the rigid body's own pose is needed; "
            "export again with the CSV export option Rotation Type = Quaternion, or export at least 3 markers."
        )
    rb_cols = {}
    if body is not None:
        rb_cols = {(head.cell("kinds", j), head.cell("axes", j)): j for j in head.columns("Rigid Body", body)}
    need = [("Rotation", a) for a in "XYZW"] + [("Position", a) for a in "XYZ"]
    if not all(k in rb_cols for k in need):
        where = f"rigid body {body!r} lacks its Rotation or Position columns" if body else "the take has no rigid body"
        raise InputError(
            f"{source}: no complete rigid-body columns ({where}) and fewer than 3 marker columns ({n_markers} labelled "
            "marker(s) of the body); a pose needs the rigid body's Rotation X, Y, Z, W and Position X, Y, Z, or 3 "
            "labelled markers: export them from Motive."
        )
    return need, [rb_cols[k] for k in need]


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
    M = raw.shape[0]
    # each column's Type, Name, ID, kind and axis
    cols = [("Marker", f"{rigid_body}:{n}", f"{k + 2}", "Position", a) for k, n in enumerate(names) for a in "XYZ"]
    blocks = [raw.reshape(M, -1)]
    if rb_q is not None:
        q_m = quat_mul_np(np.broadcast_to(quat_from_rotmat_np(C.T), np.shape(rb_q)), np.asarray(rb_q, float))  # C^T R
        p_m = np.asarray(rb_p, float) @ C * s
        blocks.insert(0, np.concatenate([q_m[:, [1, 2, 3, 0]], p_m, np.zeros((M, 1))], axis=1))
        fields = [("Rotation", a) for a in "XYZW"] + [("Position", a) for a in "XYZ"] + [("Mean Marker Error", "")]
        cols = [("Rigid Body", rigid_body, "1", kind, a) for kind, a in fields] + cols
    types, nms, ids, kinds, axes = zip(*cols)
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
    data = np.column_stack([np.arange(M), t, *blocks])
    lines += cells(data, [".0f", ".6f"] + fmts)
    atomic_write_text(path, "\n".join(lines) + "\n")
