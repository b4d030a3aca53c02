"""What every figure shares: matplotlib imported lazily (Agg), the x-y axes of the paper's figure
frame, and the atomic save."""

from __future__ import annotations

from .._runtime.files import atomic_savefig


def pyplot():
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    return plt


def xy_axes(ax) -> None:
    """Axes of a path in the paper's figure frame [mm]."""
    ax.set_xlabel("x [mm] (paper's frame)")
    ax.set_ylabel("y [mm]")
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
