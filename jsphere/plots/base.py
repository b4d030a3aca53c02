"""What every figure shares: matplotlib imported lazily (Agg), the x-y axes of a path in jsphere's
frame or the paper's figure frame, and the atomic save."""

from __future__ import annotations

from .._runtime.files import atomic_savefig


def pyplot():
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    return plt


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


def xy_axes(ax, frame: str = "paper") -> None:
    """Axes of a path in `frame` [mm], named on the axes."""
    xlabel, ylabel = FRAME_LABELS[check_frame(frame)]
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.axis("equal")
    ax.legend(fontsize=7)


def finish(plt, fig, path, margins: dict | None = None) -> None:
    """Lay out, save atomically, close. `margins` (for `fig.subplots_adjust`) fix the layout
    by hand; without them `tight_layout` measures every label (~0.1 s a figure)."""
    if margins is None:
        fig.tight_layout()
    else:
        fig.subplots_adjust(**margins)
    atomic_savefig(fig, path, dpi=120)
    plt.close(fig)
