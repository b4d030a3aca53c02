"""Time integration with diffrax: vector fields for the two input modes, and `simulate`."""

from __future__ import annotations

import functools
import warnings
from typing import Any, Callable, Literal

import diffrax as dfx
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from .._runtime import export_cache as _aot
from .batched import dispatch as _ensemble
from .batched import loop as _shared_rk
from ..controls import Torques, WheelSpeeds
from ..model.dynamics import servo_accelerations, servo_jump, solve_accelerations
from ..model.rotations import quat_normalize, quat_rate_body, quat_rate_fixed, rotmat
from ..model.linalg import cross, matvec
from .._runtime.arrays import as_array, under_jit
from ..model.params import Derived, RobotParams, derive
from .batched.components import from_components, to_components, torque_field_components, unit
from ..model.state import State, _unflatten


class Trajectory(eqx.Module):
    """A simulated motion sampled at times `ts` (a pytree; batched under `vmap`).

    Fields (platform-frame components unless said otherwise): `ts` [s]; `x, y` [m] (fixed
    frame); `gamma, alpha, beta` (fixed axes seen from the platform); `omega, Omega` [1/s];
    `chi` [rad], `chi_dot` [rad/s] wheel angles and rates; `K` [N m] axle torques (the input in
    torque mode, the torques the motors must supply in wheel-speed and gait modes);
    `q, q_shell` orientation quaternions; `segment`: index of the gait or control segment of
    each sample; `status`: 0 if the solve succeeded, 1 if the solver failed (max steps), 2 if
    values became non-finite (only seen with `throw=False`; `ok` is `status == 0`);
    `num_steps`: accepted solver steps.
    """

    ts: Float[Array, " T"]
    x: Float[Array, " T"]
    y: Float[Array, " T"]
    gamma: Float[Array, "T 3"]
    alpha: Float[Array, "T 3"]
    beta: Float[Array, "T 3"]
    omega: Float[Array, "T 3"]
    Omega: Float[Array, "T 3"]
    chi: Float[Array, "T N"]
    chi_dot: Float[Array, "T N"]
    K: Float[Array, "T N"]
    q: Float[Array, "T 4"]
    q_shell: Float[Array, "T 4"]
    segment: Int[Array, " T"]
    status: Int[Array, ""]
    num_steps: Int[Array, ""]

    @property
    def ok(self) -> Bool[Array, ""]:
        """`True` where the solve succeeded (per trial under `vmap`)."""
        return self.status == 0

    def state(self, i: int = -1) -> State:
        """The `State` at sample `i` (default: the last), e.g. to continue a simulation."""
        return _state_at(self, i)


@jax.jit  # one compiled program when called eagerly, not one per operation
def _state_at(traj: Trajectory, i) -> "State":
    z = jnp.concatenate(
        [traj.q[..., i, :], traj.q_shell[..., i, :], traj.omega[..., i, :], traj.Omega[..., i, :],
         jnp.stack([traj.x[..., i], traj.y[..., i]], -1), traj.chi[..., i, :]], axis=-1,
    )  # fmt: skip
    return _unflatten(z)


def _rebuild(leaves) -> Trajectory:
    """A `Trajectory` from its leaves (in field order; for `jsphere._runtime.export_cache`)."""
    return Trajectory(*leaves)


def _left_limit(b):
    """The largest float below `b`: evaluates a control on the left side of a jump at `b`."""
    return jnp.nextafter(b, jnp.asarray(-jnp.inf, dtype=jnp.result_type(b)))


def _control_time(t, t_end):
    return jnp.where(t >= t_end, _left_limit(jax.lax.stop_gradient(t_end)), t)


def _kin_rates(p: RobotParams, z, R, gamma, omega, Omega):
    """Rates of `[q, q_shell]` and `(x, y)` shared by every mode, with `R = Q^T` computed once
    by the caller (`gamma` is its last row, or the prescribed `gamma(t)` of a gait)."""
    v = p.R0 * cross(Omega, gamma)
    vf = matvec(R, v)  # fixed-frame velocity; (x_dot, y_dot) = ((alpha, v), (beta, v))
    return quat_rate_body(z[0:4], omega), quat_rate_fixed(z[4:8], matvec(R, Omega)), vf[:2]


def _torque_field(t, z, args):
    p, d, control, _, t_end = args
    omega, Omega = z[8:11], z[11:14]
    R = rotmat(z[0:4])
    gamma = R[2]
    K = control(_control_time(t, t_end))
    omega_dot, Omega_dot = solve_accelerations(p, d, gamma, omega, Omega, K)
    dq, dqs, dxy = _kin_rates(p, z, R, gamma, omega, Omega)
    chi_dot = -matvec(d.Sk, omega - Omega)
    return jnp.concatenate([dq, dqs, omega_dot, Omega_dot, dxy, chi_dot])


def _torque_control(t, args):
    """The axle torques `K(t)` of a torque-mode segment (left limit at its end)."""
    _, _, control, _, t_end = args
    return control(_control_time(t, t_end))


def _torque_field_soa(t, y, args, K=None):
    """`_torque_field` on a tuple of scalar components (`jsphere.solve.batched.components`), for batched solves;
    `K`: the torques as a tuple of scalars, if the caller has evaluated them already."""
    p, d = args[0], args[1]
    if K is None:
        K = _torque_control(t, args)
        K = tuple(K[..., i] for i in range(K.shape[-1]))
    return torque_field_components(p, d, K, y, unit(t))


