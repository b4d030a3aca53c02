"""The shell centre's height in a converted capture (`centre_height`, `check_centre_height`).

A shell rolling on a level floor keeps its centre at its radius `R0` above the floor; a
converted "centre" higher or lower, or rising and falling as the robot rolls, is another point
(the markers' centroid, a rigid body's pivot point, a pose topic's frame), which a fit would
blame on the model. Heights count from height 0 of the capture's fixed frame: the floor, where
the ground plane is set (OptiTrack's calibration square, Vicon's and Qualisys' L frame); a floor
elsewhere shifts the median height but not its variation, which is checked apart.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from .trial import Trial
from .validation import implausible, warn

#: the converted centre's median height may differ from the shell radius `R0` by this much [m]:
#: the markers' centroid of a platform sits centimetres from the centre, while a shell deforms,
#: and a ground plane is set on the floor, within a millimetre or two
CENTRE_HEIGHT_TOL = 3e-3
#: the converted centre's height may vary by this much [m] (5th to 95th percentile of its
#: running median over `HEIGHT_WINDOW`): a shell centre on a level floor stays within a
#: millimetre; a point off the centre rises and falls as the platform leans (a point 5 cm to
#: the side by 9 mm at a lean of 10 deg), a floor out of level by a few millimetres over the lab
CENTRE_HEIGHT_SPREAD = 5e-3
#: the window of the running median of the height [s]: marker noise of a millimetre leaves
#: about 0.3 mm in it
HEIGHT_WINDOW = 0.2


@dataclass(frozen=True)
class CentreHeight:
    """The height of a trial's shell centre over its measured frames: `median` [m], `spread`
    [m] (5th to 95th percentile of its running median over `HEIGHT_WINDOW`, so noise does not
    count) and `frames` (how many)."""

    median: float
    spread: float
    frames: int

    def summary(self) -> str:
        """`"0.1500 m (median over 151 frames), varying by 0.4 mm"`."""
        return f"{self.median:.4f} m (median over {self.frames} frames), varying by {1e3 * self.spread:.1f} mm"


def centre_height(trial: Trial) -> CentreHeight | None:
    """The `CentreHeight` of `trial`'s measured frames; None for a trial without heights."""
    if trial.z is None:
        return None
    ok = trial.valid & np.isfinite(trial.z)
    z = np.asarray(trial.z, float)[ok]
    if z.size == 0:
        return None
    step = float(np.median(np.diff(trial.t))) if trial.n_frames > 1 else HEIGHT_WINDOW
    w = max(1, int(round(HEIGHT_WINDOW / step)) | 1)
    smooth = np.median(np.lib.stride_tricks.sliding_window_view(z, w), axis=1) if z.size >= w else np.median(z)[None]
    spread = float(np.ptp(np.percentile(smooth, [5, 95])))
    return CentreHeight(float(np.median(z)), spread, int(z.size))


def check_centre_height(
    trial: Trial, R0: float, *, source: str, fix: str, example: Callable[[float], str] | None = None, floor: str = ""
) -> list[str]:
    """Compare the height of `trial`'s shell centre with the shell radius `R0` [m]: a
    `CaptureWarning` naming `source`, the height and `fix` (what to do) where its median is more
    than `CENTRE_HEIGHT_TOL` from `R0` (`example(dz)` completes it with the options that raise
    the centre by `dz` [m]; `floor` says where height 0 is), and one where it varies by more
    than `CENTRE_HEIGHT_SPREAD`. Nothing where the heights already say that the up axis is wrong
    (`implausible`'s `"height"` and `"lying"`). Returns the messages."""
    h = centre_height(trial)
    if h is None:
        return []
    found = {k for k, _ in implausible(trial.t, trial.x, trial.y, trial.q, trial.z, from_markers=True)}
    if found & {"height", "lying"}:
        return []
    msgs = []
    off = h.median - float(R0)
    if abs(off) > CENTRE_HEIGHT_TOL:
        where = f"; {floor}" if floor else ""
        msgs.append(
            f"{source}: the converted shell centre is {h.median:.4f} m above the floor (median over {h.frames} "
            f"frames{where}), {1e3 * abs(off):.1f} mm {'above' if off > 0 else 'below'} the robot's shell radius R0 = "
            f"{float(R0):.4f} m: {fix}" + (f"; {example(-off)}." if example is not None else ".")
        )
    if h.spread > CENTRE_HEIGHT_SPREAD:
        msgs.append(
            f"{source}: the converted shell centre's height varies by {1e3 * h.spread:.1f} mm (5th to 95th percentile "
            f"of its {HEIGHT_WINDOW:g} s running median), more than the {1e3 * CENTRE_HEIGHT_SPREAD:g} mm of a shell "
            f"rolling on a level floor: the floor is not level, or {fix}."
        )
    for m in msgs:
        warn(m, stacklevel=2)
    return msgs
