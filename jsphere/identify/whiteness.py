"""Are residuals white? The autocorrelation test that `fit`'s verdict and `compare` share.

A model that explains a capture leaves residuals that are the capture's noise: white, each
frame's error independent of the next. A model that misses something (dissipation, a torque
gain, a clock offset, a wrong inertia) leaves a smooth part in them, correlated over many
frames, even where it is small against the noise. Per trial and channel (`x`, `y`, `rot_x`,
`rot_y`, `rot_z`):

- the autocorrelation `r_k` at lags `k = 1..h` of the residual series about its mean, over the
  pairs of measured frames (`autocorrelation`);
- the share of lags outside the 99 % band `+- 2.576 / sqrt(N)` of white noise (as System
  Identification Toolbox's `resid` draws it; about 1 % for white residuals);
- the portmanteau statistic `Q = sum_k n_k r_k^2` (`n_k` the pairs of measured frames at lag
  `k`), chi^2 with `h` degrees of freedom for white residuals, and its p-value: the Ljung-Box
  test (Ljung & Box, Biometrika 65 (1978) 297-303) for series with gaps, each lag's
  autocorrelation over its own pairs, with variance `1 / n_k` (for a series without gaps
  `n_k = N - k`, Ljung-Box's weights to within `(N + 2) / N`). Measured on 20,000 white series
  of 400 frames, 3 % of them missing: 5.0 % below p = 0.05, 0.1 % below 1e-3
  (`tests/identify/test_whiteness.py`).

`rejects` rejects whiteness where a p-value falls below `ALPHA / n_tests` (Bonferroni over
every trial and channel tested together), so that the chance of calling a right model on a clean
capture correlated does not grow with the number of trials. The chi^2 tail is optimistic at
these sizes (25 lags, a few hundred frames): measured on 20,000 white series of 400 frames, 3 %
of them missing, 5.6 % of the p-values fall below 0.05 and 0.27 % below 1e-3; over 3 trials x 5
series at `ALPHA = 1e-4`, 4 of 3,000 right-model verdicts (0.13 %) were called correlated
(`tests/identify/test_fit_verdict.py` checks the rate on 300). Frames left out (gaps, frames a
robust loss set aside) break the series; they are not interpolated.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np
from scipy import stats

#: the 99 % two-sided quantile of the standard normal distribution
Z99 = 2.5758293035489004
#: the largest lag of the test [frames] unless one is given
LAGS = 25
#: the nominal chance that a right model on a clean capture is called correlated, over all the
#: trials and channels tested together (measured: about 1e-3, module docstring)
ALPHA = 1e-4
#: fewest measured frames a series needs to be tested (four times the largest lag)
MIN_FRAMES_PER_LAG = 4


def _pairs(valid: np.ndarray, lags: int) -> np.ndarray:
    """The pairs of measured frames at lags `0..lags`: `(lags + 1,)`."""
    return np.array([valid.sum()] + [(valid[k:] & valid[:-k]).sum() for k in range(1, lags + 1)])


def autocorrelation(e: np.ndarray, valid: np.ndarray, lags: int) -> np.ndarray:
    """Autocorrelation `(lags + 1,)` of a series `e (m,)` measured where `valid (m,)`, about its
    mean: each lag's products over its pairs of measured frames, divided by their count, over
    the variance."""
    w = np.asarray(valid, bool) & np.isfinite(e)
    if not w.any():
        return np.zeros(lags + 1)
    e = np.where(w, e - e[w].mean(), 0.0)
    c0 = (e * e).sum() / w.sum()
    pairs = _pairs(w, lags)
    out = np.ones(lags + 1)
    for k in range(1, lags + 1):
        out[k] = ((e[k:] * e[:-k]).sum() / pairs[k]) / c0 if pairs[k] and c0 > 0 else 0.0
    return out


def portmanteau(r: np.ndarray, pairs: np.ndarray) -> tuple[float, float]:
    """`(Q, p)`: `Q = sum_k n_k r_k^2` of autocorrelations `r (h + 1,)` (`r[0] = 1`) with `n_k`
    pairs of measured frames at lag `k` (`pairs (h + 1,)`), and its p-value under chi^2 with `h`
    degrees of freedom."""
    h = len(r) - 1
    q = float(np.sum(pairs[1:] * r[1:] ** 2))
    return q, float(stats.chi2.sf(q, h))


def channel(e: np.ndarray, valid: np.ndarray, lags: int = LAGS) -> dict[str, Any]:
    """The whiteness of one residual series: `acf (lags + 1,)`, `outside_99` (share of lags
    outside the 99 % band), `q`, `p` (`portmanteau`; NaN where fewer than `MIN_FRAMES_PER_LAG lags`
    frames are measured) and `frames` (measured)."""
    w = np.asarray(valid, bool) & np.isfinite(e)
    n = int(w.sum())
    r = autocorrelation(e, w, lags)
    band = Z99 / math.sqrt(max(n, 1))
    q, p = portmanteau(r, _pairs(w, lags)) if n >= MIN_FRAMES_PER_LAG * lags else (math.nan, math.nan)
    return {"acf": r, "outside_99": float(np.mean(np.abs(r[1:]) > band)), "q": q, "p": p, "frames": n, "band": band}


def rejects(p_values: Sequence[float], alpha: float = ALPHA) -> tuple[np.ndarray, float]:
    """Which of the p-values reject whiteness, at `alpha` over all of them together
    (Bonferroni): `(rejected (n,), the threshold per test)`. NaN p-values (series too short)
    reject nothing and are not counted."""
    p = np.asarray(p_values, float)
    tested = np.isfinite(p)
    cut = alpha / max(int(tested.sum()), 1)
    return tested & (p < cut), cut