def _servo_inputs(d: Derived, control: WheelSpeeds, t):
    u, u_dot = control.value_and_rate(t)
    return -matvec(d.Sk_pinv, u), -matvec(d.Sk_pinv, u_dot)


def _wheel_field(t, z, args):
    p, d, control, _, t_end = args
    Omega = z[11:14]
    R = rotmat(z[0:4])
    gamma = R[2]
    w, w_dot = _servo_inputs(d, control, _control_time(t, t_end))
    omega, omega_dot, Omega_dot, _ = servo_accelerations(p, d, gamma, Omega, w, w_dot)
    dq, dqs, dxy = _kin_rates(p, z, R, gamma, omega, Omega)
    chi_dot = -matvec(d.Sk, w)
    return jnp.concatenate([dq, dqs, omega_dot, Omega_dot, dxy, chi_dot])


def _outputs_torque(p, d, control, t, z, t_start, t_end):
    omega, Omega = z[8:11], z[11:14]
    K = control(_control_time(t, t_end))
    return omega, -matvec(d.Sk, omega - Omega), K


def _outputs_wheel(p, d, control, t, z, t_start, t_end):
    Omega = z[11:14]
    gamma = rotmat(z[0:4])[2]
    w, w_dot = _servo_inputs(d, control, _control_time(t, t_end))
    omega, _, _, K = servo_accelerations(p, d, gamma, Omega, w, w_dot)
    return omega, -matvec(d.Sk, w), K


def default_solver():
    """The default Runge-Kutta method: `diffrax.Dopri8()` (8th order). At the tolerances the
    paper's millimetre-level numbers need (rtol 1e-8 and below) it takes about 5x fewer steps
    than `Tsit5` and runs 2.5-4x faster for one trial, 1.5-1.8x under `vmap`
    (benchmarks/NOTES.md)."""
    return dfx.Dopri8()


#: Tolerances `(rtol, atol)` of `simulate` by the parameters' precision when none are given.
#: float64: positions within 1e-3 mm over the paper's 4 s manoeuvres. float32: about 100
#: machine epsilons; issue 6's problem 1 then ends within ~1e-2 mm of the float64 reference
#: (benchmarks/NOTES.md, session 14).
DEFAULT_TOLERANCES = {"float64": (1e-8, 1e-10), "float32": (1e-5, 1e-7)}

#: Below this `rtol` a float32 solve's error estimates are mostly rounding noise: steps shrink
#: and are rejected at random, worst in batches with shared steps (issue 6's problem 1, 64
#: trials: 64 shared steps at rtol 1e-5, 218 at 1e-6, 733 at 5e-7; one trial at rtol 1e-8:
#: 7,105 steps against 102 in float64).
FLOAT32_MIN_RTOL = 1e-5


def tolerances(dtype, rtol, atol, defaults=DEFAULT_TOLERANCES, *, where: str = "simulate") -> tuple[Any, Any]:
    """`(rtol, atol)` with `None` replaced by the default for `dtype` (`defaults[dtype name]`),
    and a warning when a float32 solve is asked for an `rtol` its rounding cannot resolve."""
    name = "float32" if jnp.dtype(dtype).itemsize <= 4 else "float64"
    rtol = defaults[name][0] if rtol is None else rtol
    atol = defaults[name][1] if atol is None else atol
    if name == "float32" and isinstance(rtol, (int, float)) and rtol < FLOAT32_MIN_RTOL:
        warnings.warn(
            f"{where}: rtol={rtol:g} with float32 parameters is below what float32 resolves "
            f"(~{FLOAT32_MIN_RTOL:g}, about 100 machine epsilons): the error estimates are rounding "
            "noise, so the solver takes many more steps (most of all for batches with shared steps) "
            f"or fails. Pass rtol >= {FLOAT32_MIN_RTOL:g} (the float32 default when rtol is not "
            "given) or use float64 parameters.",
            stacklevel=3,
        )
    return rtol, atol


_FAILURE_MESSAGES = (
    "jsphere: the ODE solver failed: it reached max_steps (or its step size collapsed). Raise "
    "`max_steps`, loosen `rtol`/`atol`, check that the controls are smooth between their "
    "`jump_ts` and stay finite (NaN or inf values make every step fail). Pass throw=False to get "
    "`Trajectory.ok` per trial instead of this error.",
    "jsphere: the simulation produced NaN or inf. Check the controls (they must be finite) and "
    "the initial state. Pass throw=False to get `Trajectory.ok` per trial instead of this error.",
)


def raise_on_failure(traj: Trajectory, throw: bool) -> Trajectory:
    """Turn a failed solve into an error.

    Called outside the compiled solve, so that the compiled function holds no host callback
    and can be kept in JAX's persistent compilation cache. With concrete results the error
    is a Python `RuntimeError`; under a user's `jit`/`vmap` it is raised by equinox at run
    time.
    """
    if not throw:
        return traj
    if isinstance(traj.status, jax.core.Tracer):
        status = jnp.max(traj.status)
        return eqx.tree_at(
            lambda t: t.x, traj, eqx.branched_error_if(traj.x, status != 0, jnp.maximum(status - 1, 0), _FAILURE_MESSAGES)
        )
    status = int(np.max(np.asarray(traj.status)))
    if status != 0:
        raise RuntimeError(_FAILURE_MESSAGES[status - 1])
    return traj


