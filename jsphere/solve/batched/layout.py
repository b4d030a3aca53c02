"""The named layouts of a solve (how it carries its state and how a batch takes its steps),
and the batch sizes at which the batch engine changes layout.

One idea runs through the engine under one name, *shared steps*: a batch under `vmap`
integrated as one system with one step-size sequence, accepted only when every trial meets
its own tolerance (`jsphere.solve.batched.segment`). *Components* is the state's form in every
batched layout: a tuple of scalars, each a contiguous `(batch,)` vector under `vmap`
(`jsphere.solve.batched.components`).
"""

from __future__ import annotations

import enum


class Layout(enum.Enum):
    """How one solve runs (a static argument of the compiled solves)."""

    #: the flat `(16+N,)` state in diffrax's loop: unbatched calls and small batches
    FLAT = "flat"
    #: the state as scalar components, in diffrax's loop per trial
    COMPONENTS = "components"
    #: components; the batch shares one step sequence
    SHARED_STEPS = "shared_steps"
    #: as `SHARED_STEPS`; a batch whose shared steps fail is solved again with per-trial steps,
    #: so that a failing trial fails alone (`throw=False`)
    SHARED_STEPS_RETRY = "shared_steps_retry"
    #: components; every trial takes its own steps, in lockstep in the batch loop
    PER_TRIAL_STEPS = "per_trial_steps"

    @property
    def components(self) -> bool:
        """Whether the state is carried as a tuple of scalar components."""
        return self is not Layout.FLAT

    @property
    def batch_solve(self) -> bool:
        """Whether each segment's solve goes through `jsphere.solve.batched.segment.solve`."""
        return self in (Layout.SHARED_STEPS, Layout.SHARED_STEPS_RETRY, Layout.PER_TRIAL_STEPS)

    @property
    def shared(self) -> bool:
        """Whether a batch shares one step sequence."""
        return self in (Layout.SHARED_STEPS, Layout.SHARED_STEPS_RETRY)


def steps_layout(batch_steps: str, throw: bool) -> Layout:
    """The layout a batch of at least `SHARED_MIN_BATCH` trials asks for by `batch_steps`: with
    `throw=False`, shared steps that fail are retried with per-trial steps, so that each
    failing trial is reported alone and the others keep their results (with `throw=True` a
    failure raises anyway, and the batch's programs do without the per-trial solve)."""
    if batch_steps == "per_trial":
        return Layout.PER_TRIAL_STEPS
    return Layout.SHARED_STEPS if throw else Layout.SHARED_STEPS_RETRY


#: Smallest batch that takes the batch loop's layouts (shared steps with
#: `batch_steps="shared"`, the default; per-trial steps in lockstep with `"per_trial"`);
#: smaller batches keep diffrax's per-trial loop, which compiles faster.
SHARED_MIN_BATCH = 32

#: Smallest batch that carries its state as components when the batch loop is not used.
COMPONENT_MIN_BATCH = 256

#: Largest batch one vectorised solve takes on a CPU; bigger batches run as a `lax.map` over
#: chunks of this many trials, so that the solver's working set stays in cache.
BATCH_CHUNK = 1024

#: The same on a GPU or another accelerator (`batch_chunk`), not measured: its kernels need
#: many trials each to fill the device; the gradient of a chunk keeps about 40 KB of
#: checkpoints per trial, 10 GB for this many.
ACCELERATOR_BATCH_CHUNK = 2**18


def batch_chunk() -> int:
    """The chunk size of large batches on the platform JAX computes on by default (its default
    device's, where one is set): `BATCH_CHUNK` on a CPU, `ACCELERATOR_BATCH_CHUNK` elsewhere
    (docs/decisions/batches-in-chunks-of-1024-trials.md)."""
    import jax

    device = jax.config.jax_default_device
    platform = device.platform if device is not None and not isinstance(device, str) else jax.default_backend()
    return BATCH_CHUNK if platform == "cpu" else ACCELERATOR_BATCH_CHUNK


#: Chunk size of the backward pass of large batches outside the batch loop (the flat layout's
#: VJP, recomputed).
GRAD_CHUNK = 64

#: Gradients of batches in the batch loop by its discrete adjoint
#: (`jsphere.solve.batched.adjoint`); `False` gives every batch the per-trial VJP of diffrax's
#: loop.
SHARED_ADJOINT = True
