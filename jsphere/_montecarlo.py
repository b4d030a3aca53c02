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
import time
from pathlib import Path
from typing import Mapping, Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ._controls import Sampled, Torques, WheelSpeeds
from ._gaits import Gait, simulate_gaits
from ._simulate import simulate, tolerances
from ._state import State
from ._io import atomic_write, atomic_write_json, atomic_write_text
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


class Actuators(eqx.Module):
    """Imperfect execution of a replayed command table (`mode="torques"` or `"wheel_speeds"`).

    Per trial and wheel: a gain `1 + gain_sd z`; per trial: a delay
    `max(0, delay_s + delay_sd z)` [s]; per sample: white noise of sd `white_sd` and
    band-limited noise of sd `band_sd` (white noise through a first-order low-pass filter of
    bandwidth `band_hz`), in the command's units (N m or rad/s). The command is
    `gain * (plan(t - delay) + noise)`, held at zero before the delayed start.
    """

    gain_sd: float = 0.0
    delay_s: float = 0.0
    delay_sd: float = 0.0
    white_sd: float = 0.0
    band_sd: float = 0.0
    band_hz: float = 5.0


def _noisy_table(key, plan_ts, plan_u, act: Actuators):
    dt_s = plan_ts[-1] / (plan_ts.shape[0] - 1)  # the mean sample interval
    k1, k2, k3, k4 = jax.random.split(key, 4)
    N = plan_u.shape[1]
    gain = 1.0 + act.gain_sd * jax.random.normal(k1, (N,), plan_u.dtype)
    delay = jnp.maximum(0.0, act.delay_s + act.delay_sd * jax.random.normal(k2, (), plan_u.dtype))
    u = plan_u + act.white_sd * jax.random.normal(k3, plan_u.shape, plan_u.dtype)
    if act.band_sd > 0:
        a = jnp.exp(-2.0 * jnp.pi * act.band_hz * dt_s)
        e = jax.random.normal(k4, plan_u.shape, plan_u.dtype)
        _, lp = jax.lax.scan(lambda c, x: (a * c + (1 - a) * x,) * 2, jnp.zeros(N, plan_u.dtype), e)
        u = u + act.band_sd * lp / jnp.sqrt((1 - a) / (1 + a))
    u = gain * u
    # zero until the delayed start (a duplicated time stamp encodes the jump)
    ts = jnp.concatenate([jnp.zeros((1,), plan_ts.dtype), plan_ts + delay])
    u = jnp.concatenate([jnp.zeros((1, N), u.dtype), u])
    return Sampled(ts, u, "cubic")


@eqx.filter_jit
def _run_batch(params, gaits, names, kinds, ab, seed, idx, reset, rtol, atol, mesh=None, mode="gait", plan=None,
               actuators=Actuators(), Omega0_sd=0.0, settle=1.0, max_steps=16384, jump_ts=()):  # fmt: skip
    """Trials `idx` of a study: one compiled function per structure, reused across calls."""
    dt = params.R0.dtype
    T = sum(jnp.asarray(g.T, dt) for g in gaits) if plan is None else plan[0][-1]
    ts = jnp.reshape(T, (1,))

    def one(i):
        vals = _sample(kinds, ab, seed, i, dt)
        p = params
        for j, name in enumerate(names):
            p = set_value(p, name, vals[j])
        key = jax.random.fold_in(jax.random.fold_in(jax.random.PRNGKey(seed), i), 2**20)
        k_omega, k_act = jax.random.split(key)
        dOmega = Omega0_sd * jax.random.normal(k_omega, (3,), dt)
        if mode == "gait":  # per-trial steps, as below
            tr = simulate_gaits(p, gaits, ts=ts, reset=reset, rtol=rtol, atol=atol, throw=False, Omega0=dOmega, batch_steps="per_trial")
        else:
            table = _noisy_table(k_act, plan[0], plan[1], actuators)
            s0 = State.at_rest(p)
            s0 = eqx.tree_at(lambda s: s.Omega, s0, s0.Omega + dOmega)
            ctrl = (Torques if mode == "torques" else WheelSpeeds)(table, jump_ts)
            ts_after = T + settle * jnp.linspace(0.0, 1.0, 51, dtype=dt)  # the settling phase
            # per-trial steps: every trial's result is independent of the other trials of its chunk
            tr = simulate(
                p, s0, ctrl, T + settle, ts=ts_after, rtol=rtol, atol=atol, throw=False, max_steps=max_steps,
                batch_steps="per_trial",
            )  # fmt: skip
        speed = p.R0 * jnp.linalg.norm(cross(tr.Omega[-1], tr.gamma[-1]))
        g3 = tr.gamma[:, 2]
        return vals, tr.x[-1], tr.y[-1], speed, tr.status, jnp.std(g3)

    def local(ii):  # this device's trials, in chunks of CHUNK
        out = jax.lax.map(jax.vmap(one), ii.reshape(-1, CHUNK))
        return jax.tree_util.tree_map(lambda a: a.reshape((a.shape[0] * a.shape[1],) + a.shape[2:]), out)

    if mesh is None:
        return local(idx)
    from jax.sharding import PartitionSpec

    return jax.shard_map(local, mesh=mesh, in_specs=PartitionSpec("trials"), out_specs=PartitionSpec("trials"), check_vma=False)(idx)


