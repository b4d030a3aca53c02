"""Exported solves kept on disk (`jsphere._runtime.export_cache`, used by the CLI): same results as the ordinary
call, from memory and from the file; no export for calls without a stable key; a damaged file
is replaced."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jsphere
from jsphere._runtime import export_cache as _aot
from jsphere._runtime.private import equinox_errors_as


@pytest.fixture
def aot_dir(tmp_path):
    with equinox_errors_as("nan"):  # as the CLI: no host callbacks to export
        _aot.enable(tmp_path)
        yield tmp_path / "aot"
        _aot.enable(None)


def _free_roll(p):
    state = eqx.tree_at(lambda s: s.Omega, jsphere.State.at_rest(p), jnp.array([0.0, 0.5, 0.1]))
    return jsphere.simulate(p, state, jsphere.Torques(jsphere.Zero(3)), 0.5, ts=jnp.linspace(0.0, 0.5, 6))


@pytest.mark.slow
def test_exported_solve_matches_the_direct_call_and_is_reused(aot_dir):
    p = jsphere.RobotParams.paper()
    _aot.enable(None)
    want = _free_roll(p)
    _aot.enable(aot_dir.parent)
    first = _free_roll(p)  # exports, writes the file, runs the exported program
    files = list(aot_dir.glob("*.jaxexport"))
    assert len(files) == 1
    _aot._LOADED.clear()  # as in a new process: from the file
    again = _free_roll(p.replace(R0=0.16))  # new values, same shapes: the same program
    assert list(aot_dir.glob("*.jaxexport")) == files
    for a, b in zip(jax.tree_util.tree_leaves(first), jax.tree_util.tree_leaves(want)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    _aot.enable(None)
    direct = _free_roll(p.replace(R0=0.16))
    np.testing.assert_array_equal(np.asarray(again.x), np.asarray(direct.x))
    assert float(jnp.max(jnp.abs(again.x - first.x))) > 0  # the parameters were inputs, not constants

    # a damaged file is exported again
    _aot.enable(aot_dir.parent)
    files[0].write_bytes(b"not an export")
    repaired = _free_roll(p)
    np.testing.assert_array_equal(np.asarray(repaired.y), np.asarray(want.y))
    assert files[0].stat().st_size > 1000


@pytest.mark.slow
def test_calls_without_a_stable_key_are_not_exported(aot_dir):
    p = jsphere.RobotParams.paper()
    K = jnp.array([0.01, 0.0, -0.01])
    tr = jsphere.simulate(p, jsphere.State.at_rest(p), jsphere.Torques(lambda t: K * t), 0.2)  # a lambda
    assert bool(tr.ok)
    jax.jit(lambda a: jsphere.simulate(p, jsphere.State.at_rest(p), jsphere.Torques(jsphere.Zero(3)), a).x)(
        0.2
    )  # traced
    assert not aot_dir.exists() or not list(aot_dir.glob("*.jaxexport"))
    assert _aot._stable(lambda t: t) is None and _aot._stable(object()) is None
    assert _aot._stable(1.5) == "float:1.5" and _aot._stable(jnp.sin) is not None
