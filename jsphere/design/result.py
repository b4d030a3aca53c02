"""What a design returns (`DesignResult`) and its files: one inputs table per trial and a JSON
document beside them.

File names: with one trial the table is `--out` itself (`design.csv`); with M > 1 trials it is
`<stem>_<k><suffix>` for `k = 1..M` (`design_1.csv`, `design_2.csv`). The JSON document is
`<stem>.json` (`design.json`) beside `--out`.
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path
from typing import Any

import numpy as np

from .._runtime.files import atomic_write_json
from ..capture.inputs import write_inputs_csv
from .inputs import KINDS

#: what the printed criterion is (`criterion`, `Phi` of `jsphere.design.information`)
CRITERION = "log det of the information matrix (D-optimal criterion, larger is better)"


def table_paths(out, trials: int) -> list[Path]:
    """The inputs tables of a design written to `out` (module docstring)."""
    out = Path(out)
    if trials == 1:
        return [out]
    return [out.with_name(f"{out.stem}_{k + 1}{out.suffix}") for k in range(trials)]


def json_path(out) -> Path:
    """The JSON document of a design written to `out`: `<stem>.json` beside it."""
    return Path(out).with_suffix(".json")


@dataclasses.dataclass
class DesignResult:
    """What `design_excitation` returns.

    - `kind`: `"K"` (torques) or `"chi_dot"` (wheel speeds); `free`: the free names (expanded);
      `values`: their values at the design's parameters.
    - `tables`: per trial `(t (R,), u (R, N))`, the design's inputs tables (`rate` rows per
      second); `baseline_tables`: the random multisines of the same RMS amplitude.
    - `criterion`: `{"design": .., "baseline": ..}`, the D-optimal criterion `log det(S F_v S)`
      of the fit's information at the capture rate (`jsphere.design.information`);
      `criterion_model`: the same on the optimisation's model grid.
    - `stderr_predicted`, `stderr_predicted_baseline`: per free name, the standard error a fit of
      the design's (the baseline's) trials would report, in physical units.
    - `rms`: the RMS amplitude of both (the baseline's is the design's unless that breaks a limit
      the design keeps); `limits`, `limits_baseline`: per limit the largest value, the limit and
      whether it is kept, with the wheel rates and the tilt of the accurate solver's run of the
      tables at the capture rate; `limits_model`: the design's on the search's RK4 model;
      `baseline_equal_rms`: where the baseline had to be scaled below the
      design's RMS amplitude to keep a limit, the multisine at the design's RMS for reference
      (its criterion, predicted standard errors and limits), else None; `restarts`: per restart
      the search's objective (`Phi - 1000 x penalty` on the model grid, maximised:
      `jsphere.design.optimise`) at its start (`start`) and at its best point (`final`), that
      point's limit penalty (`penalty`, without the weight) and its criterion `Phi`
      (`criterion`); `settings`: the sizes, noise levels, rates and seed; `elapsed_s`.
    """

    kind: str
    free: list[str]
    values: dict[str, float]
    duration: float
    rate: float
    tables: list[tuple[np.ndarray, np.ndarray]]
    baseline_tables: list[tuple[np.ndarray, np.ndarray]]
    criterion: dict[str, float]
    criterion_model: dict[str, float]
    stderr_predicted: dict[str, float]
    stderr_predicted_baseline: dict[str, float]
    rms: dict[str, float]
    limits: dict[str, dict[str, Any]]
    limits_baseline: dict[str, dict[str, Any]]
    limits_model: dict[str, dict[str, Any]]
    baseline_equal_rms: dict[str, Any] | None
    restarts: list[dict[str, float]]
    settings: dict[str, Any]
    elapsed_s: float

    @property
    def trial_kind(self) -> str:
        """`"torques"` or `"wheel_speeds"`: the kind of the trials the tables drive."""
        return KINDS[self.kind]

    @property
    def factor(self) -> dict[str, float]:
        """Per free name the ratio of the baseline's predicted standard error to the design's."""
        return {
            n: (self.stderr_predicted_baseline[n] / s if s > 0 else math.inf) for n, s in self.stderr_predicted.items()
        }

    def to_json(self) -> dict[str, Any]:
        """The JSON document (`design.json`): every field but the tables, `duration` and `rate`
        as `duration_s` and `rate_hz`, and `factor`."""
        d = {f.name: getattr(self, f.name) for f in dataclasses.fields(self) if not f.name.endswith("tables")}
        d["duration_s"], d["rate_hz"], d["factor"] = d.pop("duration"), d.pop("rate"), self.factor
        return d

    def save(self, out, *, baseline=None) -> list[Path]:
        """Write the inputs tables and the JSON document (each atomically, names in the module
        docstring), and with `baseline` (a path named as `out`) the baseline's tables; returns
        the paths written."""
        written = []
        for where, tables in ((out, self.tables), (baseline, self.baseline_tables)):
            if where is not None:
                for p, (t, u) in zip(table_paths(where, len(tables)), tables):
                    write_inputs_csv(p, t, u, self.trial_kind)
                    written.append(p)
        atomic_write_json(json_path(out), self.to_json())
        return [*written, json_path(out)]

    def table(self) -> str:
        """Per free name its predicted standard error for the design and the baseline, and their
        ratio; then both criteria."""
        lines = [f"{'name':<10} {'value':>12} {'SE design':>12} {'SE baseline':>12} {'factor':>8}"]
        for n in self.free:
            s, b = self.stderr_predicted[n], self.stderr_predicted_baseline[n]
            lines.append(f"{n:<10} {self.values[n]:>12.6g} {s:>12.3g} {b:>12.3g} {self.factor[n]:>8.2f}")
        c = self.criterion
        lines.append(
            f"{CRITERION}: design {c['design']:.3f}, baseline {c['baseline']:.3f} "
            f"(RMS amplitude {self.rms['design']:.4g} / {self.rms['baseline']:.4g}); {self.elapsed_s:.1f} s"
        )
        bad = [k for k, v in self.limits.items() if not v["ok"]]
        if bad:
            lines.append("limits exceeded (accurate solver): " + ", ".join(bad))
        return "\n".join(lines)
