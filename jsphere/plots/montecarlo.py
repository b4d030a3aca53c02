"""Figures of Monte-Carlo studies: stop points with their confidence ellipse, Fig. 2 as a study;
in jsphere's frame (that of `MonteCarloResult.stats()`) or the paper's figure frame (docs/model.md)."""

from __future__ import annotations

import numpy as np

from .base import check_frame, ellipse_points, finish, in_frame, paper_experiment, subplots, xy_axes


def _ellipse(st, frame: str):
    """The confidence ellipse of `MonteCarloResult.stats()` as (x, y) [mm] in `frame`."""
    e = 1e3 * ellipse_points(st)
    return in_frame(e[:, 0], e[:, 1], frame)


def _stops(res, frame: str):
    """The stop points of the successful trials [mm] in `frame`."""
    ok = np.asarray(res.status) == 0
    return in_frame(1e3 * np.asarray(res.x_final)[ok], 1e3 * np.asarray(res.y_final)[ok], frame)


def montecarlo_figure(res, path, *, planned=None, frame: str = "jsphere") -> None:
    """Stop points of a Monte-Carlo study: scatter with the 95 % ellipse, and a histogram of
    the distance from the mean stop [mm]. `planned`: the nominal stop `(x, y)` [m] in
    jsphere's frame; `frame`: `"jsphere"` (default) or `"paper"` (the paper's figure frame)."""
    check_frame(frame)
    (xf, yf), st = _stops(res, frame), res.stats()
    fig, (a, b) = subplots(1, 2, figsize=(10, 4.5))
    a.plot(xf, yf, ".", ms=2, alpha=0.4, label=f"{xf.size} trials")
    a.plot(*_ellipse(st, frame), "r-", label=f"{100 * st['ellipse']['level']:.0f}% ellipse")
    mx, my = in_frame(1e3 * st["mean_xy_m"][0], 1e3 * st["mean_xy_m"][1], frame)
    if planned is not None:
        px, py = in_frame(1e3 * planned[0], 1e3 * planned[1], frame)
        a.plot([px], [py], "kx", label="planned stop")
    xy_axes(a, frame)
    d = np.hypot(xf - mx, yf - my)
    b.hist(d, bins=60)
    b.set(xlabel="distance from the mean stop [mm]", ylabel="trials")
    finish(fig, path)


def figure2_study(kin, gait, path, *, frame: str = "jsphere") -> None:
    """Fig. 2 as a study: kinematic control (2.9) vs gait control over many perturbed robots.
    (a) the spread of `gamma_3` after the commands end, with the paper's measured values;
    (b) stop points with their 95 % ellipses and the paper's experiment, in `frame`
    (`"jsphere"`, default, or `"paper"`: the paper's figure frame)."""
    check_frame(frame)
    fig, (a, b) = subplots(1, 2, figsize=(11, 4.5))
    for res, lab in ((kin, "kinematic control (2.9)"), (gait, "gait control")):
        ok = np.asarray(res.status) == 0
        a.hist(np.asarray(res.gamma3_sd_after)[ok], bins=60, alpha=0.6, label=lab)
        b.plot(*_stops(res, frame), ".", ms=1.5, alpha=0.3, label=lab)
        b.plot(*_ellipse(res.stats(), frame), "-", lw=1)
    for v, lab in ((0.018, "paper, kinematic (measured)"), (0.001, "paper, gaits (measured)")):
        a.axvline(v, color="k", ls="--" if v > 0.01 else ":", lw=1, label=lab)
    a.set(xlabel=r"sd of $\gamma_3$ after the stop", ylabel="trials")
    a.legend(fontsize=7)
    paper_experiment(b, frame, "paper, gaits, experiment (95%)")
    xy_axes(b, frame)
    finish(fig, path)
