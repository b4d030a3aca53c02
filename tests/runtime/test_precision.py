"""float64 is opt-in: importing jsphere changes no JAX setting, `enable_x64` switches it on, and
a solve in float32 that the user did not choose warns once (`PrecisionWarning`)."""

from __future__ import annotations

import os
import subprocess
import sys
import warnings
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jsphere
from jsphere._runtime import precision
from jsphere.solve.options import tolerances

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture
def x64_off(monkeypatch):
    """JAX's float64 off for the test (restored after it), and the once-per-process warning not
    yet given."""
    monkeypatch.setattr(precision, "_warned", False)
    before = jax.config.jax_enable_x64
    jax.config.update("jax_enable_x64", False)
    try:
        yield
    finally:
        jax.config.update("jax_enable_x64", before)


def test_import_changes_no_jax_setting():
    env = {k: v for k, v in os.environ.items() if k != "JAX_ENABLE_X64"}
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT), env.get("PYTHONPATH", "")])
    out = subprocess.run(
        [sys.executable, "-c", "import jax, jsphere; print(jax.config.jax_enable_x64)"],
        capture_output=True,
        text=True,
        env=env,
        timeout=120,
    )
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "False"


def test_enable_x64_switches_float64_on(x64_off):
    assert jnp.zeros(()).dtype == jnp.float32
    jsphere.enable_x64()
    assert jax.config.jax_enable_x64
    assert jnp.zeros(()).dtype == jnp.float64


def test_float32_by_default_warns_once_and_names_the_switch(x64_off):
    p = jsphere.RobotParams.paper()
    assert p.R0.dtype == jnp.float32
    with pytest.warns(jsphere.PrecisionWarning) as record:
        assert tolerances(p.R0.dtype, None, None, where="simulate") == (1e-5, 1e-7)
    assert len(record) == 1
    message = str(record[0].message)
    assert message.startswith("simulate: float32 parameters because JAX's float64 is off")
    assert 'jax.config.update("jax_enable_x64", True)' in message and "jsphere.enable_x64()" in message
    assert record[0].filename == __file__  # it points at the caller, not into jsphere
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        tolerances(p.R0.dtype, None, None, where="simulate")  # once per process


def test_float32_chosen_with_float64_on_does_not_warn(monkeypatch):
    monkeypatch.setattr(precision, "_warned", False)
    p = jsphere.RobotParams.paper(dtype=jnp.float32)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert tolerances(p.R0.dtype, None, None) == (1e-5, 1e-7)
        assert tolerances(np.float64, None, None) == (1e-8, 1e-10)
    assert not precision._warned


def test_the_thread_local_switch_counts(monkeypatch):
    """float64 switched off only inside a block (`with jax.enable_x64(False)`, or
    `jax.experimental.disable_x64()` in older JAX) counts like the global switch."""
    if callable(getattr(jax, "enable_x64", None)):
        off = jax.enable_x64(False)
    elif callable(getattr(jax.experimental, "disable_x64", None)):
        off = jax.experimental.disable_x64()
    else:  # pragma: no cover
        pytest.skip("this JAX has no context manager for float64")
    monkeypatch.setattr(precision, "_warned", False)
    with off, pytest.warns(jsphere.PrecisionWarning):
        tolerances(jnp.float32, None, None)
    assert precision.x64_enabled()


@pytest.mark.slow
def test_simulate_gaits_in_float32_by_default_warns_and_runs(x64_off):
    p = jsphere.RobotParams.paper()
    with pytest.warns(jsphere.PrecisionWarning):
        tr = jsphere.simulate_gaits(p, [jsphere.acceleration(), jsphere.braking()], ts=jnp.array([4.0]))
    assert tr.x.dtype == jnp.float32
    np.testing.assert_allclose([float(tr.x[-1]), float(tr.y[-1])], [0.259199, 0.003594], atol=1e-4)
