"""`FieldArgs`: the arguments of the vector fields, by name."""

from __future__ import annotations

import dataclasses
from typing import Any

import equinox as eqx


class FieldArgs(eqx.Module):
    """The `args` of a vector field `f(t, z, args)` (and of its outputs), keyword fields only.
    A pytree (its leaves are the arrays of its fields), so the fields are traced, batched and
    differentiated with it.

    - `params`: the `RobotParams`;
    - `derived`: their constants (2.4), (3.4) (`jsphere.model.params.derive(params)`);
    - `control`: the control (`Torques`, `WheelSpeeds`, a function of `t`, or a gait's
      `(Gait, Qm)`);
    - `t_start`: the start of the segment [s], the origin of a gait's local time (default 0);
    - `t_end`: the end of the segment [s], where the control jumps: at and after it the control
      is evaluated at its left limit. `None` (default): the control has no jump to respect.
    """

    _: dataclasses.KW_ONLY
    params: Any
    derived: Any
    control: Any
    t_start: Any = 0.0
    t_end: Any = None
