"""`FastStart`: the programs of a command's solves kept on disk, so that the next process skips
tracing them (docs/decisions/persistent-compilation-cache-and-exported-solves.md).

The command line runs its solves' programs through a `FastStart(path)`
(`jsphere._runtime.quick_compile.programs_run_by`): each program of a call with concrete inputs
is exported once with `jax.export` (traced with equinox's checks in their `nan` mode: host
callbacks cannot be serialised) to `<path>/aot/<key>.jaxexport`; later calls, in this process or
the next, run the deserialised program, whose executable comes from JAX's persistent cache.

The key hashes everything the program depends on: its name, the source of every `jsphere`
module, the versions of jax, jaxlib, diffrax and equinox, the backend, its device count and
float precision, the tree structure of the arguments, the shapes and dtypes of their arrays,
and the values of their non-array parts. A call whose non-array parts have no stable value (a
`lambda`, a function defined outside jsphere, any object printed with its address) is not
exported, and any failure of the exported path falls back to the ordinary call.
"""

from __future__ import annotations

import functools
import hashlib
import os
import sys
from pathlib import Path
from typing import Any, Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .arrays import under_jit
from .files import atomic_write
from .precision import x64_enabled
from .private import callbacks_as_nan
from .quick_compile import jit_concrete

_PLAIN = (bool, int, float, complex, str, type(None))
_FUNCTION_MODULES = ("jsphere.", "jax.", "jax", "numpy")


class FastStart:
    """Runs the programs of solves with concrete inputs as programs exported to `path/aot`, kept
    for later processes (module docstring). `jsphere reproduce`, `fit`, `plan` and `montecarlo`
    run through `FastStart(<cache>)`. The folder is trusted code: do not point it at a directory
    that others can write to. A program with host callbacks (`EQX_ON_ERROR=raise`) cannot be
    exported and runs as usual, with a note on stderr."""

    def __init__(self, path: str | os.PathLike):
        self.path = Path(path).expanduser() / "aot"
        self._loaded: dict[str, Callable] = {}
        self._failed: set[str] = set()  # keys whose export failed (e.g. host callbacks)

    def __repr__(self) -> str:
        return f"FastStart({str(self.path.parent)!r})"

    def __call__(self, name: str, fn: Callable, rebuild: Callable, *args):
        """`fn(*args)`, through an exported program where the call has a stable key. `fn` returns
        an `equinox.Module` of arrays; `rebuild(leaves)` makes it again from its leaves (its
        tree structure is not serialised)."""
        dyn, static = eqx.partition(args, eqx.is_array)
        leaves, treedef = jax.tree_util.tree_flatten(dyn)
        if any(isinstance(x, jax.core.Tracer) for x in leaves) or under_jit():
            return fn(*args)  # traced inputs, or inside a user's jit: the caller's program
        key = _key(name, leaves, treedef, static)
        if key is not None and key not in self._failed:
            try:
                run = self._loaded.get(key) or self._load_or_export(key, fn, treedef, static, leaves)
                return rebuild(run(*_committed(leaves)))
            except Exception as e:  # noqa: BLE001 - the exported path is an optimisation only
                self._failed.add(key)  # `fn` runs itself for this key from now on; said once
                print(f"jsphere: not exporting {name} ({type(e).__name__}: {e}); running it directly", file=sys.stderr)
        return fn(*args)

    def _load_or_export(self, key, fn, treedef, static, leaves) -> Callable:
        path = self.path / f"{key}.jaxexport"
        exported = None
        if path.exists():
            try:
                exported = jax.export.deserialize(bytearray(path.read_bytes()))
            except Exception:  # noqa: BLE001 - a truncated or foreign file: export it again
                exported = None
        if exported is None:

            def flat(*lv):
                out = fn(*eqx.combine(jax.tree_util.tree_unflatten(treedef, lv), static))
                return jax.tree_util.tree_leaves(out)

            avals = [
                jax.ShapeDtypeStruct(np.shape(x), jnp.result_type(x), weak_type=bool(getattr(x, "weak_type", False)))
                for x in leaves
            ]
            with callbacks_as_nan():  # JAX cannot serialise host callbacks
                exported = jax.export.export(jax.jit(flat))(*avals)
            atomic_write(path, lambda tmp: Path(tmp).write_bytes(bytes(exported.serialize())), suffix=".tmp")
        run = jit_concrete(exported.call)
        self._loaded[key] = run
        return run


@functools.cache
def fast_start_in(folder: Path) -> FastStart:
    """The one `FastStart` of a cache folder in this process (a process running several
    commands, or a script and a command, loads each exported program once)."""
    return FastStart(folder)


def _committed(leaves: list) -> list:
    """The arguments as arrays committed to a device. A program's `call` compiles once per
    pattern of committed and uncommitted arguments (an array a program made is committed, one
    made from NumPy is not), so that a loop feeding one call's results to the next would
    compile it twice."""
    device = jax.devices()[0]
    return [x if isinstance(x, jax.Array) and x.committed else jax.device_put(x, device) for x in leaves]


@functools.cache
def environment() -> str:
    """What every exported program depends on besides its arguments (computed once): the
    source of every jsphere module, library versions, the backend and its device count (a
    program may split its work over the devices)."""
    import diffrax
    import jaxlib

    h = hashlib.sha256()
    package = Path(__file__).resolve().parent.parent
    for f in sorted(package.rglob("*.py")):
        h.update(f.relative_to(package).as_posix().encode() + b"\0" + f.read_bytes())
    for item in (jax.__version__, jaxlib.__version__, diffrax.__version__, eqx.__version__):
        h.update(item.encode() + b"\0")
    h.update(f"{jax.default_backend()}\0{jax.device_count()}\0".encode())
    return h.hexdigest()


def _stable(x: Any) -> str | None:
    """A process-independent text for a non-array leaf, or `None` if it has none."""
    if isinstance(x, _PLAIN):
        return f"{type(x).__name__}:{x!r}"
    if isinstance(x, np.dtype):
        return f"dtype:{x}"
    mod, qual = getattr(x, "__module__", None), getattr(x, "__qualname__", None)
    if callable(x) and isinstance(mod, str) and isinstance(qual, str) and "<" not in qual:
        if mod == "jsphere" or mod.startswith(_FUNCTION_MODULES):
            return f"fn:{mod}.{qual}"
    return None


def _key(name: str, leaves, treedef, static) -> str | None:
    s_leaves, s_def = jax.tree_util.tree_flatten(static)
    parts = [_stable(x) for x in s_leaves]
    if any(p is None for p in parts):
        return None
    tree = f"{treedef}|{s_def}"
    if " at 0x" in tree:  # an object identified by its address
        return None
    h = hashlib.sha256()
    for item in (
        "jsphere-aot-1",
        name,
        environment(),
        f"x64={x64_enabled()}",
        tree,
        *parts,
        *(f"{np.shape(x)}:{jnp.result_type(x)}:{bool(getattr(x, 'weak_type', False))}" for x in leaves),
    ):
        h.update(str(item).encode() + b"\0")
    return h.hexdigest()[:40]
