"""Figures in the style of the paper's Figs. 2 and 3 (matplotlib, imported lazily)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ._io import atomic_savefig


def _plt():
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    return plt


def _xy_axes(ax) -> None:
    """Axes of a path in the paper's figure frame [mm]."""
    ax.set_xlabel("x [mm] (paper's frame)")
    ax.set_ylabel("y [mm]")
    ax.axis("equal")
    ax.legend(fontsize=7)


def _finish(plt, fig, path, margins: dict | None = None) -> None:
    """Lay out, save atomically, close. `margins` (for `fig.subplots_adjust`) fix the layout
    by hand; without them `tight_layout` measures every label (~0.1 s a figure)."""
    if margins is None:
        fig.tight_layout()
    else:
        fig.subplots_adjust(**margins)
    atomic_savefig(fig, path, dpi=120)
    plt.close(fig)


def _fig_xy(tr):
    return -1e3 * np.asarray(tr.y), 1e3 * np.asarray(tr.x)  # paper's frame, mm


def figure2(rep, path) -> None:
    """Fig. 2: kinematic control (2.9) vs gait control; (a) paths, (b) `gamma_3(t)`."""
    plt = _plt()
    kin, gait = rep.trajectories["kinematic"], rep.trajectories["gait_8s"]
    fig, (a, b) = plt.subplots(1, 2, figsize=(10, 4))
    for tr, lab, st in ((kin, "kinematic model (2.9)", "-"), (gait, "dynamic model (gaits)", "--")):
        a.plot(*_fig_xy(tr), st, label=lab)
        b.plot(np.asarray(tr.ts), np.asarray(tr.gamma[:, 2]), st, label=lab)
    a.set_xlabel("x [mm] (paper's frame)")
    a.set_ylabel("y [mm]")
    a.set_title("(a) trajectories, 0-8 s")
    a.axis("equal")
    a.legend()
    s = rep.values["sigma_gamma3_t_gt_4"]
    b.axvline(4.0, color="0.6", lw=0.8)
    b.set_xlabel("t [s]")
    b.set_ylabel(r"$\gamma_3$")
    b.set_title(
        f"(b) sigma(gamma_3, t>4): kin {s['kinematic']['std']:.4f} (paper 0.018), gaits {s['gait']['std']:.1e} (paper 0.001)",
        fontsize=8,
    )
    b.legend()
    _finish(plt, fig, path, dict(left=0.07, right=0.98, bottom=0.12, top=0.92, wspace=0.22))


def figure3(rep, path) -> None:
    """Fig. 3: (a) straight line, (b) straight line with a turn; paper's and measured stops."""
    plt = _plt()
    fig, (a, b) = plt.subplots(1, 2, figsize=(10, 5))
    T = rep.trajectories
    a.plot(*_fig_xy(T["straight"]), "--", label="jsphere (no reset)")
    a.plot(*_fig_xy(T["straight_reset"]), ":", label="jsphere (reset 5.4)")
    a.plot([-0.0695], [344.6], "rx", label="paper, simulation")
    a.errorbar([-1.392], [369.2], xerr=[28.9], yerr=[37.7], fmt="ko", ms=3, label="paper, experiment (95%)")
    a.set_title("(a) rectilinear motion")
    b.plot(*_fig_xy(T["turn_reset"]), "--", label="jsphere (reset before turn)")
    b.plot(*_fig_xy(T["turn_signfixed"]), ":", label="jsphere ((5.7), sign fixed)")
    if "turn_full_stop" in T:
        b.plot(*_fig_xy(T["turn_full_stop"]), "-", lw=1, label="jsphere, braking that stops")
    b.plot([-173.2], [519.4], "rx", label="paper, simulation")
    b.errorbar([-151.3], [482.4], xerr=[32.4], yerr=[112.1], fmt="ko", ms=3, label="paper, experiment (95%)")
    b.set_title("(b) rectilinear motion with a turn")
    for ax in (a, b):
        _xy_axes(ax)
    _finish(plt, fig, path, dict(left=0.07, right=0.98, bottom=0.1, top=0.94, wspace=0.22))


