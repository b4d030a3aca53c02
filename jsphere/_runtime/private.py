"""Every use of a private part of jax, equinox or diffrax, in one place.

jsphere relies on these few internals; `tests/test_private_api.py` checks each one and says
which library changed when one of them moves:

- diffrax: the Butcher tableau of an explicit Runge-Kutta solver (`solver.tableau`, with its
  `a_lower`, `c`, `b_sol`, `b_error`, `fsal`, `ssal`), read by the shared-step loop
  (`jsphere.solve.batched.method`);
- equinox: the module-level switch of its run-time checks (`equinox._errors.EQX_ON_ERROR`),
  which the environment variable `EQX_ON_ERROR` sets only at import;
- jax: whether its backends (the CPU client) exist yet (`jax._src.xla_bridge`), since an XLA
  flag set after that changes nothing.
"""

from __future__ import annotations

import contextlib
from typing import Any, Iterator, NamedTuple


class ButcherTableau(NamedTuple):
    """The parts of a diffrax explicit Runge-Kutta tableau the shared-step loop uses."""

    a_lower: tuple  # row i: the coefficients of stage i+1 on stages 0..i
    c: Any  # the nodes of stages 1..s-1
    b_sol: Any
    b_error: Any
    fsal: bool  # first same as last
    ssal: bool  # solution same as last


def rk_tableau(solver) -> ButcherTableau:
    """The Butcher tableau of the diffrax solver `solver` (an explicit Runge-Kutta method)."""
    tab = type(solver).tableau
    return ButcherTableau(tuple(tab.a_lower), tab.c, tab.b_sol, tab.b_error, bool(tab.fsal), bool(tab.ssal))


def _equinox_errors():
    import equinox._errors as errors

    return errors


def equinox_on_error() -> str | None:
    """The mode of equinox's run-time checks (`"raise"`, `"nan"`, `"breakpoint"`, `"off"`), or
    `None` where this equinox has no such switch."""
    try:
        return getattr(_equinox_errors(), "EQX_ON_ERROR", None)
    except ImportError:  # pragma: no cover - an equinox without this module
        return None


def set_equinox_on_error(mode: str) -> str | None:
    """Switch equinox's run-time checks to `mode` for the checks traced from now on; returns the
    previous mode (`None`, and nothing changed, where this equinox has no such switch)."""
    try:
        errors = _equinox_errors()
    except ImportError:  # pragma: no cover
        return None
    old = getattr(errors, "EQX_ON_ERROR", None)
    if old is not None:
        errors.EQX_ON_ERROR = mode
    return old


@contextlib.contextmanager
def equinox_errors_as(mode: str) -> Iterator[None]:
    """`set_equinox_on_error(mode)` inside the `with` block, the previous mode after it."""
    old = set_equinox_on_error(mode)
    try:
        yield
    finally:
        if old is not None:
            set_equinox_on_error(old)


def jax_backends_initialized() -> bool:
    """Whether jax has created its backends (its CPU client) in this process: XLA flags set
    in the environment after that have no effect. `False` before jax is imported."""
    import sys

    if "jax" not in sys.modules:
        return False
    from jax._src import xla_bridge

    return bool(xla_bridge.backends_are_initialized())
