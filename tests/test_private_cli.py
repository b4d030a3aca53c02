"""The private JAX and equinox attributes that `jsphere._runtime.private_cli` relies on: a new
release that removes one fails here, naming it, rather than deep inside the command line."""

import importlib

import pytest

from jsphere._runtime import private_cli


def _private(module: str, attribute: str):
    try:
        mod = importlib.import_module(module)
    except ImportError as e:
        pytest.fail(f"{module} no longer exists ({e}); update jsphere/_runtime/private_cli.py")
    if not hasattr(mod, attribute):
        pytest.fail(f"{module}.{attribute} no longer exists; update jsphere/_runtime/private_cli.py")
    return getattr(mod, attribute)


def test_equinox_error_mode_is_a_module_attribute():
    mode = _private("equinox._errors", "EQX_ON_ERROR")
    assert mode in ("raise", "nan", "breakpoint"), f"equinox._errors.EQX_ON_ERROR is {mode!r}, not a mode"
    assert private_cli.equinox_error_mode() == mode
    previous = private_cli.set_equinox_error_mode("nan")
    try:
        assert previous == mode and private_cli.equinox_error_mode() == "nan"
    finally:
        private_cli.set_equinox_error_mode(previous)
    assert private_cli.equinox_error_mode() == mode


def test_xla_bridge_says_whether_the_backends_exist():
    asked = _private("jax._src.xla_bridge", "backends_are_initialized")
    assert callable(asked), "jax._src.xla_bridge.backends_are_initialized is no longer a function"
    import jax

    jax.numpy.zeros(1).block_until_ready()  # the backends exist now
    assert private_cli.backends_initialised() is True
