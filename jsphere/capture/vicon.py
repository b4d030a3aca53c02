"""Vicon Nexus "Trajectories" CSV exports: the reader (`read_vicon_csv`) and a writer for tests and
examples."""

from __future__ import annotations

import numpy as np

from .._runtime.errors import InputError
from .._runtime.files import atomic_write_text
from .markers import MarkerData, fixed_markers, open_export
from .text import _cut_short, _data_end, _numbers, cells, separator_hint
from .validation import _check_times


def read_vicon_csv(
    path, *, subject: str | None = None, units: str = "auto", up_axis: str = "z", allow_truncated: bool = False
) -> MarkerData:
    """Read the `Trajectories` section of a Vicon Nexus 2 CSV export (Vicon Nexus reference
    guide, "Export data to a CSV file"): a line with the section's name, the rate [Hz], a row of
    names (`Subject:Marker` in the column of each marker's X), `Frame,Sub Frame,X,Y,Z,...`, a
    units row and one row per frame, up to a blank line; other sections (`Devices`, `Joints`,
    ...) are skipped. Blank cells are gaps; unlabelled trajectories (`*N`) are left out. Time is
    `(Frame - first Frame) / rate` [s] (`Sub Frame` must be 0).

    `subject`: keeps the markers `"<subject>:..."` (default: the only subject). `units`:
    `"auto"` (the units row), `"m"` or `"mm"`. `up_axis`: Vicon is Z-up by default.
    `allow_truncated`: as in `ConvertOptions`.
    """
    source, rows = open_export(path, up_axis)
    i0, rate, file_units = _section(rows, source)
    mk = _markers(rows[i0 + 2], rows[i0 + 3], subject, source, i0 + 3)
    cols = [0, 1] + [j + a for _, j in mk for a in range(3)]
    colnames = ["Frame", "Sub Frame"] + [f"{n} {a}" for n, _ in mk for a in "XYZ"]
    end = next((i for i in range(i0 + 5, len(rows)) if not any(c.strip() for c in rows[i])), len(rows))
    if _data_end(rows, end) == end:  # the section runs to the end of the file: it may have been cut off
        end = _cut_short(rows, i0 + 5, end, len(rows[i0 + 3]), source, allow_truncated)
    data, lines = _numbers(rows[:end], i0 + 5, cols, source, colnames)  # the section ends at a blank line
    if data.shape[0] == 0:
        raise InputError(f"{source}: no data rows after the units row (line {i0 + 5}).")
    sub = np.nonzero(np.nan_to_num(data[:, 1]) != 0)[0]
    if sub.size:
        raise ValueError(
            f"{source}, line {lines[sub[0]]}: Sub Frame is not 0; export the trajectories at the camera rate."
        )
    t = (data[:, 0] - data[0, 0]) / rate
    _check_times(t, source, lines)
    markers, _ = fixed_markers(data[:, 2:].reshape(len(t), len(mk), 3), source, units, file_units, up_axis)
    return MarkerData(t, markers, tuple(n for n, _ in mk), source, lines)


def _section(rows: list[list[str]], source: str) -> tuple[int, float, str | None]:
    """The `Trajectories` section: the index of its first row, its rate [Hz] and the units of
    its units row (None where blank), its `Frame,Sub Frame,...` row checked."""
    i0 = next((i for i, r in enumerate(rows) if r and r[0].strip() == "Trajectories"), None)
    if i0 is None:
        hint = next((separator_hint(r[:1]) for r in rows if r and r[0].strip().startswith("Trajectories")), "")
        raise ValueError(
            f"{source}: no 'Trajectories' section; export the marker trajectories from Nexus as CSV{hint}."
        )
    try:
        rate = float(rows[i0 + 1][0])
    except (IndexError, ValueError):
        raise ValueError(f"{source}, line {i0 + 2}: expected the frame rate [Hz] after 'Trajectories'.") from None
    if not rate > 0:
        raise ValueError(f"{source}, line {i0 + 2}: the frame rate must be positive; got {rate}.")
    hdr = rows[i0 + 3]
    if len(hdr) < 2 or hdr[0].strip() != "Frame" or hdr[1].strip() != "Sub Frame":
        raise ValueError(f"{source}, line {i0 + 4}: expected 'Frame,Sub Frame,X,Y,Z,...'{separator_hint(hdr[:1])}.")
    unit_row = rows[i0 + 4] if len(rows) > i0 + 4 else []
    found_units = {c.strip() for c in unit_row[2:] if c.strip()}
    if not found_units <= {"mm", "m"} or len(found_units) > 1:
        raise ValueError(f"{source}, line {i0 + 5}: units row {sorted(found_units)} not understood; expected mm or m.")
    return i0, rate, found_units.pop() if found_units else None


def _markers(names: list[str], hdr: list[str], subject: str | None, source: str, line: int) -> list[tuple[str, int]]:
    """The labelled markers of `subject` (default: the only one) as `(name, column of its X)`,
    from the names row `names` (line `line`) and the `Frame,Sub Frame,X,Y,Z,...` row `hdr`."""
    named = [
        (nm, j)
        for j in range(2, len(hdr) - 2)
        if (nm := names[j].strip() if j < len(names) else "") and hdr[j].strip() == "X" and not nm.startswith("*")
    ]
    subjects = sorted({nm.split(":")[0] for nm, _ in named if ":" in nm})
    if subject is None and len(subjects) > 1:
        raise InputError(
            f"{source}, line {line}: the trajectories hold several subjects {subjects}; choose one with --subject NAME."
        )
    if subject is not None and subject not in subjects:
        raise InputError(
            f"{source}, line {line}: no subject {subject!r} in the trajectories; "
            + (f"the file has {subjects}." if subjects else "its markers have no 'Subject:' prefix: drop --subject.")
        )
    subject = subject or (subjects[0] if subjects else None)
    mk = [(nm, j) for nm, j in named if subject is None or nm.split(":")[0] == subject]
    if not mk:
        unlabelled = sum(1 for j in range(2, len(hdr) - 2) if hdr[j].strip() == "X") - len(named)
        raise InputError(
            f"{source}, line {line}: the trajectories hold no labelled markers"
            + (f" (only {unlabelled} unlabelled ones, '*N')" if unlabelled else "")
            + ": label the robot's markers in Nexus (or give them a subject) and export the trajectories again."
        )
    return mk


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
    frames = np.round((np.asarray(t, float) - t[0]) * rate) + 1
    data = np.column_stack([frames, np.zeros(len(frames)), raw.reshape(len(frames), -1)])
    lines += cells(data, [".0f", ".0f"] + [".6f" if units == "m" else ".3f"] * 3 * K)
    atomic_write_text(path, "\n".join(lines) + "\n")
