"""`FastStart`, the programs of eager solves exported to disk (what the command line runs its
solves' programs through): same results as the ordinary call, from memory and from
the file; no export for calls without a stable key; a damaged file is replaced."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jsphere
from jsphere._runtime import fast_start
from jsphere._runtime.fast_start import FastStart
from jsphere._runtime.private import equinox_errors_as
from jsphere._runtime.quick_compile import programs_run_by


@pytest.fixture
def nan_mode():
    """Every solve of the test traced with equinox's checks in `nan` mode, as the command line
    does: a trace with host callbacks (raise mode) cannot be exported."""
    with equinox_errors_as("nan"):
        yield


def _free_roll(p, programs=None):
    state = eqx.tree_at(lambda s: s.Omega, jsphere.State.at_rest(p), jnp.array([0.0, 0.5, 0.1]))
    with programs_run_by(programs):
        return jsphere.simulate(p, state, jsphere.Torques(jsphere.Zero(3)), 0.5, ts=jnp.linspace(0.0, 0.5, 6))


@pytest.mark.slow
def test_exported_solve_matches_the_direct_call_and_is_reused(tmp_path, nan_mode):
    p = jsphere.RobotParams.paper()
    aot_dir = tmp_path / "aot"
    want = _free_roll(p)
    first = _free_roll(p, FastStart(tmp_path))  # exports, writes the file, runs the exported program
    files = list(aot_dir.glob("*.jaxexport"))
    assert len(files) == 1
    again = _free_roll(p.replace(R0=0.16), FastStart(tmp_path))  # as a new process: from the file
    assert list(aot_dir.glob("*.jaxexport")) == files
    for a, b in zip(jax.tree_util.tree_leaves(first), jax.tree_util.tree_leaves(want)):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-12, atol=1e-15)
    direct = _free_roll(p.replace(R0=0.16))
    np.testing.assert_allclose(np.asarray(again.x), np.asarray(direct.x), rtol=1e-12, atol=1e-15)
    assert float(jnp.max(jnp.abs(again.x - first.x))) > 0  # the parameters were inputs, not constants

    # a damaged file is exported again
    files[0].write_bytes(b"not an export")
    repaired = _free_roll(p, FastStart(tmp_path))
    np.testing.assert_array_equal(np.asarray(repaired.y), np.asarray(first.y))
    assert files[0].stat().st_size > 1000


def test_an_exported_program_compiles_once_for_committed_and_uncommitted_arguments(tmp_path):
    """A loop feeding one call's results (committed arrays) to the next, mixed with arrays made
    from NumPy (uncommitted), runs one compiled program."""
    fs = FastStart(tmp_path)
    f = jax.jit(lambda a, b: (a * b, a + b))
    x = np.arange(3.0)
    first = fs("test.pair", f, tuple, x, x)
    second = fs("test.pair", f, tuple, first[0], x)
    third = fs("test.pair", f, tuple, jnp.asarray(x), second[1])
    (run,) = fs._loaded.values()
    assert run._cache_size() == 1
    np.testing.assert_array_equal(np.asarray(second[0]), x**3)
    np.testing.assert_array_equal(np.asarray(third[0]), x * (x**2 + x))


def _compiles(f) -> int:
    """How many programs XLA compiles while `f()` runs."""
    seen = []

    def listen(event, duration, **_):
        if event.endswith("backend_compile_duration"):
            seen.append(duration)

    jax.monitoring.register_event_duration_secs_listener(listen)
    try:
        f()
    finally:
        jax.monitoring.unregister_event_duration_listener(listen)
    return len(seen)


def test_an_exported_program_is_reused_and_one_that_cannot_be_exported_runs_itself(tmp_path):
    """A call exports its program once and a later call compiles nothing; a program that cannot
    be exported (a host callback) runs itself, its key kept apart."""
    fs, out = FastStart(tmp_path), []
    f = jax.jit(lambda a, b: (jnp.sin(a) * b, a - b))
    x = np.linspace(0.0, 1.0, 7)
    assert _compiles(lambda: out.append(fs("test.ahead", f, tuple, x, x))) >= 1
    assert len(list((tmp_path / "aot").glob("*.jaxexport"))) == 1
    assert _compiles(lambda: out.append(fs("test.ahead", f, tuple, x, 2 * x))) == 0
    np.testing.assert_array_equal(np.asarray(out[-1][1]), -x)

    h = jax.jit(lambda a: (jax.debug.callback(lambda v: None, a), a * 3.0)[1])
    out.append(fs("test.callback", h, lambda leaves: leaves[0], x))
    assert len(fs._failed) == 1
    np.testing.assert_array_equal(np.asarray(out[-1]), 3.0 * x)


@pytest.mark.slow
def test_calls_without_a_stable_key_are_not_exported(tmp_path, nan_mode):
    p = jsphere.RobotParams.paper()
    K = jnp.array([0.01, 0.0, -0.01])
    with programs_run_by(FastStart(tmp_path)):
        tr = jsphere.simulate(p, jsphere.State.at_rest(p), jsphere.Torques(lambda t: K * t), 0.2)
        assert bool(tr.ok)  # a lambda: no stable key
        jax.jit(lambda a: jsphere.simulate(p, jsphere.State.at_rest(p), jsphere.Torques(jsphere.Zero(3)), a).x)(
            0.2
        )  # traced
    assert not (tmp_path / "aot").exists() or not list((tmp_path / "aot").glob("*.jaxexport"))
    assert fast_start._stable(lambda t: t) is None and fast_start._stable(object()) is None
    assert fast_start._stable(1.5) == "float:1.5" and fast_start._stable(jnp.sin) is not None
