"""Checkpoints of a fit: the optimiser's whole state after every step, written atomically, and
read back only by the same fit (same data and configuration: the fingerprint)."""

from __future__ import annotations

import dataclasses
import hashlib
import json
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import jax.numpy as jnp
import numpy as np

from .._runtime.files import atomic_write
from ..numerics.lm import LM_KEYS
from .data import FitData
from .free import FreeParams
from .shooting import MU_LEVELS

#: version of the checkpoint's contents (part of its fingerprint: a checkpoint written by
#: another version is not resumed)
_CHECKPOINT_FORMAT = 4

#: A test's hook into every checkpoint write: called as `hook(event, path)` with `"written"`
#: when the temporary file is complete but not yet renamed into place, and `"saved"` after the
#: rename. A test raises or kills the process in it to stop a fit at a chosen point.
_checkpoint_hook: Callable[[str, Path], None] | None = None


def _config_fingerprint(data: FitData, free: FreeParams, cfg: dict) -> str:
    h = hashlib.sha256(data.fingerprint().encode())
    h.update(
        json.dumps(
            {
                "free": free.names,
                "slots": [dataclasses.astuple(s) for s in free.slots],
                "base": free.base.to_dict(),
                **cfg,
            },
            sort_keys=True,
            default=str,
        ).encode()
    )
    return h.hexdigest()


def _checkpoint_layout(
    stage: int,
    S: int,
    P: int,
    nu_shape: tuple,
    adam_shapes: Sequence[tuple],
    evaluation: dict[str, tuple],
    n_sig: int = 2,
) -> dict[str, tuple]:
    """The arrays a checkpoint at `stage` holds, with their shapes: everything the optimiser
    reads from one step to the next (`S` starts, `P` free parameters, `nu_shape` the nuisance
    parameters of one start: `(T, n)` per trial, or `(G, n)` per segment in multiple shooting).
    Stage 0 is Adam (its position, moments and best points), stages 1 and 2 the two
    Levenberg-Marquardt stages of single shooting, 4 + k level k of multiple shooting (the
    per-start damping, flags, counters and costs, and the evaluation at the current points,
    shapes `evaluation`: kept, not recomputed, because a vmapped solve's steps and so its
    last digits depend on the other starts it ran with), stage 3 the finished optimisation.
    `n_sig`: the noise levels (2 for captured poses, one per channel for onboard sensors)."""
    out = {"stage": (), "total_it": (), "sig": (n_sig,), "theta": (S, P), "nu": (S, *nu_shape), "max_defect": ()}
    if stage == 0:
        out |= {"adam_k": (), "adam_best_cost": (S,), "adam_best_theta": (S, P), "adam_best_nu": (S, *nu_shape)}
        out |= {f"adam_{i}": tuple(shape) for i, shape in enumerate(adam_shapes)}
    elif stage != 3:
        out |= {"it": (), **{k: (S,) for k in LM_KEYS}, **{f"out_{k}": v for k, v in evaluation.items()}}
    else:
        out |= {"it": (), "stage_converged": ()}
    return out


def _flat_evaluation(out: dict[str, Any]) -> dict[str, np.ndarray]:
    """An evaluation (`{"res", "J", "pose"}` or `{"blocks", "defect"}`) as named arrays."""
    if "blocks" in out:
        return {
            **dict(zip(("Hgg", "Hgn", "Hnn", "gg", "gn"), map(np.asarray, out["blocks"]))),
            "defect": np.asarray(out["defect"]),
        }
    # (trials of both kinds: the pose trials' simulated poses, then the onboard trials' readings)
    parts = out["pose"] if isinstance(out["pose"][0], tuple) else (out["pose"],)
    return {
        "res": np.asarray(out["res"]),
        "J": np.asarray(out["J"]),
        **{f"{key}_{c}": np.asarray(a) for key, part in zip(("pose", "onboard"), parts) for c, a in zip("xyq", part)},
    }


def _unflat_evaluation(a: dict[str, np.ndarray]) -> dict[str, Any]:
    if "Hgg" in a:
        return {"blocks": tuple(jnp.asarray(a[k]) for k in ("Hgg", "Hgn", "Hnn", "gg", "gn")), "defect": a["defect"]}
    parts = tuple(tuple(jnp.asarray(a[f"{key}_{c}"]) for c in "xyq") for key in ("pose", "onboard") if f"{key}_x" in a)
    return {"res": a["res"], "J": jnp.asarray(a["J"]), "pose": parts if len(parts) > 1 else parts[0]}


def _load_checkpoint(path: Path, fp: str, layout: Callable[[int], dict[str, tuple]]) -> tuple[dict | None, str | None]:
    """`(state, None)` for a checkpoint of this fit; `(None, why)` for one that cannot be used
    (damaged, or from another fit); `(None, None)` where there is none."""
    if not path.exists():
        return None, None
    try:
        with (
            open(path, "rb") as f,
            np.load(f, allow_pickle=False) as z,
        ):  # (np.load leaks the file it opens on a bad zip)
            got = {k: np.asarray(z[k]) for k in z.files}
    except Exception as e:  # noqa: BLE001 - whatever the reader trips on, the file is damaged
        first = (str(e).splitlines() or [""])[0][:100]
        return None, f"cannot be read ({type(e).__name__}{': ' + first if first else ''})"
    if "fingerprint" not in got:
        return None, "is not a checkpoint of jsphere fit (it has no fingerprint)"
    if got["fingerprint"].shape != () or str(got["fingerprint"]) != fp:
        return None, "is from another fit (other trials, options or jsphere version)"
    stage = got.get("stage")
    if stage is None or stage.shape != () or stage.dtype.kind not in "iu" or not 0 <= int(stage) < 4 + len(MU_LEVELS):
        return None, "is damaged (no valid stage)"
    for k, shape in layout(int(stage)).items():
        if k not in got:
            return None, f"is damaged (it has no {k!r})"
        if got[k].shape != shape or got[k].dtype.kind not in "biuf":
            return None, f"is damaged ({k!r} is {got[k].dtype} of shape {got[k].shape}, expected shape {shape})"
    return got, None


def _save_checkpoint(path: Path, fp: str, state: dict[str, Any]) -> None:
    def write(tmp):
        np.savez(tmp, fingerprint=np.array(fp), **state)
        if _checkpoint_hook is not None:
            _checkpoint_hook("written", path)

    atomic_write(path, write)
    if _checkpoint_hook is not None:
        _checkpoint_hook("saved", path)
