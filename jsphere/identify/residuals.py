"""The model of a trial as the fit sees it, and its compiled Jacobians: `trial_model` for
captured poses, `onboard_model` for the robot's own sensors (`jsphere.identify.onboard`).

The model of a trial is `simulate(params, state0(nu), controls)` sampled at the capture times;
the residuals are the simulated minus the captured position and orientation, whitened by
`sigma_pos` [m] and `sigma_rot` [rad]:

    r_pos = (x_sim - x_meas, y_sim - y_meas) / sigma_pos
    r_rot = Log(q_sim^-1 q_meas) / sigma_rot          (rotation vector, platform frame)

with gap frames masked. With a fitted clock offset (the last nuisance value) the inputs drive
the model at `t + offset`. In wheel-speed mode `omega(0) = Omega(0) + w(0)` follows from the
command (2.4), so the impulsive start of `simulate` changes nothing. All trials run in one
compiled function (vmapped over trials, padded to a common length with masked samples) and all
starts in the same call (vmapped over starts). The Jacobian of each trial's residuals with
respect to `(theta, nu_i)` comes from forward-mode autodiff through diffrax (`ForwardMode`): a
few dozen tangent columns instead of a reverse pass per residual.
"""

from __future__ import annotations

import functools
from typing import Any, Callable

import diffrax as dfx
import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import NamedSharding, PartitionSpec

from .._runtime.arrays import to_jax
from .._runtime.cores import split_devices, trial_mesh
from .._runtime.quick_compile import eager_jit, run_program
from ..controls import Sampled, Torques, WheelSpeeds
from ..model.kinematics import relative_rate_from_wheel_speeds
from ..model.rotations import quat_conj, quat_exp, quat_log, quat_mul
from ..model.sensors import Mounting, imu_readings
from ..model.state import State
from ..numerics.lm import arrow_step, solve_arrow
from ..solve.simulate import simulate
from . import shooting as _shooting
from .data import nuisance_names, offset_from_nuisance
from .free import FreeParams
from .mixed import stack
from .onboard import MOTION, NUISANCE, onboard_options
from .shooting import end_vector


def trial_model(p, kind, rtol, atol, max_steps, adjoint, nu, d, sig, solver=None, max_offset=0.0):
    """The model of one trial with parameters `p` (a `RobotParams`): its whitened residuals
    `(5 M,)`, its solver status, the simulated pose and the state at its last sample
    (`jsphere.identify.shooting.end_vector`, and the clock offset's nuisance value when it is
    fitted); `solver`: None for `simulate`'s default.

    `nu`: the trial's nuisance values (`jsphere.identify.data.nuisance_names`); with
    `max_offset > 0` the last is its clock offset (`offset_from_nuisance`), and the inputs drive
    the model at `t + offset` (their table's knots move by `-offset`; beyond its ends the end
    values are held)."""
    dt = p.R0.dtype
    q0 = quat_mul(d["q0"], quat_exp(nu[3:6]))
    Omega = nu[0:3]
    if max_offset > 0:
        offset = offset_from_nuisance(nu[-1], max_offset)
        table = Sampled(d["tc"] - offset, d["u"], "cubic")
        u0 = table(jnp.zeros((), dt))
    else:
        table = Sampled(d["tc"], d["u"], "cubic")
        u0 = d["u"][0]
    if kind == "wheel_speeds":
        controls = WheelSpeeds(table, ())
        omega = Omega + relative_rate_from_wheel_speeds(p, u0)
    else:
        controls = Torques(table, ())
        omega = nu[8:11]
    state0 = State(
        q=q0,
        q_shell=jnp.array([1.0, 0.0, 0.0, 0.0], dt),
        omega=omega,
        Omega=Omega,
        x=d["xy0"][0] + nu[6],
        y=d["xy0"][1] + nu[7],
        chi=jnp.zeros(p.n_wheels, dt),
    )
    tr = _solve(p, state0, controls, d, rtol, atol, max_steps, adjoint, solver)
    ex = (tr.x - d["x"]) * d["wpos"] / sig[0]
    ey = (tr.y - d["y"]) * d["wpos"] / sig[0]
    er = quat_log(quat_mul(quat_conj(tr.q), d["q"])) * d["wrot"][:, None] / sig[1]
    res = jnp.concatenate([ex, ey, er.reshape(-1)])
    end = end_vector(tr)
    if max_offset > 0:
        end = jnp.concatenate([end, nu[-1:]])
    ok = tr.ok & jnp.all(jnp.isfinite(res)) & jnp.all(jnp.isfinite(end))
    res = jnp.where(ok, res, 0.0)
    end = jnp.where(ok, end, 0.0)
    return res, ok, (tr.x, tr.y, tr.q), end