def controls_figure(tr, path, *, title: str = "") -> None:
    """Wheel torques `K(t)`, wheel rates `chi_dot(t)` and tilt `gamma_3(t)` of a trajectory."""
    plt = _plt()
    fig, axs = plt.subplots(3, 1, figsize=(7, 7), sharex=True)
    t = np.asarray(tr.ts)
    axs[0].plot(t, 1e3 * np.asarray(tr.K))
    axs[0].set_ylabel("K [mN m]")
    axs[1].plot(t, np.asarray(tr.chi_dot))
    axs[1].set_ylabel(r"$\dot\chi$ [rad/s]")
    axs[2].plot(t, np.asarray(tr.gamma[:, 2]))
    axs[2].set_ylabel(r"$\gamma_3$")
    axs[2].set_xlabel("t [s]")
    axs[0].legend([f"wheel {i + 1}" for i in range(np.asarray(tr.K).shape[1])], fontsize=7)
    if title:
        axs[0].set_title(title)
    _finish(plt, fig, path, dict(left=0.12, right=0.97, bottom=0.08, top=0.95, hspace=0.08))


#: The files `write_reproduction_figures` writes in its folder.
REPRODUCTION_FIGURES = ("fig2_kinematic_vs_gaits.png", "fig3_trajectories.png", "straight_line_controls.png")


def write_reproduction_figures(rep, out_dir) -> list[Path]:
    out = Path(out_dir)
    paths = [out / name for name in REPRODUCTION_FIGURES]
    figure2(rep, paths[0])
    figure3(rep, paths[1])
    controls_figure(rep.trajectories["straight"], paths[2], title="acceleration (5.1) + braking (5.3): controls")
    return paths


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
    plt = _plt()
    ok = np.asarray(res.status) == 0
    xf, yf = -1e3 * np.asarray(res.y_final)[ok], 1e3 * np.asarray(res.x_final)[ok]
    st = res.stats()
    fig, (a, b) = plt.subplots(1, 2, figsize=(10, 4.5))
    a.plot(xf, yf, ".", ms=2, alpha=0.4, label=f"{ok.sum()} trials")
    a.plot(*_ellipse_in_figure_frame(st), "r-", label=f"{100 * st['ellipse']['level']:.0f}% ellipse")
    mx, my = -1e3 * st["mean_xy_m"][1], 1e3 * st["mean_xy_m"][0]
    if planned is not None:
        a.plot([-1e3 * planned[1]], [1e3 * planned[0]], "kx", label="planned stop")
    _xy_axes(a)
    d = np.hypot(xf - mx, yf - my)
    b.hist(d, bins=60)
    b.set_xlabel("distance from the mean stop [mm]")
    b.set_ylabel("trials")
    _finish(plt, fig, path)


def figure2_study(kin, gait, path) -> None:
    """Fig. 2 as a study: kinematic control (2.9) vs gait control over many perturbed robots.
    (a) the spread of `gamma_3` after the commands end, with the paper's measured values;
    (b) stop points (paper's frame) with their 95 % ellipses."""
    plt = _plt()
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
    _xy_axes(b)
    _finish(plt, fig, path)


# --- system identification: the fit ---


def worst_trial(result) -> tuple[int | None, str]:
    """The index of the worst-fitting trial of a `FitResult` (the highest residual sigma
    relative to the capture's noise floor, `result.verdict["worst_trial"]`) and a line naming it
    with its ratios; `(None, "")` for a result without a verdict."""
    verdict = getattr(result, "verdict", None) or {}
    name = verdict.get("worst_trial")
    names = [t["name"] for t in result.trials]
    if name not in names:
        return None, ""
    k = names.index(name)
    row = next((t for t in verdict.get("trials", []) if t.get("name") == name), {})
    fmt = lambda r: f"{r:.2f}x" if isinstance(r, (int, float)) and np.isfinite(r) else "n/a"
    text = f"{name}: residual sigma {fmt(row.get('ratio_pos'))} / {fmt(row.get('ratio_rot'))} the noise floor (position / orientation)"
    return k, text


