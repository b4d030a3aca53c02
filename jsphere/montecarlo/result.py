"""The outcome of a Monte-Carlo study (`MonteCarloResult`) and its statistics."""

from __future__ import annotations

import dataclasses
import math
from typing import ClassVar

import numpy as np

from ..solve.status import RESULTS
from .sampling import REASONS

#: `MonteCarloResult.status` of a successful solve, and of a draw that breaks a rule of
#: `RobotParams` (not simulated; `reject_code` says which rule). Solver outcomes are >= 0.
SUCCESS, REJECTED = RESULTS.successful, RESULTS.rejected


def outcome_masks(status) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """`(ok, failed, rejected)`: the trials whose solve succeeded, whose solve failed, and whose
    draw was rejected (not simulated), from their `status`."""
    ok, rejected = np.asarray(status) == SUCCESS, np.asarray(status) == REJECTED
    return ok, ~ok & ~rejected, rejected


@dataclasses.dataclass(frozen=True)
class ComputeTime:
    """The computation of a study's batches as their time records tell it (`store.TIME_KEYS`):
    `batches` of the study, `recorded` of them with a record, `sum_s`: the sum of their compute
    times [s] (a process's first batch includes its compilation), `span_s`: from the first
    one's start to the last one's end [s], `processes`: how many processes computed them."""

    batches: int
    recorded: int
    sum_s: float
    span_s: float
    processes: int

    @classmethod
    def of(cls, records) -> "ComputeTime":
        """The `ComputeTime` of the time records of a study's batches (None for a batch with none)."""
        got = [r for r in records if r is not None]
        span = max(r["end_unix_s"] for r in got) - min(r["start_unix_s"] for r in got) if got else 0.0
        processes = len({(r["host"], r["pid"]) for r in got})
        return cls(len(records), len(got), float(sum(r["compute_s"] for r in got)), float(span), processes)


