"""Feedback that makes a plan land on the real robot: a time-varying linear-quadratic regulator
along the plan, from Jacobians of the model's flow over each control interval, the attitude
error in the tangent space of the rotation group; a terminal regulator that holds the target at
rest; the gains as a table a controller runs; the plan replayed open and closed loop on drawn
robots. See `docs/tracking.md`.

The pieces: `flow` (the interval map, the reference motion, its Jacobians), `lqr` (weights,
Riccati recursion, the terminal regulator and the conserved mode), `evaluate` (the closed loop
on drawn robots), `table` (`track.csv`, `track.json`), `track` (`track`, `Tracker`).
"""

from .evaluate import Conditions
from .lqr import Weights
from .table import read_track_csv
from .track import Tracker, track

#: the names under which `jsphere` exports them
TrackWeights = Weights
TrackConditions = Conditions

__all__ = ["Conditions", "TrackConditions", "TrackWeights", "Tracker", "Weights", "read_track_csv", "track"]
