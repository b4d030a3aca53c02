"""Names of parameters and their components: `"j"`, `"I[0,0]"`, `"r_m[2]"`, `"R_m"`.

One place shared by the Monte-Carlo runner, the fit and the CLI: parse a name, read its
value from a `RobotParams`, and write a new value (through `eqx.tree_at`, so gradients flow).
Parsing and reading live beside `RobotParams` (`jsphere.model.params`), whose file loader
checks a fit result's named values with them; writing lives here.
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp

from .params import DERIVED, RobotParams, check_index, get_value, parse_name

__all__ = ["DERIVED", "get_value", "parse_name", "set_value"]


def set_value(params: RobotParams, name: str, value) -> RobotParams:
    """A copy of `params` with the named value replaced (differentiable; not re-validated).

    Off-diagonal entries of the inertia tensor are set symmetrically (`I[0,1]` sets `I[1,0]`).
    """
    field, index = parse_name(name)
    if field == "R_m":
        direction = params.r_m / jnp.linalg.norm(params.r_m)
        return eqx.tree_at(lambda p: p.r_m, params, direction * value)
    check_index(params, field, index, name)
    old = getattr(params, field)
    value = jnp.asarray(value, dtype=old.dtype)
    if not index:
        new = jnp.broadcast_to(value, old.shape)
    else:
        new = old.at[index].set(value)
        if field == "I" and index[0] != index[1]:
            new = new.at[index[::-1]].set(value)
    return eqx.tree_at(lambda p: getattr(p, field), params, new)
