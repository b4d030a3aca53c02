"""What the other packages of jsphere share of the fit's machinery (not public API): the
compiled residual and Jacobian functions of a fit and the covariance of its free names."""

from .report import _covariance as covariance
from .residuals import _functions as fit_functions

__all__ = ["covariance", "fit_functions"]
