import atexit
import json
import os
import shutil
import tempfile
from pathlib import Path

import jax
import pytest

jax.config.update("jax_enable_x64", True)

# The CLI, run in-process by the tests, switches on the persistent caches: they go to a folder
# of this test run, never to the user's cache.
_CACHE = tempfile.mkdtemp(prefix="jsphere-test-cache-")
os.environ["JSPHERE_CACHE_DIR"] = _CACHE
atexit.register(shutil.rmtree, _CACHE, ignore_errors=True)

import jsphere  # noqa: E402
from jsphere._runtime import export_cache  # noqa: E402
from jsphere._runtime.private import equinox_on_error, set_equinox_on_error  # noqa: E402

REFERENCE = Path(__file__).resolve().parents[1].parent / "shared" / "reference" / "reference_cases.json"
if "JSPHERE_REFERENCE" in os.environ:
    REFERENCE = Path(os.environ["JSPHERE_REFERENCE"])


@pytest.fixture(autouse=True)
def _library_defaults():
    """Each test starts from the library's defaults: an in-process CLI run leaves the exported-
    program cache on and equinox's checks in `nan` mode, which would change what later tests
    trace (a program loaded from the cache is never traced again)."""
    aot, mode = export_cache._DIR, equinox_on_error()
    yield
    if export_cache._DIR != aot:
        export_cache.enable(None if aot is None else aot.parent)
    if mode is not None and equinox_on_error() != mode:
        set_equinox_on_error(mode)


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
