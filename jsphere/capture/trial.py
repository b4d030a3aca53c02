"""The trial: `Trial`, a capture's poses with the inputs that drove them (its docstring gives
the conventions), and its CSV format (`read_trial`, `write_trial`; `docs/capture.md`)."""

from __future__ import annotations

import dataclasses
from collections.abc import Iterable
from pathlib import Path
from typing import TYPE_CHECKING

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from .._runtime.errors import InputError
from .._runtime.files import atomic_write_text
from ..controls import Torques, WheelSpeeds
from ..model.params import RobotParams
from ..model.state import State
from .text import _input_columns, _numbers, cells, check_unique_columns, headed_rows, separator_hint
from .units import TRIAL_UNITS, detect_position_units, resolve_units

if TYPE_CHECKING:
    from .onboard import OnboardTrial
from .validation import POSE_COLUMNS, _checked, warn_implausible, wheel_columns
from .validation import CaptureWarning as CaptureWarning  # (the warning of every trial reader)


class Trial(eqx.Module):
    """One captured (or synthetic) trial: poses, inputs and times, as numpy arrays. Frames whose
    pose is missing (a blank cell, `nan`) are *gaps*; times and inputs are never missing.

    **Fields:**
    - `t`: `(M,)` times [s], strictly increasing.
    - `x`, `y`: `(M,)` shell-centre position in the fixed frame (Z up) [m]; NaN in gap frames.
    - `q`: `(M, 4)` unit quaternion `(w, x, y, z)` of the platform, rotating platform components
      into fixed ones (as `jsphere.State.q`: its rotation matrix has rows `alpha, beta, gamma`),
      sign-continuous; NaN rows are gaps.
    - `inputs`: `(M, N)` wheel speeds `chi_dot_i` [rad/s] or axle torques `K_i` [N m]; never NaN.
    - `kind`: `"wheel_speeds"` or `"torques"` (static).
    - `z`: `(M,)` shell-centre height [m] or `None`.
    - `name`: a label (the file stem for trials read from files) (static).
    - `source`: the file the trial was read from (`read_trial`), or None (static): the fit names
      a trial's frames set aside by its file name (`FitResult.outliers`).

    A frame missing any pose value is a gap: all its pose values are NaN. Construction
    validates (strictly increasing finite times, finite inputs, unit quaternions: a norm off by
    more than 1e-3 is an error, smaller deviations are normalised) but does not require a
    minimum length; the file readers do (`MIN_VALID_FRAMES`, `MIN_DURATION`).
    """

    t: np.ndarray
    x: np.ndarray
    y: np.ndarray
    q: np.ndarray
    inputs: np.ndarray
    kind: str = eqx.field(static=True)
    z: np.ndarray | None = None
    name: str = eqx.field(static=True, default="trial")
    source: str | None = eqx.field(static=True, default=None)

    def __init__(self, t, x, y, q, inputs, kind: str, z=None, name: str = "trial", source: str | None = None):
        t, x, y, q, inputs, z = _checked(t, x, y, q, inputs, kind, z, source=f"trial {name!r}", check_length=False)
        self.t, self.x, self.y, self.q, self.inputs, self.kind, self.z, self.name = t, x, y, q, inputs, kind, z, name
        self.source = None if source is None else str(source)

    @property
    def n_wheels(self) -> int:
        return int(self.inputs.shape[1])

    @property
    def n_frames(self) -> int:
        return int(self.t.shape[0])

    @property
    def duration(self) -> float:
        """`t[-1] - t[0]` [s]."""
        return float(self.t[-1] - self.t[0])

    @property
    def valid(self) -> np.ndarray:
        """`(M,)` bool: True where the frame has a pose (not a gap)."""
        ok = np.isfinite(self.x) & np.isfinite(self.y) & np.all(np.isfinite(self.q), axis=1)
        if self.z is not None:
            ok &= np.isfinite(self.z)
        return ok

    @property
    def input_names(self) -> list[str]:
        """`["chi_dot_1", ...]` or `["K_1", ...]`."""
        return wheel_columns(self.kind, self.n_wheels)

    def controls(self, kind: str = "cubic") -> WheelSpeeds | Torques:
        """The recorded inputs as a control: `WheelSpeeds` or `Torques`, `.from_samples(t,
        inputs, kind=kind)` (cubic Hermite by default; held constant outside `[t0, t1]`)."""
        cls = WheelSpeeds if self.kind == "wheel_speeds" else Torques
        return cls.from_samples(jnp.asarray(self.t), jnp.asarray(self.inputs), kind=kind)

    def state0_guess(self, params: RobotParams) -> State:
        """A `State` for `t[0]`: orientation and position of the first valid frame (even if it is
        later than `t[0]`), shell frame aligned with the fixed frame, velocities and wheel angles
        zero. Good for trials that start at rest."""
        k = np.nonzero(self.valid)[0]
        if k.size == 0:
            raise ValueError(f"trial {self.name!r}: no valid frame, so no initial pose.")
        k = int(k[0])
        dt = params.R0.dtype
        z3 = jnp.zeros(3, dt)
        return State(
            q=jnp.asarray(self.q[k], dt),
            q_shell=jnp.array([1.0, 0.0, 0.0, 0.0], dt),
            omega=z3,
            Omega=z3,
            x=jnp.asarray(self.x[k], dt),
            y=jnp.asarray(self.y[k], dt),
            chi=jnp.zeros(params.n_wheels, dt),
        )

    def replace(self, **changes) -> Trial:
        """A copy with some fields changed (validated again)."""
        return dataclasses.replace(self, **changes)

    def __repr__(self) -> str:
        return (
            f"Trial(name={self.name!r}, kind={self.kind!r}, frames={self.n_frames}, valid={int(self.valid.sum())}, "
            f"wheels={self.n_wheels}, duration={self.duration:.3f} s)"
        )