def assemble(p, d, ts, zs, omega, chi_dot, K, segment, status, num_steps) -> Trajectory:
    """Build a `Trajectory` from flat states `zs (T, 16+N)` and the mode's outputs."""
    q = quat_normalize(zs[:, 0:4])
    R = rotmat(q)
    return Trajectory(
        ts=ts, x=zs[:, 14], y=zs[:, 15], gamma=R[:, 2], alpha=R[:, 0], beta=R[:, 1],
        omega=omega, Omega=zs[:, 11:14], chi=zs[:, 16:], chi_dot=chi_dot, K=K,
        q=q, q_shell=quat_normalize(zs[:, 4:8]), segment=segment, status=status, num_steps=num_steps,
    )  # fmt: skip


def _sample_masks(ts_out, a, b, last: bool):
    """Which output times segment `[a, b]` reports. A time on a boundary goes to the later
    segment, except that a time stamp given twice gives the left limit first, then the right."""
    first_dup = jnp.concatenate([ts_out[1:] == ts_out[:-1], jnp.zeros((1,), bool)])
    starts = (ts_out > a) | ((ts_out == a) & ~first_dup)
    ends = (ts_out < b) | ((ts_out == b) & (first_dup | last))
    return starts & ends


def _homogeneous(controls):
    """Stack per-segment controls if they share their structure and static parts."""
    parts = [eqx.partition(c, eqx.is_array) for c in controls]
    dyn0, st0 = parts[0]
    tdef = jax.tree_util.tree_structure(dyn0)
    for dyn, st in parts[1:]:
        if jax.tree_util.tree_structure(dyn) != tdef or not eqx.tree_equal(st, st0):
            return None
        if any(jnp.shape(u) != jnp.shape(v) for u, v in zip(jax.tree_util.tree_leaves(dyn), jax.tree_util.tree_leaves(dyn0))):
            return None
    stacked = jax.tree_util.tree_map(lambda *xs: jnp.stack([jnp.asarray(x) for x in xs]), *[d for d, _ in parts])
    return stacked, st0


def solve_segments(
    field,
    outputs,
    p: RobotParams,
    d: Derived,
    segments: list,
    z0,
    ts_out,
    *,
    jump_fn=None,
    solver,
    rtol,
    atol,
    max_steps,
    adjoint,
    component_field=None,
    component_control=None,
    shared=False,
):
    """Integrate `field(t, z, (p, d, control, a, b))` over consecutive segments
    `(control, a, b)`, restarting at each (after `z = jump_fn(k, a, z, control)` if given),
    and sample the flat state and `outputs(p, d, control, t, z, a, b)` at `ts_out`.

    Segments whose controls share a structure (e.g. the paper's gaits) run in one
    `lax.scan`, so compile time does not grow with their number. With `component_field`
    (the same field on a tuple of scalar components, `jsphere.solve.batched.components`) the solver carries the
    state as that tuple: faster under `vmap` (contiguous components), slower unbatched; with
    `shared="shared"` as well, a batch under `vmap` shares one step sequence
    (`jsphere.solve.batched.dispatch`), and with `shared="shared_fallback"` a batch whose shared steps fail
    is solved again with per-trial steps, so that a failing trial fails alone (and a trial
    that failed in an earlier segment is left out of the later ones' step control); with
    `shared="per_trial"` it runs in the same loop with each
    trial's own steps; the field's inputs are given by `component_control(t, args)` (default:
    the torques).
    """
    n_seg = len(segments)
    T = ts_out.shape[0]
    N = d.k.shape[0]
    dt = z0.dtype
    controller = dfx.PIDController(rtol=rtol, atol=atol)

    def one_segment(carry, k, control, a, b):
        z, zs, om, cd, Ks, seg, code, steps = carry
        if jump_fn is not None:
            z = jump_fn(k, a, z, control)
        t_save = jnp.clip(ts_out, a, b)
        if shared == "shared_fallback":  # a trial that failed in an earlier segment stays out of the step control
            z = jnp.where(code != 0, jnp.nan, z)
        if shared:
            ys, failed, n_acc = _ensemble.solve(
                component_field, component_control or _torque_control, solver, rtol, atol, max_steps, adjoint, to_components(z), (p, d, control, a, b), t_save,
                per_trial=shared == "per_trial", fallback=shared == "shared_fallback",
            )
            ys = from_components(ys)
        else:
            term, y0 = (dfx.ODETerm(field), z) if component_field is None else (dfx.ODETerm(component_field), to_components(z))
            sol = dfx.diffeqsolve(
                term, solver, a, b, None, y0, (p, d, control, a, b),
                saveat=dfx.SaveAt(ts=t_save, t1=True), stepsize_controller=controller,
                max_steps=max_steps, throw=False, adjoint=adjoint,
            )  # fmt: skip
            ys = sol.ys if component_field is None else from_components(sol.ys)
            failed, n_acc = sol.result != dfx.RESULTS.successful, sol.stats["num_accepted_steps"]
        mask = _sample_masks(ts_out, a, b, k == n_seg - 1)
        out = jax.vmap(lambda t, zz: outputs(p, d, control, t, zz, a, b))(t_save, ys[:-1])
        zs = jnp.where(mask[:, None], ys[:-1], zs)
        om = jnp.where(mask[:, None], out[0], om)
        cd = jnp.where(mask[:, None], out[1], cd)
        Ks = jnp.where(mask[:, None], out[2], Ks)
        seg = jnp.where(mask, k, seg)
        # diffrax fills the save points it never reached with inf, so decide by its result first
        bad_start = ~jnp.all(jnp.isfinite(field(a, z, (p, d, control, a, b))))
        finite = jnp.all(jnp.isfinite(ys)) & jnp.all(jnp.isfinite(out[2]))
        status = jnp.where(failed, jnp.where(bad_start, 2, 1), jnp.where(finite, 0, 2))
        code = jnp.where(code != 0, code, status)
        steps = steps + n_acc
        return (ys[-1], zs, om, cd, Ks, seg, code, steps)

    carry = (
        z0, jnp.zeros((T, z0.shape[0]), dt), jnp.zeros((T, 3), dt), jnp.zeros((T, N), dt),
        jnp.zeros((T, N), dt), jnp.zeros((T,), jnp.int32), jnp.array(0, jnp.int32), jnp.array(0, jnp.int32),
    )  # fmt: skip
    controls = [c for c, _, _ in segments]
    stacked = _homogeneous(controls) if n_seg > 1 else None
    if stacked is None:
        for k, (control, a, b) in enumerate(segments):
            carry = one_segment(carry, jnp.array(k, jnp.int32), control, a, b)
    else:
        dyn, static = stacked
        xs = (jnp.arange(n_seg, dtype=jnp.int32), dyn, jnp.stack([a for _, a, _ in segments]),
              jnp.stack([b for _, _, b in segments]))  # fmt: skip

        def body(c, x):
            k, dc, a, b = x
            return one_segment(c, k, eqx.combine(dc, static), a, b), None

        carry, _ = jax.lax.scan(body, carry, xs)
    _, zs, om, cd, Ks, seg, code, steps = carry
    return zs, om, cd, Ks, seg, code, steps


