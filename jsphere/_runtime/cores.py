"""Every CPU core for a batch of trials: JAX's CPU backend as one device per core, and a
batch's arrays split over those devices along their trial axis, so that one
`jax.jit(jax.vmap(simulate))` runs each device's share on its own core (a batched solve's
kernels are too small for XLA to split across threads: docs/decisions/one-cpu-device-per-core.md,
measured in `docs/performance.md`, "Every core"). jax is imported inside the functions, so that
importing this module stays cheap."""

from __future__ import annotations

import os

#: the one sentence that says when the device count can be set
WHEN = "call jsphere.use_cpu_cores() right after `import jax`, before any JAX operation runs"


def use_cpu_cores(n: int | None = None) -> int:
    """Make JAX's CPU backend `n` devices (default: the cores this process may run on), so that a batch
    split over them with `shard_trials` runs on `n` cores; returns `n`.

    This is JAX's `jax_num_cpu_devices`, which takes effect only before JAX runs its first
    operation: call it right after `import jax` (and `jsphere.enable_x64()`). `jax.devices()`
    then lists `n` CPU devices; a computation whose inputs are not split runs on the first. On
    a machine whose default backend is a GPU this changes nothing there.
    Raises `RuntimeError` (one line, what to do) when JAX has already started with another
    count; the same count again is allowed.
    """
    import jax

    if n is None:  # the cores this process may run on (its affinity mask where the system has one)
        n = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1
    n = int(n)
    if n < 1:
        raise ValueError(f"use_cpu_cores: n must be at least 1, got {n}")
    try:
        jax.config.update("jax_num_cpu_devices", n)
    except RuntimeError:
        have = len(jax.devices("cpu"))
        if have != n:
            raise RuntimeError(f"use_cpu_cores({n}): JAX already runs with {have} CPU device(s); {WHEN}") from None
    return n


def split_devices(n: int, devices=None) -> list:
    """The devices a batch of `n` equal shares is split over: the first `k` of `devices`
    (default: every device of JAX's default backend), `k` the most that divide `n`."""
    import jax

    devices = list(jax.devices() if devices is None else devices)
    return devices[: max(k for k in range(1, len(devices) + 1) if n % k == 0)]


def trial_mesh(devices=None):
    """A one-axis mesh, `"trials"`, over `devices` (default: every device of JAX's default
    backend)."""
    import jax
    import numpy as np
    from jax.sharding import Mesh

    return Mesh(np.array(jax.devices() if devices is None else list(devices)), ("trials",))


def shard_trials(tree, devices=None):
    """`tree` with each array split along its first (trial) axis over `devices` (default:
    every device of JAX's default backend), for a batched call such as
    `jax.jit(jax.vmap(simulate))` to run each device's share on its own device. Results come
    back split the same way; `np.asarray` gathers them.

    Every array leaf needs a first axis whose length is a multiple of the number of devices
    (`ValueError` otherwise, naming both); other leaves are returned as they are. With one
    device this places the arrays there.
    """
    import jax
    from jax.sharding import NamedSharding, PartitionSpec

    mesh = trial_mesh(devices)
    k = mesh.devices.size
    split = NamedSharding(mesh, PartitionSpec("trials"))

    def place(x):
        if not hasattr(x, "__array__"):  # jax and numpy arrays and scalars
            return x
        shape = getattr(x, "shape", ())
        if len(shape) == 0 or shape[0] % k:
            got = "a scalar" if len(shape) == 0 else f"{shape[0]} trials"
            raise ValueError(
                f"shard_trials: {got} cannot be split over {k} devices; use a batch whose length is a multiple of {k}"
            )
        return jax.device_put(x, split)

    return jax.tree_util.tree_map(place, tree)
