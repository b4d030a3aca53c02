"""The persistent compilation cache: a second process loads the first one's programs."""

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from jsphere._runtime import compilation_cache as cc

ROOT = Path(__file__).resolve().parents[2]

#: a new process: cache on, the first `simulate_gaits` as a script calls it; prints the JAX
#: cache hits and misses of that call, the stop point and equinox's mode after it (unchanged)
CHILD = """
import json, sys
from jax import monitoring
import jsphere
jsphere.enable_x64()
from jsphere._runtime.compilation_cache import enable_compilation_cache
import equinox._errors as errors

events = {"hits": 0, "misses": 0}
def listen(name, **kw):
    if name == "/jax/compilation_cache/cache_hits": events["hits"] += 1
    if name == "/jax/compilation_cache/cache_misses": events["misses"] += 1
path = enable_compilation_cache(sys.argv[1])
p = jsphere.RobotParams.paper()
gaits = [jsphere.acceleration(), jsphere.braking()]
monitoring.register_event_listener(listen)
tr = jsphere.simulate_gaits(p, gaits)
x = float(tr.x[-1])
print(json.dumps({**events, "x": x, "status": int(tr.status), "path": str(path), "mode": errors.EQX_ON_ERROR}))
"""


def _run(cache: Path) -> dict:
    env = {k: v for k, v in os.environ.items() if k not in ("EQX_ON_ERROR", "JSPHERE_CACHE_DIR")}
    env["PYTHONPATH"] = str(ROOT)
    proc = subprocess.run(
        [sys.executable, "-c", CHILD, str(cache)], capture_output=True, text=True, env=env, timeout=600
    )
    assert proc.returncode == 0, proc.stderr
    return json.loads(proc.stdout.strip().splitlines()[-1])


@pytest.mark.slow
def test_second_process_hits_the_cache(tmp_path):
    cache = tmp_path / "cache"
    first = _run(cache)
    assert first["path"] == str(cache) and first["status"] == 0 and first["mode"] == "raise"
    assert first["misses"] > 0
    written = sorted(p.name for p in cache.iterdir() if p.is_file())
    assert len(written) >= first["misses"]  # every program of the call was written
    second = _run(cache)
    assert second["misses"] == 0 and second["hits"] > 0, second
    assert second["x"] == first["x"]


def test_default_dir(monkeypatch, tmp_path):
    monkeypatch.delenv("JSPHERE_CACHE_DIR", raising=False)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert cc.default_cache_dir() == tmp_path / "xdg" / "jsphere" / "jax"
    monkeypatch.delenv("XDG_CACHE_HOME")
    assert cc.default_cache_dir() == Path.home() / ".cache" / "jsphere" / "jax"
    monkeypatch.setenv("JSPHERE_CACHE_DIR", str(tmp_path / "mine"))
    assert cc.default_cache_dir() == tmp_path / "mine"


def _error_if_program(on_error: str = "default") -> str:
    """The lowered text of a jitted `eqx.error_if` check, traced now."""
    import equinox as eqx
    import jax
    import jax.numpy as jnp

    return jax.jit(lambda x: eqx.error_if(x, x < 0, "negative", on_error=on_error)).lower(jnp.ones(2)).as_text()


@pytest.fixture
def raise_mode(monkeypatch):
    """equinox's checks in their default `raise` mode, as at import (the CLI switches it)."""
    import equinox._errors as errors

    monkeypatch.delenv("EQX_ON_ERROR", raising=False)
    monkeypatch.setattr(errors, "EQX_ON_ERROR", "raise")


def test_callbacks_as_nan_nests_and_restores(raise_mode):
    import equinox._errors as errors

    with cc.callbacks_as_nan():
        with cc.callbacks_as_nan():
            assert "callback" not in _error_if_program()
        assert "callback" not in _error_if_program()
        assert "callback" in _error_if_program("raise")  # an explicit mode stays as written
    assert "callback" in _error_if_program()
    with pytest.raises(RuntimeError), cc.callbacks_as_nan():
        raise RuntimeError
    assert "callback" in _error_if_program()
    assert errors.EQX_ON_ERROR == "raise"  # equinox's own switch is never changed


def test_callbacks_as_nan_is_per_thread(raise_mode):
    """A block in one thread leaves the checks traced by another thread meanwhile alone."""
    import threading

    inside, seen = threading.Event(), {}

    def other():
        inside.wait(60)
        seen["text"] = _error_if_program()

    t = threading.Thread(target=other)
    t.start()
    with cc.callbacks_as_nan():
        inside.set()
        t.join(60)
    assert "callback" in seen["text"]