def simulate(
    params: RobotParams,
    state0: State,
    controls: Torques | WheelSpeeds,
    t1: float,
    *,
    t0: float = 0.0,
    ts: Float[ArrayLike, " T"] | None = None,
    rtol: float | None = None,
    atol: float | None = None,
    solver: dfx.AbstractSolver | None = None,
    max_steps: int = 16384,
    throw: bool = True,
    adjoint: dfx.AbstractAdjoint | None = None,
    batch_steps: Literal["shared", "per_trial"] = "shared",
) -> Trajectory:
    """Integrate the equations of motion (3.4), (3.5) with (2.2)-(2.4) from `state0`.

    **Arguments:**
    - `params`: a `RobotParams`.
    - `state0`: a `State` at time `t0`.
    - `controls`: `Torques(fn)` (axle torques, the paper's input) or `WheelSpeeds(fn)`
      (commanded wheel rates: servo constraints). In wheel-speed mode the initial velocities
      are first made consistent with the command by the impulsive momentum balance of the
      control-free equation (`servo_jump`), and again at each of the control's `jump_ts`.
    - `t1`: final time [s].
    - `ts`: times at which to report the motion (default `[t0, t1]`).
    - `rtol`, `atol`: tolerances of the adaptive step-size controller. Default 1e-8, 1e-10
      (positions within 1e-3 mm over the paper's 4 s manoeuvres); with float32 parameters
      1e-5, 1e-7 (`DEFAULT_TOLERANCES`; a float32 `rtol` below 1e-5 warns: its error
      estimates would be rounding noise).
    - `solver`: a diffrax solver (default `Dopri8`); `adjoint`: a diffrax adjoint (default
      `RecursiveCheckpointAdjoint`; use `diffrax.ForwardMode()` for `jax.jacfwd`).
    - `throw`: raise on solver failure (max steps, NaN). With `throw=False` the failure is
      reported in `Trajectory.ok` instead (per trial under `vmap`): a trial that fails fails
      alone, and the others get the results they get in a batch without it (a batch with
      shared steps that fail is solved again with per-trial steps).
    - `batch_steps`: under `vmap` (from 32 trials, `SHARED_MIN_BATCH`), in torque mode with the
      default adjoint, `"shared"` (default) integrates the batch with one step sequence,
      accepted only when every trial meets its tolerance (~3.6x faster at 1024 trials;
      results depend on the batch within the tolerance; `max_steps` and `num_steps` count
      the shared steps; `jsphere.solve.batched.dispatch`); its gradient is the discrete adjoint of the
      shared steps (within the tolerance of the per-trial gradient). `"per_trial"` gives each
      trial its own step-size control: with `Dopri8`, `Dopri5` or `Tsit5` the batch runs in
      the same vectorised loop, every trial with its own times, steps, failures and
      `num_steps` (in lockstep: ~0.7x the shared rate, ~4x diffrax's vmapped loop), so a
      trial's result is bitwise the same in any batch; its gradient is the discrete adjoint
      of those per-trial steps (~2-3x faster than per-trial VJPs of diffrax's loop). It
      changes nothing for unbatched calls, nor when `t0`, `t1`, `ts` or `jump_ts` are
      batched.

    Pure JAX: jit, vmap (over parameters, states, controls) and grad work.
    """
    if not isinstance(state0, State):
        raise TypeError(f"simulate: state0 must be a jsphere.State (e.g. State.at_rest(params)); got {type(state0).__name__}.")
    if not isinstance(controls, (Torques, WheelSpeeds)):
        raise TypeError(
            "simulate: controls must be jsphere.Torques(fn) or jsphere.WheelSpeeds(fn); "
            f"got {type(controls).__name__}."
        )
    out_shape = jax.eval_shape(controls, as_array(t0, params.R0.dtype)).shape
    if out_shape != (params.n_wheels,):
        raise ValueError(
            f"simulate: the controls return shape {out_shape} at t0 but the robot has {params.n_wheels} wheels; "
            f"fn(t) must return ({params.n_wheels},)."
        )
    if state0.chi.shape[-1] != params.n_wheels:
        raise ValueError(f"simulate: state0.chi has {state0.chi.shape[-1]} wheels but params has {params.n_wheels}.")
    if batch_steps not in ("shared", "per_trial"):
        raise ValueError(f"simulate: batch_steps must be 'shared' or 'per_trial'; got {batch_steps!r}.")
    dt = params.R0.dtype
    rtol, atol = tolerances(dt, rtol, atol)
    ts_out = None if ts is None else as_array(ts, dt)
    if ts_out is not None and not isinstance(ts_out, jax.core.Tracer):
        tsn = np.asarray(ts_out)
        if tsn.ndim != 1 or np.any(np.diff(tsn) < 0) or not np.all(np.isfinite(tsn)):
            raise ValueError("simulate: ts must be a finite, non-decreasing 1-D array of times.")
    traj = _solve(
        params, state0, controls, as_array(t0, dt), as_array(t1, dt), ts_out,
        solver or default_solver(), rtol, atol, max_steps, adjoint or dfx.RecursiveCheckpointAdjoint(), batch_layout(batch_steps, throw),
    )  # fmt: skip
    return raise_on_failure(traj, throw)


