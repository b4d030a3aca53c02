"""What the other packages of jsphere share of the model's machinery (not public API): the
parameter fields in their order and the flat state's unflattening."""

from .fields import FIELDS as FIELDS
from .state import State

unflatten = State.unflatten

__all__ = ["FIELDS", "unflatten"]
