"""The persistent compilation cache: a second process loads the first one's programs."""

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from jsphere._runtime import compilation_cache as cc

ROOT = Path(__file__).resolve().parents[2]

#: a new process: cache on, the first `simulate_gaits` traced in equinox's "nan" mode; prints
#: the JAX cache hits and misses of that call, the stop point and the mode restored after it
CHILD = """
import json, sys
from jax import monitoring
import jsphere
jsphere.enable_x64()
from jsphere._runtime.compilation_cache import callbacks_as_nan, enable_compilation_cache
import equinox._errors as errors

events = {"hits": 0, "misses": 0}
def listen(name, **kw):
    if name == "/jax/compilation_cache/cache_hits": events["hits"] += 1
    if name == "/jax/compilation_cache/cache_misses": events["misses"] += 1
path = enable_compilation_cache(sys.argv[1])
p = jsphere.RobotParams.paper()
gaits = [jsphere.acceleration(), jsphere.braking()]
monitoring.register_event_listener(listen)
with callbacks_as_nan():
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


def test_callbacks_as_nan_restores_the_mode(monkeypatch):
    import equinox._errors as errors

    monkeypatch.delenv("EQX_ON_ERROR", raising=False)
    before = errors.EQX_ON_ERROR
    with cc.callbacks_as_nan():
        assert errors.EQX_ON_ERROR == "nan"
        with cc.callbacks_as_nan():
            assert errors.EQX_ON_ERROR == "nan"
        assert errors.EQX_ON_ERROR == "nan"
    assert errors.EQX_ON_ERROR == before
    with pytest.raises(RuntimeError), cc.callbacks_as_nan():
        raise RuntimeError
    assert errors.EQX_ON_ERROR == before


def test_explicit_environment_wins(monkeypatch):
    import equinox._errors as errors

    monkeypatch.setenv("EQX_ON_ERROR", "raise")
    before = errors.EQX_ON_ERROR
    with cc.callbacks_as_nan():
        assert errors.EQX_ON_ERROR == before


def test_nan_mode_leaves_no_host_callback(monkeypatch):
    """An `eqx.error_if` check is a host callback, unless traced inside `callbacks_as_nan()`."""
    import equinox as eqx
    import equinox._errors as errors
    import jax
    import jax.numpy as jnp

    monkeypatch.delenv("EQX_ON_ERROR", raising=False)
    monkeypatch.setattr(errors, "EQX_ON_ERROR", "raise")  # as at import (the CLI's cache switches it)

    def lowered():
        return jax.jit(lambda x: eqx.error_if(x, x < 0, "negative")).lower(jnp.ones(2)).as_text()

    with cc.callbacks_as_nan():
        assert "callback" not in lowered()
    assert "callback" in lowered()


#: a new process: cache on, the quickstart's eager gradient of the stop point; prints the JAX
#: cache misses of that call, the gradient and the exported programs kept
CHILD_GRAD = """
import json, sys
import jax, jax.numpy as jnp
from jax import monitoring
jax.config.update("jax_enable_x64", True)
import jsphere

events = {"misses": 0}
def listen(name, **kw):
    if name == "/jax/compilation_cache/cache_misses": events["misses"] += 1
path = jsphere.enable_compilation_cache(sys.argv[1])
options = jsphere.SolverOptions(programs=jsphere.FastStart(path))
p = jsphere.RobotParams.paper()
def stop(theta_max):
    gaits = [jsphere.acceleration(theta_max=theta_max), jsphere.braking(theta_max=theta_max)]
    return jsphere.simulate_gaits(p, gaits, ts=jnp.array([4.0]), options=options).x[-1]
monitoring.register_event_listener(listen)
g = float(jax.grad(stop)(0.1))
print(json.dumps({**events, "grad": g, "exported": sorted(f.name for f in (path / "aot").iterdir())}))
"""


@pytest.mark.slow
def test_second_process_gradient_is_loaded(tmp_path):
    """An eager `jax.grad` through `simulate_gaits` with a `FastStart` exports its programs; a
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