def read_trial(path, *, units: str = "auto", max_gap_fraction: float = 0.5) -> Trial | OnboardTrial:
    """Read one trial CSV (format: `docs/capture.md`): `#` lines before the header are comments
    (`# units: mm` declares the units of `x, y, z`), then columns `t, x, y, qw, qx, qy, qz`,
    `chi_dot_1..N` or `K_1..N`, optionally `z`; other columns are ignored; blank or `nan` pose
    cells make the frame a gap. A file with an onboard-sensor trial's columns (`gyro_x`, ..., no
    pose) is returned as an `OnboardTrial` (`read_onboard_trial`).

    `units`: `"auto"` (the `# units:` line, else detected, else metres), `"m"` or `"mm"`; one
    that contradicts the file's line or the detected units is an error. `max_gap_fraction`: the
    largest fraction of gap frames accepted.

    Raises `ValueError` naming the file, the line (1-based) and the column of the first problem:
    missing or misnumbered columns, blank times or inputs, times not increasing, non-unit
    quaternions, a trial under 10 valid frames or 0.2 s, too many gaps, wrong units.
    """
    path = Path(path)
    source, meta, rows, k = headed_rows(
        path, "the first non-comment line must name the columns t, x, y, qw, qx, qy, qz, ..."
    )
    header, at = [h.strip() for h in rows[k]], f"{source}, line {k + 1}"
    missing = [c for c in POSE_COLUMNS if c not in header]
    if missing and "gyro_x" in header:  # the robot's own sensors
        from .onboard import read_onboard_trial

        return read_onboard_trial(path)
    if missing:
        raise ValueError(
            f"{at}: missing required column(s) {', '.join(missing)}; a trial CSV needs {', '.join(POSE_COLUMNS)} and "
            f"chi_dot_1..N or K_1..N (see docs/capture.md){separator_hint(rows[k])}."
        )
    kind, in_cols = _input_columns(header, at)
    names = [*POSE_COLUMNS, *(["z"] if "z" in header else []), *(header[j] for j in in_cols)]
    check_unique_columns(header, at, [*names, "z"])
    data, lines = _numbers(rows, k + 1, [header.index(c) for c in names], source, names, width=len(header))
    if data.shape[0] == 0:
        raise ValueError(f"{source}: the trial is too short: no data rows after the header.")
    zcol = data[:, 7] if "z" in header else None
    evidence = "positions/height" if "units" in meta else "magnitude of the positions/height"
    detected = detect_position_units(data[:, 1:3], zcol)
    scale = resolve_units(units, meta.get("units"), detected, source, TRIAL_UNITS, evidence)
    z = None if zcol is None else zcol * scale
    t, x, y, q, inputs, z = _checked(
        data[:, 0],
        data[:, 1] * scale,
        data[:, 2] * scale,
        data[:, 3:7],
        data[:, 7 + (zcol is not None) :],
        kind,
        z,
        source=source,
        lines=lines,
        input_names=names[7 + (zcol is not None) :],
        max_gap_fraction=max_gap_fraction,
    )
    warn_implausible(t, x, y, q, source, z, units_hint="declare '# units: mm' in the file")
    return Trial(t, x, y, q, inputs, kind, z, name=meta.get("name", path.stem), source=source)


def read_trials(paths: Iterable, **kwargs) -> list[Trial | OnboardTrial]:
    """`read_trial` on each path (a directory stands for its `*.csv` files, sorted; hidden
    files, such as a temporary file a killed writer left, are skipped). A directory without
    such files is an `InputError` naming it."""
    out = []
    for p in paths:
        p = Path(p)
        if p.is_dir():
            files = [f for f in sorted(p.glob("*.csv")) if not f.name.startswith(".")]
            if not files:
                raise InputError(
                    f"{p} holds no trial CSV files (*.csv); give the folder of the trials or the files themselves."
                )
            out += [read_trial(f, **kwargs) for f in files]
        else:
            out.append(read_trial(p, **kwargs))
    return out


def trial_to_csv(trial: Trial) -> str:
    """The text of `write_trial`: times to 1 µs, positions to 1 µm, quaternions to 1e-9,
    inputs to 10 significant digits; gaps as blank cells."""
    cols = list(POSE_COLUMNS) + (["z"] if trial.z is not None else []) + trial.input_names
    out = [
        "# jsphere trial v1",
        f"# name: {trial.name}",
        f"# kind: {trial.kind}",
        "# units: m",
        ",".join(cols),
    ]
    z = [] if trial.z is None else [trial.z[:, None]]
    data = np.concatenate([np.stack([trial.t, trial.x, trial.y], 1), trial.q, *z, trial.inputs], axis=1)
    out += cells(data, [".6f"] * 3 + [".9f"] * 4 + [".6f"] * len(z) + [".10g"] * trial.n_wheels)
    return "\n".join(out) + "\n"


def write_trial(path, trial: Trial) -> None:
    """Write `trial` to `path` in the trial CSV format (atomically; see `trial_to_csv`)."""
    if not isinstance(trial, Trial):
        raise TypeError(f"write_trial: expected a jsphere.Trial; got {type(trial).__name__}.")
    atomic_write_text(path, trial_to_csv(trial))
