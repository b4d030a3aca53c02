"""What every figure shares: matplotlib imported lazily (Agg), the figure made and saved
atomically, the x-y axes of a path in jsphere's frame or the paper's figure frame, a study's
confidence ellipse and the paper's measured stop."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .._runtime.files import atomic_savefig


def pyplot():
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    return plt


def subplots(*args, **kwargs):
    """`plt.subplots` with matplotlib imported lazily: the figure and its axes."""
    return pyplot().subplots(*args, **kwargs)


#: the axis labels of a path in each frame: jsphere's fixed frame (the gaits move along +x) and
#: the paper's figure frame (Figs. 2, 3 and (5.5): turned by +90 degrees, `x_fig = -y`, `y_fig = x`)
FRAME_LABELS = {
    "jsphere": ("x [mm] (jsphere frame: x along the motion)", "y [mm] (jsphere frame)"),
    "paper": ("x [mm] (paper's figure frame: -y of jsphere)", "y [mm] (paper's figure frame: x of jsphere)"),
}


def check_frame(frame: str) -> str:
    if frame not in FRAME_LABELS:
        raise ValueError(f"frame must be 'jsphere' or 'paper'; got {frame!r}.")
    return frame


def in_frame(x, y, frame: str):
    """Positions `(x, y)` in jsphere's frame, in `frame` (`"paper"`: `(-y, x)`)."""
    return (-y, x) if check_frame(frame) == "paper" else (x, y)


def ellipse_points(stats: dict, n: int = 200) -> np.ndarray:
    """The confidence ellipse of `MonteCarloResult.stats()` as `(n, 2)` points [m], jsphere's frame."""
    minor, major = stats["ellipse"]["semi_axes_m"]
    ang, (x0, y0) = stats["ellipse"]["angle_rad"], stats["mean_xy_m"]
    t = np.linspace(0, 2 * np.pi, n)
    e1, e2 = np.array([np.cos(ang), np.sin(ang)]), np.array([-np.sin(ang), np.cos(ang)])
    return (np.array([x0, y0])[:, None] + major * np.outer(e1, np.cos(t)) + minor * np.outer(e2, np.sin(t))).T


def paper_experiment(ax, frame: str = "paper", label: str = "paper, experiment (95%)") -> None:
    """The paper's measured stop of the straight-line gaits with its 95 % interval [mm] in `frame`."""
    (xf, yf), (dx, dy) = (-1.392, 369.2), (28.9, 37.7)  # the paper's figure frame
    if frame == "jsphere":  # x = y_fig, y = -x_fig
        (xf, yf), (dx, dy) = (yf, -xf), (dy, dx)
    ax.errorbar([xf], [yf], xerr=[dx], yerr=[dy], fmt="ko", ms=3, label=label)


def xy_axes(ax, frame: str = "paper") -> None:
    """Axes of a path in `frame` [mm], named on the axes."""
    xlabel, ylabel = FRAME_LABELS[check_frame(frame)]
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.axis("equal")
    ax.legend(fontsize=7)


def finish(fig, path, margins: dict | None = None) -> Path:
    """Lay out, save atomically to `path`, close; return `Path(path)`. `margins` (for
    `fig.subplots_adjust`) fix the layout by hand; without them `tight_layout` measures every
    label (~0.1 s a figure)."""
    if margins is None:
        fig.tight_layout()
    else:
        fig.subplots_adjust(**margins)
    atomic_savefig(fig, Path(path), dpi=120)
    pyplot().close(fig)
    return Path(path)
