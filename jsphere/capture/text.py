"""Reading capture text files: encodings, CSV rows, numeric cells, input columns and exports cut
short, shared by the trial, inputs, body-marker and raw-export readers."""

from __future__ import annotations

import codecs
import csv
import io
import math
import re
from collections.abc import Iterable, Sequence
from pathlib import Path

import numpy as np

from .._runtime.errors import InputError
from .validation import INPUT_PREFIX, warn


def read_text(path) -> str:
    """The text of a CSV file: UTF-8 with or without a byte-order mark (a spreadsheet's "CSV
    UTF-8"), or UTF-16 with one. Another encoding (Latin-1 cannot be told from other code pages,
    so it is not guessed) or a binary file (a NUL byte: a C3D or a spreadsheet's own format) is
    an `InputError` naming the file, the line and the byte.
    """
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"{path} does not exist.")
    raw = path.read_bytes()
    if raw.startswith((codecs.BOM_UTF16_LE, codecs.BOM_UTF16_BE)):
        try:
            return raw.decode("utf-16")
        except UnicodeDecodeError as e:
            raise InputError(
                f"{path}: starts like UTF-16 text but does not decode as UTF-16 ({e.reason}); save it as UTF-8 CSV."
            ) from None
    if b"\x00" in raw:
        line = raw.count(b"\n", 0, raw.index(b"\x00")) + 1
        c3d = len(raw) >= 512 and raw[1] == 0x50
        raise InputError(
            f"{path}, line {line}: a binary file, not CSV text (it holds a NUL byte)"
            + (
                "; it looks like a C3D file: read it with jsphere convert --format c3d."
                if c3d
                else "; give the CSV export of the data."
            )
        )
    try:
        return raw.decode("utf-8-sig")
    except UnicodeDecodeError as e:
        line = raw.count(b"\n", 0, e.start) + 1
        raise InputError(
            f"{path}, line {line}: not UTF-8 text (byte 0x{raw[e.start]:02x} at byte {e.start}: {e.reason}); the file "
            "is in another encoding, e.g. Latin-1 or Windows-1252: save it as UTF-8 (in a spreadsheet: 'CSV UTF-8')."
        ) from None


def cells(data: np.ndarray, formats: Sequence[str]) -> list[str]:
    """The rows of `data` as written lines, each column in its format of `formats`: blank where
    a value is not finite (a gap), never `-0`."""
    return [
        ",".join("" if not np.isfinite(v) else format(v + 0.0, f) for v, f in zip(row, formats))
        for row in np.asarray(data, float)
    ]


def separator_hint(header: Sequence[str]) -> str:
    """`"; ..."` advice when a header row read as CSV is one cell holding `;` or a tab (a
    spreadsheet that saved with another separator), else `""`."""
    cells = [c for c in header if c.strip()]
    for sep, name in ((";", "semicolons"), ("\t", "tabs")):
        if len(cells) == 1 and sep in cells[0]:
            return (
                f"; the columns are separated by {name}, not commas (a spreadsheet's regional setting): save it as CSV "
                "with commas between the columns and points as decimal marks"
            )
    return ""


def check_unique_columns(header: Sequence[str], source: str, wanted: Iterable[str]) -> None:
    """Raise `InputError` if one of the `wanted` columns appears twice in `header` (which one
    would be read is a guess)."""
    for name in wanted:
        where = [j + 1 for j, h in enumerate(header) if h == name]
        if len(where) > 1:
            raise InputError(f"{source}: column {name!r} appears {len(where)} times (columns {where}); keep one.")


def csv_rows(text: str, source: str, delimiter: str = ",") -> list[list[str]]:
    """`text` split into CSV rows (`csv.reader`; `delimiter`: a tab for TSV); a malformed file
    is an `InputError` naming it."""
    try:
        return list(csv.reader(io.StringIO(text, newline=""), delimiter=delimiter))
    except csv.Error as e:
        raise InputError(f"{source}: not a readable CSV file ({e}).") from None


#: a comment line `# key: value` (or `# key = value`)
_META = re.compile(r"^#\s*(\w+)\s*[:=]\s*(.*?)\s*$")


def comments(rows: list[list[str]]) -> tuple[dict[str, str], int]:
    """The `# key: value` comments of the lines before the header row (lines starting with `#`,
    and blank ones) as `{key: value}` (keys in lower case), and the index of the header row
    (`len(rows)` where there is none)."""
    meta, k = {}, 0
    while k < len(rows) and (not any(c.strip() for c in rows[k]) or rows[k][0].lstrip().startswith("#")):
        if m := _META.match(",".join(rows[k]).strip()):
            meta[m.group(1).lower()] = m.group(2)
        k += 1
    return meta, k


def headed_rows(path, needs: str, what: str = "trial file") -> tuple[str, dict[str, str], list[list[str]], int]:
    """A table read up to its header: `(source, comments, rows, k)`, `rows[k]` the header row
    (line `k + 1`). A missing file is a `FileNotFoundError` naming it as
    `what`, a file without a header row an `InputError` ending in `needs` (what it must name)."""
    path, rows = _read_lines(path, what)
    meta, k = comments(rows)
    if k == len(rows):
        raise InputError(f"{path}: no header line; {needs}.")
    return str(path), meta, rows, k


#: the end of the error for a trial with both input families
_BOTH = "; a trial holds one kind of input (wheel speeds or torques): keep one set of columns."


