"""Floating-point precision. JAX computes in float32 unless `jax_enable_x64` is on; jsphere
leaves that switch to the user (`enable_x64`), and says once per process when its solves run
in float32 only because the switch is off (`PrecisionWarning`).

jax is imported inside the functions, so that importing this module stays cheap."""

from __future__ import annotations

import sys
import warnings

#: the top-level modules whose frames a warning skips to point at the caller's own line
_LIBRARY_PACKAGES = frozenset(
    "jsphere jax jaxlib equinox diffrax optax optimistix lineax jaxtyping contextlib functools".split()
)

#: the one sentence that says how to turn float64 on
HOW_TO_ENABLE = (
    'turn float64 on with jax.config.update("jax_enable_x64", True) or jsphere.enable_x64(), '
    "before creating any arrays."
)


class PrecisionWarning(UserWarning):
    """jsphere computes in float32 because JAX's float64 (`jax_enable_x64`) is off. Issued once
    per process, by the first solve (`simulate`, `simulate_gaits`, `fit`, `plan`,
    `monte_carlo`, `reproduce`) whose parameters are float32 while float64 is off. The paper's
    numbers are at the 0.1 mm level, which float32 solves do not reach."""


def enable_x64() -> None:
    """Switch JAX's float64 on for this process: `jax.config.update("jax_enable_x64", True)`.

    Call it before creating any arrays (arrays made before keep their float32). jsphere never
    changes this switch by itself, except the `jsphere` command line for its own commands.
    """
    import jax

    jax.config.update("jax_enable_x64", True)


def x64_enabled() -> bool:
    """Whether JAX creates float64 arrays here and now (`jax_enable_x64`, including its
    thread-local and context-manager settings)."""
    import jax
    import numpy as np

    return jax.dtypes.canonicalize_dtype(np.float64) == np.float64


_warned = False


def _caller_stacklevel() -> int:
    """The `stacklevel` of `warnings.warn`, called from the function that calls this one, that
    names the first frame outside jsphere and the JAX libraries (the user's call)."""
    frame, level = sys._getframe(2), 2
    while frame is not None and frame.f_globals.get("__name__", "").partition(".")[0] in _LIBRARY_PACKAGES:
        frame, level = frame.f_back, level + 1
    return level


def warn_if_float32_by_default(dtype, where: str) -> None:
    """Warn (`PrecisionWarning`, once per process) when a solve in `where` runs with parameters
    of `dtype` float32 while JAX's float64 is off: float32 that the user did not choose. With
    float64 on, float32 parameters were asked for and nothing is said."""
    global _warned
    import numpy as np

    if _warned or np.dtype(dtype).itemsize > 4 or x64_enabled():
        return
    _warned = True
    warnings.warn(
        f"{where}: float32 parameters because JAX's float64 is off; jsphere's default tolerances and the "
        f"paper's 0.1 mm numbers need float64: {HOW_TO_ENABLE}",
        PrecisionWarning,
        stacklevel=_caller_stacklevel(),
    )