def fit_figures(result, out_dir, *, stem: str = "fit") -> list[Path]:
    """`<stem>_overlay.png` (captured and fitted paths, one colour per trial) and
    `<stem>_residuals.png` (position [mm] and orientation [deg] residuals vs time per trial)
    for a `jsphere.FitResult`; written atomically into `out_dir`.

    The worst-fitting trial (`worst_trial`) is drawn bold and named in the overlay's title, and
    comes first in the residual figure, titled with its name and its residual sigmas relative
    to the capture's noise floor, and the fit's status."""
    plt = _plt()
    out_dir = Path(out_dir)
    trials = result.trials
    worst, worst_text = worst_trial(result)
    status = f"status: {result.status}; " if getattr(result, "status", "") else ""
    fig, ax = plt.subplots(figsize=(6.5, 6))
    for k, tr in enumerate(trials):
        s = tr["series"]
        c = f"C{k % 10}"
        bold = k == worst and len(trials) > 1
        ax.plot(1e3 * s["x"], 1e3 * s["y"], ".", ms=1.5, color=c, alpha=0.5)
        label = f"{tr['name']} ({1e3 * tr['rms_pos_m']:.2f} mm){' - worst' if bold else ''}"
        ax.plot(1e3 * s["x_sim"], 1e3 * s["y_sim"], "-", lw=2.2 if bold else 1, color=c, label=label)
    ax.set_xlabel("x [mm]")
    ax.set_ylabel("y [mm]")
    title = "captured (dots) and fitted (lines) paths; RMS position residual"
    if worst_text:
        title += f"\n{status}worst {worst_text}"
    ax.set_title(title, fontsize=8 if worst_text else 9)
    ax.axis("equal")
    if len(trials) <= 12:
        ax.legend(fontsize=7)
    overlay = out_dir / f"{stem}_overlay.png"
    _finish(plt, fig, overlay)

    verdict = getattr(result, "verdict", None) or {}
    fp, fr = verdict.get("noise_floor_pos_m"), verdict.get("noise_floor_rot_deg")
    floor_pos = f", noise floor {1e3 * fp:.3f} mm" if isinstance(fp, float) and np.isfinite(fp) else ""
    floor_rot = f", noise floor {fr:.3f} deg" if isinstance(fr, float) and np.isfinite(fr) else ""
    n = len(trials)
    order = list(range(n)) if worst is None else [worst] + [k for k in range(n) if k != worst]
    fig, axes = plt.subplots(n, 2, figsize=(10, 1.6 * n + 0.8 + (0.3 if worst_text else 0.0)), sharex="row", squeeze=False)
    for row, k in enumerate(order):
        tr = trials[k]
        s = tr["series"]
        a, b = axes[row]
        a.plot(s["t"], 1e3 * s["pos_err"][:, 0], lw=0.6, label="x")
        a.plot(s["t"], 1e3 * s["pos_err"][:, 1], lw=0.6, label="y")
        for i, lab in enumerate("xyz"):
            b.plot(s["t"], s["rot_err_deg"][:, i], lw=0.6, label=lab)
        emph = {"color": "C3", "fontweight": "bold"} if k == worst and n > 1 else {}
        a.set_ylabel(f"{tr['name']}\n[mm]", fontsize=7, **emph)
        b.set_ylabel("[deg]", fontsize=7)
        if row == 0:
            a.set_title(f"position residual (sigma {1e3 * result.sigma_pos:.3f} mm{floor_pos})", fontsize=9)
            b.set_title(f"orientation residual (sigma {np.degrees(result.sigma_rot):.3f} deg{floor_rot})", fontsize=9)
            a.legend(fontsize=6, loc="upper right")
            b.legend(fontsize=6, loc="upper right")
    if worst_text:
        fig.suptitle(f"{status}worst-fitting trial first: {worst_text}", fontsize=9)
    axes[-1, 0].set_xlabel("t [s]")
    axes[-1, 1].set_xlabel("t [s]")
    residuals = out_dir / f"{stem}_residuals.png"
    _finish(plt, fig, residuals)
    return [overlay, residuals]


# --- end system identification ---


# ---- planning (issue 4) ----------------------------------------------------------------------
def plan_figure(plan, path, *, compare=None, title: str = "") -> None:
    """A `Plan`: path with target and heading arrows, `K(t)`, `chi_dot(t)`, tilt with limits
    (see `jsphere._plan_plots.plan_figure`)."""
    from ._plan_plots import plan_figure as _plan_figure

    _plan_figure(plan, path, compare=compare, title=title)


# ---- end planning ----------------------------------------------------------------------------
