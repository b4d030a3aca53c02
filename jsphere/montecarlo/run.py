"""Monte-Carlo studies of gait motions: vmapped batches, deterministic seeds, resumable files.

Each trial `i` draws its parameters from `jax.random.fold_in(PRNGKey(seed), i)`, so a study is
the same whatever the batch size or the number of devices; a draw that breaks a rule of
`RobotParams` is rejected (not simulated) or, for "truncate" distributions, drawn again;
batches are sharded over all local devices; finished batches are written atomically to `out/`
and a killed study resumes there (a corrupt batch file is recomputed).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import os
import sys
import time
import warnings
import zipfile
from pathlib import Path
from typing import ClassVar, Mapping, Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..controls import Sampled, Torques, WheelSpeeds
from .._runtime.checks import is_number, real, whole
from .._runtime.errors import InputError
from ..gaits.gaits import Gait, simulate_gaits
from ..solve.simulate import simulate, tolerances
from ..model.state import State
from .._runtime.files import atomic_write, atomic_write_json, temporary_pattern
from ..model.linalg import cross
from ..model.names import get_value, parse_name, set_value
from ..model.params import RULES, RobotParams, rule_code

_DISTRIBUTIONS = {"normal": ("mean", "sd"), "uniform": ("low", "high")}
#: the optional last entry of a distribution: redraw until the parameter set is valid
TRUNCATE = "truncate"
#: redraws of a "truncate" distribution before a draw that is still invalid is rejected
MAX_REDRAWS = 100
#: `MonteCarloResult.status` of a trial whose drawn parameters break a rule of `RobotParams`
#: (not simulated; `reject_code` says which rule). Solver outcomes are >= 0 (`Trajectory.status`).
REJECTED = -1
#: why a draw is rejected, by `reject_code`: 0 valid, then every rule of `RobotParams`
#: (`jsphere.model.params.RULES`), then a drawn `R_m` that is not a positive distance
REASONS: tuple[str, ...] = ("valid", *(rule.reason for rule in RULES), "R_m <= 0")


#: the numeric settings of a study: name -> checker (`load_study` checks a study file's keys
#: with the same table, under the file's names)
SETTINGS = {
    "n": lambda w, k, v: whole(w, k, v, 1),
    "seed": lambda w, k, v: whole(w, k, v, 0, 2**32 - 1),
    "batch_size": lambda w, k, v: whole(w, k, v, 1),
    "settle": lambda w, k, v: real(w, k, v, unit="s"),
    "Omega0_sd": lambda w, k, v: real(w, k, v, unit="1/s"),
    "plan_rate": lambda w, k, v: real(w, k, v, strict=True, unit="Hz"),
    "max_steps": lambda w, k, v: whole(w, k, v, 1),
    "wait_timeout": lambda w, k, v: real(w, k, v, unit="s"),
}


def check_settings(where: str, values: Mapping, names: Mapping[str, str] | None = None) -> dict:
    """Check the numeric settings `values` (keys of `SETTINGS`) and return them converted;
    an error names the value as `names` maps it (e.g. `{"n": "trials"}`)."""
    names = names or {}
    return {k: SETTINGS[k](where, names.get(k, k), v) for k, v in values.items()}


def _target(params: RobotParams, name: str) -> tuple:
    """What a name sets, for finding two names that set the same value."""
    field, index = parse_name(name)
    if field == "R_m":
        return ("r_m",)
    if field == "I" and len(index) == 2:
        index = tuple(sorted(index))
    return (field, index)


def _check_vary(params: RobotParams, vary: Mapping[str, Sequence]) -> list[tuple[str, str, float, float, bool]]:
    """`[(name, kind, a, b, truncate)]` of a valid `vary`, else `InputError` naming the entry."""
    if not isinstance(vary, Mapping):
        raise InputError(f"vary must be a table {{name: [kind, a, b]}}, e.g. {{\"r_m[2]\": [\"normal\", -0.027, 1e-4]}}; got {vary!r}.")
    out, seen = [], {}
    for name, spec in vary.items():
        if not isinstance(name, str):
            raise InputError(f"vary: parameter names are strings such as 'j' or 'I[0,0]'; got {name!r}.")
        parse_name(name)
        if name != "R_m":
            get_value(params, name)  # checks the index fits
        form = (f"vary[{name!r}] must be ['normal', mean, sd] or ['uniform', low, high], optionally followed by "
                f"'{TRUNCATE}'")  # fmt: skip
        if not isinstance(spec, (tuple, list)) or len(spec) not in (3, 4) or spec[0] not in _DISTRIBUTIONS:
            raise InputError(f"{form}; got {spec!r}.")
        if len(spec) == 4 and spec[3] != TRUNCATE:
            raise InputError(f"{form}; got {spec[3]!r} as its last entry.")
        kind = spec[0]
        for label, v in zip(_DISTRIBUTIONS[kind], spec[1:3]):
            if not is_number(v) or not math.isfinite(v):
                raise InputError(f"vary[{name!r}]: the {label} must be a finite number; got {v!r}.")
        a, b = float(spec[1]), float(spec[2])
        if kind == "normal" and not b >= 0:
            raise InputError(f"vary[{name!r}]: the standard deviation must be >= 0; got {b}.")
        if kind == "uniform" and not b >= a:
            raise InputError(f"vary[{name!r}]: uniform needs low <= high; got ({a}, {b}).")
        if get_value(params, name).ndim != 0:
            raise InputError(f"vary[{name!r}]: vary scalar components (e.g. 'I[0,0]'), not a whole field.")
        t = _target(params, name)
        other = next((o for o, ot in seen.items() if ot == t or (t[0] == ot[0] == "r_m" and (len(t) == 1 or len(ot) == 1))), None)
        if other is not None:
            raise InputError(f"vary: {other!r} and {name!r} set the same value; vary one of them.")
        seen[name] = t
        out.append((name, kind, a, b, len(spec) == 4))
    return out


def _sample(kinds: tuple[str, ...], ab, keys, dtype):
    """One value per varied name, from its key."""
    vals = []
    for j, kind in enumerate(kinds):
        a, b = ab[j, 0], ab[j, 1]
        if kind == "normal":
            vals.append(a + b * jax.random.normal(keys[j], dtype=dtype))
        else:
            vals.append(a + (b - a) * jax.random.uniform(keys[j], dtype=dtype))
    return jnp.stack(vals)


def _with_values(params: RobotParams, names, vals) -> RobotParams:
    p = params
    for j, name in enumerate(names):
        p = set_value(p, name, vals[j])
    return p


def _draw_code(params: RobotParams, names, vals):
    """`reject_code` of a draw: 0 if the parameter set is valid, else the first broken rule
    (`REASONS`)."""
    code = rule_code(_with_values(params, names, vals))
    for j, name in enumerate(names):
        if name == "R_m":
            code = jnp.where(vals[j] <= 0, len(REASONS) - 1, code)
    return code


def _draw(params, names, kinds, ab, trunc, seed, i, dtype):
    """Values of every varied name for trial `i` (deterministic in `(seed, i)` only) and their
    `reject_code`. Variable `j` draws from `fold_in(fold_in(PRNGKey(seed), i), j)`; while the
    set is invalid, the "truncate" variables are redrawn from that key folded with the attempt
    number (at most `MAX_REDRAWS` times), so a study whose draws are all valid is the same
    with or without "truncate"."""
    key = jax.random.fold_in(jax.random.PRNGKey(seed), i)
    keys = [jax.random.fold_in(key, j) for j in range(len(kinds))]
    if not kinds:
        return jnp.zeros((0,), dtype), jnp.zeros((), jnp.int32)
    vals = _sample(kinds, ab, keys, dtype)
    code = _draw_code(params, names, vals)

    def cond(c):
        attempt, _, code = c
        return (code != 0) & jnp.any(trunc) & (attempt < MAX_REDRAWS)

    def body(c):
        attempt, vals, _ = c
        attempt = attempt + 1
        new = _sample(kinds, ab, [jax.random.fold_in(k, attempt) for k in keys], dtype)
        vals = jnp.where(trunc, new, vals)
        return attempt, vals, _draw_code(params, names, vals)

    _, vals, code = jax.lax.while_loop(cond, body, (jnp.zeros((), jnp.int32), vals, code))
    return vals, code


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

    def __check_init__(self):
        for name in ("gain_sd", "delay_s", "delay_sd", "white_sd", "band_sd"):
            real("Actuators", name, getattr(self, name))
        real("Actuators", "band_hz", self.band_hz, strict=True, unit="Hz")


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
def _run_batch(params, gaits, names, kinds, ab, trunc, seed, idx, reset, rtol, atol, mesh=None, mode="gait", plan=None,
               actuators=Actuators(), Omega0_sd=0.0, settle=1.0, max_steps=16384, jump_ts=()):  # fmt: skip
    """Trials `idx` of a study: one compiled function per structure, reused across calls.

    A draw that breaks a rule of `RobotParams` is not simulated as drawn: the nominal
    parameters stand in for it (so that its solve is an ordinary one and does not hold up its
    chunk), and its outcomes are replaced by NaN and the status `REJECTED`."""
    dt = params.R0.dtype
    T = sum(jnp.asarray(g.T, dt) for g in gaits) if plan is None else plan[0][-1]
    ts = jnp.reshape(T, (1,))

    def one(i):
        vals, code = _draw(params, names, kinds, ab, trunc, seed, i, dt)
        p = _with_values(params, names, vals)
        valid = code == 0
        if names:  # the nominal robot in place of an invalid draw (only the varied leaves change)
            p = jax.tree_util.tree_map(lambda a, b: a if a is b else jnp.where(valid, a, b), p, params)
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
        nan = jnp.asarray(jnp.nan, dt)
        outcomes = tuple(jnp.where(valid, v, nan) for v in (tr.x[-1], tr.y[-1], speed, jnp.std(g3)))
        status = jnp.where(valid, tr.status, REJECTED)
        return vals, outcomes[0], outcomes[1], outcomes[2], status, outcomes[3], code

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
    speed of the shell centre at the end; `status`: 0 for a successful solve, 1 or 2 for a
    failed one (see `Trajectory.status`), `REJECTED` (-1) for a draw whose parameters break a
    rule of `RobotParams` (not simulated; its outcomes are NaN); `gamma3_sd_after`: standard
    deviation of `gamma_3` over the settling time after the commands end (replay modes; the
    paper's sigma of Fig. 2; 0 in gait mode, where the gaits end on exact stationary motions);
    `reject_code`: 0 for a valid draw, else the index in `REASONS` of the rule it breaks.
    """

    REJECTED: ClassVar[int] = REJECTED
    REASONS: ClassVar[tuple[str, ...]] = REASONS

    n: int
    seed: int
    samples: dict[str, np.ndarray]
    x_final: np.ndarray
    y_final: np.ndarray
    speed_final: np.ndarray
    status: np.ndarray
    gamma3_sd_after: np.ndarray
    elapsed_s: float = 0.0
    reject_code: np.ndarray | None = None

    def rejections(self) -> dict[str, int]:
        """`{reason: number of draws}` of the rejected draws, most frequent first."""
        codes = np.zeros(self.n, np.int64) if self.reject_code is None else np.asarray(self.reject_code)
        counts = np.bincount(codes[codes > 0], minlength=len(REASONS))
        order = sorted(np.flatnonzero(counts), key=lambda c: (-counts[c], c))
        return {REASONS[c]: int(counts[c]) for c in order}

    def stats(self, level: float = 0.95) -> dict:
        """Stop-point mean, covariance, the `level` confidence ellipse and quantiles (successful
        trials only), with the counts of successful trials (`n_ok`), solver failures
        (`n_failed`, and `failed_status`: per status) and rejected draws (`n_rejected`, and
        `rejected`: per broken rule)."""
        status = np.asarray(self.status)
        ok = status == 0
        rejected = status == REJECTED
        failed = ~ok & ~rejected
        codes, counts = np.unique(status[failed], return_counts=True)
        head = {"n": int(self.n), "n_ok": int(ok.sum()), "n_failed": int(failed.sum()),
                "failed_status": {str(int(c)): int(k) for c, k in zip(codes, counts)},
                "n_rejected": int(rejected.sum()), "rejected": self.rejections()}  # fmt: skip
        if not ok.any():
            return head
        xy = np.stack([self.x_final[ok], self.y_final[ok]], axis=1)
        mean = xy.mean(axis=0)
        cov = np.cov(xy, rowvar=False) if len(xy) > 1 else np.zeros((2, 2))
        evals, evecs = np.linalg.eigh(cov)
        s = -2.0 * math.log(1.0 - level)  # chi-squared quantile with 2 degrees of freedom
        q = [0.025, 0.5, 0.975]
        return {
            **head, "mean_xy_m": mean.tolist(), "cov_xy_m2": cov.tolist(),
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
    """A hash of everything that changes a study's results (also the rules a draw must meet and
    the redraw limit of "truncate")."""
    leaves = [np.asarray(x).tolist() for x in jax.tree_util.tree_leaves((params, gaits)) if hasattr(x, "shape")]
    text = json.dumps([leaves, str(params.R0.dtype), str(jax.tree_util.tree_structure(gaits)), spec, seed, batch_size,
                       repr(reset), rtol, atol, REASONS, MAX_REDRAWS, CHUNK])  # fmt: skip
    return hashlib.sha256(text.encode()).hexdigest()[:16]


#: the arrays of a batch file
_BATCH_KEYS = ("vals", "x", "y", "speed", "status", "gamma3_sd", "reject")
#: the hidden temporary files of `jsphere._runtime.files.atomic_write` in a study folder, by the file they become
_TEMPORARY = temporary_pattern(r"(batch_(\d{6})|manifest|stats|stop_points)", r"\.(npz|tmp|png)")


def _load_batch(path: Path, B: int, n_vary: int) -> dict | None:
    """The arrays of a batch file, or `None` (with a warning naming the file) if it cannot be
    read or does not hold a batch of this study (a truncated copy, a full disk, random bytes)."""
    try:
        with open(path, "rb") as fh:
            if not zipfile.is_zipfile(fh):
                raise ValueError("not an .npz archive: empty, cut short or overwritten")
            fh.seek(0)
            with np.load(fh, allow_pickle=False) as z:
                part = {key: z[key] for key in z.files}
        if set(part) != set(_BATCH_KEYS):
            raise ValueError(f"arrays {sorted(part)}, expected {sorted(_BATCH_KEYS)}")
        shapes = {key: part[key].shape for key in _BATCH_KEYS}
        if shapes["vals"] != (B, n_vary) or any(shapes[k] != (B,) for k in _BATCH_KEYS if k != "vals"):
            raise ValueError(f"shapes {shapes} do not match a batch of {B} trials")
    except Exception as e:  # noqa: BLE001 - any unreadable file is recomputed
        reason = str(e) if isinstance(e, ValueError) else f"{type(e).__name__}: {e}"
        warnings.warn(f"monte_carlo: {path} is corrupt or incomplete ({reason}); recomputing that batch.", MonteCarloWarning,
                      stacklevel=3)  # fmt: skip
        return None
    return part


def _save_batch(path: Path, part: dict) -> None:
    """Write a batch atomically as an `.npz` file whose bytes depend on its arrays only (fixed
    member order and time stamps), so a resumed study's files equal an uninterrupted one's."""

    def write(tmp):
        with zipfile.ZipFile(tmp, "w", compression=zipfile.ZIP_STORED) as zf:
            for key in _BATCH_KEYS:
                info = zipfile.ZipInfo(f"{key}.npy", date_time=(1980, 1, 1, 0, 0, 0))
                with zf.open(info, "w", force_zip64=True) as f:
                    np.lib.format.write_array(f, np.ascontiguousarray(part[key]), allow_pickle=False)

    atomic_write(path, write)


class MonteCarloWarning(UserWarning):
    """Something `monte_carlo` repaired on its own (a corrupt batch file it recomputes)."""


def _remove_temporary_files(folder: Path, mine: set[int], single: bool) -> None:
    """Remove the hidden temporary files a killed run left in the study folder: those of this
    process's batches, and (with a single process, where no other process may be writing them)
    those of the manifest, the statistics and the figure."""
    for f in folder.iterdir():
        m = _TEMPORARY.fullmatch(f.name)
        if m and (int(m.group(2)) in mine if m.group(2) else single):
            f.unlink(missing_ok=True)


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
      `|r_m|`, keeping its direction). Every drawn parameter set is checked against the rules
      of `RobotParams` (`jsphere.model.params.RULES`: positive masses, a valid inertia tensor, the
      centre of mass inside the shell, ...); a draw that breaks one is not simulated: its
      status is `REJECTED` and `stats()` counts it by the rule it breaks. A distribution
      followed by `"truncate"` (`("normal", 0.8, 0.3, "truncate")`) is truncated to the valid
      range instead: while a draw is invalid, every "truncate" distribution is drawn again
      (at most `MAX_REDRAWS` times), which samples it conditioned on a valid robot.
    - `n`, `seed`: number of trials and the seed (`0 <= seed < 2**32`). Trial `i` uses the key
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
      study is refused). A batch file that cannot be read (cut short, overwritten) is
      recomputed, with a `MonteCarloWarning` naming it; the hidden temporary files a killed
      run leaves are removed.
    - `progress`: print a progress line to stderr.
    - `process_index`, `process_count`: for several processes (hosts) sharing one study: each
      computes the batches `k` with `k % process_count == process_index` and writes them to
      `out` (which all processes must see), then reads the others' batches from there (waiting
      up to `wait_timeout` s). Default: `jax.process_index()` / `jax.process_count()`, i.e. one
      process unless `jax.distributed.initialize()` was called (see docs/montecarlo.md).

    Every argument is checked before any work; a bad one raises `InputError` naming it.

    Returns a `MonteCarloResult` (`x_final`, `y_final`, ... arrays of length `n`; `.stats()`).
    """
    settings = check_settings("monte_carlo", {"n": n, "seed": seed, "batch_size": batch_size, "settle": settle,
                                              "Omega0_sd": Omega0_sd, "plan_rate": plan_rate, "max_steps": max_steps,
                                              "wait_timeout": wait_timeout})  # fmt: skip
    n, seed, batch_size = settings["n"], settings["seed"], settings["batch_size"]
    settle, Omega0_sd, plan_rate, max_steps = (settings[k] for k in ("settle", "Omega0_sd", "plan_rate", "max_steps"))
    for name, tol in (("rtol", rtol), ("atol", atol)):
        if tol is not None:
            real("monte_carlo", name, tol, strict=True)
    if mode not in ("gait", "torques", "wheel_speeds"):
        raise InputError(f"monte_carlo: mode must be 'gait', 'torques' or 'wheel_speeds'; got {mode!r}.")
    if actuators is not None and mode == "gait":
        raise InputError("monte_carlo: actuators apply to replayed commands; use mode='torques' or 'wheel_speeds'.")
    if actuators is not None and not isinstance(actuators, Actuators):
        raise InputError(f"monte_carlo: actuators must be a jsphere.Actuators; got {type(actuators).__name__}.")
    actuators = actuators or Actuators()
    pi = jax.process_index() if process_index is None else whole("monte_carlo", "process_index", process_index, 0)
    pc = jax.process_count() if process_count is None else whole("monte_carlo", "process_count", process_count, 1)
    if not 0 <= pi < pc:
        raise InputError(f"monte_carlo: process_index must be in [0, process_count); got {pi} of {pc}.")
    if pc > 1 and out is None:
        raise InputError("monte_carlo: with several processes, pass `out`, a folder that every process can read and write.")
    spec = _check_vary(params, vary)
    rtol, atol = tolerances(params.R0.dtype, rtol, atol, where="monte_carlo")
    if isinstance(gaits, (str, bytes)) or not isinstance(gaits, Sequence):
        raise InputError(f"monte_carlo: gaits must be a non-empty list of jsphere.Gait; got {type(gaits).__name__}.")
    gaits = list(gaits)
    if not gaits or not all(isinstance(g, Gait) for g in gaits):
        raise InputError("monte_carlo: gaits must be a non-empty list of jsphere.Gait (e.g. [acceleration(), braking()]).")
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
    names = tuple(name for name, _, _, _, _ in spec)
    kinds = tuple(kind for _, kind, _, _, _ in spec)
    ab = jnp.asarray(np.array([[a, b] for _, _, a, b, _ in spec], dtype=np.float64).reshape(len(spec), 2), dtype=params.R0.dtype)
    trunc = jnp.asarray(np.array([t for *_, t in spec], dtype=bool))
    mesh = None
    if nd > 1:  # each device runs its share of every batch
        from jax.sharding import Mesh

        mesh = Mesh(np.array(devices), ("trials",))

    folder = Path(out) if out is not None else None
    cmd_fp = None if commands is None else hashlib.sha256(np.ascontiguousarray(plan[1]).tobytes() + np.ascontiguousarray(plan[0]).tobytes()).hexdigest()
    replay = (actuators, plan_rate, settle, cmd_fp, max_steps) if mode != "gait" else ()
    fp = _fingerprint(params, gaits, spec, seed, B, (reset, mode, repr(replay), Omega0_sd), rtol, atol)
    mine = [k for k in range(n_batches) if k % pc == pi]  # this process's share (all of them on one host)
    if folder is not None:
        _open_study_folder(folder, fp, n, seed, B, vary, set(mine), pc == 1)

    parts: list = [None] * n_batches
    t_start = time.perf_counter()
    done_new = 0

    def path_of(k):
        return folder / f"batch_{k:06d}.npz" if folder is not None else None

    def compute(k):
        idx = jnp.arange(k * B, (k + 1) * B, dtype=jnp.int32)
        out_k = _run_batch(params, gaits, names, kinds, ab, trunc, jnp.asarray(seed, jnp.uint32), idx, reset, rtol, atol,
                           mesh, mode, plan, actuators, Omega0_sd, settle, max_steps, jump_ts)  # fmt: skip
        part = dict(zip(_BATCH_KEYS, (np.asarray(a) for a in jax.device_get(out_k))))
        if folder is not None:
            _save_batch(path_of(k), part)
        return part

    # this process's finished batches first (a corrupt one is recomputed below), then the rest
    for k in mine:
        if path_of(k) is not None and path_of(k).exists():
            parts[k] = _load_batch(path_of(k), B, len(spec))
    todo = [k for k in mine if parts[k] is None]
    for count, k in enumerate(todo):
        parts[k] = compute(k)
        done_new += B
        if progress:
            el = time.perf_counter() - t_start
            rate = done_new / el if el > 0 else float("nan")
            left = (len(todo) - count - 1) * B / rate if rate > 0 else float("nan")
            print(f"\r[jsphere montecarlo] batch {count + 1}/{len(todo)}  {min(done_new, n)}/{n} trials  "
                  f"{rate:,.0f} trials/s  eta {left:,.0f} s ", end="", file=sys.stderr, flush=True)  # fmt: skip
    if progress and done_new:
        print(file=sys.stderr)
    # the other processes' batches, from the shared folder
    deadline = time.monotonic() + wait_timeout
    for k in range(n_batches):
        while parts[k] is None:
            path = path_of(k)
            if path.exists():
                parts[k] = _load_batch(path, B, len(spec))
                if parts[k] is None:  # unreadable: compute it here (the same bytes as its owner's)
                    parts[k] = compute(k)
            elif time.monotonic() > deadline:
                raise TimeoutError(f"monte_carlo: batch {k} ({path}) did not appear within {wait_timeout} s; is every process running?")
            else:
                time.sleep(0.2)
    cat = {key: np.concatenate([p[key] for p in parts])[:n] for key in parts[0]}
    samples = {name: cat["vals"][:, j] for j, name in enumerate(names)}
    res = MonteCarloResult(n=n, seed=seed, samples=samples, x_final=cat["x"], y_final=cat["y"],
                           speed_final=cat["speed"], status=cat["status"], gamma3_sd_after=cat["gamma3_sd"],
                           elapsed_s=time.perf_counter() - t_start, reject_code=cat["reject"])  # fmt: skip
    if folder is not None:
        atomic_write_json(folder / "stats.json", res.stats())
    return res


def _open_study_folder(folder: Path, fp: str, n: int, seed: int, B: int, vary, mine: set[int], single: bool) -> None:
    """Create the study folder with its manifest, or check that it holds this study; remove the
    temporary files a killed run left there."""
    if folder.exists() and not folder.is_dir():
        raise InputError(f"monte_carlo: out = {folder} is a file; give a folder for the study (it is created if missing).")
    folder.mkdir(parents=True, exist_ok=True)
    manifest = folder / "manifest.json"
    if manifest.exists():
        try:
            old = json.loads(manifest.read_text())
            if not isinstance(old, dict):
                raise ValueError("not a JSON object")
        except (ValueError, UnicodeDecodeError) as e:
            raise InputError(
                f"monte_carlo: {manifest} is not a valid study manifest ({e}), so the batches in {folder} cannot be "
                "trusted; delete the folder (or choose another `out`) to run the study again."
            ) from None
        if old.get("fingerprint") != fp or old.get("n") != n:
            raise InputError(
                f"monte_carlo: {folder} holds a different study (other parameters, gaits, vary, seed, n or "
                "batch size); choose another `out` folder or delete it."
            )
    else:
        if any(folder.glob("batch_*.npz")):
            raise InputError(
                f"monte_carlo: {folder} holds batch files but no manifest.json, so it cannot tell which study they "
                "belong to; delete them (or choose another `out` folder)."
            )
        atomic_write_json(manifest, {"fingerprint": fp, "n": n, "seed": seed, "batch_size": B,
                                     "vary": {k: list(v) for k, v in vary.items()}})  # fmt: skip
    _remove_temporary_files(folder, mine, single)
