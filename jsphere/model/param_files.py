"""A robot's parameter set read from a file or a table (`RobotParams.load`, `from_dict`): the
keys checked (every required field, nothing else), the values checked to be numbers of each
field's shape, a fit result's two copies checked to agree, and one line naming the defaults
used for the keys a file leaves out."""

from __future__ import annotations

from typing import Any

import jax
import numpy as np

from .._runtime.errors import InputError
from .fields import FIELDS, OPTIONAL, TABLE
from .names import get_value

#: the files whose left-out keys have been named, with those keys (`note_defaults`)
_NOTED: set[tuple[str, tuple[str, ...]]] = set()


def keys_checked(d: Any, where: str) -> dict[str, Any]:
    """`d` with the wheel aliases resolved, after checking that it holds every required field
    and nothing else (`InputError` starting with `where`, naming the key)."""
    import difflib

    if not isinstance(d, dict):
        raise InputError(f"{where}: a parameter set must be a table of fields {list(FIELDS)}; got {type(d).__name__}.")
    d = dict(d)
    for alias, field in (("r", "wheel_r"), ("n", "wheel_n"), ("alpha", "wheel_alpha")):
        if alias in d and field not in d:
            d[field] = d.pop(alias)
    unknown = sorted(set(d) - set(FIELDS), key=str)
    if unknown:
        k = unknown[0]
        close = difflib.get_close_matches(str(k), FIELDS, n=1)
        hint = f" (did you mean {close[0]!r}?)" if close else ""
        raise InputError(
            f"{where}: unknown key {k!r}{hint}; the keys of a robot are {', '.join(FIELDS)} "
            "(examples/robot.toml lists them)."
        )
    missing = [f for f in FIELDS if f not in d and f not in OPTIONAL]
    if missing:
        which = ", ".join(f"{f!r} ({TABLE[f].meaning})" for f in missing)
        raise InputError(
            f"{where}: missing required key{'s' if len(missing) > 1 else ''} {which}; add "
            f"{'them' if len(missing) > 1 else 'it'} (examples/robot.toml shows every key, docs/robot.md how to measure it)."
        )
    return d


def note_defaults(path, left_out: list[str]) -> None:
    """One warning line on the `jsphere` logger naming the optional keys a file leaves out and
    the defaults used, once per file and set of keys in a process."""
    import logging
    import os

    key = (os.path.abspath(os.fspath(path)), tuple(left_out))
    if not left_out or key in _NOTED:
        return
    _NOTED.add(key)
    logging.getLogger("jsphere").warning(
        f"warning: {path} leaves out {', '.join(left_out)}; using {', '.join(OPTIONAL[f][1] for f in left_out)}. "
        "Write the key(s) in the file to use your robot's value (docs/robot.md)."
    )


def check_fit_copies(path, values: dict[str, Any], p) -> None:
    """Refuse a fit result whose `values` (the free parameters) disagree with its `params`
    beyond a relative 1e-9 (`InputError` naming the parameter and both values)."""
    for name, v in values.items():
        try:
            have = np.asarray(get_value(p, str(name)), np.float64)
        except ValueError:
            raise InputError(
                f"{path}: values has an unknown parameter {name!r}; it names no field of params."
            ) from None
        try:
            want = np.asarray(v, np.float64)  # a None (null) is NaN, not checked
        except (TypeError, ValueError):
            raise InputError(f"{path}: values[{name!r}] must be a number (or lists of numbers); got {v!r}.") from None
        if want.shape != have.shape:
            raise InputError(f"{path}: values[{name!r}] has shape {want.shape}, params has {have.shape} for it.")
        scale = float(np.max(np.abs(have))) if have.size else 0.0
        tol = 1e-9 * np.maximum(np.abs(want), np.abs(have)) + 1e-12 * scale
        bad = np.flatnonzero(np.isfinite(want) & ~(np.abs(want - have) <= tol))
        if bad.size:
            i = int(bad[0])
            a, b = float(want.flat[i]), float(have.flat[i])
            sub = "" if want.ndim == 0 else f"[{','.join(map(str, np.unravel_index(i, want.shape)))}]"
            raise InputError(
                f"{path}: values[{name!r}]{sub} = {a!r} disagrees with params ({name}{sub} = {b!r}), the copy the "
                "robot is read from; edit params (and values to match), or delete values."
            )


def _not_a_number(v: Any) -> str | None:
    """Why `v` (a number or nested lists of numbers) is not numeric, or None if it is."""
    if isinstance(v, (list, tuple)):
        return next((r for r in map(_not_a_number, v) if r is not None), None)
    if isinstance(v, (bool, np.bool_)):
        return f"not a boolean ({str(bool(v)).lower()})"
    if isinstance(v, (int, float, np.integer, np.floating)):
        return None
    if isinstance(v, str):
        return f"not a string ({v!r}; write numbers without quotes)"
    if hasattr(v, "dtype") and hasattr(v, "shape"):  # NumPy and JAX arrays
        return None if np.dtype(v.dtype).kind in "iuf" else f"not an array of {np.dtype(v.dtype)}"
    return "not null" if v is None else f"not a {type(v).__name__}"


def number_array(value: Any, what: str, expected: str) -> Any:
    """`value` (a number or nested lists of numbers) as a float64 NumPy array; a JAX array is
    returned as it is. Raises `InputError` starting with `what` for a boolean, a string or
    another non-number anywhere in `value`, and for ragged lists (naming `expected`, the shape
    wanted in words)."""
    why = _not_a_number(value)
    if why is not None:
        raise InputError(f"{what}: the value must be a number, {why}.")
    if isinstance(value, (jax.Array, jax.core.Tracer)):
        return value
    try:
        return np.asarray(value, dtype=np.float64)
    except ValueError:
        raise InputError(f"{what}: a ragged list (rows of different lengths); expected {expected}.") from None


def checked_fields(d: dict[str, Any]) -> dict[str, Any]:
    """The fields of a parameter set as arrays, each checked to be numbers of its field's shape
    (`InputError` naming the field and the expected shape)."""
    out = {}
    for f in sorted(d, key=FIELDS.index):  # wheel_r before the fields whose shape follows it
        v = d[f]
        expected = TABLE[f].shape
        a = number_array(v, f"RobotParams.{f}", expected)
        shape = tuple(np.shape(a))
        if f in ("wheel_n", "wheel_alpha") and "wheel_r" in out:
            ok = shape == tuple(np.shape(out["wheel_r"]))
        elif f == "wheel_r":
            ok = len(shape) == 2 and shape[1] == 3 and shape[0] >= 3
        else:
            ok = shape == {"I": (3, 3), "r_m": (3,)}.get(f, ())
        if not ok:
            raise InputError(f"RobotParams.{f}: expected {expected}; got shape {shape}.")
        out[f] = a
    return out
