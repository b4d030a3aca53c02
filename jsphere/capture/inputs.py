"""Inputs tables: the wheel speeds or torques that drove a capture, in a CSV of their own."""

from __future__ import annotations

import numpy as np

from .._runtime.errors import InputError
from .._runtime.files import atomic_write_text
from .text import _cut_short, _input_columns, _numbers, cells, check_unique_columns, headed_rows, separator_hint
from .validation import KINDS, _check_inputs, _check_times, wheel_columns


def read_inputs_csv(
    path, *, kind: str | None = None, allow_truncated: bool = False
) -> tuple[np.ndarray, np.ndarray, str, list[str]]:
    """Read an inputs table: columns `t` [s] and `chi_dot_1..N` [rad/s] or `K_1..N` [N m] (lines
    starting with `#` before the header are comments). Returns `(t, values, kind, names)`.

    A table holding both families (a plan's CSV, `jsphere plan --out`) needs `kind`, which
    chooses the columns: `"chi_dot"` (or `"wheel_speeds"`) or `"K"` (or `"torques"`); other
    columns are ignored. Blank cells, NaN and non-increasing times are errors naming the line. A
    last row with fewer cells than the header (a file cut off mid-row) is an `InputError` naming
    both counts; with `allow_truncated=True` it is a `CaptureWarning` and the row is dropped."""
    want = input_kind(kind)
    needs = "the inputs table needs columns t and chi_dot_1..N or K_1..N"
    source, _, rows, k = headed_rows(path, needs, "capture file")
    header, at = [h.strip() for h in rows[k]], f"{source}, line {k + 1}"
    if "t" not in header:
        raise ValueError(f"{at}: missing required column t (time [s]){separator_hint(rows[k])}.")
    kind, in_cols = _input_columns(header, at, want, _BOTH)
    names = [header[j] for j in in_cols]
    check_unique_columns(header, at, ["t", *names])
    end = _cut_short(rows, k + 1, None, len(header), source, allow_truncated, noun="rows")
    data, lines = _numbers(rows[:end], k + 1, [header.index("t")] + in_cols, source, ["t"] + names)
    if data.shape[0] < 2:
        raise ValueError(f"{source}: the inputs table needs at least 2 rows.")
    _check_times(data[:, 0], source, lines)
    _check_inputs(data[:, 0], data[:, 1:], names, source, lines)
    return data[:, 0], data[:, 1:], kind, names


#: the end of the error for an inputs table with both input families
_BOTH = " (a plan's CSV holds both); choose one family with jsphere convert --input-kind chi_dot or --input-kind K."
#: the names of the input families: the CLI's `chi_dot` / `K` and the trial's kinds
KIND_NAMES = {"chi_dot": "wheel_speeds", "K": "torques", "wheel_speeds": "wheel_speeds", "torques": "torques"}


def input_kind(kind: str | None) -> str | None:
    """`"wheel_speeds"` or `"torques"` for an input family named `chi_dot`, `K`, `wheel_speeds`
    or `torques` (None stays None); `InputError` for another name."""
    if kind is None:
        return None
    if kind not in KIND_NAMES:
        raise InputError(f"input kind {kind!r}: choose 'chi_dot' (wheel speeds) or 'K' (torques).")
    return KIND_NAMES[kind]


def write_inputs_csv(path, t: np.ndarray, values: np.ndarray, kind: str) -> None:
    """Write an inputs table (see `read_inputs_csv`) atomically."""
    if kind not in KINDS:
        raise ValueError(f"write_inputs_csv: kind must be one of {KINDS}; got {kind!r}.")
    values = np.asarray(values, float).reshape(len(t), -1)
    cols = ["t", *wheel_columns(kind, values.shape[1])]
    lines = cells(np.column_stack([t, values]), [".6f"] + [".10g"] * values.shape[1])
    atomic_write_text(path, "\n".join([",".join(cols), *lines]) + "\n")


def interpolate_inputs(t_in: np.ndarray, values: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Inputs at times `t`, linearly interpolated from the table `(t_in, values)` (`(T, N)`)."""
    return np.stack([np.interp(t, t_in, values[:, i]) for i in range(values.shape[1])], axis=1)
