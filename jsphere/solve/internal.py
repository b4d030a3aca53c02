"""What the other packages of jsphere share of the solver's machinery (not public API): the
vector fields of torque and wheel-speed mode on the flat state, their outputs `(omega, chi_dot,
K)` at a state, the rates they share, and the rebuilding of a `Trajectory` from its leaves."""

from .fields import _outputs_torque as torque_outputs
from .fields import _outputs_wheel as wheel_outputs
from .fields import _rates as rates
from .fields import _torque_field as torque_field
from .fields import _wheel_field as wheel_field
from .trajectory import _rebuild as rebuild

__all__ = ["rates", "rebuild", "torque_field", "torque_outputs", "wheel_field", "wheel_outputs"]
