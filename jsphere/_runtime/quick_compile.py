"""XLA options for the programs of single, eager calls: compiled for a short first call.

On the CPU, XLA's older (non-MLIR) fusion emitters and LLVM's optimisation level 1 compile a
script's first solve or gradient about twice as fast, and the program runs as fast
(docs/decisions/eager-solves-compile-with-xla-s.md). `JSPHERE_XLA_DEFAULTS=1` keeps XLA's own
defaults, and an option named in `XLA_FLAGS` keeps the value given there. The programs hold no
host callback, so that JAX's persistent cache keeps them
(docs/decisions/jsphere-s-programs-hold-no-host.md).
"""

from __future__ import annotations

import contextlib
import functools
import os
from typing import Callable, Iterator

import equinox as eqx
import jax
import numpy as np

from .arrays import traced, transformed, under_jit
from .private import callbacks_as_nan

#: XLA options of the programs of eager calls on the CPU
CPU_OPTIONS = {"xla_cpu_use_fusion_emitters": False, "xla_backend_optimization_level": 1}
#: the environment variable that keeps XLA's defaults
DEFAULTS_VARIABLE = "JSPHERE_XLA_DEFAULTS"


@functools.cache
def _cpu_options_accepted() -> bool:
    """Whether this is the CPU backend and its XLA accepts `CPU_OPTIONS` (checked once per
    process by compiling a one-operation program)."""
    try:
        if jax.default_backend() != "cpu":
            return False
        jax.jit(lambda x: x + 1, compiler_options=CPU_OPTIONS).lower(np.float32(0.0)).compile()
        return True
    except Exception:  # noqa: BLE001 - an XLA without these options: its defaults
        return False


def options() -> dict | None:
    """The compiler options for an eager call's program here, or `None` for XLA's defaults:
    `CPU_OPTIONS` where this XLA accepts them, less any option named in `XLA_FLAGS` (e.g. by
    `jsphere reproduce`), which stays as set there."""
    if os.environ.get(DEFAULTS_VARIABLE, "") not in ("", "0") or not _cpu_options_accepted():
        return None
    flags = os.environ.get("XLA_FLAGS", "")
    return {k: v for k, v in CPU_OPTIONS.items() if k not in flags} or None


def eager_jit(fn: Callable) -> Callable:
    """`equinox.filter_jit(fn)`, compiled with `options()` when called eagerly with concrete
    arrays; traced calls use the plain `filter_jit` (one compiled function per shape each),
    and calls under `jvp` or `vmap` (`transformed`) inside a `jit` call `fn` itself.
    Traced in either way, equinox's run-time checks in `fn` are in their `nan` mode (no host
    callback: see above).

    (Measured with `benchmarks/first_result.py`: inlined under `jvp` and `vmap`, a fit's
    residual-Jacobian program traces and compiles in 0.7x the time; inlined in every traced
    call, the first gait solve and gradient compile 1.5x longer, as a function called at
    several places is then compiled at each.)"""
    plain = eqx.filter_jit(fn)
    quick: list = []

    def eager():
        if not quick:
            opts = options()
            quick.append(eqx.filter_jit(fn, compiler_options=opts) if opts else plain)
        return quick[0]

    @functools.wraps(fn)
    def call(*args, **kwargs):
        with callbacks_as_nan():  # read where the call is traced: no host callback in the program
            if traced((args, kwargs)):
                # under `jvp` or `vmap` inside a `jit`, the function is traced into the caller's
                # program: a nested program would be processed again by each transformation around it
                inline = transformed((args, kwargs)) and under_jit()
                return fn(*args, **kwargs) if inline else plain(*args, **kwargs)
            return eager()(*args, **kwargs)

    return call


def jit_concrete(fn: Callable) -> Callable:
    """`jax.jit(fn)` with `options()`, for a function only ever called with concrete arrays
    (an exported program's `call`)."""
    opts = options()
    return jax.jit(fn, compiler_options=opts) if opts else jax.jit(fn)


#: how the named programs of calls with concrete inputs run in this process (`run_program`):
#: `[None]`, directly; `jsphere.enable_compilation_cache` (for the rest of the process) and the
#: command line (for a command) set a `jsphere._runtime.fast_start.FastStart` (every thread)
_RUNNER: list = [None]


def run_programs_by(runner: Callable | None) -> None:
    """From now on in this process, `run_program(name, fn, rebuild, *args)` is `runner(name, fn,
    rebuild, *args)` (`None`: `fn(*args)`), outside any `programs_run_by` block."""
    _RUNNER[0] = runner


@contextlib.contextmanager
def programs_run_by(runner: Callable | None) -> Iterator[None]:
    """While the block runs (in any thread), `run_program(name, fn, rebuild, *args)` is `runner(name, fn,
    rebuild, *args)` (the application's choice: the command line keeps its programs exported
    for the next process, `jsphere.cli.compilation.fast_start`)."""
    previous, _RUNNER[0] = _RUNNER[0], runner
    try:
        yield
    finally:
        _RUNNER[0] = previous


def run_program(name: str, fn: Callable, rebuild: Callable, *args):
    """`fn(*args)`, or the runner's `runner(name, fn, rebuild, *args)` in its place where the
    application set one (`programs_run_by`). `fn` returns a pytree of arrays and
    `rebuild(leaves)` makes it again from its leaves; `name` names the program."""
    runner = _RUNNER[0]
    return fn(*args) if runner is None else runner(name, fn, rebuild, *args)
