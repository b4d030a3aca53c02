"""Figures in the style of the paper's Figs. 2 and 3 and the straight-line controls; the paths are
drawn in the paper's figure frame (`x_fig = -y`, `y_fig = x`), as the paper draws them."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .base import finish, paper_experiment, subplots, xy_axes


def _fig_xy(tr):
    return -1e3 * np.asarray(tr.y), 1e3 * np.asarray(tr.x)  # paper's frame, mm


def figure2(rep, path) -> None:
    """Fig. 2: kinematic control (2.9) vs gait control; (a) paths, (b) `gamma_3(t)`."""
    kin, gait = rep.trajectories["kinematic"], rep.trajectories["gait_8s"]
    fig, (a, b) = subplots(1, 2, figsize=(10, 4))
    for tr, lab, st in ((kin, "kinematic model (2.9)", "-"), (gait, "dynamic model (gaits)", "--")):
        a.plot(*_fig_xy(tr), st, label=lab)
        b.plot(np.asarray(tr.ts), np.asarray(tr.gamma[:, 2]), st, label=lab)
    a.set_title("(a) trajectories, 0-8 s")
    xy_axes(a)
    s = rep.values["sigma_gamma3_t_gt_4"]
    b.axvline(4.0, color="0.6", lw=0.8)
    b.set(xlabel="t [s]", ylabel=r"$\gamma_3$")
    b.set_title(
        f"(b) sigma(gamma_3, t>4): kin {s['kinematic']['std']:.4f} (paper 0.018), gaits {s['gait']['std']:.1e} (paper 0.001)",
        fontsize=8,
    )
    b.legend()
    finish(fig, path, dict(left=0.07, right=0.98, bottom=0.12, top=0.92, wspace=0.22))


def figure3(rep, path) -> None:
    """Fig. 3: (a) straight line, (b) straight line with a turn; paper's and measured stops."""
    T = rep.trajectories
    fig, (a, b) = subplots(1, 2, figsize=(10, 5))
    a.plot(*_fig_xy(T["straight"]), "--", label="jsphere (no reset)")
    a.plot(*_fig_xy(T["straight_reset"]), ":", label="jsphere (reset 5.4)")
    a.plot([-0.0695], [344.6], "rx", label="paper, simulation")
    paper_experiment(a)
    a.set_title("(a) rectilinear motion")
    b.plot(*_fig_xy(T["turn_reset"]), "--", label="jsphere (reset before turn)")
    b.plot(*_fig_xy(T["turn_signfixed"]), ":", label="jsphere ((5.7), sign fixed)")
    if "turn_full_stop" in T:
        b.plot(*_fig_xy(T["turn_full_stop"]), "-", lw=1, label="jsphere, braking that stops")
    b.plot([-173.2], [519.4], "rx", label="paper, simulation")
    b.errorbar([-151.3], [482.4], xerr=[32.4], yerr=[112.1], fmt="ko", ms=3, label="paper, experiment (95%)")
    b.set_title("(b) rectilinear motion with a turn")
    for ax in (a, b):
        xy_axes(ax)
    finish(fig, path, dict(left=0.07, right=0.98, bottom=0.1, top=0.94, wspace=0.22))


def controls_figure(tr, path, *, title: str = "") -> None:
    """Wheel torques `K(t)`, wheel rates `chi_dot(t)` and tilt `gamma_3(t)` of a trajectory."""
    fig, axs = subplots(3, 1, figsize=(7, 7), sharex=True)
    labels = ("K [mN m]", r"$\dot\chi$ [rad/s]", r"$\gamma_3$")
    for ax, v, label in zip(axs, (1e3 * np.asarray(tr.K), tr.chi_dot, tr.gamma[:, 2]), labels):
        ax.plot(np.asarray(tr.ts), np.asarray(v))
        ax.set_ylabel(label)
    axs[2].set_xlabel("t [s]")
    axs[0].legend([f"wheel {i + 1}" for i in range(np.asarray(tr.K).shape[1])], fontsize=7)
    if title:
        axs[0].set_title(title)
    finish(fig, path, dict(left=0.12, right=0.97, bottom=0.08, top=0.95, hspace=0.08))


#: The files `write_reproduction_figures` writes in its folder.
REPRODUCTION_FIGURES = ("fig2_kinematic_vs_gaits.png", "fig3_trajectories.png", "straight_line_controls.png")


def write_reproduction_figures(rep, out_dir) -> list[Path]:
    out = Path(out_dir)
    paths = [out / name for name in REPRODUCTION_FIGURES]
    figure2(rep, paths[0])
    figure3(rep, paths[1])
    controls_figure(rep.trajectories["straight"], paths[2], title="acceleration (5.1) + braking (5.3): controls")
    return paths
