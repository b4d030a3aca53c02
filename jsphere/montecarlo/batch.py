"""One batch of a Monte-Carlo study: its trials simulated in vmapped chunks, sharded over the
local devices, in one compiled function (`run_batch`) reused for every batch of a study."""

from __future__ import annotations

import diffrax as dfx
import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float, Int, UInt32

from ..controls import Torques, WheelSpeeds
from ..gaits.gaits import Gait, simulate_gaits
from ..model.linalg import cross
from ..model.params import RobotParams
from ..model.state import Flat, State
from ..model.uncertainty import draw_key
from ..planning.tracking.evaluate import Conditions, run_one
from ..solve.simulate import Trajectory, simulate
from ..solve.status import RESULTS
from .sampling import PERTURBATION_FOLD, Actuators, Uncertainty

#: trials per vmapped chunk. Every trial is computed inside a vmap of exactly this width,
#: whatever the batch size or device count, which keeps results bitwise reproducible (XLA
#: may pick other kernels, summing in another order, for other widths).
CHUNK = 64
#: the output times of the settling phase after replayed commands end
SETTLE_SAMPLES = 51


class Replay(eqx.Module):
    """Commands replayed open loop on every trial's robot (`mode` "torques" or
    "wheel_speeds"): the plan `(ts, values)` (ending on a jump to zero at its last time), as
    `actuators` execute it, then `settle` seconds without commands; at most `max_steps`
    solver steps; `jump_ts`: the plan's jumps (when the actuators keep them in place)."""

    mode: str
    plan: tuple[Float[Array, " t"], Float[Array, "t N"]]
    actuators: Actuators
    settle: float
    max_steps: int
    jump_ts: tuple[float, ...]


class ClosedLoop(eqx.Module):
    """A feedback table run closed loop on every trial's robot (`StudyOptions.track`) by the
    tracking evaluation's step (`jsphere.planning.tracking.evaluate.run_one`): per interval of
    `ts_h` seconds, `K = K_ff - G e` under `conditions`, clipped to `max_torque`; after the last
    row that row is held, for `n_settle` intervals."""

    ts_h: float
    K_ff: Float[Array, "M N"]
    ref: Float[Array, "M S"]
    G: Float[Array, "M N 11"]
    target: Float[Array, "2"]
    conditions: Conditions
    max_torque: float | None
    n_settle: int
    mode: str = "track"


class Trials(eqx.Module):
    """What every trial of a study shares: the nominal robot, the gaits (or the commands of
    `replay`), the draws' distributions and seed, the solver's settings (`solver` None for the
    default; `max_steps`: gait mode's step limit) and the `mesh` of devices (None for one)."""

    params: RobotParams
    gaits: list[Gait]
    draws: Uncertainty
    seed: UInt32[Array, ""]
    reset: bool | list
    rtol: float
    atol: float
    Omega0_sd: float
    replay: Replay | ClosedLoop | None
    mesh: jax.sharding.Mesh | None
    solver: dfx.AbstractSolver | None = None
    max_steps: int = 16384

    @property
    def duration(self):
        """When the gaits (or the replayed commands) end [s]."""
        dt = self.params.R0.dtype
        if isinstance(self.replay, ClosedLoop):
            return jnp.asarray(self.replay.ts_h * (self.replay.K_ff.shape[0] - 1), dt)
        return sum(jnp.asarray(g.T, dt) for g in self.gaits) if self.replay is None else self.replay.plan[0][-1]


