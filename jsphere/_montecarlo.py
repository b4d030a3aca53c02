"""Monte-Carlo studies of gait motions: vmapped batches, deterministic seeds, resumable files.

Each trial `i` draws its parameters from `jax.random.fold_in(PRNGKey(seed), i)`, so a study is
the same whatever the batch size or the number of devices; batches are sharded over all local
devices; finished batches are written atomically to `out/` and a killed study resumes there.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import os
import sys
import tempfile
import time
from pathlib import Path
from typing import Mapping, Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ._gaits import Gait, simulate_gaits
from ._io import atomic_write_text
from ._linalg import cross
from ._names import get_value, parse_name, set_value
from ._params import RobotParams

_DISTRIBUTIONS = {"normal": ("mean", "sd"), "uniform": ("low", "high")}


def _check_vary(params: RobotParams, vary: Mapping[str, Sequence]) -> list[tuple[str, str, float, float]]:
    out = []
    for name, spec in vary.items():
        parse_name(name)
        if name != "R_m":
            get_value(params, name)  # checks the index fits
        if not isinstance(spec, (tuple, list)) or len(spec) != 3 or spec[0] not in _DISTRIBUTIONS:
            raise ValueError(f"vary[{name!r}] must be ('normal', mean, sd) or ('uniform', low, high); got {spec!r}.")
        kind, a, b = spec[0], float(spec[1]), float(spec[2])
        if kind == "normal" and not b >= 0:
            raise ValueError(f"vary[{name!r}]: the standard deviation must be >= 0; got {b}.")
        if kind == "uniform" and not b >= a:
            raise ValueError(f"vary[{name!r}]: uniform needs low <= high; got ({a}, {b}).")
        if get_value(params, name).ndim != 0:
            raise ValueError(f"vary[{name!r}]: vary scalar components (e.g. 'I[0,0]'), not a whole field.")
        out.append((name, kind, a, b))
    return out


def _sample(kinds: tuple[str, ...], ab, seed, i, dtype):
    """Values of every varied name for trial `i` (deterministic in `(seed, i)` only)."""
    key = jax.random.fold_in(jax.random.PRNGKey(seed), i)
    vals = []
    for j, kind in enumerate(kinds):
        k = jax.random.fold_in(key, j)
        a, b = ab[j, 0], ab[j, 1]
        if kind == "normal":
            vals.append(a + b * jax.random.normal(k, dtype=dtype))
        else:
            vals.append(a + (b - a) * jax.random.uniform(k, dtype=dtype))
    return jnp.stack(vals) if vals else jnp.zeros((0,), dtype)


#: trials per vmapped chunk. Every trial is computed inside a vmap of exactly this width,
#: whatever the batch size or device count, which keeps results bitwise reproducible (XLA
#: may pick other kernels, summing in another order, for other widths).
CHUNK = 64


@eqx.filter_jit
def _run_batch(params, gaits, names, kinds, ab, seed, idx, reset, rtol, atol, mesh=None):
    """Trials `idx` of a study: one compiled function per structure, reused across calls."""
    dt = params.R0.dtype
    ts = jnp.reshape(sum(jnp.asarray(g.T, dt) for g in gaits), (1,))

    def one(i):
        vals = _sample(kinds, ab, seed, i, dt)
        p = params
        for j, name in enumerate(names):
            p = set_value(p, name, vals[j])
        tr = simulate_gaits(p, gaits, ts=ts, reset=reset, rtol=rtol, atol=atol, throw=False)
        speed = p.R0 * jnp.linalg.norm(cross(tr.Omega[-1], tr.gamma[-1]))
        return vals, tr.x[-1], tr.y[-1], speed, tr.status

    def local(ii):  # this device's trials, in chunks of CHUNK
        out = jax.lax.map(jax.vmap(one), ii.reshape(-1, CHUNK))
        return jax.tree_util.tree_map(lambda a: a.reshape((-1,) + a.shape[2:]), out)

    if mesh is None:
        return local(idx)
    from jax.sharding import PartitionSpec

    return jax.shard_map(local, mesh=mesh, in_specs=PartitionSpec("trials"), out_specs=PartitionSpec("trials"), check_vma=False)(idx)


@dataclasses.dataclass
class MonteCarloResult:
    """Per-trial outcomes of `monte_carlo` (NumPy arrays of length `n`).

    `samples[name]`: the drawn values; `x_final, y_final` [m]: stop point; `speed_final` [m/s]:
    speed of the shell centre at the end; `status`: 0 for a successful solve (see
    `Trajectory.status`).
    """

    n: int
    seed: int
    samples: dict[str, np.ndarray]
    x_final: np.ndarray
    y_final: np.ndarray
    speed_final: np.ndarray
    status: np.ndarray
    elapsed_s: float = 0.0

    def stats(self, level: float = 0.95) -> dict:
        """Stop-point mean, covariance, the `level` confidence ellipse and quantiles (successful
        trials only)."""
        ok = self.status == 0
        xy = np.stack([self.x_final[ok], self.y_final[ok]], axis=1)
        mean = xy.mean(axis=0)
        cov = np.cov(xy, rowvar=False) if len(xy) > 1 else np.zeros((2, 2))
        evals, evecs = np.linalg.eigh(cov)
        s = -2.0 * math.log(1.0 - level)  # chi-squared quantile with 2 degrees of freedom
        q = [0.025, 0.5, 0.975]
        return {
            "n": int(self.n), "n_failed": int((~ok).sum()), "mean_xy_m": mean.tolist(), "cov_xy_m2": cov.tolist(),
            "sd_xy_m": np.sqrt(np.diag(cov)).tolist(),
            "ellipse": {"level": level, "semi_axes_m": np.sqrt(np.maximum(evals, 0) * s).tolist(),
                        "angle_rad": float(math.atan2(evecs[1, -1], evecs[0, -1]))},
            "quantiles": {"q": q, "x_m": np.quantile(xy[:, 0], q).tolist(), "y_m": np.quantile(xy[:, 1], q).tolist()},
            "distance_m": {"mean": float(np.hypot(*xy.T).mean()), "sd": float(np.hypot(*xy.T).std(ddof=1)) if len(xy) > 1 else 0.0},
            "speed_final_m_s": {"mean": float(self.speed_final[ok].mean()), "max": float(self.speed_final[ok].max())},
        }  # fmt: skip


def _fingerprint(params, gaits, spec, seed, batch_size, reset, rtol, atol) -> str:
    leaves = [np.asarray(x).tolist() for x in jax.tree_util.tree_leaves((params, gaits)) if hasattr(x, "shape")]
    text = json.dumps([leaves, str(jax.tree_util.tree_structure(gaits)), spec, seed, batch_size, repr(reset), rtol, atol])
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def _save_npz(path: Path, **arrays) -> None:
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.stem}.", suffix=".npz")
    os.close(fd)
    try:
        np.savez(tmp, **arrays)
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def monte_carlo(
    params: RobotParams,
    gaits: Sequence[Gait],
    *,
    vary: Mapping[str, Sequence],
    n: int,
    seed: int = 0,
    batch_size: int = 1024,
    reset=False,
    rtol: float = 1e-8,
    atol: float = 1e-10,
    out: str | os.PathLike | None = None,
    progress: bool = True,
) -> MonteCarloResult:
    """Run the gaits `n` times with parameters drawn from `vary`; return the stop points.

    **Arguments:**
    - `params`: the nominal `RobotParams`; `gaits`: a list as for `simulate_gaits`.
    - `vary`: `{name: ("normal", mean, sd) | ("uniform", low, high)}` with names as in
      `jsphere fit --free`: `"j"`, `"m0"`, `"I[0,0]"`, `"r_m[2]"`, or `"R_m"` (the distance
      `|r_m|`, keeping its direction).
    - `n`, `seed`: number of trials and the seed. Trial `i` uses the key
      `fold_in(PRNGKey(seed), i)`: the same study whatever `batch_size` or device count.
    - `batch_size`: trials per compiled call (memory stays bounded for any `n`); rounded up to
      a multiple of 64 times the number of local devices, over which each batch is sharded.
      Inside, trials run in vmapped chunks of 64 (`CHUNK`), so results are bitwise identical
      for any batch size and device count.
    - `out`: a folder. Each finished batch is written there atomically, with a manifest; run
      the same call again after an interruption and it resumes (a folder holding a different
      study is refused).
    - `progress`: print a progress line to stderr.

    Returns a `MonteCarloResult` (`x_final`, `y_final`, ... arrays of length `n`; `.stats()`).
    """
    if n < 1:
        raise ValueError(f"monte_carlo: n must be >= 1; got {n}.")
    spec = _check_vary(params, vary)
    gaits = list(gaits)
    if not gaits or not all(isinstance(g, Gait) for g in gaits):
        raise TypeError("monte_carlo: gaits must be a non-empty list of jsphere.Gait.")
    devices = jax.local_devices()
    nd = len(devices)
    unit = CHUNK * nd
    B = int(math.ceil(max(1, min(batch_size, n)) / unit) * unit)
    n_batches = int(math.ceil(n / B))
    names = tuple(name for name, _, _, _ in spec)
    kinds = tuple(kind for _, kind, _, _ in spec)
    ab = jnp.asarray([[a, b] for _, _, a, b in spec], dtype=params.R0.dtype).reshape(len(spec), 2)
    mesh = None
    if nd > 1:  # each device runs its share of every batch
        from jax.sharding import Mesh

        mesh = Mesh(np.array(devices), ("trials",))

    folder = Path(out) if out is not None else None
    fp = _fingerprint(params, gaits, spec, seed, B, reset, rtol, atol)
    if folder is not None:
        folder.mkdir(parents=True, exist_ok=True)
        manifest = folder / "manifest.json"
        if manifest.exists():
            old = json.loads(manifest.read_text())
            if old.get("fingerprint") != fp or old.get("n") != n:
                raise ValueError(
                    f"monte_carlo: {folder} holds a different study (other parameters, gaits, vary, seed, n or "
                    "batch size); choose another `out` folder or delete it."
                )
        else:
            atomic_write_text(manifest, json.dumps({"fingerprint": fp, "n": n, "seed": seed, "batch_size": B,
                                                    "vary": {k: list(v) for k, v in vary.items()}}, indent=2))  # fmt: skip

    parts = []
    t_start = time.perf_counter()
    done_new = 0
    for k in range(n_batches):
        path = folder / f"batch_{k:06d}.npz" if folder is not None else None
        if path is not None and path.exists():
            with np.load(path) as z:
                parts.append({key: z[key] for key in z.files})
            continue
        idx = jnp.arange(k * B, (k + 1) * B, dtype=jnp.int32)
        out_k = _run_batch(params, gaits, names, kinds, ab, jnp.asarray(seed, jnp.uint32), idx, reset, rtol, atol, mesh)
        vals, x, y, speed, status = jax.device_get(out_k)
        part = {"vals": np.asarray(vals), "x": np.asarray(x), "y": np.asarray(y), "speed": np.asarray(speed),
                "status": np.asarray(status)}  # fmt: skip
        if path is not None:
            _save_npz(path, **part)
        parts.append(part)
        done_new += B
        if progress:
            el = time.perf_counter() - t_start
            rate = done_new / el if el > 0 else float("nan")
            left = (n_batches - k - 1) * B / rate if rate > 0 else float("nan")
            print(f"\r[jsphere montecarlo] batch {k + 1}/{n_batches}  {min((k + 1) * B, n)}/{n} trials  "
                  f"{rate:,.0f} trials/s  eta {left:,.0f} s ", end="", file=sys.stderr, flush=True)  # fmt: skip
    if progress and done_new:
        print(file=sys.stderr)
    cat = {key: np.concatenate([p[key] for p in parts])[:n] for key in parts[0]}
    samples = {name: cat["vals"][:, j] for j, (name, _, _, _) in enumerate(spec)}
    res = MonteCarloResult(n=n, seed=seed, samples=samples, x_final=cat["x"], y_final=cat["y"],
                           speed_final=cat["speed"], status=cat["status"], elapsed_s=time.perf_counter() - t_start)  # fmt: skip
    if folder is not None:
        atomic_write_text(folder / "stats.json", json.dumps(res.stats(), indent=2) + "\n")
    return res
