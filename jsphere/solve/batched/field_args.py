"""`FieldArgs`: the arguments of the vector fields, by name."""

from __future__ import annotations

from typing import Any, NamedTuple


class FieldArgs(NamedTuple):
    """The `args` of a vector field `f(t, z, args)` (and of its outputs) on one segment of a
    solve, `[t_start, t_end]`. A pytree (its leaves are the arrays of its fields), so the
    fields are traced, batched and differentiated with it.

    - `params`: the `RobotParams`;
    - `derived`: their constants (2.4), (3.4) (`jsphere.model.params.derive(params)`);
    - `control`: the segment's control (`Torques`, `WheelSpeeds`, a function of `t`, or a
      gait's `(Gait, Qm)`), evaluated at the left limit at `t_end`;
    - `t_start`, `t_end`: the segment's ends.
    """

    params: Any
    derived: Any
    control: Any
    t_start: Any
    t_end: Any
