"""The robot's motor and motion limits (`Limits`): what the planner keeps to and excitation
design respects."""

from __future__ import annotations

import math

import equinox as eqx

from .._runtime.checks import is_number
from .._runtime.checks import is_traced as _traced
from .._runtime.errors import InputError


class Limits(eqx.Module):
    """Motor and motion limits (SI). `None` switches a limit off.

    Defaults for the paper's robot (whose motors the paper does not specify): the paper's own
    gaits need at most 0.011 N m and 4.8 rad/s; a 1.4 m rest-to-rest run in 8 s needs about
    0.02 N m and 15 rad/s. The defaults leave room for that and are typical of small geared
    DC motors: `max_torque = 0.1` N m per wheel, `max_wheel_speed = 20` rad/s (191 rpm),
    `max_tilt = 0.35` rad (20 deg, platform tilt `theta = |u|`), `max_torque_rate = 1` N m/s,
    `max_time = 12` s (upper bound of the duration `T`), `min_time = 1` s.
    """

    max_torque: float | None = 0.1
    max_wheel_speed: float | None = 20.0
    max_tilt: float | None = 0.35
    max_torque_rate: float | None = 1.0
    max_time: float = 12.0
    min_time: float = 1.0

    def __check_init__(self):
        for name in ("max_torque", "max_wheel_speed", "max_tilt", "max_torque_rate"):
            v = getattr(self, name)
            if v is not None and not _traced(v) and not (is_number(v) and float(v) > 0):
                raise InputError(f"Limits.{name} must be a positive number (or None for no limit); got {v!r}.")
        for name in ("min_time", "max_time"):
            v = getattr(self, name)
            if not _traced(v) and not (is_number(v) and math.isfinite(v)):
                raise InputError(f"Limits.{name} must be a finite number of seconds; got {v!r}.")
        if not _traced(self.min_time, self.max_time) and not 0 < float(self.min_time) < float(self.max_time):
            raise InputError(f"Limits: need 0 < min_time < max_time; got {self.min_time}, {self.max_time}.")
