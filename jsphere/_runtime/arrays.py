"""Array helpers that keep small host values from becoming XLA programs."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from jax.interpreters.partial_eval import DynamicJaxprTracer
from jaxtyping import Array


def as_array(x, dtype) -> Array:
    """`jnp.asarray(x, dtype)`, except that a Python or NumPy value is converted by NumPy first.

    Converting a Python float with `jnp.asarray` is an XLA program (a weak-to-strong
    `convert_element_type`): compiled once, then loaded from the persistent cache by every new
    process (`docs/performance.md`, "Few programs in a run of `jsphere reproduce`").
    JAX arrays and tracers go through `jnp.asarray` unchanged.
    """
    if isinstance(x, (jax.Array, jax.core.Tracer)):
        return jnp.asarray(x, dtype=dtype)
    if isinstance(x, (list, tuple)) and any(
        isinstance(v, (jax.Array, jax.core.Tracer)) for v in jax.tree_util.tree_leaves(x)
    ):
        return jnp.asarray(x, dtype=dtype)
    return jax.device_put(np.asarray(x, dtype=dtype))  # (`jnp.asarray` would lower a copy program)


def to_jax(x) -> Array:
    """`jnp.asarray(x)` (dtype and weak type alike) without the copy program `jnp.asarray` lowers
    for a Python or NumPy value (see `as_array`)."""
    if isinstance(x, (jax.Array, jax.core.Tracer)):
        return x
    if isinstance(x, (bool, int, float, complex, np.ndarray, np.generic)):
        return jax.device_put(x)
    return jnp.asarray(x)


def under_jit() -> bool:
    """Whether this code is being traced by `jax.jit` (a constant made here is then a tracer).

    A NumPy scalar becomes a device array without compiling anything, unlike an eager JAX
    operation (e.g. `jnp.zeros(()) + 0.0`, one more small program per process).
    """
    return isinstance(jax.device_put(np.float32(0.0)), jax.core.Tracer)


def transformed(tree) -> bool:
    """Whether a leaf of `tree` is traced by a transformation other than `jit` (`jvp`, `vmap`)."""
    return any(
        isinstance(x, jax.core.Tracer) and not isinstance(x, DynamicJaxprTracer)
        for x in jax.tree_util.tree_leaves(tree)
    )


def traced(tree) -> bool:
    """Whether a call may be under a transformation: traced leaves in `tree`, or inside a `jit`."""
    return any(isinstance(x, jax.core.Tracer) for x in jax.tree_util.tree_leaves(tree)) or under_jit()
