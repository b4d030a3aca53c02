import atexit
import gc
import json
import os
import shutil
import tempfile
from pathlib import Path

import jax
import pytest

jax.config.update("jax_enable_x64", True)

# The CLI, run in-process by the tests, switches on JAX's persistent cache and exports its
# solves: they go to a folder of this test run, never to the user's cache.
_CACHE = tempfile.mkdtemp(prefix="jsphere-test-cache-")
os.environ["JSPHERE_CACHE_DIR"] = _CACHE
atexit.register(shutil.rmtree, _CACHE, ignore_errors=True)

import jsphere  # noqa: E402

REFERENCE = Path(__file__).resolve().parents[1].parent / "shared" / "reference" / "reference_cases.json"
if "JSPHERE_REFERENCE" in os.environ:
    REFERENCE = Path(os.environ["JSPHERE_REFERENCE"])


#: memory maps of a test process above which JAX's compiled programs are dropped after a test file
MAX_MAPS = 16_000


def memory_maps() -> int | None:
    """The number of memory maps of this process (Linux), else None."""
    try:
        with open("/proc/self/maps") as f:
            return sum(1 for _ in f)
    except OSError:
        return None


@pytest.fixture(autouse=True, scope="module")
def _bounded_compiled_programs():
    """Every program XLA compiles for the CPU holds memory maps of its own (its code and
    data), and a test worker that runs half the slow lane keeps thousands of programs: past the
    kernel's limit on maps (`vm.max_map_count`, 65,530 by default) XLA's next compilation
    crashes the worker. After a test file that leaves this process with more than `MAX_MAPS`,
    JAX's caches are cleared, which frees them (later files compile again, or load from the
    persistent cache)."""
    yield
    n = memory_maps()
    if n is not None and n > MAX_MAPS:
        jax.clear_caches()
        gc.collect()


@pytest.fixture(scope="session")
def reference():
    """The independent derivation's values (../shared/reference); tests skip where it is absent."""
    if not REFERENCE.exists():
        pytest.skip(f"reference data not found at {REFERENCE}")
    return json.loads(REFERENCE.read_text())


@pytest.fixture(scope="session")
def ref_params(reference):
    return {k: jsphere.RobotParams.from_dict(v) for k, v in reference["param_sets"].items()}


@pytest.fixture(scope="session")
def paper():
    return jsphere.RobotParams.paper()


@pytest.fixture(scope="session")
def straight(paper):
    """Acceleration (5.1) + braking (5.3) of the paper's robot, true end states, 100 Hz."""
    return jsphere.simulate_gaits(paper, [jsphere.acceleration(), jsphere.braking()])


@pytest.fixture
def programs_compiled(monkeypatch):
    """The XLA programs lowered while the test runs (one entry each), to check that host values
    become device arrays without one."""
    from jax._src.interpreters import pxla

    seen = []
    lower = pxla.lower_sharding_computation

    def count(*args, **kwargs):
        seen.append(args[1] if len(args) > 1 else "?")
        return lower(*args, **kwargs)

    monkeypatch.setattr(pxla, "lower_sharding_computation", count)
    return seen