def _solve(p, state0, controls, d, rtol, atol, max_steps, adjoint, solver):
    """A trial's motion at its sample times `d["ts"]`, as every model of a trial solves it: no
    exception on failure (`tr.ok`), per-trial steps (forward mode: diffrax's own vmap)."""
    return simulate(
        p,
        state0,
        controls,
        d["t1"],
        ts=d["ts"],
        rtol=rtol,
        atol=atol,
        solver=solver,
        max_steps=max_steps,
        throw=False,
        adjoint=adjoint,
        batch_steps="diffrax",
    )


def onboard_model(p, kind, rtol, atol, max_steps, adjoint, nu, d, sig, solver=None, hold=False, at_rest=True):
    """The model of one onboard trial with parameters `p` (a `RobotParams`): its whitened
    residuals `(M (6 + N),)` (gyro, accelerometer, encoders, each sample-major), its solver
    status, the simulated readings `(gyro (M, 3), acc (M, 3), chi (M, N))` with the biases `nu`
    added, and an empty end state (onboard trials are single-shot). `sig`: the channels' noise
    levels (`CHANNELS`); `hold`: the inputs are held between samples; `at_rest`: the trial
    starts at rest, else from the initial motion of `nu[6 + N:]` (`MOTION`)."""
    dt, N = p.R0.dtype, p.n_wheels
    table = Sampled(d["tc"], d["u"], "zoh" if hold else "cubic")
    controls = WheelSpeeds(table, ()) if kind == "wheel_speeds" else Torques(table, ())
    state0 = State.at_rest(p)
    if not at_rest:
        m = nu[6 + N :]
        Omega = m[0:3]
        q0 = quat_mul(state0.q, quat_exp(jnp.concatenate([m[3:5], jnp.zeros(1, dt)])))
        omega = Omega + relative_rate_from_wheel_speeds(p, d["u"][0]) if kind == "wheel_speeds" else m[5:8]
        state0 = State(q=q0, q_shell=state0.q_shell, omega=omega, Omega=Omega, x=state0.x, y=state0.y, chi=state0.chi)
    tr = _solve(p, state0, controls, d, rtol, atol, max_steps, adjoint, solver)
    gyro, acc = imu_readings(p, Mounting(d["imu_pos"], d["imu_rot"]), tr.gamma, tr.omega, tr.Omega, tr.K)
    gyro, acc, chi = gyro + nu[0:3], acc + nu[3:6], tr.chi - tr.chi[:1] + nu[6 : 6 + N]
    w = d["w"][:, None]
    res = jnp.concatenate(
        [
            ((a - d[k]) * w / s).reshape(-1)
            for a, k, s in ((gyro, "gyro", sig[0]), (acc, "acc", sig[1]), (chi, "chi", sig[2]))
        ]
    )
    ok = tr.ok & jnp.all(jnp.isfinite(res))
    return jnp.where(ok, res, 0.0), ok, (gyro, acc, chi), jnp.zeros(1, dt)


