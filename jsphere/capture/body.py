"""The body frame of a marker set: marker coordinates read from a file (`read_body_markers`),
matched to an export's marker names, or estimated from the first complete frame."""

from __future__ import annotations

import numpy as np

from .._runtime.errors import InputError
from .text import _parse_cell, _read_lines, separator_hint
from .units import BODY_UNITS, detect_marker_units, resolve_units, units_in_force
from .validation import warn


def read_body_markers(path, *, units: str = "auto") -> dict[str, np.ndarray]:
    """Read marker coordinates in the platform frame: a CSV with columns `name, x, y, z` (`#`
    lines are comments; a comment `# units: mm` declares millimetres). Returns `{name: (3,)
    array}` in metres for `markers_to_trial`.

    `units`: `"auto"` (the `# units:` line, else detected), `"m"` or `"mm"`. Detected from the
    largest distance of a marker from their centroid: 5 mm-1 m on a robot of this kind, so
    5-1000 means millimetres (converted, with a `CaptureWarning` saying so); anything else, or
    a declaration that contradicts the numbers, is an `InputError`.
    """
    if units not in BODY_UNITS.choices:
        raise InputError(BODY_UNITS.bad_declared.format(declared=units))
    path, rows = _read_lines(path)
    source = str(path)
    file_units = None
    for r in rows:
        if r and r[0].lstrip().startswith("#"):
            key, _, value = ",".join(r).lstrip("# ").partition(":")
            if key.strip().lower() == "units":
                file_units = units_in_force("auto", value.strip().strip(",").strip(), source, BODY_UNITS)
    units = units_in_force(units, file_units, source, BODY_UNITS)
    rows = [
        (i + 1, r) for i, r in enumerate(rows) if r and any(c.strip() for c in r) and not r[0].lstrip().startswith("#")
    ]
    if not rows or [c.strip() for c in rows[0][1]] != ["name", "x", "y", "z"]:
        raise ValueError(
            f"{source}: the first line must be the header 'name,x,y,z' (marker coordinates in the platform frame, m)"
            f"{separator_hint(rows[0][1]) if rows else ''}."
        )
    out = {}
    for line, r in rows[1:]:
        if len(r) != 4:
            raise ValueError(f"{source}, line {line}: expected 4 cells (name, x, y, z); got {len(r)}.")
        xyz = np.array([_parse_cell(c, source, line, k) for c, k in zip(r[1:], "xyz")])
        if not np.all(np.isfinite(xyz)):
            raise ValueError(f"{source}, line {line}: marker {r[0].strip()!r} has a blank coordinate.")
        if r[0].strip() in out:
            raise InputError(
                f"{source}, line {line}: marker {r[0].strip()!r} is listed twice; keep one row per marker."
            )
        out[r[0].strip()] = xyz
    if len(out) < 3:
        raise ValueError(f"{source}: {len(out)} marker(s); a pose needs at least 3.")
    b = np.stack(list(out.values()))
    spread = float(np.max(np.linalg.norm(b - b.mean(0), axis=1)))
    detected = detect_marker_units(b[None])
    scale = resolve_units(units, None, detected, source, BODY_UNITS, f"{spread:.4g}")
    if units == "auto" and detected == "mm":
        warn(
            f"{source}: the marker coordinates look like millimetres (the markers lie up to {spread:.4g} from their "
            "centroid; metres would make the robot metres wide): read as mm. Add a line '# units: mm' to the file "
            "to say so, or give metres.",
            stacklevel=2,
        )
    return {k: v * scale for k, v in out.items()}


def _match_body_markers(body: dict, names: tuple[str, ...], source: str) -> np.ndarray:
    """Rows of `body` in the order of `names` (full name, or the part after `Subject:`); NaN rows
    for markers that `body` does not list (they are then left out of the fit)."""
    out = np.full((len(names), 3), np.nan)
    for k, n in enumerate(names):
        for key in (n, n.split(":", 1)[-1]):
            if key in body:
                out[k] = np.asarray(body[key], float)
                break
    if np.sum(np.all(np.isfinite(out), axis=1)) < 3:
        raise ValueError(
            f"{source}: fewer than 3 of the export's markers {list(names)} are among the body markers {sorted(body)}; "
            "name them as in the export (with or without the 'Subject:' prefix)."
        )
    return out


def estimate_body_markers(markers: np.ndarray, source: str = "markers") -> tuple[np.ndarray, int]:
    """Body-frame marker coordinates from the first frame where every marker is seen: the
    positions minus their centroid, in the fixed axes of that frame. Returns `(body, frame)`."""
    full = np.nonzero(np.all(np.isfinite(markers), axis=(1, 2)))[0]
    if full.size == 0:
        raise ValueError(
            f"{source}: no frame shows all {markers.shape[1]} markers, so the body cannot be estimated; "
            "give --body-markers FILE (their coordinates in the platform frame) or drop a marker that is never seen."
        )
    k = int(full[0])
    return markers[k] - markers[k].mean(0), k