def _solve(trials: Trials, p: RobotParams, T, dOmega, key) -> Trajectory:
    """Trial robot `p` executing the gaits exactly, saved at their end `T`, or under the replayed
    commands as its actuators execute them, then settling. Every trial takes its own steps, so
    that its result is independent of the other trials of its chunk."""
    common = dict(rtol=trials.rtol, atol=trials.atol, solver=trials.solver, throw=False, batch_steps="per_trial")
    rp = trials.replay
    if rp is None:
        ts = jnp.reshape(T, (1,))
        return simulate_gaits(
            p, trials.gaits, ts=ts, reset=trials.reset, max_steps=trials.max_steps, Omega0=dOmega, **common
        )
    s0 = State.at_rest(p)
    s0 = eqx.tree_at(lambda s: s.Omega, s0, s0.Omega + dOmega)
    ctrl = (Torques if rp.mode == "torques" else WheelSpeeds)(rp.actuators.table(key, *rp.plan), rp.jump_ts)
    ts_after = T + rp.settle * jnp.linspace(0.0, 1.0, SETTLE_SAMPLES, dtype=p.R0.dtype)  # the settling phase
    return simulate(p, s0, ctrl, T + rp.settle, ts=ts_after, max_steps=rp.max_steps, **common)


def _closed_loop(trials: Trials, p: RobotParams, key) -> tuple:
    """Trial robot `p` under the feedback table: `(x, y, speed, status, gamma3_sd)` at the end of
    the settling time; `status` is `nonfinite` where the end state is not finite; the tilt's
    spread is not recorded (0)."""
    cl = trials.replay
    one = jnp.ones((), cl.ref.dtype)
    _, speed, _, zT = run_one(
        p, key, cl.ts_h, cl.K_ff, cl.ref, cl.G, cl.target, cl.conditions, cl.max_torque, cl.n_settle, one
    )
    ok = jnp.all(jnp.isfinite(zT)) & jnp.isfinite(speed)
    status = jnp.where(ok, int(RESULTS.successful), int(RESULTS.nonfinite))
    return zT[Flat.x], zT[Flat.y], speed, status, jnp.zeros_like(speed)


def _trial(trials: Trials, T, i: Int[Array, ""]) -> tuple:
    """Trial `i`, whose gaits or commands end at `T`: `(vals, x, y, speed, status, gamma3_sd,
    reject_code)`. A draw that breaks a rule of `RobotParams` is solved with the nominal robot
    (so as not to hold up its chunk), its outcomes NaN and its status `RESULTS.rejected`."""
    params = trials.params
    dt = params.R0.dtype
    vals, code = trials.draws.draw_one(params, trials.seed, i)
    valid = code == 0
    p = trials.draws.robot(params, vals, valid)
    k_omega, k_act = jax.random.split(jax.random.fold_in(draw_key(trials.seed, i), PERTURBATION_FOLD))
    dOmega = trials.Omega0_sd * jax.random.normal(k_omega, (3,), dt)
    if isinstance(trials.replay, ClosedLoop):
        x, y, speed, status, g3sd = _closed_loop(trials, p, k_act)
    else:
        tr = _solve(trials, p, T, dOmega, k_act)
        x, y, status, g3sd = tr.x[-1], tr.y[-1], tr.status, jnp.std(tr.gamma[:, 2])
        speed = p.R0 * jnp.linalg.norm(cross(tr.Omega[-1], tr.gamma[-1]))
    x, y, speed, g3sd = (jnp.where(valid, v, jnp.asarray(jnp.nan, dt)) for v in (x, y, speed, g3sd))
    return vals, x, y, speed, jnp.where(valid, status, int(RESULTS.rejected)), g3sd, code


@eqx.filter_jit
def run_batch(trials: Trials, idx: Int[Array, " B"]) -> tuple:
    """Trials `idx` of a study, as stacked `_trial` outcomes: one compiled function per
    structure, reused across calls."""
    T = trials.duration

    def local(ii):  # this device's trials, in chunks of CHUNK
        out = jax.lax.map(jax.vmap(lambda i: _trial(trials, T, i)), ii.reshape(-1, CHUNK))
        return jax.tree_util.tree_map(lambda a: a.reshape((a.shape[0] * a.shape[1],) + a.shape[2:]), out)

    if trials.mesh is None:
        return local(idx)
    from jax.sharding import PartitionSpec

    spec = PartitionSpec("trials")
    return jax.shard_map(local, mesh=trials.mesh, in_specs=spec, out_specs=spec, check_vma=False)(idx)
