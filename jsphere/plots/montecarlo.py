"""Figures of Monte-Carlo studies: stop points with their confidence ellipse, Fig. 2 as a study."""

from __future__ import annotations

import numpy as np

from .base import finish, pyplot, xy_axes


def _ellipse_in_figure_frame(st):
    """The confidence ellipse of `MonteCarloResult.stats()` as (x, y) in the paper's frame [mm]."""
    minor, major = st["ellipse"]["semi_axes_m"]
    ang, (x0, y0) = st["ellipse"]["angle_rad"], st["mean_xy_m"]
    t = np.linspace(0, 2 * np.pi, 200)
    e1, e2 = np.array([np.cos(ang), np.sin(ang)]), np.array([-np.sin(ang), np.cos(ang)])
    ell = np.array([x0, y0])[:, None] + major * np.outer(e1, np.cos(t)) + minor * np.outer(e2, np.sin(t))
    return -1e3 * ell[1], 1e3 * ell[0]


def montecarlo_figure(res, path, *, planned=None) -> None:
    """Stop points of a Monte-Carlo study: scatter with the 95 % ellipse, and a histogram of
    the distance from the mean stop (paper's figure frame, mm)."""
    plt = pyplot()
    ok = np.asarray(res.status) == 0
    xf, yf = -1e3 * np.asarray(res.y_final)[ok], 1e3 * np.asarray(res.x_final)[ok]
    st = res.stats()
    fig, (a, b) = plt.subplots(1, 2, figsize=(10, 4.5))
    a.plot(xf, yf, ".", ms=2, alpha=0.4, label=f"{ok.sum()} trials")
    a.plot(*_ellipse_in_figure_frame(st), "r-", label=f"{100 * st['ellipse']['level']:.0f}% ellipse")
    mx, my = -1e3 * st["mean_xy_m"][1], 1e3 * st["mean_xy_m"][0]
    if planned is not None:
        a.plot([-1e3 * planned[1]], [1e3 * planned[0]], "kx", label="planned stop")
    xy_axes(a)
    d = np.hypot(xf - mx, yf - my)
    b.hist(d, bins=60)
    b.set_xlabel("distance from the mean stop [mm]")
    b.set_ylabel("trials")
    finish(plt, fig, path)


def figure2_study(kin, gait, path) -> None:
    """Fig. 2 as a study: kinematic control (2.9) vs gait control over many perturbed robots.
    (a) the spread of `gamma_3` after the commands end, with the paper's measured values;
    (b) stop points (paper's frame) with their 95 % ellipses."""
    plt = pyplot()
    fig, (a, b) = plt.subplots(1, 2, figsize=(11, 4.5))
    for res, lab in ((kin, "kinematic control (2.9)"), (gait, "gait control")):
        ok = np.asarray(res.status) == 0
        a.hist(np.asarray(res.gamma3_sd_after)[ok], bins=60, alpha=0.6, label=lab)
        st = res.stats()
        b.plot(-1e3 * np.asarray(res.y_final)[ok], 1e3 * np.asarray(res.x_final)[ok], ".", ms=1.5, alpha=0.3, label=lab)
        b.plot(*_ellipse_in_figure_frame(st), "-", lw=1)
    for v, lab in ((0.018, "paper, kinematic (measured)"), (0.001, "paper, gaits (measured)")):
        a.axvline(v, color="k", ls="--" if v > 0.01 else ":", lw=1, label=lab)
    a.set_xlabel(r"sd of $\gamma_3$ after the stop")
    a.set_ylabel("trials")
    a.legend(fontsize=7)
    b.errorbar([-1.392], [369.2], xerr=[28.9], yerr=[37.7], fmt="ko", ms=3, label="paper, gaits, experiment (95%)")
    xy_axes(b)
    finish(plt, fig, path)
