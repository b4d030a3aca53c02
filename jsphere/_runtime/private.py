"""Every use of a private part of jax, equinox or diffrax, in one place.

jsphere relies on these few internals; `tests/runtime/test_private_api.py` checks each one and says
which library changed when one of them moves:

- diffrax: the Butcher tableau of an explicit Runge-Kutta solver (`solver.tableau`, with its
  `a_lower`, `c`, `b_sol`, `b_error`, `fsal`, `ssal`), read by the shared-step loop
  (`jsphere.solve.batched.method`);
- equinox: the mode of its run-time checks (`equinox._errors.EQX_ON_ERROR`, which the
  environment variable `EQX_ON_ERROR` sets only at import) and the two functions `eqx.error_if`
  calls (`equinox._errors.branched_error_if_impl_jit` and `branched_error_if_impl`), in front of
  which one pass-through traces each check in the mode `equinox_errors_as` or
  `callbacks_as_nan` asks for (equinox's own switch is never changed);
- jax: whether its backends (the CPU client) exist yet (`jax._src.xla_bridge`), since an XLA
  flag set after that changes nothing; the distributed runtime's barrier
  (`jax._src.distributed`), which waits longer than the CPU collectives do; its persistent
  cache's reset (`jax._src.compilation_cache.reset_cache`), after the cache's folder changed.

A moved name fails loudly where it is used (an `ImportError` or `AttributeError` naming it),
never silently.
"""

from __future__ import annotations

import contextlib
import os
import threading
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
    """equinox's module of run-time checks, with the names jsphere reads or wraps; an
    `ImportError` naming the missing name where an upgrade moved one."""
    import equinox
    import equinox._errors as errors

    for name in _EQUINOX_NAMES:
        if not hasattr(errors, name):
            raise ImportError(
                f"equinox {equinox.__version__} has no `equinox._errors.{name}`, which jsphere's switch of "
                "equinox's run-time checks uses; update jsphere/_runtime/private.py."
            )
    return errors


#: equinox's private names: the mode its checks read when traced with `on_error="default"` (set
#: from the environment variable `EQX_ON_ERROR` at import) and the two functions that
#: `eqx.error_if` calls (jitted for array predicates, directly for Python booleans)
_EQUINOX_NAMES = ("EQX_ON_ERROR", "branched_error_if_impl_jit", "branched_error_if_impl")

_LOCK = threading.Lock()
_MODE: list[str] = []  # the mode `equinox_errors_as` sets for every thread (innermost last)
_NAN_DEPTH = threading.local()  # per thread: how many `callbacks_as_nan()` blocks are open


def _mode(on_error: str) -> str:
    """The mode a check traced now runs in: an explicit mode as written; for equinox's default,
    `"nan"` inside this thread's `callbacks_as_nan()`, else `equinox_errors_as`'s mode, else
    equinox's own."""
    if on_error != "default":
        return on_error
    return "nan" if getattr(_NAN_DEPTH, "n", 0) > 0 else _MODE[-1] if _MODE else on_error


def _install() -> None:
    """Put a pass-through in front of equinox's two checks (once per process) that traces each
    check in `_mode(on_error)`. The mode is a static argument of equinox's jit, so the traces of
    each mode are kept apart; with nothing switched every check goes through unchanged."""
    errors = _equinox_errors()
    with _LOCK:
        for name in _EQUINOX_NAMES[1:]:
            current = getattr(errors, name)
            if getattr(current, "__jsphere_mode__", False):
                continue

            def impl(x, pred, index, msgs, *, on_error, _current=current):
                return _current(x, pred, index, msgs, on_error=_mode(on_error))

            impl.__jsphere_mode__ = True
            setattr(errors, name, impl)


def equinox_on_error() -> str:
    """The mode of equinox's run-time checks (`"raise"`, `"nan"`, `"breakpoint"`, `"off"`) for a
    check traced now outside `callbacks_as_nan()`: `equinox_errors_as`'s, else equinox's own."""
    return _MODE[-1] if _MODE else _equinox_errors().EQX_ON_ERROR


@contextlib.contextmanager
def equinox_errors_as(mode: str) -> Iterator[None]:
    """Trace equinox's run-time checks in `mode` inside the `with` block, in every thread (the mode
    is read when a check is traced; a check with an explicit `on_error` stays as written);
    blocks nest. equinox's own switch is never changed."""
    _install()
    with _LOCK:
        _MODE.append(mode)
    try:
        yield
    finally:
        with _LOCK:
            _MODE.pop()


def jax_backends_initialized() -> bool:
    """Whether jax has created its backends (its CPU client) in this process: XLA flags set
    in the environment after that have no effect. `False` before jax is imported."""
    import sys

    if "jax" not in sys.modules:
        return False
    from jax._src import xla_bridge

    return bool(xla_bridge.backends_are_initialized())


def reset_jax_compilation_cache() -> None:
    """Make JAX open its persistent cache again (after its directory changed): `jax._src`."""
    from jax._src import compilation_cache

    compilation_cache.reset_cache()


@contextlib.contextmanager
def callbacks_as_nan() -> Iterator[None]:
    """Trace equinox's run-time checks in `"nan"` mode (no host callbacks) inside the block, in
    this thread: as `equinox_errors_as("nan")`, read when a check is traced; an explicit
    `EQX_ON_ERROR` in the environment wins (e.g. `EQX_ON_ERROR=breakpoint` for debugging). A
    failed check then returns NaN, which a solve reports through `Trajectory.status`."""
    if "EQX_ON_ERROR" in os.environ:
        yield
        return
    _install()
    _NAN_DEPTH.n = getattr(_NAN_DEPTH, "n", 0) + 1
    try:
        yield
    finally:
        _NAN_DEPTH.n -= 1


def distributed_barrier(name: str, timeout_s: float) -> None:
    """Wait until every process of JAX's distributed runtime reaches the barrier `name` (at most
    `timeout_s`): the runtime's client (`jax._src.distributed.global_state.client`). JAX's CPU
    collectives (gloo) give a late process 30 s; this barrier lets processes that compile or
    compute for longer meet before a collective. Nothing without the runtime."""
    from jax._src import distributed

    client = distributed.global_state.client
    if client is not None:
        client.wait_at_barrier(name, int(timeout_s * 1000))
