"""The private JAX and equinox APIs the command line uses, each behind one small function.

Every use names the private attribute and why no public API serves; `tests/test_private_cli.py`
fails with a clear message when a new JAX or equinox release removes one.
"""

from __future__ import annotations


def equinox_error_mode() -> str | None:
    """Equinox's run-time error mode (`"raise"`, `"nan"`, `"breakpoint"`), or None where this
    equinox has no such setting.

    Private: `equinox._errors.EQX_ON_ERROR`. Equinox reads the environment variable
    `EQX_ON_ERROR` once, at import, into this attribute; it has no public getter."""
    try:
        import equinox._errors as eqx_errors
    except ImportError:  # pragma: no cover - a future equinox without this module
        return None
    return getattr(eqx_errors, "EQX_ON_ERROR", None)


def set_equinox_error_mode(mode: str) -> str | None:
    """Set equinox's run-time error mode for the programs traced from now on; return the
    previous mode (None, and nothing set, where this equinox has no such setting).

    Private: `equinox._errors.EQX_ON_ERROR`. The environment variable `EQX_ON_ERROR` is read
    once, when equinox is imported (which `import jsphere` has done by then), and equinox has no
    public setter. The command line sets `"nan"`: JAX does not persist executables that contain
    host callbacks, and equinox's `"raise"` checks are host callbacks."""
    try:
        import equinox._errors as eqx_errors
    except ImportError:  # pragma: no cover - a future equinox without this module
        return None
    previous = getattr(eqx_errors, "EQX_ON_ERROR", None)
    if previous is not None:
        eqx_errors.EQX_ON_ERROR = mode
    return previous


def backends_initialised() -> bool:
    """Whether JAX has created its backends (the XLA clients) in this process.

    Private: `jax._src.xla_bridge.backends_are_initialized`. The public ways to ask
    (`jax.devices()`, `jax.default_backend()`) create the backends, after which `XLA_FLAGS`
    no longer changes anything; the command line asks before it sets such a flag."""
    from jax._src import xla_bridge

    return bool(xla_bridge.backends_are_initialized())
