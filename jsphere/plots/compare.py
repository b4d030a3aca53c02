"""The figure of a model compared with one trial: measured against simulated, the residuals and
their autocorrelation with the 99 % band of white noise."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .base import finish, subplots


def compare_figure(report: dict, path) -> Path:
    """One trial of a `jsphere.CompareResult` (an entry of its `trials`, with its `series`): the
    measured (dots) and simulated (lines) `x` and `y` against time [mm], the position [mm] and
    orientation [deg] residuals, and the residuals' autocorrelation per channel with the 99 %
    band; titled with the trial's name and its fits [%]. Written atomically to `path`."""
    s = report["series"]
    t, r, f = np.asarray(s["t"]), np.asarray(s["residuals"]), s["fit_percent"]
    fig, (a, b, c) = subplots(3, 1, figsize=(8, 9))
    for key, colour in (("x", "C0"), ("y", "C1")):
        a.plot(t, 1e3 * np.asarray(s[key]), ".", ms=2, color=colour, alpha=0.5, label=f"{key} measured")
        a.plot(t, 1e3 * np.asarray(s[f"{key}_sim"]), "-", lw=1.2, color=colour, label=f"{key} simulated")
    a.set_title(f"{report['name']}: fit x {f['x']:.1f} %, y {f['y']:.1f} %, rot {f['rot']:.1f} %", fontsize=9)
    b.plot(t, 1e3 * r[:, 0], lw=0.8, label="x [mm]")
    b.plot(t, 1e3 * r[:, 1], lw=0.8, label="y [mm]")
    for k in range(3):
        b.plot(t, np.degrees(r[:, 2 + k]), lw=0.6, alpha=0.7, label=f"rot {'xyz'[k]} [deg]")
    acf, band = np.asarray(s["acf"]), float(s["band"])
    for k, name in enumerate(s["channels"]):
        c.plot(np.arange(1, acf.shape[1]), acf[k, 1:], "o-", ms=3, lw=0.8, label=name)
    c.axhspan(-band, band, color="0.85", zorder=0, label="99 % band")
    out = report["whiteness"]["acf_outside_99"]
    c.set_title(f"residual autocorrelation: {100 * out:.1f} % of the lags outside the 99 % band", fontsize=9)
    ylabels = ("position [mm]", "residual (simulated - measured)", "autocorrelation")
    for ax, xlabel, ylabel, ncol in zip((a, b, c), ("t [s]", "t [s]", "lag [samples]"), ylabels, (2, 5, 6)):
        if ax is not a:
            ax.axhline(0.0, color="k", lw=0.5)
        ax.set(xlabel=xlabel, ylabel=ylabel)
        ax.legend(fontsize=7, ncol=ncol)
    return finish(fig, path)