def _input_columns(header: list[str], source: str, want: str | None = None, both: str = _BOTH) -> tuple[str, list[int]]:
    """The kind and the column indices of `chi_dot_1..N` or `K_1..N`, in wheel order: those of
    the kind `want` where given (the other family's columns ignored), else of the one family
    of `header` (a header with both is an error ending in `both`)."""
    found = {}
    for kind, prefix in INPUT_PREFIX.items():
        pat = re.compile(rf"^{re.escape(prefix)}(\d+)$")
        cols = {int(m.group(1)): j for j, h in enumerate(header) if (m := pat.match(h))}
        if cols:
            found[kind] = cols
    if want is not None:
        if want not in found:
            raise ValueError(
                f"{source}: no {INPUT_PREFIX[want]}1..N columns for input kind {want!r}; the table has {', '.join(header)}."
            )
        found = {want: found[want]}
    if len(found) == 2:
        raise ValueError(f"{source}: both chi_dot_* and K_* columns are present{both}")
    if not found:
        raise ValueError(
            f"{source}: no input columns; add chi_dot_1..chi_dot_N (wheel speeds, rad/s) or K_1..K_N (torques, N m). "
            f"Header: {header}"
        )
    kind, cols = next(iter(found.items()))
    n = max(cols)
    missing = [i for i in range(1, n + 1) if i not in cols]
    if missing:
        prefix = INPUT_PREFIX[kind]
        raise ValueError(
            f"{source}: wheel columns must be numbered 1..N without gaps; missing {', '.join(f'{prefix}{i}' for i in missing)} "
            f"(found {', '.join(f'{prefix}{i}' for i in sorted(cols))})."
        )
    return kind, [cols[i] for i in range(1, n + 1)]


def _parse_cell(cell: str, source: str, line: int, column: str) -> float:
    s = cell.strip()
    if s == "":
        return math.nan
    try:
        return float(s)
    except ValueError:
        raise ValueError(f"{source}, line {line}, column {column}: {s!r} is not a number.") from None


def _read_lines(path, what: str = "capture file", delimiter: str = ",") -> tuple[Path, list[list[str]]]:
    """The CSV rows of a text file (`read_text`); a missing file is a `FileNotFoundError` naming
    it as `what`."""
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"{what} {path} does not exist.")
    return path, csv_rows(read_text(path), str(path), delimiter)


def _data_end(rows, start: int, end: int | None = None) -> int:
    """The end of the data rows `rows[start:end]` without the trailing empty rows."""
    end = len(rows) if end is None else end
    while end > start and not any(c.strip() for c in rows[end - 1]):
        end -= 1
    return end


def _cut_short(
    rows,
    start: int,
    end: int | None,
    ncols: int,
    source: str,
    allow: bool,
    *,
    declared: int | None = None,
    field: str = "",
    noun: str = "frames",
) -> int:
    """Check the data rows `rows[start:end]` of an export for a file that was cut short: a last
    row with fewer cells than the header row (`ncols`: the copy or the export broke off
    mid-row), or fewer rows than the header declares (`declared`, from its `field`). Raises an
    `InputError` naming the file and both counts; with `allow`, issues a `CaptureWarning`
    instead. Returns the end of the complete rows (the cut row is dropped; `end` None: the end
    of the rows without the trailing empty ones)."""
    end = _data_end(rows, start) if end is None else end
    cut_row = end > start and len(rows[end - 1]) < ncols
    n = end - start - int(cut_row)
    parts = []
    if declared is not None and n < declared:
        parts.append(f"the header declares {declared} {noun} ({field}) but the file holds {n}")
    if cut_row:
        parts.append(f"its last row (line {end}) has {len(rows[end - 1])} of {ncols} cells, cut off mid-row")
    if parts:
        cut_short(source, "; ".join(parts), n, f"complete {noun}", allow, stacklevel=4)
    return end - int(cut_row)


def cut_short(source: str, what: str, n: int, noun: str, allow: bool, stacklevel: int = 3) -> None:
    """Raise an `InputError` for a file cut short (`what`: how, with both counts); with `allow`
    and `n > 0`, issue a `CaptureWarning` instead: the `n` `noun` (`"complete frames"`) are used."""
    if not allow or n == 0:
        raise InputError(
            f"{source}: the file is cut short: {what} (the copy or the export broke off). Export or copy it again"
            + (f", or pass --allow-truncated to use the {n} {noun}." if n else ".")
        )
    warn(f"{source}: the file is cut short: {what}; using the {n} {noun}.", stacklevel=stacklevel)


def _numbers(
    rows, start: int, cols: list[int], source: str, names: list[str], *, width: int | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Parse `rows[start:]` at `cols` into floats (blank -> NaN); trailing empty rows dropped.
    Returns `(data, lines)` with the rows' 1-based lines in the file. With `width`, a row with another number of cells is an error naming its line
    (a last row with fewer: a file cut off)."""
    body = rows[start : _data_end(rows, start)]
    data = np.full((len(body), len(cols)), np.nan)
    lines = np.arange(len(body)) + start + 1
    for i, row in enumerate(body):
        if width is not None and len(row) != width:
            cut = (
                " (the file looks cut off: copy or export it again)" if i == len(body) - 1 and len(row) < width else ""
            )
            raise ValueError(f"{source}, line {lines[i]}: {len(row)} cells but the header has {width} columns{cut}.")
        for jj, j in enumerate(cols):
            if j < len(row):
                data[i, jj] = _parse_cell(row[j], source, int(lines[i]), names[jj])
    return data, lines
