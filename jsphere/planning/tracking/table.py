"""`track.csv`, the gains as a table a robot's controller runs (`Tracker.table`, `Tracker.to_csv`;
`Tracker.to_json` writes `track.json` beside it), and its reader.

Columns (binding; SI units): `t`; feed-forward torques `K_1..K_N` [N m]; the reference state
`x, y` [m], `qw, qx, qy, qz` (the platform's attitude, platform -> fixed components, as a trial
CSV), `omega_1..3`, `Omega_1..3` [1/s] (platform components, as `State`); gains `G_i_j` [N m per
unit of error component j] for wheel `i = 1..N` and error component `j = 1..11` of
`e = (x - x_r, y - y_r, a_1, a_2, a_3, omega - omega_r, Omega - Omega_r)`, `a` the rotation
vector of `R_r^T R`. Command: `K = K_ff - G e`, held from a row's `t` to the next row's; after
the last row, that row is held.
"""

from __future__ import annotations

import numpy as np

from ..._runtime.errors import InputError
from ...model.state import ERROR_SIZE, Flat

#: the reference state's columns and where they are in the flat state (`Flat`)
STATE_COLUMNS = (
    *zip(("x", "y", "qw", "qx", "qy", "qz"), (Flat.x, Flat.y, 0, 1, 2, 3)),
    *((f"omega_{i + 1}", 8 + i) for i in range(3)),
    *((f"Omega_{i + 1}", 11 + i) for i in range(3)),
)


def column_names(n_wheels: int) -> list[str]:
    """The header of `track.csv` for `n_wheels` wheels."""
    return (
        ["t"]
        + [f"K_{i + 1}" for i in range(n_wheels)]
        + [name for name, _ in STATE_COLUMNS]
        + [f"G_{i + 1}_{j + 1}" for i in range(n_wheels) for j in range(ERROR_SIZE)]
    )


def read_track_csv(path) -> dict[str, np.ndarray]:
    """Read `track.csv`: `{"t" (M,), "K_ff" (M, N), "x", "y", "q" (M, 4), "omega" (M, 3),
    "Omega" (M, 3), "G" (M, N, 11)}`. A missing column, a cell that is not a finite number or
    times that do not increase raise `InputError` naming the file."""
    try:
        with open(path) as f:
            header = f.readline().strip().split(",")
        data = np.loadtxt(path, delimiter=",", skiprows=1, ndmin=2)
    except FileNotFoundError:
        raise InputError(f"{path}: no such track table.") from None
    except ValueError as e:
        raise InputError(f"{path}: not a table of numbers: {e}") from None
    N = sum(1 for h in header if h.startswith("K_"))
    want = column_names(N)
    if N < 1 or header != want:
        missing = [c for c in want if c not in header]
        raise InputError(
            f"{path}: not a track table (jsphere track --out): expected the columns t, K_1..K_N, x, y, qw..qz, "
            f"omega_1..3, Omega_1..3, G_i_j" + (f"; missing {missing[:4]}" if missing else "; in that order") + "."
        )
    if data.shape[1] != len(header) or not np.all(np.isfinite(data)):
        raise InputError(f"{path}: every row must have {len(header)} finite numbers.")
    t = data[:, 0]
    if len(t) < 1 or np.any(np.diff(t) <= 0):
        raise InputError(f"{path}: the times t must increase from row to row.")
    c = {h: data[:, k] for k, h in enumerate(header)}
    return {
        "t": t,
        "K_ff": np.stack([c[f"K_{i + 1}"] for i in range(N)], axis=1),
        "x": c["x"],
        "y": c["y"],
        "q": np.stack([c[k] for k in ("qw", "qx", "qy", "qz")], axis=1),
        "omega": np.stack([c[f"omega_{k}"] for k in (1, 2, 3)], axis=1),
        "Omega": np.stack([c[f"Omega_{k}"] for k in (1, 2, 3)], axis=1),
        "G": np.stack([[c[f"G_{i + 1}_{j + 1}"] for j in range(ERROR_SIZE)] for i in range(N)], axis=0).transpose(
            2, 0, 1
        ),
    }
