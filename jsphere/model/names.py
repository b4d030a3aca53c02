"""Names of parameters and their components: `"j"`, `"I[0,0]"`, `"r_m[2]"`, `"R_m"`.

One place shared by the Monte-Carlo runner, the fit, the file loader and the CLI: parse a name,
read its value from a `RobotParams`, and write a new value (through `eqx.tree_at`, so gradients
flow).
"""

from __future__ import annotations

import re

import equinox as eqx
import jax.numpy as jnp

from .fields import FIELDS

__all__ = ["DERIVED", "MOUNTING", "get_value", "parse_name", "set_value"]

_NAME = re.compile(r"^\s*([A-Za-z_][A-Za-z0-9_]*)\s*(?:\[\s*([0-9\s,]+)\s*\])?\s*$")
#: derived names: `R_m = |r_m|` (scales r_m along its direction)
DERIVED = ("R_m",)
#: the IMU's mounting (`jsphere.Mounting`), which a fit of onboard-sensor trials may free: its
#: position [m] and a small rotation [rad] about the IMU's axes applied to the given orientation;
#: three components each, no values in a `RobotParams`
MOUNTING = ("imu_position", "imu_rotation")


def parse_name(name: str) -> tuple[str, tuple[int, ...]]:
    """`"I[0,1]"` -> `("I", (0, 1))`; `"j"` -> `("j", ())`. Raises `ValueError` naming the
    fields when the name is unknown or the index does not fit the field's shape."""
    if not isinstance(name, str):
        raise ValueError(f"a parameter name must be a string such as 'j' or 'I[0,0]'; got {name!r}.")
    m = _NAME.match(name)
    if not m:
        raise ValueError(
            f"cannot parse parameter name {name!r}; use a field ({', '.join(FIELDS)}), a component such as 'I[0,0]' or 'r_m[2]', or 'R_m'."
        )
    field, idx = m.group(1), m.group(2)
    index = tuple(int(i) for i in idx.split(",") if i.strip()) if idx else ()
    if field not in FIELDS and field not in DERIVED and field not in MOUNTING:
        raise ValueError(
            f"unknown parameter {field!r} in {name!r}; fields are {', '.join(FIELDS)} (and 'R_m'; "
            "'imu_position', 'imu_rotation' in a fit of onboard-sensor trials)."
        )
    if field in DERIVED and index:
        raise ValueError(f"{field} is a scalar; got {name!r}.")
    if field in MOUNTING and (len(index) > 1 or (index and index[0] > 2)):
        raise ValueError(f"{name!r}: {field} has 3 components, {field}[0] .. {field}[2].")
    return field, index


def check_index(params, field: str, index: tuple[int, ...], name: str):
    shape = getattr(params, field).shape
    if len(index) not in (0, len(shape)) or any(i >= s for i, s in zip(index, shape)):
        raise ValueError(f"{name!r}: index {list(index)} does not fit {field} of shape {shape}.")


def get_value(params, name: str):
    """The value a name refers to (an array for a whole field)."""
    field, index = parse_name(name)
    if field == "R_m":
        return params.R_m
    _robot(field, name)
    check_index(params, field, index, name)
    v = getattr(params, field)
    return v[index] if index else v


def set_value(params, name: str, value):
    """A copy of `params` with the named value replaced (differentiable; not re-validated).

    Off-diagonal entries of the inertia tensor are set symmetrically (`I[0,1]` sets `I[1,0]`).
    """
    field, index = parse_name(name)
    if field == "R_m":
        direction = params.r_m / jnp.linalg.norm(params.r_m)
        return eqx.tree_at(lambda p: p.r_m, params, direction * value)
    _robot(field, name)
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


def _robot(field: str, name: str) -> None:
    if field in MOUNTING:
        raise ValueError(f"{name!r} is the IMU's mounting, not a parameter of the robot (RobotParams).")