def test_explicit_environment_wins(monkeypatch):
    monkeypatch.setenv("EQX_ON_ERROR", "raise")
    with cc.callbacks_as_nan():
        assert "callback" in _error_if_program()


def test_nan_mode_leaves_no_host_callback(raise_mode):
    """An `eqx.error_if` check is a host callback, unless traced inside `callbacks_as_nan()`."""
    with cc.callbacks_as_nan():
        assert "callback" not in _error_if_program()
    assert "callback" in _error_if_program()


def _stop(throw: bool, grad: bool = False):
    """The lowered text of a caller's `jit` around the quickstart's stop point (or its gradient)."""
    import jax
    import jax.numpy as jnp

    import jsphere

    p = jsphere.RobotParams.paper()

    def stop(theta_max):
        gaits = [jsphere.acceleration(theta_max=theta_max), jsphere.braking(theta_max=theta_max)]
        return jsphere.simulate_gaits(p, gaits, ts=jnp.array([4.0]), throw=throw).x[-1]

    return jax.jit(jax.grad(stop) if grad else stop).lower(jnp.asarray(0.1, jnp.float64)).as_text()


def test_solves_hold_no_host_callback(raise_mode):
    """jsphere's programs, traced in equinox's default `raise` mode, hold no host callback
    (diffrax's checks are traced in `nan` mode, a failure is the status): JAX's persistent
    cache keeps them, and a caller's `jit` around a solve with `throw=False`. With
    `throw=True` inside a caller's `jit` the failure is raised by a check in that program."""
    assert "callback" not in _stop(throw=False)
    assert "callback" not in _stop(throw=False, grad=True)
    assert "callback" in _stop(throw=True)


#: a new process: cache on, the quickstart's eager gradient of the stop point; prints the JAX
#: cache misses of that call, the gradient and the exported programs kept
CHILD_GRAD = """
import json, sys
import jax, jax.numpy as jnp
from jax import monitoring
jax.config.update("jax_enable_x64", True)
import jsphere
from jsphere._runtime.fast_start import FastStart
from jsphere._runtime.quick_compile import programs_run_by

events = {"misses": 0}
def listen(name, **kw):
    if name == "/jax/compilation_cache/cache_misses": events["misses"] += 1
path = jsphere.enable_compilation_cache(sys.argv[1])
p = jsphere.RobotParams.paper()
def stop(theta_max):
    gaits = [jsphere.acceleration(theta_max=theta_max), jsphere.braking(theta_max=theta_max)]
    return jsphere.simulate_gaits(p, gaits, ts=jnp.array([4.0])).x[-1]
monitoring.register_event_listener(listen)
with programs_run_by(FastStart(path)):  # as the command line runs its solves
    g = float(jax.grad(stop)(0.1))
print(json.dumps({**events, "grad": g, "exported": sorted(f.name for f in (path / "aot").iterdir())}))
"""


@pytest.mark.slow
def test_second_process_gradient_is_loaded(tmp_path):
    """An eager `jax.grad` through `simulate_gaits` run by a `FastStart` exports its programs; a
    second process loads them and compiles nothing, with the same gradient."""
    cache = tmp_path / "cache"
    env = {k: v for k, v in os.environ.items() if k not in ("EQX_ON_ERROR", "JSPHERE_CACHE_DIR")}
    env["PYTHONPATH"] = str(ROOT)

    def run():
        proc = subprocess.run(
            [sys.executable, "-c", CHILD_GRAD, str(cache)], capture_output=True, text=True, env=env, timeout=600
        )
        assert proc.returncode == 0, proc.stderr
        assert "not exporting" not in proc.stderr, proc.stderr
        return json.loads(proc.stdout.strip().splitlines()[-1])

    first = run()
    assert first["misses"] > 0 and len(first["exported"]) == 1, first  # the solve with its forward-mode Jacobian
    second = run()
    assert second["misses"] == 0, second
    assert second["exported"] == first["exported"]
    assert second["grad"] == first["grad"]
    assert abs(first["grad"] - 2.5847084951773) < 1e-9


@pytest.mark.parametrize("ts", [[0.0, 2.0, 1.0], [0.0, float("nan")], [[0.0, 1.0]]])
def test_gait_output_times_are_checked_on_the_host(ts):
    """diffrax's check of the output times makes values NaN inside the program (reported as
    `RESULTS.nonfinite`): concrete times are refused before the solve, with their rule."""
    import jsphere

    p = jsphere.RobotParams.paper()
    with pytest.raises(ValueError, match=r"^simulate_gaits: ts must be a finite, non-decreasing 1-D array"):
        jsphere.simulate_gaits(p, [jsphere.acceleration(), jsphere.braking()], ts=ts)