@dataclasses.dataclass
class MonteCarloResult:
    """Per-trial outcomes of `monte_carlo` (NumPy arrays of length `n`).

    `samples[name]`: the drawn values; `x_final, y_final` [m]: stop point; `speed_final` [m/s]:
    speed of the shell centre at the end; `status`: the `RESULTS` code of each trial:
    `successful` (0), a solver failure (`max_steps_reached` 1, `nonfinite` 2), or `rejected`
    (-1, `REJECTED`) for a draw that breaks a rule of `RobotParams` (not simulated; outcomes
    NaN); `results`: the same as `RESULTS` members; `gamma3_sd_after`: standard deviation of
    `gamma_3` over the settling time after the commands end (replay modes; the paper's sigma
    of Fig. 2; 0 in gait mode); `reject_code`: 0 for a valid draw, else the index in `REASONS`
    of the rule it breaks. `elapsed_s`: the wall time of the call that returned the result (0
    for `store.read_result`); `compute_time`: with a study folder, its batches' `ComputeTime`;
    `trials`: the index of each trial in its study where they are not `0 .. n - 1` (a study
    folder read before every batch is there, `store.read_result`), else None.
    """

    REJECTED: ClassVar[int] = REJECTED
    REASONS: ClassVar[tuple[str, ...]] = REASONS

    n: int
    seed: int
    samples: dict[str, np.ndarray]
    x_final: np.ndarray
    y_final: np.ndarray
    speed_final: np.ndarray
    status: np.ndarray
    gamma3_sd_after: np.ndarray
    elapsed_s: float = 0.0
    reject_code: np.ndarray | None = None
    compute_time: ComputeTime | None = None
    trials: np.ndarray | None = None

    @classmethod
    def of_batches(cls, parts: list[dict], names, n: int, seed: int, **more) -> "MonteCarloResult":
        """The result of a study's batches `parts` (arrays by `store.BATCH_KEYS`) joined and cut to
        `n` trials, `names` the varied names of their `vals` columns; `more`: the other fields."""
        cat = {key: np.concatenate([p[key] for p in parts])[:n] for key in parts[0]}
        return cls(
            n=n,
            seed=seed,
            samples={name: cat["vals"][:, j] for j, name in enumerate(names)},
            x_final=cat["x"],
            y_final=cat["y"],
            speed_final=cat["speed"],
            status=cat["status"],
            gamma3_sd_after=cat["gamma3_sd"],
            reject_code=cat["reject"],
            **more,
        )

    @property
    def results(self) -> np.ndarray:
        """`status` as `RESULTS` members (an object array of length `n`)."""
        return np.array([RESULTS(int(c)) for c in np.asarray(self.status)], object)

    def outcomes(self) -> dict[str, int]:
        """`{RESULTS name: number of trials}` of the outcomes that occur, by code."""
        codes, counts = np.unique(np.asarray(self.status), return_counts=True)
        return {RESULTS(int(c)).name: int(k) for c, k in zip(codes, counts)}

    def rejections(self) -> dict[str, int]:
        """`{reason: number of draws}` of the rejected draws, most frequent first."""
        codes = np.zeros(self.n, np.int64) if self.reject_code is None else np.asarray(self.reject_code)
        counts = np.bincount(codes[codes > 0], minlength=len(REASONS))
        order = sorted(np.flatnonzero(counts), key=lambda c: (-counts[c], c))
        return {REASONS[c]: int(counts[c]) for c in order}

    def stats(self, level: float = 0.95) -> dict:
        """Stop-point mean, covariance, the `level` confidence ellipse and quantiles (successful
        trials only), with the counts of successful trials (`n_ok`), solver failures
        (`n_failed`, and `failed_status`: per status code), rejected draws (`n_rejected`, and
        `rejected`: per broken rule) and every outcome by its `RESULTS` name (`outcomes`)."""
        status = np.asarray(self.status)
        ok, failed, rejected = outcome_masks(status)
        codes, counts = np.unique(status[failed], return_counts=True)
        head = {
            "n": int(self.n),
            "n_ok": int(ok.sum()),
            "n_failed": int(failed.sum()),
            "failed_status": {str(int(c)): int(k) for c, k in zip(codes, counts)},
            "n_rejected": int(rejected.sum()),
            "rejected": self.rejections(),
            "outcomes": self.outcomes(),
        }
        if not ok.any():
            return head
        return {**head, **self._stop_statistics(ok, level)}

    def _stop_statistics(self, ok: np.ndarray, level: float) -> dict:
        """The statistics of the successful trials `ok`: stop points, speeds and tilt."""
        xy = np.stack([self.x_final[ok], self.y_final[ok]], axis=1)
        mean = xy.mean(axis=0)
        cov = np.cov(xy, rowvar=False) if len(xy) > 1 else np.zeros((2, 2))
        evals, evecs = np.linalg.eigh(cov)
        s = -2.0 * math.log(1.0 - level)  # chi-squared quantile with 2 degrees of freedom
        q, d, g = [0.025, 0.5, 0.975], np.hypot(*xy.T), self.gamma3_sd_after[ok]
        return {
            "mean_xy_m": mean.tolist(),
            "cov_xy_m2": cov.tolist(),
            "sd_xy_m": np.sqrt(np.diag(cov)).tolist(),
            "ellipse": {
                "level": level,
                "semi_axes_m": np.sqrt(np.maximum(evals, 0) * s).tolist(),
                "angle_rad": float(math.atan2(evecs[1, -1], evecs[0, -1])),
            },
            "quantiles": {"q": q, "x_m": np.quantile(xy[:, 0], q).tolist(), "y_m": np.quantile(xy[:, 1], q).tolist()},
            "distance_m": {"mean": float(d.mean()), "sd": float(d.std(ddof=1)) if len(d) > 1 else 0.0},
            "speed_final_m_s": {"mean": float(self.speed_final[ok].mean()), "max": float(self.speed_final[ok].max())},
            "gamma3_sd_after": {"mean": float(g.mean()), "q": q, "quantiles": np.quantile(g, q).tolist()},
        }
