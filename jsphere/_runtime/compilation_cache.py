"""A persistent compilation cache for jsphere's programs, shared by the library and the CLI.

`enable_compilation_cache(path)` switches on JAX's persistent compilation cache, so that a new
process loads the programs an earlier one compiled instead of compiling them again, and keeps
jsphere's eager solves exported beside them, so that it skips tracing them too (the command line
does the same for its commands, `jsphere.cli.compilation.fast_start`). JAX
never writes an executable that holds a host callback, and jsphere's programs hold none
(docs/decisions/jsphere-s-programs-hold-no-host.md): the cache keeps a script's eager solves
and gradients, and a caller's own `jit` around solves with `throw=False`. With `throw=True`
inside a caller's `jit`, the failure is raised by an equinox check in the caller's program, a
host callback: that program is compiled again by each process.
"""

from __future__ import annotations

import os
from pathlib import Path

#: the environment variable that chooses the cache directory (before `XDG_CACHE_HOME`)
CACHE_DIR_VARIABLE = "JSPHERE_CACHE_DIR"


def default_cache_dir() -> Path:
    """`$JSPHERE_CACHE_DIR` if set, else `$XDG_CACHE_HOME/jsphere/jax`, else
    `~/.cache/jsphere/jax`."""
    explicit = os.environ.get(CACHE_DIR_VARIABLE)
    if explicit:
        return Path(explicit).expanduser()
    base = os.environ.get("XDG_CACHE_HOME")
    root = Path(base).expanduser() if base else Path.home() / ".cache"
    return root / "jsphere" / "jax"


def enable_compilation_cache(path: str | os.PathLike | None = None, *, export: bool = True) -> Path:
    """Keep compiled programs in `path` (default `default_cache_dir()`) for later processes.

    Switches on JAX's persistent compilation cache (`persistent_cache`), and with `export`
    (default) runs jsphere's eager solves and gradients for the rest of the process through
    programs exported to `path/aot` (`jsphere._runtime.fast_start.FastStart`, as the command
    line does), so that a new process skips tracing them as well as compiling them: the
    README's first gait solve and gradient then take a fraction of a second in a second
    process. `export=False` keeps JAX's cache alone. Returns the directory used (created if
    missing). Inside your own `jax.jit`, pass `throw=False` and read `Trajectory.ok` for the
    whole program to be kept (module docstring). The cache is trusted code: do not point it at
    a directory that others can write to.
    """
    from .fast_start import fast_start_in
    from .quick_compile import run_programs_by

    target = persistent_cache(path)
    run_programs_by(fast_start_in(target) if export else None)
    return target


def persistent_cache(path: str | os.PathLike | None = None) -> Path:
    """JAX's persistent compilation cache in `path` (default `default_cache_dir()`, created if
    missing), with no thresholds: every program is written, as the eager operations around a
    solve compile in milliseconds each, and reloading them is still cheaper than compiling them
    again. A setting of JAX for the whole process; returns the directory."""
    import jax

    from .private import reset_jax_compilation_cache

    target = Path(path).expanduser() if path is not None else default_cache_dir()
    target.mkdir(parents=True, exist_ok=True)
    previous = jax.config.jax_compilation_cache_dir
    jax.config.update("jax_compilation_cache_dir", str(target))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", -1)  # -1: no size threshold
    if previous and Path(previous) != target:
        reset_jax_compilation_cache()  # JAX opens its cache once; a new directory needs a fresh one
    return target


from .private import callbacks_as_nan as callbacks_as_nan  # noqa: E402  (re-exported)
