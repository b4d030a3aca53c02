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


def test_equinox_error_mode_switch():
    mode = private.equinox_on_error()
    assert mode in ("raise", "nan", "breakpoint", "off"), (
        "equinox no longer has `equinox._errors.EQX_ON_ERROR` (the switch of its run-time checks that "
        "the CLI sets to 'nan' for cacheable programs); update jsphere/_runtime/private.py."
    )
    with private.equinox_errors_as("nan"):
        assert private.equinox_on_error() == "nan"
    assert private.equinox_on_error() == mode


def test_equinox_nan_mode_takes_effect():
    """The switch is read when a check is traced: in `nan` mode a failed check gives NaN, not an error."""
    import equinox as eqx
    import jax.numpy as jnp

    with private.equinox_errors_as("nan"):
        out = jax.jit(lambda x: eqx.error_if(x, x > 0, "positive"))(jnp.array(1.0))
    assert np.isnan(float(out)), "equinox ignores equinox._errors.EQX_ON_ERROR now; update jsphere/_runtime/private.py."


def test_equinox_jitted_check():
    """`callbacks_as_nan` passes its mode to the jitted check `eqx.error_if` calls for array
    predicates (`equinox._errors.branched_error_if_impl_jit`)."""
    import equinox as eqx
    import equinox._errors as errors
    import jax.numpy as jnp

    assert callable(getattr(errors, "branched_error_if_impl_jit", None)), (
        f"equinox {eqx.__version__} no longer has `equinox._errors.branched_error_if_impl_jit` (the jitted check "
        "`eqx.error_if` calls, which jsphere traces in `nan` mode so that JAX's cache keeps its programs); update "
        "jsphere/_runtime/private.py."
    )
    with private.callbacks_as_nan():
        out = jax.jit(lambda x: eqx.error_if(x, x > 0, "positive"))(jnp.array(1.0))
    assert np.isnan(float(out)), (
        f"equinox {eqx.__version__}: `eqx.error_if` no longer goes through `equinox._errors.branched_error_if_impl_jit` "
        "(a check inside `callbacks_as_nan()` was not traced in `nan` mode); update jsphere/_runtime/private.py."
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