# ----------------------------------------------------------------- batched layout dispatch
#
# Under `vmap`, torque-mode solves carry the state as a tuple of scalar components
# (`jsphere.solve.batched.components`): each component is then one contiguous `(batch,)` vector and XLA on CPU
# vectorises the right-hand side (3.4) over the batch, about 3x faster at batch 1024 than the
# flat `(batch, 16+N)` layout, which in turn is faster for a single trial. `simulate` cannot
# see a `vmap` from inside, so the choice is made by `jax.custom_batching.custom_vmap`: the
# unbatched call runs the flat layout, the batching rule vmaps the component layout (batches
# of at least `COMPONENT_MIN_BATCH`, in chunks of `BATCH_CHUNK`). As `custom_vmap` has no
# reverse mode, the default adjoint wraps it in a custom VJP whose differentiated pass is the
# flat layout with diffrax's own VJP (the component layout's VJP is ~200x slower: XLA handles
# the transposed scalar code badly). Its forward pass is again a `custom_vmap`: small batches
# keep the pullback's residuals; large ones run the component layout and recompute the flat
# VJP in the backward pass, in chunks of `GRAD_CHUNK` trials. `ForwardMode` uses the
# `custom_vmap` directly (its `jvp` is supported). Other adjoints, wheel-speed mode and
# concrete (untraced) calls keep the flat layout. From `SHARED_MIN_BATCH` trials (and unless
# `batch_steps="per_trial"`) the undifferentiated batched pass also shares one step sequence
# over the batch (`jsphere.solve.batched.dispatch`, a `custom_vmap` around each segment's solve), and the
# backward pass of a gradient is then the discrete adjoint of those shared steps
# (`_shared_rk`, `SHARED_ADJOINT`); with `batch_steps="per_trial"` the same loop takes each
# trial's own steps in lockstep, and the backward pass is the discrete adjoint of those
# (other solvers than Dopri8, Dopri5, Tsit5: each trial's own solve recomputed).


class _ClosedControl(eqx.Module):
    """A control function with every tracer it closed over made an explicit leaf, so that a
    `vmap`ped amplitude inside a `lambda` is an input of the dispatched solve.
    (`jax.closure_convert` hoists only values that may carry a tangent, not batched ones;
    `eqx.filter_closure_convert` hoists every array.)"""

    fn: Callable  # eqx.filter_closure_convert(lambda dyn, t: ..., dyn, t0)
    dyn: Any

    def __call__(self, t):
        return self.fn(self.dyn, t)


def _explicit_closure(controls, t0):
    fn = controls.fn
    dyn, static = eqx.partition(fn, eqx.is_array)
    conv = eqx.filter_closure_convert(lambda dy, t: eqx.combine(dy, static)(t), dyn, t0)
    if not any(isinstance(c, jax.core.Tracer) for c in jax.tree_util.tree_leaves(conv)):
        return controls  # nothing traced is closed over: keep the control (and its compilation)
    return type(controls)(_ClosedControl(conv, dyn), controls.jump_ts)


def _has_tracer(tree) -> bool:
    return any(isinstance(x, jax.core.Tracer) for x in jax.tree_util.tree_leaves(tree))


def _traced(tree) -> bool:
    if _has_tracer(tree):
        return True
    return under_jit()


def _dispatched(run):
    """`run(leaves, components)` as a `custom_vmap` over a flat list of arrays: the flat layout
    unbatched, the component layout batched. (A flat list: `custom_vmap`'s JVP rule does not
    accept `None` nodes in its inputs.)"""

    @jax.custom_batching.custom_vmap
    def f(leaves):
        return run(leaves, False)

    @f.def_vmap
    def _rule(axis_size, in_batched, leaves):
        if not any(jax.tree_util.tree_leaves(in_batched)):  # e.g. the primal part of a batched jvp
            out = run(leaves, False)
            return out, jax.tree_util.tree_map(lambda _: False, out)
        out = _chunked_vmap(lambda lv: run(lv, _batched_layout(run, axis_size)), axis_size, in_batched, leaves)
        return out, jax.tree_util.tree_map(lambda _: True, out)

    return f


def batch_layout(batch_steps: str, throw: bool) -> str:
    """The internal form of `batch_steps`: with `throw=False`, a batch with shared steps
    (`"shared_fallback"`) is solved again with per-trial steps when its shared steps fail, so
    that each failing trial is reported alone and the others keep their results. (With
    `throw=True` a failure raises anyway, and the batch's programs do without the per-trial
    solve.)"""
    return "shared_fallback" if batch_steps == "shared" and not throw else batch_steps


