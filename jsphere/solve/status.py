"""Named result codes of a solve, as `Trajectory.status` reports them (one per trial under `vmap`),
and of a Monte-Carlo trial, as `MonteCarloResult.status` reports them."""

from __future__ import annotations

import enum

import numpy as np


class RESULTS(enum.IntEnum):
    """How a solve ended (the integers are those stored in `Trajectory.status` and in files).

    - `successful` (0): the solver reached the final time and every value is finite;
    - `max_steps_reached` (1): the solver stopped before the final time: it took `max_steps`
      steps, or its step size collapsed;
    - `nonfinite` (2): the state, the rates or the inputs became NaN or inf (including
      inputs that are non-finite from the start, and a check of diffrax or of the controls
      that failed inside the compiled solve, which makes values NaN there);
    - `rejected` (-1): not solved: a Monte-Carlo trial whose drawn parameters break a rule
      of `RobotParams` (`MonteCarloResult.status` only; `Trajectory.status` is never
      negative).

    An `IntEnum`: `traj.status == RESULTS.successful` works on arrays of codes, and
    `RESULTS.message(code)` gives the text `simulate` raises for a failure.
    """

    successful = 0
    max_steps_reached = 1
    nonfinite = 2
    rejected = -1

    @classmethod
    def message(cls, code) -> str:
        """The explanation of `code` (an integer, a member, or a 0-d array)."""
        return _MESSAGES[cls(int(np.asarray(code)))]

    @classmethod
    def failure_messages(cls) -> tuple[str, ...]:
        """The messages of the solver's failure codes `1, 2, ...` in order
        (`eqx.branched_error_if` indexes them by `code - 1`)."""
        return tuple(_MESSAGES[c] for c in sorted(cls) if c > cls.successful)


_MESSAGES = {
    RESULTS.successful: "jsphere: the solve succeeded.",
    RESULTS.max_steps_reached: (
        "jsphere: the ODE solver failed: it reached max_steps (or its step size collapsed). Raise "
        "`max_steps`, loosen `rtol`/`atol`, check that the controls are smooth between their "
        "`jump_ts` and stay finite (NaN or inf values make every step fail). Pass throw=False to get "
        "`Trajectory.ok` per trial instead of this error."
    ),
    RESULTS.nonfinite: (
        "jsphere: the simulation produced NaN or inf. Check the controls (they must be finite), "
        "the initial state and the output times `ts` (finite, non-decreasing). Pass throw=False to get "
        "`Trajectory.ok` per trial instead of this error."
    ),
    RESULTS.rejected: (
        "jsphere: the trial was not simulated: its drawn parameters break a rule of RobotParams "
        "(`MonteCarloResult.reject_code` says which). Narrow the distributions or truncate them."
    ),
}
