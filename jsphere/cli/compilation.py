"""How a `jsphere` command compiles: the persistent compilation cache shared by its runs and
exported solves (`fast_start`) and, for a one-off job, quick rather than fast programs
(`compile_for_one_run`). The library's solves are pure: this is the command line's choice, made
at its edge. The measurements behind it: docs/performance.md."""

from __future__ import annotations

import contextlib
import os
import sys
from typing import Iterator

_ONE_RUN_XLA_FLAG = "--xla_backend_optimization_level=0"


@contextlib.contextmanager
def fast_start(cache: bool = True, export: bool = True) -> Iterator:
    """While a command runs, with `cache`: its programs kept for the next run in the persistent
    cache (`persistent_cache`), and with `export` too, its solves run through a `FastStart` of
    that cache, exported for the next process. Yields that `FastStart`, or `None`.

    JAX does not persist executables that hold host callbacks, as equinox's run-time checks are:
    for the command (its inputs validated before any solve) those checks are traced in their
    `nan` mode unless `EQX_ON_ERROR` is set."""
    from .._runtime.compilation_cache import default_cache_dir, persistent_cache
    from .._runtime.fast_start import fast_start_in
    from .._runtime.private import equinox_errors_as, equinox_on_error
    from .._runtime.quick_compile import programs_run_by

    if not cache:
        yield None
        return
    try:
        folder = persistent_cache(default_cache_dir())
    except Exception as e:  # a read-only home must not stop the run
        print(f"jsphere: compilation cache disabled ({e})", file=sys.stderr)
        yield None
        return
    quiet = "EQX_ON_ERROR" in os.environ or equinox_on_error() != "raise"
    runner = fast_start_in(folder) if export else None
    with contextlib.nullcontext() if quiet else equinox_errors_as("nan"), programs_run_by(runner):
        yield runner


def compile_for_one_run() -> bool:
    """Have XLA compile this process's programs quickly rather than make them fast
    (`--xla_backend_optimization_level=0`) unless `XLA_FLAGS` sets the level; returns whether the
    flag is in force. For `jsphere reproduce`, whose ~30 solves of a few milliseconds each cost
    less than their compilation. The flag is part of the persistent cache's key, so these
    executables serve no other command; set after JAX's CPU client exists, it changes nothing."""
    flags = os.environ.get("XLA_FLAGS", "")
    if "xla_backend_optimization_level" in flags:
        return _ONE_RUN_XLA_FLAG in flags.split()
    if "jax" in sys.modules:
        from .._runtime.private import jax_backends_initialized

        if jax_backends_initialized():
            return False
    os.environ["XLA_FLAGS"] = f"{flags} {_ONE_RUN_XLA_FLAG}".strip()
    return True
