"""What the other packages of jsphere share of the gaits' machinery (not public API): the
vector field of a prescribed gait on the flat state and its outputs."""

from .gaits import _gait_field as gait_field
from .gaits import _gait_outputs as gait_outputs

__all__ = ["gait_field", "gait_outputs"]
