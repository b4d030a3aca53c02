"""The trial: `Trial` and its CSV format (`read_trial`, `write_trial`).

A *trial* is what a motion-capture session records about the robot plus the inputs that drove
it: times `t` [s], the shell-centre position `x, y` (optionally `z`) [m] in the fixed frame
(Z up), the platform orientation as a unit quaternion `(w, x, y, z)` rotating platform
components into fixed ones (the convention of `jsphere.State.q`; its rotation matrix has rows
`alpha, beta, gamma`), and per wheel either the commanded/encoder wheel speeds `chi_dot_i`
[rad/s] or the axle torques `K_i` [N m]. `docs/capture.md` describes the file format.

Frames where the pose is missing (a blank cell, `nan`) are *gaps*: their `x, y, q` (and `z`)
are NaN and `Trial.valid` is False there. Times and inputs are never missing.
"""

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
from .validation import INPUT_PREFIX, POSE_COLUMNS, _checked, warn_implausible
from .validation import CaptureWarning as CaptureWarning  # (the warning of every trial reader)

# --------------------------------------------------------------------------- Trial


class Trial(eqx.Module):
    """One captured (or synthetic) trial: poses, inputs and times, as numpy arrays.

    **Fields:**
    - `t`: `(M,)` times [s], strictly increasing.
    - `x`, `y`: `(M,)` shell-centre position in the fixed frame (Z up) [m]; NaN in gap frames.
    - `q`: `(M, 4)` unit quaternion `(w, x, y, z)` of the platform, rotating platform components
      into fixed ones (as `jsphere.State.q`), sign-continuous; NaN rows are gaps.
    - `inputs`: `(M, N)` wheel speeds `chi_dot_i` [rad/s] or axle torques `K_i` [N m]; never NaN.
    - `kind`: `"wheel_speeds"` or `"torques"` (static).
    - `z`: `(M,)` shell-centre height [m] or `None`.
    - `name`: a label (the file stem for trials read from files) (static).
    - `source`: the file the trial was read from (`read_trial`), or None (static): the fit names
      a trial's frames set aside by its file name (`FitResult.outliers`).

    A frame is a gap if any of its pose values is missing; then all its pose values are NaN.
    Construction validates (strictly increasing finite times, finite inputs, unit quaternions:
    a norm off by more than 1e-3 is an error, smaller deviations are normalised) but does not
    require a minimum length; the file readers do (`MIN_VALID_FRAMES`, `MIN_DURATION`).
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

    # -------------------------------------------------------------- views
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
        return [f"{INPUT_PREFIX[self.kind]}{i + 1}" for i in range(self.n_wheels)]

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


# --------------------------------------------------------------------------- CSV format


def read_trial(path, *, units: str = "auto", max_gap_fraction: float = 0.5) -> Trial | OnboardTrial:
    """Read one trial CSV (format: `docs/capture.md`).

    A file with the columns of an onboard-sensor trial (`gyro_x`, ..., no pose) is read by
    `read_onboard_trial` and returned as an `OnboardTrial`.

    Lines starting with `#` before the header are comments; `# units: mm` declares the
    position units (`x, y, z`; default metres). Columns `t, x, y, qw, qx, qy, qz` are required,
    then `chi_dot_1..chi_dot_N` or `K_1..K_N`, optionally `z`; other columns are ignored.
    Blank or `nan` pose cells make the frame a gap.

    **Arguments:**
    - `units`: `"auto"` (the file's `# units:` line, else detected, else metres), `"m"` or
      `"mm"`. A declared unit that contradicts the file's `# units:` line or the detected one
      is an error.
    - `max_gap_fraction`: the largest fraction of gap frames accepted.

    Raises `ValueError` naming the file, the line (1-based, as an editor counts) and the column
    of the first problem: missing columns, mixed or misnumbered input columns, blank/NaN times
    or inputs, non-increasing or duplicated times, non-unit quaternions, too-short trials (fewer
    than 10 valid frames or under 0.2 s), too many gaps, wrong units.
    """
    path = Path(path)
    source, meta, rows, header_line = headed_rows(path, "t, x, y, qw, qx, qy, qz, ...")
    header = [h.strip() for h in rows[0]]
    missing = [c for c in POSE_COLUMNS if c not in header]
    if missing and "gyro_x" in header:  # the robot's own sensors
        from .onboard import read_onboard_trial

        return read_onboard_trial(path)
    if missing:
        raise ValueError(
            f"{source}, line {header_line}: missing required column(s) {', '.join(missing)}; a trial CSV needs "
            f"{', '.join(POSE_COLUMNS)} and chi_dot_1..N or K_1..N (see docs/capture.md){separator_hint(rows[0])}."
        )
    kind, in_cols = _input_columns(header, f"{source}, line {header_line}")
    check_unique_columns(header, f"{source}, line {header_line}", [*POSE_COLUMNS, "z", *(header[j] for j in in_cols)])
    has_z = "z" in header
    data, line_no = _table(rows, header, in_cols, header_line, source)
    zcol = data[:, 7] if has_z else None
    evidence = "positions/height" if "units" in meta else "magnitude of the positions/height"
    detected = detect_position_units(data[:, 1:3], zcol)
    scale = resolve_units(units, meta.get("units"), detected, source, TRIAL_UNITS, evidence)
    x, y = data[:, 1] * scale, data[:, 2] * scale
    z = zcol * scale if has_z else None
    t, x, y, q, inputs, z = _checked(
        data[:, 0],
        x,
        y,
        data[:, 3:7],
        data[:, 8 if has_z else 7 :],
        kind,
        z,
        source=source,
        lines=line_no,
        input_names=[header[j] for j in in_cols],
        max_gap_fraction=max_gap_fraction,
    )
    name = meta.get("name", path.stem)
    warn_implausible(t, x, y, q, source, z, units_hint="declare '# units: mm' in the file")
    return Trial(t, x, y, q, inputs, kind, z, name=name, source=source)


def _table(rows, header: list[str], in_cols: list[int], header_line: int, source: str):
    """The pose columns, `z` where present, and the inputs of every data row as floats (blank:
    NaN), and the rows' 1-based lines."""
    col = {h: j for j, h in enumerate(header)}
    extra = ["z"] if "z" in col else []
    names = [*POSE_COLUMNS, *extra, *(header[j] for j in in_cols)]
    use = [col[c] for c in POSE_COLUMNS + tuple(extra)] + in_cols
    data, line_no = _numbers(rows, 1, use, source, names, width=len(header), line0=header_line - 1)
    if data.shape[0] == 0:
        raise ValueError(f"{source}: the trial is too short: no data rows after the header.")
    return data, line_no


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