class _Functions:
    """The compiled functions of one fit configuration (cached: a second fit with the same
    free names, transforms, input kind, solver settings and shapes does not compile again).

    `jacobian(base, theta (S,P), nu (S,T,n), data, sigmas)`: whitened residuals `(S,T,K)`,
    solver status `(S,T)`, their Jacobian `(S,T,K,P+n)` with respect to `(theta, nu_i)` and
    the simulated poses, vmapped over starts and trials; `step(res, J, lam)`: the LM step of
    single shooting. `segments(...)`: the same for the segments of multiple shooting, with each
    segment's end state and its Jacobian; `assemble(...)`: their normal-equation blocks, cost and
    defects (`jsphere.identify.shooting.assemble`); `solve(blocks, lam)`: the LM step from blocks.

    `split`: `run` splits the starts x trials of `jacobian` and `segments` over
    as many devices as divide them (`jsphere.use_cpu_cores`: one per CPU core), each device
    solving its share (`jax.shard_map`); their inputs are copied to those devices and their
    outputs come back to the default device, where the other programs run. A call of
    `jacobian` or `segments` itself runs on one device.
    """

    def __init__(
        self,
        free: FreeParams,
        kind: str,
        rtol: float,
        atol: float,
        max_steps: int,
        solver: dfx.AbstractSolver | None,
        max_offset: float = 0.0,
        split: bool = False,
        measure: str = "pose",
    ):
        P = free.size
        self.split = split and not measure.startswith("mixed")
        # what the programs close over, as a stable text (an object shown by its address has none)
        key = repr((free.slots, kind, rtol, atol, max_steps, solver, max_offset, measure))
        self.key = None if " at 0x" in key or measure.startswith("mixed") else key

        onboard = measure.split(":")[-1]

        def pose_model(p, nu, d, sig):
            return trial_model(p, kind, rtol, atol, max_steps, dfx.ForwardMode(), nu, d, sig, solver, max_offset)

        def onboard_model_(p, nu, d, sig):
            return onboard_model(
                p, kind, rtol, atol, max_steps, dfx.ForwardMode(), nu, d, sig, solver, **onboard_options(onboard)
            )

        def jac_one(base, th, nu, d, sig, ends, model):
            def f(z):
                p = free.to_params(z[:P], base)
                at = d
                if free.frees_mounting:
                    pos, rot = free.mounting_at(z[:P], d["imu_pos"], d["imu_rot"])
                    at = d | {"imu_pos": pos, "imu_rot": rot}
                res, ok, pose, end = model(p, z[P:], at, sig)
                return ((res, end) if ends else res), (res, ok, pose, end)

            J, (res, ok, pose, end) = jax.jacfwd(f, has_aux=True)(jnp.concatenate([th, nu]))
            return (res, ok, J[0], pose, end, J[1]) if ends else (res, ok, J, pose)

        def every(base, th, nu, d, sig, ends, split, model=None):
            """`jac_one` of every start and trial, in one `vmap` over both (one batching of the
            solve); with `split`, each of `_devices(nu)` solves its share. Trials of both kinds
            (`jsphere.identify.mixed`): each part in its own `vmap`, stacked."""
            if model is None and measure.startswith("mixed"):
                return every_mixed(base, th, nu, d, sig)
            model = model or (pose_model if measure == "pose" else onboard_model_)
            S, T = nu.shape[:2]
            d = jax.tree_util.tree_map(lambda a: jnp.tile(a, (S,) + (1,) * (a.ndim - 1)), d)
            solves = jax.vmap(functools.partial(jac_one, ends=ends, model=model), in_axes=(None, 0, 0, 0, None))
            devices = _devices(nu) if split else ()
            if len(devices) > 1:
                one, trials = PartitionSpec(), PartitionSpec("trials")
                solves = jax.shard_map(
                    solves,
                    mesh=trial_mesh(devices),
                    in_specs=(one, trials, trials, trials, one),
                    out_specs=trials,
                    check_vma=False,
                )
            out = solves(base, jnp.repeat(th, T, axis=0), nu.reshape((S * T,) + nu.shape[2:]), d, sig)
            return jax.tree_util.tree_map(lambda a: a.reshape((S, T) + a.shape[1:]), out)

        def every_mixed(base, th, nu, d, sig):
            N, (Tp, Mp), Mo = d["onboard"]["chi"].shape[-1], d["pose"]["ts"].shape, d["onboard"]["ts"].shape[1]
            own = (len(nuisance_names(kind, max_offset > 0)), len(NUISANCE) + N)
            own = (own[0], own[1] + (0 if onboard_options(onboard)["at_rest"] else len(MOTION[kind])))
            n = nu.shape[-1]
            outs = (
                every(base, th, nu[:, :Tp, : own[0]], d["pose"], sig[:2], False, False, pose_model),
                every(base, th, nu[:, Tp:, : own[1]], d["onboard"], sig[2:], False, False, onboard_model_),
            )
            n_res = max(5 * Mp + n - own[0], (6 + N) * Mo + n - own[1])
            return stack(outs, nu, P, Tp, own, n_res)

        # (single shooting needs no Jacobian of the trials' end states)
        self.jacobian = eager_jit(functools.partial(every, ends=False, split=False))
        self.segments = eager_jit(functools.partial(every, ends=True, split=False))
        self._split = {
            "jacobian": eager_jit(functools.partial(every, ends=False, split=True)),
            "segments": eager_jit(functools.partial(every, ends=True, split=True)),
        }
        self.step = eager_jit(jax.vmap(functools.partial(arrow_step, P=P)))

        def assemble(res, J, e, Je, nu, mu, seg, scale):
            return _shooting.assemble(kind, P, res, J, e, Je, nu, mu, seg, scale)

        self.assemble = eager_jit(jax.vmap(assemble, in_axes=(0, 0, 0, 0, 0, None, None, None)))
        self.solve = eager_jit(jax.vmap(solve_arrow, in_axes=(0, 0)))

    def _program(self, name: str, args) -> tuple[Callable, tuple, bool]:
        """The function `run(_, name, *args)` calls, its arguments placed where it runs, and
        whether it spans several devices."""
        devices = _devices(args[2]) if self.split and name in self._split else ()
        if len(devices) < 2:
            return getattr(self, name), args, False
        everywhere = NamedSharding(trial_mesh(devices), PartitionSpec())
        placed = jax.tree_util.tree_map(
            lambda x: jax.device_put(x, everywhere) if isinstance(x, (jax.Array, np.ndarray)) else x, args
        )
        return self._split[name], placed, True

    def run(self, name: str, *args):
        """`self.<name>(*args)` (split over devices with `split`), through `run_program` where
        the program has a stable key (the command line keeps it, exported, for the next process)."""
        fn, args, split = self._program(name, args)
        if self.key is None:
            out = fn(*args)
        else:
            rebuild = functools.partial(jax.tree_util.tree_unflatten, _OUTPUTS[name])
            out = run_program(f"fit.{name}:{self.key}:{split}", fn, rebuild, *args)
        if not split:
            return out
        # on the default device, uncommitted as every other program's inputs are (a committed
        # array would compile each later program again)
        return jax.tree_util.tree_map(lambda a: to_jax(np.asarray(a)), out)