def _batched_layout(run, axis_size):
    """The `components` argument of `_simulate` for a batch of `axis_size` trials: `"shared"`
    or `"shared_fallback"` (one step sequence; `batch_layout`), `"per_trial"` (each trial's own
    steps, in lockstep in the same loop), or whether to use the component layout with diffrax's
    loop per trial."""
    if axis_size >= SHARED_MIN_BATCH and (run.shared or run.lean):
        return run.shared if run.shared else "per_trial"
    return axis_size >= COMPONENT_MIN_BATCH


#: Smallest batch that shares one step sequence (`simulate(..., batch_steps="shared")`, the
#: default; `jsphere.solve.batched.dispatch`). Problem 1 of benchmarks/ with `jsphere.solve.batched.loop` (session
#: 8, against per-trial steps): 1.2x at 8 trials, 1.4x at 16, 2.1x at 32; smaller batches keep
#: per-trial steps, which compile ~2x faster (5 against 10 s).
SHARED_MIN_BATCH = 32


#: Smallest batch that uses the component layout (`layouts.py`: at 64 trials the flat layout
#: was 1.1x faster, at 1024 the component layout 2.6x).
COMPONENT_MIN_BATCH = 256


#: Largest batch one vectorised solve takes; bigger batches run as a `lax.map` over chunks of
#: this many trials, so the solver's working set (stage buffers of every component) stays in
#: cache on CPU (benchmarks/NOTES.md: a single vmap of 16384 trials ran 4x slower per trial).
BATCH_CHUNK = 1024