@dataclasses.dataclass
class MonteCarloResult:
    """Per-trial outcomes of `monte_carlo` (NumPy arrays of length `n`).

    `samples[name]`: the drawn values; `x_final, y_final` [m]: stop point; `speed_final` [m/s]:
    speed of the shell centre at the end; `status`: 0 for a successful solve (see
    `Trajectory.status`); `gamma3_sd_after`: standard deviation of `gamma_3` over the settling
    time after the commands end (replay modes; the paper's sigma of Fig. 2; 0 in gait mode,
    where the gaits end on exact stationary motions).
    """

    n: int
    seed: int
    samples: dict[str, np.ndarray]
    x_final: np.ndarray
    y_final: np.ndarray
    speed_final: np.ndarray
    status: np.ndarray
    gamma3_sd_after: np.ndarray
    elapsed_s: float = 0.0

    def stats(self, level: float = 0.95) -> dict:
        """Stop-point mean, covariance, the `level` confidence ellipse and quantiles (successful
        trials only)."""
        ok = self.status == 0
        if not ok.any():
            return {"n": int(self.n), "n_failed": int(self.n)}
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
            "gamma3_sd_after": {"mean": float(self.gamma3_sd_after[ok].mean()),
                                "q": q, "quantiles": np.quantile(self.gamma3_sd_after[ok], q).tolist()},
        }  # fmt: skip


def _fingerprint(params, gaits, spec, seed, batch_size, reset, rtol, atol) -> str:
    leaves = [np.asarray(x).tolist() for x in jax.tree_util.tree_leaves((params, gaits)) if hasattr(x, "shape")]
    text = json.dumps([leaves, str(jax.tree_util.tree_structure(gaits)), spec, seed, batch_size, repr(reset), rtol, atol])
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def _load_npz(path: Path) -> dict:
    with np.load(path) as z:
        return {key: z[key] for key in z.files}


def _save_npz(path: Path, **arrays) -> None:
    atomic_write(path, lambda tmp: np.savez(tmp, **arrays))


