"""`simulate`: the equations of motion integrated with diffrax from a state, under torques or
commanded wheel speeds."""

from __future__ import annotations

from typing import Any, Callable

import diffrax as dfx
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import ArrayLike, Float

from .._runtime.arrays import as_array
from .._runtime.arrays import traced as _traced
from .._runtime.quick_compile import eager_jit, run_program
from ..controls import Torques, WheelSpeeds
from ..model.dynamics import servo_jump
from ..model.params import RobotParams, derive
from ..model.rotations import rotmat
from ..model.state import Flat, State
from .batched import dispatch as _dispatch
from .batched.layout import Layout, steps_layout
from .fields import (
    _outputs_torque,
    _outputs_wheel,
    _servo_inputs,
    _torque_field,
    _torque_field_soa,
    _wheel_field,
)
from .options import (
    DEFAULT_TOLERANCES,
    FLOAT32_MIN_RTOL,
    SolverOptions,
    default_solver,
    solver_options,
    tolerances,
)
from .segments import solve_segments
from .trajectory import Trajectory, _rebuild, raise_on_failure

__all__ = [
    "simulate",
    "Trajectory",
    "SolverOptions",
    "tolerances",
    "default_solver",
    "DEFAULT_TOLERANCES",
    "FLOAT32_MIN_RTOL",
]


def simulate(
    params: RobotParams,
    state0: State,
    controls: Torques | WheelSpeeds,
    t1: float,
    *,
    t0: float = 0.0,
    ts: Float[ArrayLike, " T"] | None = None,
    options: SolverOptions | None = None,
    **shortcuts,
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
    - `options`: a `SolverOptions` (`rtol`, `atol`, `solver`, `max_steps`, `throw`, `adjoint`,
      `batch_steps`: what each does is told there). Each field is also a keyword of
      `simulate` (a shortcut: a keyword given wins over `options`). Default tolerances 1e-8,
      1e-10 (positions within 1e-3 mm over the paper's 4 s manoeuvres); with float32
      parameters 1e-5, 1e-7 (`DEFAULT_TOLERANCES`).

    Pure JAX: jit, vmap (over parameters, states, controls) and grad work.
    """
    _check_inputs(params, state0, controls, t0)
    opts = solver_options(options, where="simulate", **shortcuts)
    dt = params.R0.dtype
    t0, t1 = as_array(t0, dt), as_array(t1, dt)
    engine = isinstance(controls, Torques) and batch_engine_applies(opts)
    if engine:
        controls = _explicit_closure(controls, t0)
    args = (params, state0, controls, t0, t1, output_times(ts, dt, "simulate"))
    return run_solve("simulate", _simulate, args, opts, opts.tolerances(dt), engine)


def _check_inputs(params, state0, controls, t0) -> None:
    """`simulate`'s arguments: a `State` and a control of as many wheels as the robot has."""
    if not isinstance(state0, State):
        raise TypeError(
            f"simulate: state0 must be a jsphere.State (e.g. State.at_rest(params)); got {type(state0).__name__}."
        )
    if not isinstance(controls, (Torques, WheelSpeeds)):
        raise TypeError(
            f"simulate: controls must be jsphere.Torques(fn) or jsphere.WheelSpeeds(fn); got {type(controls).__name__}."
        )
    out_shape = jax.eval_shape(controls, as_array(t0, params.R0.dtype)).shape
    if out_shape != (params.n_wheels,):
        raise ValueError(
            f"simulate: the controls return shape {out_shape} at t0 but the robot has {params.n_wheels} wheels; "
            f"fn(t) must return ({params.n_wheels},)."
        )
    if state0.chi.shape[-1] != params.n_wheels:
        raise ValueError(f"simulate: state0.chi has {state0.chi.shape[-1]} wheels but params has {params.n_wheels}.")


def output_times(ts, dt, where: str):
    """The output times `ts` as an array of `dt` (`None` stays `None`), checked when concrete
    (finite, non-decreasing, 1-D): the solve's own check of them makes values NaN rather than
    raising."""
    if ts is None:
        return None
    out = as_array(ts, dt)
    if not isinstance(out, jax.core.Tracer):
        tsn = np.asarray(out)
        if tsn.ndim != 1 or np.any(np.diff(tsn) < 0) or not np.all(np.isfinite(tsn)):
            raise ValueError(f"{where}: ts must be a finite, non-decreasing 1-D array of times.")
    return out


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


def batch_engine_applies(opts: SolverOptions) -> bool:
    """Whether a traced solve (of a mode that has a component field) goes through the batch
    engine (`jsphere.solve.batched.dispatch`): an adjoint the engine supports, and
    `batch_steps` other than `"diffrax"`. Every other call takes diffrax's path directly."""
    engine_adjoint = type(opts.adjoint_or_default()) in (dfx.RecursiveCheckpointAdjoint, dfx.ForwardMode)
    return engine_adjoint and opts.batch_steps != "diffrax"


def run_solve(name: str, fn, args, opts: SolverOptions, tol, engine: bool) -> Trajectory:
    """`fn(*args, solver, rtol, atol, max_steps, adjoint)` (a solve of `simulate` or
    `simulate_gaits`) with the state layout chosen by batching, raising on failure as
    `opts.throw` asks: concrete calls (which no `vmap` can be around) and calls the batch
    engine does not take (`engine` false) run `fn` directly (`run_program`); traced ones go
    through the engine's batching rule (`jsphere.solve.batched.dispatch`)."""
    flat = (opts.solver_or_default(), *tol, opts.max_steps, opts.adjoint_or_default())
    if not engine or not _traced(args):
        traj = run_program(name, fn, _rebuild, *args, *flat)
    else:
        traj = _dispatch.solve(fn, _rebuild, args, flat, steps_layout(opts.batch_steps, opts.throw))
    return raise_on_failure(traj, opts.throw)


@eager_jit
def _simulate(
    params, state0, controls, t0, t1, ts_out, solver, rtol, atol, max_steps, adjoint, layout=Layout.FLAT, derived=None
):
    dt = params.R0.dtype
    d = derive(params) if derived is None else derived
    if ts_out is None:
        ts_out = jnp.stack([t0, t1])
    field, outputs = (
        (_torque_field, _outputs_torque) if isinstance(controls, Torques) else (_wheel_field, _outputs_wheel)
    )
    edges = [t0] + [jnp.clip(jnp.asarray(tj, dt), t0, t1) for tj in controls.jump_ts] + [t1]
    segments = [(controls, a, b) for a, b in zip(edges[:-1], edges[1:])]
    z0 = state0.flatten().astype(dt)
    jump_fn = None
    if isinstance(controls, WheelSpeeds):

        def jump_fn(k, t, z, control):
            gamma = rotmat(z[Flat.q])[2]
            w, _ = _servo_inputs(d, controls, t)
            omega, Omega = servo_jump(params, d, gamma, z[Flat.omega], z[Flat.Omega], w)
            return Flat.replace(z, omega=omega, Omega=Omega)

    return solve_segments(
        field,
        outputs,
        params,
        d,
        segments,
        z0,
        ts_out,
        (solver, rtol, atol, max_steps, adjoint),
        jump_fn=jump_fn,
        layout=layout,
        component_field=_torque_field_soa if layout.components else None,
    )
