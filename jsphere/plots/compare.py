"""The figure of a model compared with one trial: measured against simulated, the residuals and
their autocorrelation with the 99 % band of white noise."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .base import finish, pyplot


def compare_figure(report: dict, path) -> Path:
    """One trial of a `jsphere.CompareResult` (an entry of its `trials`, with its `series`): the
    measured (dots) and simulated (lines) `x` and `y` against time [mm], the position [mm] and
    orientation [deg] residuals, and the residuals' autocorrelation per channel with the 99 %
    band; titled with the trial's name and its fits [%]. Written atomically to `path`."""
    plt = pyplot()
    s = report["series"]
    t = np.asarray(s["t"])
    fig, axes = plt.subplots(3, 1, figsize=(8, 9))
    ax = axes[0]
    for key, colour in (("x", "C0"), ("y", "C1")):
        ax.plot(t, 1e3 * np.asarray(s[key]), ".", ms=2, color=colour, alpha=0.5, label=f"{key} measured")
        ax.plot(t, 1e3 * np.asarray(s[f"{key}_sim"]), "-", lw=1.2, color=colour, label=f"{key} simulated")
    ax.set(xlabel="t [s]", ylabel="position [mm]")
    ax.legend(fontsize=7, ncol=2)
    f = s["fit_percent"]
    ax.set_title(f"{report['name']}: fit x {f['x']:.1f} %, y {f['y']:.1f} %, rot {f['rot']:.1f} %", fontsize=9)
    r = np.asarray(s["residuals"])
    ax = axes[1]
    ax.plot(t, 1e3 * r[:, 0], lw=0.8, label="x [mm]")
    ax.plot(t, 1e3 * r[:, 1], lw=0.8, label="y [mm]")
    for k in range(3):
        ax.plot(t, np.degrees(r[:, 2 + k]), lw=0.6, alpha=0.7, label=f"rot {'xyz'[k]} [deg]")
    ax.axhline(0.0, color="k", lw=0.5)
    ax.set(xlabel="t [s]", ylabel="residual (simulated - measured)")
    ax.legend(fontsize=7, ncol=5)
    ax = axes[2]
    acf, band = np.asarray(s["acf"]), float(s["band"])
    lags = np.arange(acf.shape[1])
    for k, name in enumerate(s["channels"]):
        ax.plot(lags[1:], acf[k, 1:], "o-", ms=3, lw=0.8, label=name)
    ax.axhspan(-band, band, color="0.85", zorder=0, label="99 % band")
    ax.axhline(0.0, color="k", lw=0.5)
    out = report["whiteness"]["acf_outside_99"]
    ax.set_title(f"residual autocorrelation: {100 * out:.1f} % of the lags outside the 99 % band", fontsize=9)
    ax.set(xlabel="lag [samples]", ylabel="autocorrelation")
    ax.legend(fontsize=7, ncol=6)
    finish(plt, fig, Path(path))
    return Path(path)
