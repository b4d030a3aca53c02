"""Every use of a private part of jax, equinox or diffrax, in one place.

jsphere relies on these few internals; `tests/runtime/test_private_api.py` checks each one and says
which library changed when one of them moves:

- diffrax: the Butcher tableau of an explicit Runge-Kutta solver (`solver.tableau`, with its
  `a_lower`, `c`, `b_sol`, `b_error`, `fsal`, `ssal`), read by the shared-step loop
  (`jsphere.solve.batched.method`);
- equinox: the module-level switch of its run-time checks (`equinox._errors.EQX_ON_ERROR`),
  which the environment variable `EQX_ON_ERROR` sets only at import, and the jitted check that
  `eqx.error_if` calls (`equinox._errors.branched_error_if_impl_jit`), which
  `callbacks_as_nan` passes its mode;
- jax: whether its backends (the CPU client) exist yet (`jax._src.xla_bridge`), since an XLA
  flag set after that changes nothing; the distributed runtime's barrier
  (`jax._src.distributed`), which waits longer than the CPU collectives do.
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


def reset_jax_compilation_cache() -> None:
    """Make JAX open its persistent cache again (after its directory changed): `jax._src`."""
    try:
        from jax._src import compilation_cache as _cc

        _cc.reset_cache()
    except (ImportError, AttributeError):  # pragma: no cover - another JAX layout
        pass


def _errors_module():
    """equinox's module of run-time checks, if it has the name `callbacks_as_nan` wraps
    (`branched_error_if_impl_jit`, which `eqx.error_if` calls for array predicates; `None`
    otherwise: then the block changes nothing)."""
    try:
        import equinox._errors as errors
    except ImportError:  # pragma: no cover - a future equinox without this module
        return None
    return errors if hasattr(errors, "branched_error_if_impl_jit") else None


_LOCK = threading.Lock()
_NAN_DEPTH = threading.local()  # per thread: how many `callbacks_as_nan()` blocks are open


def _nan_here() -> bool:
    return getattr(_NAN_DEPTH, "n", 0) > 0


def _install(errors) -> None:
    """Put a pass-through in front of equinox's jitted check (once per process): a check in the
    `"default"` mode traced inside a `callbacks_as_nan()` block of this thread is traced in
    `"nan"` mode (a static argument of equinox's jit, so its traces are kept apart from the
    other modes'); every other check goes through unchanged."""
    with _LOCK:
        current = errors.branched_error_if_impl_jit
        if getattr(current, "__jsphere_nan__", False):
            return

        def impl(x, pred, index, msgs, *, on_error):
            if on_error == "default" and _nan_here():
                on_error = "nan"
            return current(x, pred, index, msgs, on_error=on_error)

        impl.__jsphere_nan__ = True
        errors.branched_error_if_impl_jit = impl


@contextlib.contextmanager
def callbacks_as_nan() -> Iterator[None]:
    """Trace equinox's run-time checks in `"nan"` mode (no host callbacks) inside the block.

    The mode is read when a check is *traced*: a program compiled before, or outside the
    block, keeps the mode it was traced with. Only this thread's checks in equinox's default
    mode change (`eqx.error_if(..., on_error="raise")` stays as written); blocks nest, and an
    explicit `EQX_ON_ERROR` in the environment wins (e.g. `EQX_ON_ERROR=breakpoint` for
    debugging). A failed check then returns NaN: jsphere's solves trace diffrax's checks
    this way and report a failure through `Trajectory.status`.
    """
    errors = _errors_module()
    if errors is None or "EQX_ON_ERROR" in os.environ:
        yield
        return
    _install(errors)
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