def _devices(nu) -> list:
    """The devices the starts x trials (or segments) of `nu (S, T, n)` are split over."""
    return split_devices(nu.shape[0] * nu.shape[1])


#: the structure of each program's output (`_Functions.run` rebuilds it from the leaves)
_OUTPUTS = {
    name: jax.tree_util.tree_structure(template)
    for name, template in {
        "jacobian": (0, 0, 0, (0, 0, 0)),
        "segments": (0, 0, 0, (0, 0, 0), 0, 0),
        "step": (0, 0, 0),
        "assemble": ((0, 0, 0, 0, 0), 0, 0),
        "solve": (0, 0, 0),
    }.items()
}


_CACHE: dict[Any, _Functions] = {}


def _functions(
    free: FreeParams,
    kind: str,
    rtol: float,
    atol: float,
    max_steps: int,
    solver: dfx.AbstractSolver | None = None,
    max_offset: float = 0.0,
    split: bool = False,
    measure: str = "pose",
) -> _Functions:
    """The compiled functions of a configuration; `solver`: a diffrax solver (hashable, as
    diffrax's are), None for `simulate`'s default; `max_offset` > 0: the clock offsets are
    fitted; `split`: see `_Functions`; `measure`: `"pose"` (captured poses, `trial_model`) or
    an onboard trial's `jsphere.identify.onboard.measure_name` (`onboard_model`)."""
    key = (free.slots, kind, rtol, atol, max_steps, solver, max_offset, split, measure)
    if key not in _CACHE:
        _CACHE[key] = _Functions(free, kind, rtol, atol, max_steps, solver, max_offset, split, measure)
    return _CACHE[key]
