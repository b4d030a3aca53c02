"""Synthetic capture: smooth random input programs, capture-like trials simulated from them, and
the markers a capture system would see."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from ..controls import Torques, WheelSpeeds
from ..controls import eval_controls as eval_controls  # (tests evaluate the programs through this module)
from ..model.params import RobotParams
from ..model.rotations import quat_from_rotvec_np, quat_mul_np, rotmat_np
from ..model.state import State
from .onboard import simulated
from .trial import Trial
from .validation import KINDS


def _smoothstep(u):
    """`0` for `u <= 0`, `1` for `u >= 1`, `u^3 (10 - 15 u + 6 u^2)` between (C2)."""
    u = jnp.clip(u, 0.0, 1.0)
    return u * u * u * (10.0 + u * (-15.0 + 6.0 * u))


class RandomSines(eqx.Module):
    """`f_i(t) = ramp(t) sum_k amp[i, k] sin(2 pi freq[i, k] t + phase[i, k])` per wheel i, with a
    C2 ramp from 0 at `t = 0` to 1 at `t = ramp_time` (so the robot starts from rest smoothly)."""

    amp: Float[Array, "N K"]
    freq: Float[Array, "N K"]
    phase: Float[Array, "N K"]
    ramp_time: Float[Array, ""]

    def __call__(self, t):
        s = _smoothstep(t / self.ramp_time)
        return s * jnp.sum(self.amp * jnp.sin(2 * jnp.pi * self.freq * t + self.phase), axis=-1)


def default_amplitude(params: RobotParams, kind: str) -> float:
    """A moderate input amplitude: for wheel speeds the largest wheel rate of the kinematic
    model (2.9) rolling at 0.3 m/s (over 8 headings) [rad/s]; for torques `0.05 m g R_m` [N m]
    (5% of the platform's largest gravity torque)."""
    if kind == "wheel_speeds":
        from ..model.kinematics import kinematic_wheel_speeds

        h = np.linspace(0.0, 2 * np.pi, 8, endpoint=False)
        v = jnp.asarray(0.3 * np.stack([np.cos(h), np.sin(h)], axis=1), params.R0.dtype)
        return float(jnp.max(jnp.abs(jax.vmap(lambda r: kinematic_wheel_speeds(params, r))(v))))
    return float(0.05 * params.m * params.g * params.R_m)


def random_inputs(
    params: RobotParams,
    t1: float,
    *,
    kind: str = "wheel_speeds",
    amplitude: float | None = None,
    n_sines: int = 3,
    f_min: float = 0.2,
    f_max: float = 1.5,
    ramp_time: float = 0.5,
    seed: int = 0,
) -> WheelSpeeds | Torques:
    """A smooth, exciting input program: per wheel, `n_sines` sines of random frequencies in
    `[f_min, f_max]` [Hz], phases and weights, bounded by `amplitude` (rad/s for wheel speeds, N m
    for torques; default `default_amplitude`), ramped in from 0 over `ramp_time` [s].

    Returns `WheelSpeeds(RandomSines(...))` or `Torques(RandomSines(...))`: a Module whose
    coefficients are array leaves, so programs from other seeds reuse one compilation. `t1` is
    accepted for symmetry with `synthetic_trial` and checked, but the program is defined for all t.
    """
    if kind not in KINDS:
        raise ValueError(f"random_inputs: kind must be one of {KINDS}; got {kind!r}.")
    if not t1 > 0:
        raise ValueError(f"random_inputs: t1 must be positive; got {t1}.")
    if not (0 < f_min <= f_max):
        raise ValueError(f"random_inputs: need 0 < f_min <= f_max; got {f_min}, {f_max}.")
    if not ramp_time > 0:
        raise ValueError(f"random_inputs: ramp_time must be positive; got {ramp_time}.")
    a = default_amplitude(params, kind) if amplitude is None else float(amplitude)
    rng = np.random.default_rng(seed)
    N = params.n_wheels
    w = rng.uniform(0.5, 1.0, (N, n_sines))
    amp = a * w / n_sines
    freq = rng.uniform(f_min, f_max, (N, n_sines))
    phase = rng.uniform(0, 2 * np.pi, (N, n_sines))
    dt = params.R0.dtype
    fn = RandomSines(jnp.asarray(amp, dt), jnp.asarray(freq, dt), jnp.asarray(phase, dt), jnp.asarray(ramp_time, dt))
    return WheelSpeeds(fn) if kind == "wheel_speeds" else Torques(fn)


def _dropout_mask(rng: np.random.Generator, M: int, dropout: float, max_burst: int = 5) -> np.ndarray:
    """`(M,)` bool, True where a frame is dropped: bursts of 1..`max_burst` frames (uniform,
    mean 3) start with probability `dropout / 3`, so that about a fraction `dropout` is lost.
    Frame 0 is always kept (the initial pose)."""
    drop = np.zeros(M, bool)
    if dropout <= 0:
        return drop
    starts = np.nonzero(rng.random(M) < dropout / ((1 + max_burst) / 2))[0]
    lengths = rng.integers(1, max_burst + 1, starts.size)
    for s, n in zip(starts, lengths):
        drop[s : s + n] = True
    drop[0] = False
    return drop


def synthetic_trial(
    params: RobotParams,
    controls: WheelSpeeds | Torques,
    t1: float,
    *,
    state0: State | None = None,
    rate: float = 100.0,
    pos_sd: float = 1e-3,
    rot_sd_deg: float = 0.5,
    dropout: float = 0.0,
    seed: int = 0,
    name: str = "synthetic",
    rtol: float = 1e-10,
    atol: float = 1e-12,
) -> Trial:
    """A capture-like trial from a simulation: `controls` simulated from `state0` (default at
    rest; tolerances `rtol, atol`, errors raised) and sampled at `rate` [Hz] from 0 to `t1` [s],
    with Gaussian noise of `pos_sd` [m] on `x, y`, the platform quaternion turned by a random
    small rotation (rotation vector of `rot_sd_deg` [deg] per axis, platform frame), gaps in
    bursts of 1-5 frames covering about a fraction `dropout` (the first frame kept), and the
    commanded inputs `controls(t)`, without noise. Deterministic for a given `seed`.
    """
    if not rate > 0 or not t1 > 0:
        raise ValueError(f"synthetic_trial: rate and t1 must be positive; got rate={rate}, t1={t1}.")
    if not 0.0 <= dropout < 1.0:
        raise ValueError(f"synthetic_trial: dropout must be in [0, 1); got {dropout}.")
    ts, traj, u, kind = simulated(params, controls, t1, state0, rate, rtol, atol)
    rng = np.random.default_rng(seed)
    M = ts.shape[0]
    x = np.asarray(traj.x) + rng.normal(0.0, pos_sd, M)
    y = np.asarray(traj.y) + rng.normal(0.0, pos_sd, M)
    noise = quat_from_rotvec_np(rng.normal(0.0, np.deg2rad(rot_sd_deg), (M, 3)))
    q = quat_mul_np(np.asarray(traj.q), noise)
    drop = _dropout_mask(rng, M, dropout)
    x[drop], y[drop], q[drop] = np.nan, np.nan, np.nan
    return Trial(ts, x, y, q, u, kind, None, name=name)


def add_glitches(
    trial: Trial,
    *,
    ghost: float = 0.01,
    ghost_jump: tuple[float, float] = (0.01, 0.05),
    swaps: int = 2,
    swap_frames: tuple[int, int] = (5, 15),
    swap_deg: tuple[float, float] = (30.0, 90.0),
    seed: int = 0,
) -> tuple[Trial, np.ndarray]:
    """`trial` with the glitches of a real capture, and the 0-based rows it spoiled (sorted).

    - ghost frames: each measured frame (not the first) with probability `ghost`, its position
      moved by `ghost_jump` [m] (uniform between the two) in a random horizontal direction, for
      that frame alone (a reflection taken for a marker);
    - marker swaps: `swaps` bursts of `swap_frames` consecutive frames (uniform between the two,
      inclusive) at random places (not overlapping, not the first frame), whose orientation is
      turned by `swap_deg` [deg] (uniform, one angle per burst) about a random axis (the rigid
      body fit flips while two markers are swapped).

    Gaps stay gaps; deterministic for a given `seed`."""
    rng = np.random.default_rng(seed)
    M = trial.n_frames
    x, y, q = np.array(trial.x, float), np.array(trial.y, float), np.array(trial.q, float)
    bad = np.zeros(M, bool)
    lo, hi = swap_frames
    for _ in range(swaps):
        for _try in range(100):
            n = int(rng.integers(lo, hi + 1))
            k = int(rng.integers(1, max(M - n, 2)))
            if not bad[max(k - 1, 0) : k + n + 1].any():
                break
        axis = rng.normal(size=3)
        angle = np.deg2rad(rng.uniform(*swap_deg))
        turn = quat_from_rotvec_np(angle * axis / np.linalg.norm(axis))
        q[k : k + n] = quat_mul_np(q[k : k + n], np.broadcast_to(turn, (min(n, M - k), 4)))
        bad[k : k + n] = True
    ghosts = (rng.random(M) < ghost) & ~bad
    ghosts[0] = False
    k = np.flatnonzero(ghosts)
    jump = rng.uniform(*ghost_jump, k.size)
    heading = rng.uniform(0.0, 2 * np.pi, k.size)
    x[k] += jump * np.cos(heading)
    y[k] += jump * np.sin(heading)
    bad |= ghosts
    bad &= trial.valid
    return Trial(trial.t, x, y, q, trial.inputs, trial.kind, trial.z, name=trial.name), np.flatnonzero(bad)


def default_marker_set(R0: float = 0.15) -> np.ndarray:
    """Four non-coplanar markers (platform frame, relative to the shell centre) [m] on a
    platform inside a shell of radius `R0`: a stand of about `R0/2`."""
    a = 0.5 * R0
    return np.array([[a, 0.0, 0.1 * a], [-0.5 * a, 0.8 * a, 0.0], [-0.5 * a, -0.8 * a, 0.0], [0.0, 0.2 * a, 0.7 * a]])


def synthetic_markers(
    trial: Trial,
    body_markers: np.ndarray,
    *,
    z: float = 0.15,
    body_offset=(0.0, 0.0, 0.0),
    alignment: np.ndarray | None = None,
    marker_sd: float = 2e-4,
    dropout: float = 0.0,
    seed: int = 0,
) -> np.ndarray:
    """Marker positions `(M, K, 3)` [m] that a capture system would see for `trial`'s poses.

    The shell centre is at `(x, y, z)` (`trial.z` if it has one, else `z`, the shell radius);
    marker k is at `centre - R body_offset + R alignment^T body_markers[k]` with `R` the platform
    rotation; Gaussian noise of `marker_sd` [m] per coordinate; each marker independently
    missing (NaN) with probability `dropout`; gap frames of `trial` give NaN markers.
    """
    rng = np.random.default_rng(seed)
    A = np.eye(3) if alignment is None else np.asarray(alignment, float)
    R = rotmat_np(np.where(np.isfinite(trial.q), trial.q, 1.0))
    zz = trial.z if trial.z is not None else np.full(trial.n_frames, float(z))
    centre = np.stack([trial.x, trial.y, zz], axis=1)
    off = np.asarray(body_offset, float)
    b_pl = np.asarray(body_markers, float) @ A  # rows: A^T b_k
    m = centre[:, None] - np.einsum("mij,j->mi", R, off)[:, None] + np.einsum("mij,kj->mki", R, b_pl)
    m = m + rng.normal(0.0, marker_sd, m.shape)
    m[rng.random(m.shape[:2]) < dropout] = np.nan
    m[~trial.valid] = np.nan
    return m
