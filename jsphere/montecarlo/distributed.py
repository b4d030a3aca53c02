"""One study on several processes of a JAX multi-process job (`monte_carlo(..., distributed=True)`,
`jsphere montecarlo --distributed`): each batch's trial indices sharded over a global mesh of
every process's devices and gathered back whole on every process. The processes run the same
batches in lockstep (the collectives of a batch pair up), so process 0 decides what to compute
and shares it (`share_from_process_0`).
"""

from __future__ import annotations

import itertools
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._runtime.checks import whole
from .._runtime.errors import InputError
from .._runtime.private import distributed_barrier


def start_distributed(distributed) -> bool:
    """Whether the study runs distributed (`monte_carlo`'s `distributed`); with True or a
    `Distributed`, start JAX's distributed runtime unless it is running."""
    from .options import Distributed

    if distributed is None:
        return jax.distributed.is_initialized() and jax.process_count() > 1
    if distributed is not True and distributed is not False and not isinstance(distributed, Distributed):
        raise InputError(f"monte_carlo: distributed must be True, False, None or a Distributed; got {distributed!r}.")
    if distributed is False or jax.distributed.is_initialized():
        return distributed is not False
    setup = distributed if isinstance(distributed, Distributed) else Distributed()
    coordinator, num_processes, process_id = setup.coordinator, setup.num_processes, setup.process_id
    host, _, port = str(coordinator).rpartition(":")
    if coordinator is not None and (not host or not port.isdigit()):
        raise InputError(f"monte_carlo: coordinator must be HOST:PORT (of process 0); got {coordinator!r}.")
    if num_processes is not None:
        num_processes = whole("monte_carlo", "num_processes", num_processes, 1)
    if process_id is not None:
        process_id = whole("monte_carlo", "process_id", process_id, 0)
    if (process_id or 0) >= (num_processes or math.inf):
        raise InputError(f"monte_carlo: process_id must be below num_processes; got {process_id} of {num_processes}.")
    try:
        jax.distributed.initialize(coordinator_address=coordinator, num_processes=num_processes, process_id=process_id)
    except RuntimeError as e:
        if "must be called before" not in str(e):
            raise
        raise InputError(
            "monte_carlo: distributed=True: JAX's distributed runtime starts only before JAX makes any array; call "
            "jax.distributed.initialize() at the top of the script (the `jsphere montecarlo --distributed` command "
            "does)."
        ) from None
    except ValueError as e:
        raise InputError(
            f"monte_carlo: distributed=True: JAX's distributed runtime could not start ({e}). Outside a cluster that "
            "JAX detects (SLURM, Open MPI, ...), give the coordinator HOST:PORT, the number of processes and this "
            "process's id."
        ) from None
    return True


#: how long a process waits for the others at a barrier before a collective [s]
BARRIER_TIMEOUT_S = 24 * 3600.0
_barriers = itertools.count()


def meet(what: str) -> None:
    """Wait for every process before a collective: JAX's CPU collectives fail when a process
    comes more than 30 s after the others (one still compiling, or computing a slower shard),
    the runtime's barrier waits `BARRIER_TIMEOUT_S`. Every process calls the same sequence."""
    distributed_barrier(f"jsphere-montecarlo-{next(_barriers)}-{what}", BARRIER_TIMEOUT_S)


def share_from_process_0(tree):
    """`tree` as process 0 has it, on every process (each passes a tree of the same shapes)."""
    from jax.experimental import multihost_utils

    meet("share")
    return jax.tree_util.tree_map(np.asarray, multihost_utils.broadcast_one_to_all(tree))


def global_indices(mesh: jax.sharding.Mesh, lo: int, hi: int) -> jax.Array:
    """The trial indices `lo .. hi - 1` as a global array sharded over `mesh`: each process
    makes only its own devices' shards."""
    from jax.sharding import NamedSharding, PartitionSpec

    idx = np.arange(lo, hi, dtype=np.int32)
    return jax.make_array_from_callback(idx.shape, NamedSharding(mesh, PartitionSpec("trials")), lambda s: idx[s])


def gather_batch(out) -> tuple:
    """The outcomes of a batch, sharded over every process's devices, whole on every process."""
    from jax.experimental import multihost_utils

    jax.block_until_ready(out)
    meet("gather")
    return tuple(np.asarray(a) for a in multihost_utils.process_allgather(out, tiled=True))


def batch_template(trials, padded: int, batch_size: int) -> dict:
    """Zero arrays with the shapes and dtypes of a batch's outcomes, by `BATCH_KEYS`: `batch_size`
    trials of a batch computed as `padded` trials."""
    from .batch import run_batch
    from .store import BATCH_KEYS

    shapes = eqx.filter_eval_shape(run_batch, trials, jax.ShapeDtypeStruct((padded,), jnp.int32))
    return {key: np.zeros((batch_size,) + s.shape[1:], s.dtype) for key, s in zip(BATCH_KEYS, shapes)}
