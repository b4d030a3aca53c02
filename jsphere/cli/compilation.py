"""How a `jsphere` process compiles: the persistent compilation cache shared by its runs
(`enable_compilation_cache`) and, for a one-off job, quick rather than fast programs
(`compile_for_one_run`). The measurements behind both: docs/performance.md."""

from __future__ import annotations

import os
import sys

_ONE_RUN_XLA_FLAG = "--xla_backend_optimization_level=0"


def enable_compilation_cache() -> None:
    """Persist XLA executables between processes, in the library's one cache
    (`jsphere.enable_compilation_cache`: `$JSPHERE_CACHE_DIR`, else `$XDG_CACHE_HOME/jsphere/jax`,
    else `~/.cache/jsphere/jax`), so a second run skips compilation.

    JAX does not persist executables that contain host callbacks, and equinox's run-time
    checks inside diffrax are host callbacks. For the CLI (whose inputs are validated before
    any solve, and whose solver failures jsphere reports itself, outside the compiled code)
    those checks are switched to equinox's `nan` mode unless `EQX_ON_ERROR` is set.

    Every executable is kept, however quick its compilation: `jsphere reproduce` compiles about
    a hundred small programs (eager operations between the solves) besides its solves, and with
    JAX's default threshold (1 s) a second run would compile them again.
    """
    from .._runtime.compilation_cache import default_cache_dir
    from .._runtime.compilation_cache import enable_compilation_cache as enable
    from .._runtime.private import equinox_on_error, set_equinox_on_error

    if "EQX_ON_ERROR" not in os.environ and equinox_on_error() == "raise":
        set_equinox_on_error("nan")
    try:
        enable(default_cache_dir())
    except Exception as e:  # a read-only home must not stop the run
        print(f"jsphere: compilation cache disabled ({e})", file=sys.stderr)


def compile_for_one_run() -> bool:
    """Have XLA compile this process's programs quickly rather than make them fast
    (`--xla_backend_optimization_level=0`, LLVM without its optimisation passes), unless
    `XLA_FLAGS` already sets the level. Returns whether the flag is in force.

    For `jsphere reproduce`, whose first run is almost all compilation: each of its ~30 solves
    is a single trajectory of a few milliseconds, so slower programs cost less than the
    compilation they save. The flag is part of the persistent cache's key (JAX hashes
    `XLA_FLAGS`), so these executables never serve other commands. It must be set before JAX
    creates its CPU client; later it changes nothing.
    """
    flags = os.environ.get("XLA_FLAGS", "")
    if "xla_backend_optimization_level" in flags:
        return _ONE_RUN_XLA_FLAG in flags.split()
    if "jax" in sys.modules:
        from .._runtime.private import jax_backends_initialized

        if jax_backends_initialized():
            return False
    os.environ["XLA_FLAGS"] = f"{flags} {_ONE_RUN_XLA_FLAG}".strip()
    return True
