"""A persistent compilation cache for jsphere's programs, shared by the library and the CLI.

`enable_compilation_cache(path)` switches on JAX's persistent compilation cache (every
executable kept, however quick its compilation or small its size) and jsphere's cache of
exported programs (`jsphere._runtime.export_cache`) in the same directory, so that a new
process loads the programs an earlier one compiled instead of compiling them again.

JAX never writes an executable that contains a host callback, and equinox's run-time checks
(`eqx.error_if`, used by diffrax, e.g. on `SaveAt(ts=...)`) are host callbacks in equinox's
default `"raise"` mode. `callbacks_as_nan()` traces with equinox's `"nan"` mode instead: a
failed check then returns NaN in place of raising, with no host callback in the program.
jsphere validates its inputs on the host before a solve and reports solver failures through
`Trajectory.status` (1: the solver failed, 2: non-finite values), so a program traced this
way reports a failure there rather than by an exception from inside the compiled code.
"""

from __future__ import annotations

import contextlib
import os
import threading
from pathlib import Path
from typing import Iterator

#: the environment variable that chooses the cache directory (before `XDG_CACHE_HOME`)
CACHE_DIR_VARIABLE = "JSPHERE_CACHE_DIR"

_LOCK = threading.Lock()


def default_cache_dir() -> Path:
    """`$JSPHERE_CACHE_DIR` if set, else `$XDG_CACHE_HOME/jsphere/jax`, else
    `~/.cache/jsphere/jax`."""
    explicit = os.environ.get(CACHE_DIR_VARIABLE)
    if explicit:
        return Path(explicit).expanduser()
    base = os.environ.get("XDG_CACHE_HOME")
    root = Path(base).expanduser() if base else Path.home() / ".cache"
    return root / "jsphere" / "jax"


def enable_compilation_cache(path: str | os.PathLike | None = None) -> Path:
    """Keep compiled programs in `path` (default `default_cache_dir()`) for later processes.

    Switches on JAX's persistent compilation cache with no thresholds (every program is
    written: the eager operations around a solve compile in milliseconds each, and reloading
    them is still cheaper than compiling them again) and jsphere's cache of exported
    programs under `path/aot`. Returns the directory used (created if missing).

    Programs with host callbacks are not written by JAX; trace the solves inside
    `callbacks_as_nan()` for them to be kept. The cache is trusted code: do not point it at a
    directory that others can write to.
    """
    import jax

    from . import export_cache

    target = Path(path).expanduser() if path is not None else default_cache_dir()
    target.mkdir(parents=True, exist_ok=True)
    previous = jax.config.jax_compilation_cache_dir
    jax.config.update("jax_compilation_cache_dir", str(target))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", -1)  # -1: no size threshold
    if previous and Path(previous) != target:
        _reset_jax_cache()  # JAX opens its cache once; a new directory needs a fresh one
    export_cache.enable(target)
    return target


def _reset_jax_cache() -> None:
    try:
        from jax._src import compilation_cache as _cc

        _cc.reset_cache()
    except (ImportError, AttributeError):  # pragma: no cover - another JAX layout
        pass


def _errors_module():
    """equinox's module of run-time checks, if it has the two names `callbacks_as_nan` sets
    (`None` otherwise: then the block changes nothing)."""
    try:
        import equinox._errors as errors
    except ImportError:  # pragma: no cover - a future equinox without this module
        return None
    ok = hasattr(errors, "EQX_ON_ERROR") and hasattr(errors, "branched_error_if_impl_jit")
    return errors if ok else None


_NAN_IMPL = None


def _nan_impl(errors):
    """equinox's jitted check with the `"default"` mode read as `"nan"`: a jit of its own, so
    its traces are kept apart from those of the `"raise"` mode (equinox keys its cache of
    traced checks on the arguments, not on the mode)."""
    global _NAN_IMPL
    if _NAN_IMPL is None:
        import equinox as eqx

        def impl(x, pred, index, msgs, *, on_error):
            mode = "nan" if on_error == "default" else on_error
            return errors.branched_error_if_impl(x, pred, index, msgs, on_error=mode)

        _NAN_IMPL = eqx.filter_jit(impl)
    return _NAN_IMPL


@contextlib.contextmanager
def callbacks_as_nan() -> Iterator[None]:
    """Trace equinox's run-time checks in `"nan"` mode (no host callbacks) inside the block.

    The mode is read when a check is *traced*: wrap the first call of a solve (the one that
    traces and compiles it); a program compiled before, or outside the block, keeps the mode
    it was traced with. An explicit `EQX_ON_ERROR` in the environment wins (e.g.
    `EQX_ON_ERROR=breakpoint` for debugging), and the previous mode is restored on exit.
    Failures inside such programs are reported through `Trajectory.status`, not raised.
    Not thread-safe against checks traced in other threads meanwhile (they see `"nan"` too).
    """
    errors = _errors_module()
    if errors is None or "EQX_ON_ERROR" in os.environ:
        yield
        return
    with _LOCK:
        previous = errors.EQX_ON_ERROR, errors.branched_error_if_impl_jit
        errors.EQX_ON_ERROR, errors.branched_error_if_impl_jit = "nan", _nan_impl(errors)
    try:
        yield
    finally:
        with _LOCK:
            errors.EQX_ON_ERROR, errors.branched_error_if_impl_jit = previous
