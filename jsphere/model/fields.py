"""The fields of a robot's parameter set (`RobotParams`), in their order, once: what each is,
its shape, and the default of those a parameter file may leave out. Validation, the file
readers and the parameter names read this table."""

from __future__ import annotations

from typing import NamedTuple


class Field(NamedTuple):
    """One field of `RobotParams`: `meaning` (with its unit, for messages), `shape` (in words,
    for a file's value of the wrong shape), `ndim` (its trailing dimensions: the rest are batch
    dimensions of stacked sets) and, for a field a file may leave out, its `default` and how
    `RobotParams.load` names the default used."""

    meaning: str
    shape: str = "a number"
    ndim: int = 0
    default: float | None = None
    default_text: str = ""


_ROWS = "a list of N rows of 3 numbers, one per wheel of wheel_r (shape (N, 3))"

#: every field, in the order of `RobotParams`
TABLE: dict[str, Field] = {
    "R0": Field("the shell radius [m]"),
    "m0": Field("the shell mass [kg]"),
    "I0": Field("the shell's moment of inertia [kg m^2]"),
    "Rw": Field("the omniwheel radius [m]"),
    "wheel_r": Field(
        "the wheel centres, one row per wheel [m]", "a list of N >= 3 rows of 3 numbers (shape (N, 3))", 2
    ),
    "wheel_n": Field("the unit axle directions, one row per wheel", _ROWS, 2),
    "wheel_alpha": Field("the unit roller axes, one row per wheel", _ROWS, 2),
    "m": Field("the platform mass with wheels [kg]"),
    "I": Field("the platform's inertia tensor about the shell centre [kg m^2]", "a 3x3 nested list (shape (3, 3))", 2),
    "r_m": Field("the platform's centre of mass [m]", "a list of 3 numbers (shape (3,))", 1),
    "j": Field(
        "the axial moment of inertia of one wheel [kg m^2]", default=0.0, default_text="j = 0 kg m^2 (massless wheels)"
    ),
    "g": Field("the gravitational acceleration [m/s^2]", default=9.81, default_text="g = 9.81 m/s^2"),
    "c_roll": Field(
        "the viscous rolling resistance [N m s]", default=0.0, default_text="c_roll = 0 N m s (no rolling resistance)"
    ),
    "c_axle": Field(
        "the viscous axle friction [N m s]", default=0.0, default_text="c_axle = 0 N m s (no axle friction)"
    ),
    "k_tau": Field("the torque gain", default=1.0, default_text="k_tau = 1 (torques applied as commanded)"),
}
#: the names of the fields, in order
FIELDS = tuple(TABLE)
#: The fields a parameter file may leave out, with the default used and how `load` names it.
#: The others (the geometry, the masses and inertias) are required: a robot has no default mass.
OPTIONAL: dict[str, tuple[float, str]] = {
    f: (c.default, c.default_text) for f, c in TABLE.items() if c.default is not None
}
