"""The private parts of jax, equinox and diffrax that jsphere relies on (`jsphere._runtime.private`):
each test names the library and what changed, so that an upgrade that moves one fails here
first, with a message that says what to fix."""

import time

import diffrax as dfx
import jax
import numpy as np
import pytest

from jsphere._runtime import private
from jsphere.solve.batched.method import SUPPORTED, tableau


@pytest.mark.parametrize("solver_cls", SUPPORTED, ids=lambda c: c.__name__)
def test_diffrax_runge_kutta_tableau(solver_cls):
    solver = solver_cls()
    try:
        tab = private.rk_tableau(solver)
    except AttributeError as e:
        pytest.fail(
            f"diffrax {dfx.__version__} changed {solver_cls.__name__}.tableau (ButcherTableau with a_lower, c, "
            f"b_sol, b_error, fsal, ssal), which jsphere's batch loop reads: {e}. Update jsphere/_runtime/private.py."
        )
    assert tab.fsal and tab.ssal, f"diffrax {dfx.__version__}: {solver_cls.__name__} is no longer FSAL/SSAL"
    assert len(tab.a_lower) == len(np.asarray(tab.c)), f"diffrax {dfx.__version__}: tableau shapes changed"
    assert callable(getattr(solver, "interpolation_cls", None)), f"diffrax {dfx.__version__}: interpolation_cls is gone"
    assert tableau(solver) is not None


def _equinox_name(name: str):
    """`equinox._errors.<name>`, or a failure that names it."""
    import equinox as eqx

    try:
        import equinox._errors as errors

        return getattr(errors, name)
    except (ImportError, AttributeError) as e:
        pytest.fail(
            f"equinox {eqx.__version__} no longer has `equinox._errors.{name}`, through which jsphere traces "
            f"equinox's run-time checks in `nan` mode (so that JAX's cache keeps its programs): {e}. Update "
            "jsphere/_runtime/private.py."
        )


@pytest.mark.parametrize("name", private._EQUINOX_NAMES)
def test_equinox_private_names(name):
    """Each private name of equinox that the switch reads or wraps is there."""
    value = _equinox_name(name)
    if name == "EQX_ON_ERROR":
        assert value in ("raise", "nan", "breakpoint", "off"), f"equinox's EQX_ON_ERROR is {value!r}"
    else:
        assert callable(value), f"`equinox._errors.{name}` is not a function any more"


def test_equinox_error_mode_switch(monkeypatch):
    """`equinox_errors_as` traces the checks in its mode and leaves equinox's own switch alone."""
    import equinox as eqx
    import jax.numpy as jnp

    monkeypatch.delenv("EQX_ON_ERROR", raising=False)
    own = _equinox_name("EQX_ON_ERROR")
    mode = private.equinox_on_error()
    with private.equinox_errors_as("nan"):
        assert private.equinox_on_error() == "nan"
        out = jax.jit(lambda x: eqx.error_if(x, x > 0, "positive"))(jnp.array(1.0))
        assert np.isnan(float(out)), (
            f"equinox {eqx.__version__}: `eqx.error_if` no longer goes through `equinox._errors."
            "branched_error_if_impl_jit` (a check inside `equinox_errors_as('nan')` was not traced in `nan` mode); "
            "update jsphere/_runtime/private.py."
        )
        with pytest.warns(UserWarning, match="nan"):  # a Python boolean: `branched_error_if_impl`
            out = eqx.error_if(np.ones(1), True, "positive")
        assert np.isnan(out).all(), (
            f"equinox {eqx.__version__}: `eqx.error_if` on a Python boolean no longer goes through "
            "`equinox._errors.branched_error_if_impl`; update jsphere/_runtime/private.py."
        )
    assert private.equinox_on_error() == mode
    assert _equinox_name("EQX_ON_ERROR") == own


def test_equinox_jitted_check(monkeypatch):
    """`callbacks_as_nan` passes its mode to the jitted check `eqx.error_if` calls for array
    predicates (`equinox._errors.branched_error_if_impl_jit`)."""
    import equinox as eqx
    import jax.numpy as jnp

    monkeypatch.delenv("EQX_ON_ERROR", raising=False)
    _equinox_name("branched_error_if_impl_jit")
    with private.callbacks_as_nan():
        out = jax.jit(lambda x: eqx.error_if(x, x > 0, "positive"))(jnp.array(1.0))
    assert np.isnan(float(out)), (
        f"equinox {eqx.__version__}: `eqx.error_if` no longer goes through `equinox._errors.branched_error_if_impl_jit` "
        "(a check inside `callbacks_as_nan()` was not traced in `nan` mode); update jsphere/_runtime/private.py."
    )


def test_a_moved_equinox_name_is_loud(monkeypatch):
    """A renamed equinox internal stops the switch with an error naming it, never silently."""
    import equinox._errors as errors

    monkeypatch.delattr(errors, "branched_error_if_impl_jit")
    with pytest.raises(ImportError, match="equinox._errors.branched_error_if_impl_jit"):
        with private.equinox_errors_as("nan"):
            pass


def test_jax_compilation_cache_reset():
    try:
        from jax._src import compilation_cache

        compilation_cache.reset_cache  # noqa: B018
    except (ImportError, AttributeError) as e:
        pytest.fail(
            f"jax {jax.__version__} moved jax._src.compilation_cache.reset_cache, which "
            f"`jsphere.enable_compilation_cache` calls when the cache's folder changes: {e}. Update "
            "jsphere/_runtime/private.py."
        )


def test_jax_backends_initialized():
    try:
        from jax._src import xla_bridge

        xla_bridge.backends_are_initialized  # noqa: B018
    except (ImportError, AttributeError) as e:
        pytest.fail(
            f"jax {jax.__version__} moved jax._src.xla_bridge.backends_are_initialized, which the CLI uses to "
            f"know whether an XLA flag still takes effect: {e}. Update jsphere/_runtime/private.py."
        )
    jax.numpy.zeros(1).block_until_ready()
    assert private.jax_backends_initialized() is True


def test_jax_distributed_barrier():
    try:
        from jax._src import distributed

        distributed.global_state.client  # noqa: B018
    except (ImportError, AttributeError) as e:
        pytest.fail(
            f"jax {jax.__version__} moved jax._src.distributed.global_state.client, whose barrier "
            f"`monte_carlo(distributed=True)` uses before its collectives: {e}. Update jsphere/_runtime/private.py."
        )
    # no runtime in this process: no client, and the barrier returns at once
    assert distributed.global_state.client is None
    t0 = time.perf_counter()
    assert private.distributed_barrier("unused", 1.0) is None
    assert time.perf_counter() - t0 < 0.5