def _chunked_vmap(fn, axis_size, in_batched, *args, chunk=None):
    """`vmap(fn)` over the batched leaves of `args`, in chunks of at most `chunk` trials
    (default `BATCH_CHUNK`)."""
    chunk = chunk or BATCH_CHUNK
    in_axes = tuple(jax.tree_util.tree_map(lambda b: 0 if b else None, b) for b in in_batched)
    if axis_size <= chunk:
        return jax.vmap(fn, in_axes=in_axes, axis_size=axis_size)(*args)
    n = -(-axis_size // chunk)
    pad = n * chunk - axis_size

    def split(x):  # pad with copies of the last trial (valid inputs), then (n, chunk, ...)
        x = jnp.concatenate([x, jnp.repeat(x[-1:], pad, axis=0)]) if pad else x
        return x.reshape((n, chunk) + x.shape[1:])

    batched = [eqx.partition(a, b) for a, b in zip(args, in_batched)]
    chunks = tuple(jax.tree_util.tree_map(split, bt) for bt, _ in batched)

    def one(ch):
        full = tuple(eqx.combine(c, un) for c, (_, un) in zip(ch, batched))
        return jax.vmap(fn, in_axes=in_axes, axis_size=chunk)(*full)

    out = jax.lax.map(one, chunks)
    return jax.tree_util.tree_map(lambda x: x.reshape((n * chunk,) + x.shape[2:])[:axis_size], out)


@functools.partial(jax.custom_vjp, nondiff_argnums=(0,))
def _reverse(run, leaves):
    return _dispatched(run)(leaves)


def _large(axis_size, in_batched) -> bool:
    return axis_size >= COMPONENT_MIN_BATCH and any(jax.tree_util.tree_leaves(in_batched))


def _shared_grad(run, axis_size, in_batched) -> bool:
    """Whether a batch's gradient is the discrete adjoint of its shared steps (`_shared_rk`)."""
    return run.shared_grad and isinstance(_batched_layout(run, axis_size), str) and any(jax.tree_util.tree_leaves(in_batched))


def _reverse_fwd(run, leaves):
    """The primal with the layout chosen by batching, and residuals for `_reverse_bwd`.

    Unbatched or in small batches: the flat layout's VJP (diffrax's checkpointed adjoint), its
    residuals kept as arrays (the leaves of the pullback). In batches that share their steps
    (`_shared_grad`) or are large: the batched layout, and no residuals (placeholders of the
    same structure; the backward pass recomputes). `custom_vmap` needs one output structure
    for both, hence the placeholders.
    """
    cell = run.cell  # the pullback's structure, for the backward pass

    def flat_vjp(lv):
        out, pull = jax.vjp(lambda l: run(l, False), lv)
        res, cell["res_def"] = jax.tree_util.tree_flatten(pull)
        return out, res

    @jax.custom_batching.custom_vmap
    def f(lv):
        return flat_vjp(lv)

    @f.def_vmap
    def _rule(axis_size, in_batched, lv):
        (batched,) = in_batched
        if _shared_grad(run, axis_size, batched) or _large(axis_size, batched):
            out = _chunked_vmap(lambda l: run(l, _batched_layout(run, axis_size)), axis_size, in_batched, lv)
            # unbatched placeholders (one trial's worth) for the residuals the backward pass won't read
            one = [jax.ShapeDtypeStruct(jnp.shape(x)[int(b):], jnp.result_type(x)) for x, b in zip(lv, batched)]
            res = [jnp.zeros(r.shape, r.dtype) for r in jax.eval_shape(lambda l: flat_vjp(l)[1], one)]
            return (out, res), (jax.tree_util.tree_map(lambda _: True, out), [False] * len(res))
        out, res = jax.vmap(flat_vjp, in_axes=([0 if b else None for b in batched],), axis_size=axis_size)(lv)
        return (out, res), jax.tree_util.tree_map(lambda _: True, (out, res))

    out, res = f(list(leaves))
    return out, (list(leaves), res)


def _reverse_bwd(run, residuals, ct):
    """Apply the pullback saved by `_reverse_fwd`. In batches that share their steps
    (`_shared_grad`): the VJP of the batched solve, whose shared steps have a discrete adjoint
    (`jsphere.solve.batched.loop`), in chunks of `BATCH_CHUNK` trials (`_shared_vjp`). In other large
    batches: the flat layout's VJP recomputed per trial, in chunks of `GRAD_CHUNK` trials
    (~1.5x faster at 1024 than one vmap of it)."""
    leaves, res = residuals
    res_def = run.cell["res_def"]
    flat_ct, ct_def = jax.tree_util.tree_flatten(ct)
    keep = [jnp.result_type(c) != jax.dtypes.float0 for c in flat_ct]

    def full_ct(cts, like):
        it = iter(cts)
        return jax.tree_util.tree_unflatten(ct_def, [next(it) if k else np.zeros(jnp.shape(o), jax.dtypes.float0) for k, o in zip(keep, like)])

    def saved(lv, rs, cts):
        pull = jax.tree_util.tree_unflatten(res_def, rs)
        return pull(full_ct(cts, flat_ct))[0]

    def recompute(lv, cts):
        out, pull = jax.vjp(lambda l: run(l, False), lv)
        return pull(full_ct(cts, jax.tree_util.tree_leaves(out)))[0]

    @jax.custom_batching.custom_vmap
    def f(lv, rs, cts):
        return saved(lv, rs, cts)

    @f.def_vmap
    def _rule(axis_size, in_batched, lv, rs, cts):
        if _shared_grad(run, axis_size, in_batched[0]):
            out = _shared_vjp(run, axis_size, in_batched[0], in_batched[2], lv, cts, full_ct)
        elif _large(axis_size, in_batched[0]):
            out = _chunked_vmap(recompute, axis_size, in_batched[::2], lv, cts, chunk=GRAD_CHUNK)
        else:
            in_axes = tuple(jax.tree_util.tree_map(lambda b: 0 if b else None, b) for b in in_batched)
            out = jax.vmap(saved, in_axes=in_axes, axis_size=axis_size)(lv, rs, cts)
        return out, jax.tree_util.tree_map(lambda _: True, out)

    return (f(leaves, res, [c for k, c in zip(keep, flat_ct) if k]),)


#: Chunk size of the backward pass of large batches (the flat layout's VJP, recomputed).
GRAD_CHUNK = 64


#: Gradients of batches with shared (or, since session 13, per-trial) steps through `_shared_rk`'s discrete adjoint
#: (`_shared_vjp`): on problem 3, 1.5x faster than the per-trial flat VJP at 64 trials and
#: 2.3x at 1024, within 3e-7 of its gradient (benchmarks/NOTES.md, session 10; in session 9
#: it was ~140x slower, until the parameter leaves reached the field's VJPs element by
#: element and the field's `kept` points stopped XLA recomputing shared parts per kernel).
#: `False` gives every batch the per-trial VJP.
SHARED_ADJOINT = True


def _shared_vjp(run, axis_size, lv_batched, ct_batched, lv, cts, full_ct):
    """Per-trial cotangents of the leaves `lv` of a batch solved in `_shared_rk`'s loop (shared
    or per-trial steps), for the cotangents `cts` of its outputs: `jax.vjp` of the batched
    solve (`vmap` inside, so the
    batching rule of `_ensemble.solve` runs before differentiation and `_shared_rk`'s adjoint
    applies), chunk by chunk (`BATCH_CHUNK` trials: padding trials get zero cotangents). The
    cotangents of leaves shared by the batch are sums over the batch; they are returned in the
    first trial's row (zeros elsewhere), which sums to the same."""
    chunk = min(axis_size, BATCH_CHUNK)
    layout = _batched_layout(run, axis_size)  # "shared", "shared_fallback" or "per_trial"
    n = -(-axis_size // chunk)
    pad = n * chunk - axis_size
    in_axes = [0 if b else None for b in lv_batched]

    def split(x, zero):  # (axis_size, ...) -> (n, chunk, ...); pad with the last trial (or zeros)
        if pad:
            x = jnp.concatenate([x, jnp.zeros_like(x[-pad:]) if zero else jnp.repeat(x[-1:], pad, axis=0)])
        return x.reshape((n, chunk) + x.shape[1:])

    ct_b = [split(c, True) if b else c for c, b in zip(cts, ct_batched)]
    lv_b = [split(x, False) if b else x for x, b in zip(lv, lv_batched)]

    inexact = [jnp.issubdtype(jnp.result_type(x), jnp.inexact) for x in lv]

    def one(ch):
        l_ch, c_ch = ch
        full = [c if b else x for c, x, b in zip(l_ch, lv, lv_batched)]
        cc = [c if b else x for c, x, b in zip(c_ch, cts, ct_batched)]
        out, pull = jax.vjp(lambda l: jax.vmap(lambda x: run(x, layout), in_axes=(in_axes,), axis_size=chunk)(l), full)
        g = pull(full_ct(cc, jax.tree_util.tree_leaves(out)))[0]
        return [x if k else None for x, k in zip(g, inexact)]  # no float0 through the map

    xs = ([x if b else None for x, b in zip(lv_b, lv_batched)], [c if b else None for c, b in zip(ct_b, ct_batched)])
    grads = jax.lax.map(one, xs) if n > 1 else jax.tree_util.tree_map(lambda g: g[None], one(jax.tree_util.tree_map(lambda x: x[0], xs)))
    result = []
    for g, b, x in zip(grads, lv_batched, lv):
        if g is None:  # integer leaves
            result.append(np.zeros((axis_size,) + jnp.shape(x)[int(b):], jax.dtypes.float0))
        elif b:
            result.append(g.reshape((n * chunk,) + g.shape[2:])[:axis_size])
        else:  # the batch's sum, in the first trial's row
            total = jnp.sum(g, axis=0)
            result.append(jnp.zeros((axis_size,) + total.shape, total.dtype).at[0].set(total))
    return result


_reverse.defvjp(_reverse_fwd, _reverse_bwd)


#: Batched torque- and gait-mode solves use the component layout; `False` keeps the flat
#: layout everywhere (for A/B measurements: benchmarks/layouts.py, benchmarks/ensemble.py).
COMPONENT_LAYOUT = True


def _solve(params, state0, controls, t0, t1, ts_out, solver, rtol, atol, max_steps, adjoint, batch_steps="shared") -> Trajectory:
    """`_simulate` with the state layout chosen by batching (see the comment above)."""
    flat = (solver, rtol, atol, max_steps, adjoint)
    if (
        not COMPONENT_LAYOUT
        or not isinstance(controls, Torques)
        or type(adjoint) not in (dfx.RecursiveCheckpointAdjoint, dfx.ForwardMode)
    ):
        return _aot.call("simulate", _simulate, _rebuild, params, state0, controls, t0, t1, ts_out, *flat)
    controls = _explicit_closure(controls, t0)
    args = (params, state0, controls, t0, t1, ts_out)
    if not _traced(args):  # concrete inputs: no vmap can be around this call
        return _aot.call("simulate", _simulate, _rebuild, *args, *flat)
    return by_layout(_simulate, args, flat, batch_steps)


def by_layout(fn, args, flat, batch_steps):
    """`fn(*args, *flat, components=..., derived=...)` with the state layout chosen by batching:
    the flat state for a single call, the component layout under `vmap` (with one step
    sequence for the batch when `batch_steps == "shared"`); reverse mode through `_reverse`,
    forward mode (`flat[-1]` a `diffrax.ForwardMode`) through `_dispatched`. `args[0]` are the
    `RobotParams`; `flat` ends with the adjoint."""
    adjoint = flat[-1]
    # only traced leaves are inputs of the dispatched solve; concrete ones stay constants (folded by XLA)
    dyn, static = eqx.partition(args, lambda x: isinstance(x, jax.core.Tracer))
    leaves, treedef = jax.tree_util.tree_flatten(dyn)

    derived = None
    if not _has_tracer(args[0]):  # concrete parameters: (2.4), (3.4)'s constants as constants (folded by XLA)
        with jax.ensure_compile_time_eval():
            derived = derive(args[0])

    def run(lv, components):
        a = eqx.combine(jax.tree_util.tree_unflatten(treedef, lv), static)
        return fn(*a, *flat, components=components, derived=derived)

    run.cell = {}
    # the shared layout's name (`batch_layout`), or False for per-trial steps
    run.shared = batch_steps if batch_steps.startswith("shared") and not isinstance(adjoint, dfx.ForwardMode) else False
    # gradients of shared steps by their discrete adjoint, where `_shared_rk` is the integrator
    # batches integrated by `_shared_rk`'s loop: shared steps, or per-trial steps in lockstep;
    # their gradients by its discrete adjoint
    run.lean = _shared_rk.tableau(flat[0]) is not None and not isinstance(adjoint, dfx.ForwardMode)
    run.shared_grad = SHARED_ADJOINT and run.lean

    if isinstance(adjoint, dfx.ForwardMode):
        return _dispatched(run)(leaves)
    return _reverse(run, leaves)


@eqx.filter_jit
def _simulate(params, state0, controls, t0, t1, ts_out, solver, rtol, atol, max_steps, adjoint, components=False, derived=None):
    dt = params.R0.dtype
    d = derive(params) if derived is None else derived
    if ts_out is None:
        ts_out = jnp.stack([t0, t1])
    field, outputs = (_torque_field, _outputs_torque) if isinstance(controls, Torques) else (_wheel_field, _outputs_wheel)
    edges = [t0] + [jnp.clip(jnp.asarray(tj, dt), t0, t1) for tj in controls.jump_ts] + [t1]
    segments = [(controls, a, b) for a, b in zip(edges[:-1], edges[1:])]
    z0 = state0.flatten().astype(dt)
    jump_fn = None
    if isinstance(controls, WheelSpeeds):

        def jump_fn(k, t, z, control):
            gamma = rotmat(z[0:4])[2]
            w, _ = _servo_inputs(d, controls, t)
            omega, Omega = servo_jump(params, d, gamma, z[8:11], z[11:14], w)
            return jnp.concatenate([z[:8], omega, Omega, z[14:]])

    zs, om, cd, Ks, seg, ok, steps = solve_segments(
        field, outputs, params, d, segments, z0, ts_out, jump_fn=jump_fn, solver=solver,
        rtol=rtol, atol=atol, max_steps=max_steps, adjoint=adjoint,
        component_field=_torque_field_soa if components else None, shared=components if isinstance(components, str) else False,
    )  # fmt: skip
    return assemble(params, d, ts_out, zs, om, cd, Ks, seg, ok, steps)
