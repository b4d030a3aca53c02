"""Checks of a user's numbers (counts, seeds, durations, rates, weights) before any work.

Each raises `InputError` with one line that names the value: `"WHERE: NAME must be ...; got
VALUE."`. Booleans and strings are not numbers, a count is not truncated (`10.9` is refused,
`1e4` is 10000), and NaN or an infinity is never accepted. NumPy and Python only: no compiled
program, and traced values (inside `jit`/`grad`) are left to the caller.
"""

from __future__ import annotations

import math

import jax
import numpy as np

from .errors import InputError


def is_number(v) -> bool:
    """A real number (Python or NumPy), not a boolean."""
    return isinstance(v, (int, float, np.integer, np.floating)) and not isinstance(v, (bool, np.bool_))


def is_traced(*vs) -> bool:
    """Whether any of `vs` is a JAX array or tracer (checked by the caller under `jit`, not here)."""
    return any(isinstance(v, (jax.core.Tracer, jax.Array)) for v in vs)


def whole(where: str, name: str, v, low: int, high: int | None = None) -> int:
    """`v` as an int if it is a whole number in `[low, high]` (a float such as `1e4` that is
    whole is accepted; `10.9` is not truncated), else `InputError` naming `name`."""
    rng = f">= {low}" if high is None else f"in [{low}, {high}]"
    if not is_number(v) or not math.isfinite(v) or v != math.floor(v) or v < low or (high is not None and v > high):
        raise InputError(f"{where}: {name} must be a whole number {rng}; got {v!r}.")
    return int(v)


def real(where: str, name: str, v, *, low: float | None = 0.0, strict: bool = False, unit: str = "") -> float:
    """`v` as a float if it is a finite number `>= low` (`> low` with `strict`; any finite
    number with `low=None`), else `InputError` naming `name`."""
    unit = f" [{unit}]" if unit else ""
    bound = "" if low is None else f" {'>' if strict else '>='} {low:g}"
    if not is_number(v) or not math.isfinite(v) or (low is not None and (v <= low if strict else v < low)):
        raise InputError(f"{where}: {name} must be a finite number{bound}{unit}; got {v!r}.")
    return float(v)


def finite(where: str, name: str, value, *, positive: bool = False, unit: str = "") -> None:
    """Raise `InputError` naming `name` if a concrete `value` (a number or an array) is not
    finite everywhere, or not `> 0` everywhere with `positive`. A traced value or a function
    (a gait profile) is not checked."""
    if isinstance(value, jax.core.Tracer) or callable(value):
        return
    what = ("a positive number" if positive else "a finite number") + (f" [{unit}]" if unit else "")
    bad = isinstance(value, (bool, np.bool_, str, bytes)) or value is None
    if not bad:
        try:
            a = np.asarray(value, dtype=np.float64)
        except (TypeError, ValueError):
            bad = True
        else:
            bad = not np.all(np.isfinite(a)) or (positive and not np.all(a > 0))
    if bad:
        raise InputError(f"{where}: {name} must be {what}; got {value!r}.")
