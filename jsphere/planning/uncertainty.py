"""The parameter distribution that robust planning plans against: `jsphere.model.uncertainty`."""

from ..model.uncertainty import Uncertainty as Uncertainty
from ..model.uncertainty import stack_params as stack_params

__all__ = ["Uncertainty", "stack_params"]
