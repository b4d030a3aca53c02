"""Figures of a fit: captured and fitted paths, residuals, the worst-fitting trial named."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from .base import finish, subplots


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


def _set_aside(series) -> np.ndarray:
    """Where the frames of a trial's series were set aside by the fit's loss (none if not given)."""
    out = series.get("set_aside")
    return np.zeros(len(series["t"]), bool) if out is None else np.asarray(out, bool)


def fit_figures(result, out_dir, *, stem: str = "fit") -> list[Path]:
    """`<stem>_overlay.png` (captured and fitted paths, one colour per trial) and
    `<stem>_residuals.png` (position [mm] and orientation [deg] residuals vs time per trial)
    for a `jsphere.FitResult`; written atomically into `out_dir`.

    The worst-fitting trial (`worst_trial`) is drawn bold and named in the overlay's title, and
    comes first in the residual figure, titled with its name and its residual sigmas relative
    to the capture's noise floor, and the fit's status. Frames a robust loss set aside (ghost
    frames, marker swaps: `FitResult.outliers`) are red crosses in both figures, and the
    residual axes are scaled to the frames kept.

    For onboard-sensor trials (`result.sigmas` set), the two files of `onboard_figures`; for trials
    of both kinds, the pose trials' two files and the onboard trials' `<stem>_onboard_overlay.png`
    and `<stem>_onboard_residuals.png`."""
    parts = (getattr(result, "verdict", None) or {}).get("parts")
    if parts:
        pose = [t for t in result.trials if "rms_pos_m" in t]
        onboard = [t for t in result.trials if "rms_pos_m" not in t]
        capture = dataclasses.replace(result, trials=pose, verdict=parts["capture"], sigmas={})
        sensors = dataclasses.replace(result, trials=onboard, verdict=parts["onboard"])
        return _pose_figures(capture, out_dir, stem) + onboard_figures(sensors, out_dir, stem=f"{stem}_onboard")
    if getattr(result, "sigmas", None):
        return onboard_figures(result, out_dir, stem=stem)
    return _pose_figures(result, out_dir, stem)


def _status(result) -> str:
    return f"status: {result.status}; " if getattr(result, "status", "") else ""


def _residual_figure(trials, worst, panels, titles, path, size, suptitle: str, fontsize: float, lw: float) -> Path:
    """Every trial's residuals against time, a row per trial (the worst first, named in bold red)
    and a column per panel `(series key, scale, line labels or None for 1..N, y label)`, titled
    over the first row; the frames a robust loss set aside are red crosses at the axes' edge,
    the axes scaled to the frames kept. Written atomically to `path`."""
    n = len(trials)
    order = list(range(n)) if worst is None else [worst] + [k for k in range(n) if k != worst]
    fig, axes = subplots(n, len(panels), figsize=size, sharex="row", squeeze=False)
    for row, k in enumerate(order):
        s = trials[k]["series"]
        out = _set_aside(s)
        for ax, (key, unit, labels, ylabel) in zip(axes[row], panels):
            err = s[key]
            for i, lab in enumerate(labels or [f"{i + 1}" for i in range(err.shape[1])]):
                ax.plot(s["t"], unit * err[:, i], lw=lw, label=lab)
            if out.any():
                kept = unit * err[~out]
                top = np.nanmax(np.abs(kept)) * 1.1 if np.isfinite(kept).any() else 1.0
                ax.set_ylim(-top, top)
                ax.plot(s["t"][out], np.full(int(out.sum()), 0.9 * top), "x", ms=3, color="red", label="set aside")
            if ylabel:
                ax.set_ylabel(ylabel, fontsize=7)
        emph = {"color": "C3", "fontweight": "bold"} if k == worst and n > 1 else {}
        axes[row][0].set_ylabel(f"{trials[k]['name']}{panels[0][3]}", fontsize=7, **emph)
    for ax, title in zip(axes[0], titles):
        ax.set_title(title, fontsize=fontsize)
        ax.legend(fontsize=6, loc="upper right")
    for ax in axes[-1]:
        ax.set_xlabel("t [s]")
    if suptitle:
        fig.suptitle(suptitle, fontsize=9)
    return finish(fig, path)


def _pose_figures(result, out_dir, stem: str) -> list[Path]:
    """`fit_figures` of a fit to captured poses."""
    out_dir, trials = Path(out_dir), result.trials
    worst, worst_text = worst_trial(result)
    status = _status(result)
    fig, ax = subplots(figsize=(6.5, 6))
    for k, tr in enumerate(trials):
        s = tr["series"]
        c = f"C{k % 10}"
        bold = k == worst and len(trials) > 1
        ax.plot(1e3 * s["x"], 1e3 * s["y"], ".", ms=1.5, color=c, alpha=0.5)
        label = f"{tr['name']} ({1e3 * tr['rms_pos_m']:.2f} mm){' - worst' if bold else ''}"
        ax.plot(1e3 * s["x_sim"], 1e3 * s["y_sim"], "-", lw=2.2 if bold else 1, color=c, label=label)
        out = _set_aside(s)
        if out.any():
            ax.plot(1e3 * s["x"][out], 1e3 * s["y"][out], "x", ms=4, color="red")
    ax.set(xlabel="x [mm]", ylabel="y [mm]")
    n_out = sum(int(_set_aside(tr["series"]).sum()) for tr in trials)
    title = "captured (dots) and fitted (lines) paths; RMS position residual"
    if n_out:
        title += f"; {n_out} frames set aside (red crosses)"
    if worst_text:
        title += f"\n{status}worst {worst_text}"
    ax.set_title(title, fontsize=8 if worst_text else 9)
    ax.axis("equal")
    if len(trials) <= 12:
        ax.legend(fontsize=7)
    overlay = finish(fig, out_dir / f"{stem}_overlay.png")

    verdict = getattr(result, "verdict", None) or {}
    fp, fr = verdict.get("noise_floor_pos_m"), verdict.get("noise_floor_rot_deg")
    floor_pos = f", noise floor {1e3 * fp:.3f} mm" if isinstance(fp, float) and np.isfinite(fp) else ""
    floor_rot = f", noise floor {fr:.3f} deg" if isinstance(fr, float) and np.isfinite(fr) else ""
    titles = (
        f"position residual (sigma {1e3 * result.sigma_pos:.3f} mm{floor_pos})",
        f"orientation residual (sigma {np.degrees(result.sigma_rot):.3f} deg{floor_rot})",
    )
    panels = (("pos_err", 1e3, "xy", "\n[mm]"), ("rot_err_deg", 1.0, "xyz", "[deg]"))
    size = (10, 1.6 * len(trials) + 0.8 + (0.3 if worst_text else 0.0))
    suptitle = f"{status}worst-fitting trial first: {worst_text}" if worst_text else ""
    residuals = out_dir / f"{stem}_residuals.png"
    return [overlay, _residual_figure(trials, worst, panels, titles, residuals, size, suptitle, 9, 0.6)]


def onboard_figures(result, out_dir, *, stem: str = "fit") -> list[Path]:
    """`<stem>_overlay.png`: the worst trial's recorded readings (dots) and fitted ones (lines,
    biases included) per channel; `<stem>_residuals.png`: every trial's residuals per channel
    (gyro [rad/s], accelerometer [m/s^2], encoders [mrad]), the worst first, each channel titled
    with its noise level, floor and ratio."""
    out_dir = Path(out_dir)
    trials, verdict = result.trials, getattr(result, "verdict", None) or {}
    names, worst = [t["name"] for t in trials], worst_trial(result)[0] or 0
    status = _status(result)
    channels = (("gyro", "gyro [rad/s]", 1.0), ("acc", "accelerometer [m/s^2]", 1.0), ("chi", "encoders [mrad]", 1e3))
    s = trials[worst]["series"]
    fig, axes = subplots(3, 1, figsize=(8, 7), sharex=True)
    for ax, (key, label, _) in zip(axes, channels):
        meas, fitted = s[key], s[key] + s[f"{key}_err"]
        for i in range(meas.shape[1]):
            ax.plot(s["t"], meas[:, i], ".", ms=1.5, color=f"C{i}", alpha=0.5)
            ax.plot(s["t"], fitted[:, i], "-", lw=0.8, color=f"C{i}", label=f"{i + 1}" if key == "chi" else "xyz"[i])
        ax.set_ylabel(label.replace("[mrad]", "[rad]"), fontsize=8)
        ax.legend(fontsize=6, loc="upper left")
    axes[-1].set_xlabel("t [s]")
    fig.suptitle(f"{status}trial {names[worst]!r}: recorded (dots) and fitted (lines) readings", fontsize=9)
    overlay = finish(fig, out_dir / f"{stem}_overlay.png")

    chan, titles = verdict.get("channels", {}), []
    for (key, label, unit), c in zip(channels, ("gyro", "acc", "encoders")):
        v = chan.get(c, {})
        floor, ratio = unit * v.get("noise_floor", np.nan), v.get("ratio", np.nan)
        titles.append(f"{label}: sigma {unit * result.sigmas[c]:.3g}, floor {floor:.3g} ({ratio:.2f}x)")
    panels = [(f"{key}_err", unit, None if key == "chi" else "xyz", "") for key, _, unit in channels]
    size, suptitle = (12, 1.6 * len(trials) + 1.0), f"{status}residuals per channel, the worst-fitting trial first"
    residuals = out_dir / f"{stem}_residuals.png"
    return [overlay, _residual_figure(trials, worst, panels, titles, residuals, size, suptitle, 8, 0.5)]
