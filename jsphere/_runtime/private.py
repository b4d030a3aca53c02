"""Every use of a private part of jax, equinox or diffrax, in one place.

jsphere relies on these few internals; `tests/runtime/test_private_api.py` checks each one and says
which library changed when one of them moves:

- diffrax: the Butcher tableau of an explicit Runge-Kutta solver (`solver.tableau`, with its
  `a_lower`, `c`, `b_sol`, `b_error`, `fsal`, `ssal`), read by the shared-step loop
  (`jsphere.solve.batched.method`);
- equinox: the module-level switch of its run-time checks (`equinox._errors.EQX_ON_ERROR`),
  which the environment variable `EQX_ON_ERROR` sets only at import;
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
    """equinox's module of run-time checks, if it has the two names `callbacks_as_nan` sets
    (`None` otherwise: then the block changes nothing)."""
    try:
        import equinox._errors as errors
    except ImportError:  # pragma: no cover - a future equinox without this module
        return None
    ok = hasattr(errors, "EQX_ON_ERROR") and hasattr(errors, "branched_error_if_impl_jit")
    return errors if ok else None


_LOCK = threading.Lock()
_NAN_IMPL = None


def _nan_impl(errors):
    """equinox's jitted check with the `"default"` mode read as `"nan"`: a jit of its own, so
    its traces are kept apart from those of the `"raise"` mode (equinox keys its cache of
    traced checks on the arguments, not on the mode)."""
    global _NAN_IMPL
    if _NAN_IMPL is None:
        import equinox as eqx

        def impl(x, pred, index, msgs, *, on_error):
            mode = "nan" if on_error == "default" else on_error
            return errors.branched_error_if_impl(x, pred, index, msgs, on_error=mode)

        _NAN_IMPL = eqx.filter_jit(impl)
    return _NAN_IMPL


@contextlib.contextmanager
def callbacks_as_nan() -> Iterator[None]:
    """Trace equinox's run-time checks in `"nan"` mode (no host callbacks) inside the block.

    The mode is read when a check is *traced*: wrap the first call of a solve (the one that
    traces and compiles it); a program compiled before, or outside the block, keeps the mode
    it was traced with. An explicit `EQX_ON_ERROR` in the environment wins (e.g.
    `EQX_ON_ERROR=breakpoint` for debugging), and the previous mode is restored on exit.
    Failures inside such programs are reported through `Trajectory.status`, not raised.
    Not thread-safe against checks traced in other threads meanwhile (they see `"nan"` too).
    """
    errors = _errors_module()
    if errors is None or "EQX_ON_ERROR" in os.environ:
        yield
        return
    with _LOCK:
        previous = errors.EQX_ON_ERROR, errors.branched_error_if_impl_jit
        errors.EQX_ON_ERROR, errors.branched_error_if_impl_jit = "nan", _nan_impl(errors)
    try:
        yield
    finally:
        with _LOCK:
            errors.EQX_ON_ERROR, errors.branched_error_if_impl_jit = previous


def distributed_barrier(name: str, timeout_s: float) -> None:
    """Wait until every process of JAX's distributed runtime reaches the barrier `name` (at most
    `timeout_s`): the runtime's client (`jax._src.distributed.global_state.client`). JAX's CPU
    collectives (gloo) give a late process 30 s; this barrier lets processes that compile or
    compute for longer meet before a collective. Nothing without the runtime."""
    from jax._src import distributed

    client = distributed.global_state.client
    if client is not None:
        client.wait_at_barrier(name, int(timeout_s * 1000))
