"""Figures of a `Plan` (matplotlib, imported lazily): path with the target, controls, tilt."""

from __future__ import annotations

import numpy as np

from .base import finish, pyplot


def plan_figure(plan, path, *, compare=None, title: str = "") -> None:
    """(a) the path in the fixed frame (x, y) [m] with the start, the waypoints/target and
    heading arrows; (b) wheel torques `K_i(t)`; (c) wheel rates `chi_dot_i(t)`; (d) tilt
    `theta(t)` [deg] with the limits as dashed lines. `compare`: extra `(label, Trajectory)`
    paths drawn in (a), e.g. the paper's hand-made gaits or a replay of the table."""
    cols = plan.table()
    fig = pyplot().figure(figsize=(11, 7))
    gs = fig.add_gridspec(3, 2, width_ratios=[1.1, 1])
    a, b = fig.add_subplot(gs[:, 0]), fig.add_subplot(gs[0, 1])
    c, d = fig.add_subplot(gs[1, 1], sharex=b), fig.add_subplot(gs[2, 1], sharex=b)
    a.plot(cols["x"], cols["y"], "-", lw=1.5, label="plan")
    for lab, tr in compare or ():
        a.plot(np.asarray(tr.x), np.asarray(tr.y), "--", lw=1, label=lab)
    a.plot([0.0], [0.0], "ko", ms=4, label="start")
    stops = [leg[:2] for leg in np.asarray(plan.legs)[1:]] + [plan.target[:2]]
    a.plot([s[0] for s in stops], [s[1] for s in stops], "r+", ms=12, mew=2, label="waypoints / target")
    t = cols["t"]
    idx = np.linspace(0, len(t) - 1, 12).astype(int)
    L = 0.05 * max(np.ptp(cols["x"]), np.ptp(cols["y"]), 0.1)
    h = cols["heading"][idx]
    arrows = dict(angles="xy", scale_units="xy", scale=1 / L, width=0.004, color="0.4", label="platform heading")
    a.quiver(cols["x"][idx], cols["y"][idx], np.cos(h), np.sin(h), **arrows)
    a.set(xlabel="x [m]", ylabel="y [m]")
    a.axis("equal")
    a.legend(fontsize=7)
    a.set_title(title or ("feasible plan" if plan.feasible else "NOT feasible: best plan found"), fontsize=9)
    N = plan.params.n_wheels
    for i in range(N):
        b.plot(t, 1e3 * cols[f"K_{i + 1}"], label=f"wheel {i + 1}")
        c.plot(t, cols[f"chi_dot_{i + 1}"])
    d.plot(t, np.degrees(cols["tilt"]))
    rep = plan.limits_report
    for ax, key, scale in ((b, "torque_N_m", 1e3), (c, "wheel_speed_rad_s", 1.0), (d, "tilt_rad", 180 / np.pi)):
        if key in rep and rep[key]["max"] > 0.5 * rep[key]["limit"]:
            for sgn in (1, -1) if ax is not d else (1,):
                ax.axhline(sgn * scale * rep[key]["limit"], color="r", ls="--", lw=0.8)
    b.set_ylabel("K [mN m]")
    b.legend(fontsize=7)
    c.set_ylabel(r"$\dot\chi$ [rad/s]")
    d.set(xlabel="t [s]", ylabel="tilt [deg]")
    finish(fig, path)