def monte_carlo(
    params: RobotParams,
    gaits: Sequence[Gait],
    *,
    vary: Mapping[str, Sequence],
    n: int,
    seed: int = 0,
    batch_size: int = 1024,
    reset=False,
    rtol: float | None = None,
    atol: float | None = None,
    mode: str = "gait",
    actuators: Actuators | None = None,
    Omega0_sd: float = 0.0,
    plan_rate: float = 200.0,
    settle: float = 1.0,
    commands: tuple | None = None,
    max_steps: int = 65536,
    out: str | os.PathLike | None = None,
    progress: bool = True,
    process_index: int | None = None,
    process_count: int | None = None,
    wait_timeout: float = 24 * 3600.0,
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
    - `mode`: `"gait"` (default): each trial executes the gaits exactly (the paper's
      model: `gamma(t)` prescribed, the motors supply whatever torque it takes). `"torques"` or
      `"wheel_speeds"`: the commands planned once with the nominal `params` (sampled at
      `plan_rate` Hz) are replayed open loop on each perturbed robot, through `actuators`
      (gain, delay, white and band-limited noise; `Actuators`), for the gaits' duration plus
      `settle` seconds: "where does the real robot stop?".
    - `commands`: `(ts, values)`, a command table to replay instead of the gaits' plan (e.g.
      the kinematic control (2.9) for the paper's Fig. 2 comparison); starts at `t = 0`, repeat
      a time stamp to encode a jump (wheel-speed jumps are impulses, see `simulate`); the motors
      stop at its last time. `gaits` is then not replayed (pass the gaits the commands belong
      to, for the record).
    - `rtol`, `atol`: the solver's tolerances; default 1e-8, 1e-10 (float32 parameters: 1e-5,
      1e-7, as `simulate`).
    - `max_steps`: solver step limit per trial in the replay modes (noisy commands need many
      steps: the noise is interpolated smoothly and the solver follows it).
    - `Omega0_sd`: sd of a perturbation of the initial shell angular velocity [1/s].
    - `out`: a folder. Each finished batch is written there atomically, with a manifest; run
      the same call again after an interruption and it resumes (a folder holding a different
      study is refused).
    - `progress`: print a progress line to stderr.
    - `process_index`, `process_count`: for several processes (hosts) sharing one study: each
      computes the batches `k` with `k % process_count == process_index` and writes them to
      `out` (which all processes must see), then reads the others' batches from there (waiting
      up to `wait_timeout` s). Default: `jax.process_index()` / `jax.process_count()`, i.e. one
      process unless `jax.distributed.initialize()` was called (see docs/montecarlo.md).

    Returns a `MonteCarloResult` (`x_final`, `y_final`, ... arrays of length `n`; `.stats()`).
    """
    if n < 1:
        raise ValueError(f"monte_carlo: n must be >= 1; got {n}.")
    if mode not in ("gait", "torques", "wheel_speeds"):
        raise ValueError(f"monte_carlo: mode must be 'gait', 'torques' or 'wheel_speeds'; got {mode!r}.")
    if actuators is not None and mode == "gait":
        raise ValueError("monte_carlo: actuators apply to replayed commands; use mode='torques' or 'wheel_speeds'.")
    actuators = actuators or Actuators()
    pi = jax.process_index() if process_index is None else int(process_index)
    pc = jax.process_count() if process_count is None else int(process_count)
    if not 0 <= pi < pc:
        raise ValueError(f"monte_carlo: process_index must be in [0, process_count); got {pi} of {pc}.")
    if pc > 1 and out is None:
        raise ValueError("monte_carlo: with several processes, pass `out`, a folder that every process can read and write.")
    spec = _check_vary(params, vary)
    rtol, atol = tolerances(params.R0.dtype, rtol, atol, where="monte_carlo")
    gaits = list(gaits)
    if not gaits or not all(isinstance(g, Gait) for g in gaits):
        raise TypeError("monte_carlo: gaits must be a non-empty list of jsphere.Gait.")
    devices = jax.local_devices()
    nd = len(devices)
    unit = CHUNK * nd
    B = int(math.ceil(max(1, min(batch_size, n)) / unit) * unit)
    n_batches = int(math.ceil(n / B))
    plan, jump_ts = None, ()
    if commands is not None and mode == "gait":
        raise ValueError("monte_carlo: `commands` are replayed; use mode='torques' or 'wheel_speeds'.")
    if mode != "gait":
        if commands is None:
            nominal = simulate_gaits(params, gaits, reset=reset, rate=plan_rate)
            tsn = np.asarray(nominal.ts)
            u = np.asarray(nominal.K if mode == "torques" else nominal.chi_dot)
        else:
            tsn, u = np.asarray(commands[0], np.float64), np.asarray(commands[1], np.float64)
            Sampled(jnp.asarray(tsn), jnp.asarray(u))  # validates the table
            if tsn[0] != 0.0 or u.shape[1:] != (params.n_wheels,):
                raise ValueError(f"monte_carlo: commands must start at t = 0 and have {params.n_wheels} columns; got t0 = {tsn[0]}, shape {u.shape}.")
        # the motors stop when the plan ends: a jump to zero at its last time stamp
        tsn, u = np.concatenate([tsn, tsn[-1:]]), np.concatenate([u, np.zeros_like(u[:1])])
        plan = (jnp.asarray(tsn, params.R0.dtype), jnp.asarray(u, params.R0.dtype))
        if actuators.delay_s == 0 and actuators.delay_sd == 0:  # jumps stay where the plan has them
            jump_ts = tuple(float(t) for t in tsn[1:][np.diff(tsn) == 0] if t > 0)
    names = tuple(name for name, _, _, _ in spec)
    kinds = tuple(kind for _, kind, _, _ in spec)
    ab = jnp.asarray(np.array([[a, b] for _, _, a, b in spec], dtype=np.float64).reshape(len(spec), 2), dtype=params.R0.dtype)
    mesh = None
    if nd > 1:  # each device runs its share of every batch
        from jax.sharding import Mesh

        mesh = Mesh(np.array(devices), ("trials",))

    folder = Path(out) if out is not None else None
    cmd_fp = None if commands is None else hashlib.sha256(np.ascontiguousarray(plan[1]).tobytes() + np.ascontiguousarray(plan[0]).tobytes()).hexdigest()
    fp = _fingerprint(params, gaits, spec, seed, B, (reset, mode, repr(actuators), Omega0_sd, plan_rate, settle, cmd_fp), rtol, atol)
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
            atomic_write_json(manifest, {"fingerprint": fp, "n": n, "seed": seed, "batch_size": B,
                                         "vary": {k: list(v) for k, v in vary.items()}})  # fmt: skip

    parts: list = [None] * n_batches
    t_start = time.perf_counter()
    done_new = 0
    mine = [k for k in range(n_batches) if k % pc == pi]  # this process's share (all of them on one host)
    for count, k in enumerate(mine):
        path = folder / f"batch_{k:06d}.npz" if folder is not None else None
        if path is not None and path.exists():
            parts[k] = _load_npz(path)
            continue
        idx = jnp.arange(k * B, (k + 1) * B, dtype=jnp.int32)
        out_k = _run_batch(params, gaits, names, kinds, ab, jnp.asarray(seed, jnp.uint32), idx, reset, rtol, atol, mesh,
                           mode, plan, actuators, Omega0_sd, settle, max_steps, jump_ts)  # fmt: skip
        vals, x, y, speed, status, g3 = jax.device_get(out_k)
        part = {"vals": np.asarray(vals), "x": np.asarray(x), "y": np.asarray(y), "speed": np.asarray(speed),
                "status": np.asarray(status), "gamma3_sd": np.asarray(g3)}  # fmt: skip
        if path is not None:
            _save_npz(path, **part)
        parts[k] = part
        done_new += B
        if progress:
            el = time.perf_counter() - t_start
            rate = done_new / el if el > 0 else float("nan")
            left = (len(mine) - count - 1) * B / rate if rate > 0 else float("nan")
            print(f"\r[jsphere montecarlo] batch {count + 1}/{len(mine)}  {min(done_new, n)}/{n} trials  "
                  f"{rate:,.0f} trials/s  eta {left:,.0f} s ", end="", file=sys.stderr, flush=True)  # fmt: skip
    if progress and done_new:
        print(file=sys.stderr)
    # the other processes' batches, from the shared folder
    deadline = time.monotonic() + wait_timeout
    for k in range(n_batches):
        while parts[k] is None:
            path = folder / f"batch_{k:06d}.npz"
            if path.exists():
                parts[k] = _load_npz(path)
            elif time.monotonic() > deadline:
                raise TimeoutError(f"monte_carlo: batch {k} ({path}) did not appear within {wait_timeout} s; is every process running?")
            else:
                time.sleep(0.2)
    cat = {key: np.concatenate([p[key] for p in parts])[:n] for key in parts[0]}
    samples = {name: cat["vals"][:, j] for j, (name, _, _, _) in enumerate(spec)}
    res = MonteCarloResult(n=n, seed=seed, samples=samples, x_final=cat["x"], y_final=cat["y"],
                           speed_final=cat["speed"], status=cat["status"], gamma3_sd_after=cat["gamma3_sd"],
                           elapsed_s=time.perf_counter() - t_start)  # fmt: skip
    if folder is not None:
        atomic_write_json(folder / "stats.json", res.stats())
    return res
