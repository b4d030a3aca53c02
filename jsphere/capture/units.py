"""Length units of capture files: detected from the numbers (`detect_marker_units`,
`detect_position_units`) and resolved against what the file and the caller declare
(`resolve_units`, one resolver for raw exports, trials and body markers)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .._runtime.errors import InputError

#: metres per unit of the length units a capture file may declare
UNIT_SCALE = {"m": 1.0, "cm": 1e-2, "mm": 1e-3}
_WORDS = {"m": "metres", "cm": "centimetres", "mm": "millimetres"}


def detect_marker_units(markers: np.ndarray) -> str | None:
    """`"m"`, `"mm"` or None from the spread of the markers about their centroid (a marker set on
    a ball of radius 0.1-0.3 m spreads 5 mm to 1 m): median over frames of the largest distance."""
    full = np.all(np.isfinite(markers), axis=(1, 2))
    if not np.any(full) or markers.shape[1] < 2:
        return None
    f = markers[full]
    r = np.median(np.max(np.linalg.norm(f - f.mean(1, keepdims=True), axis=2), axis=1))
    if 0.005 <= r <= 1.0:
        return "m"
    if 5.0 <= r <= 1000.0:
        return "mm"
    return None


def detect_position_units(values: np.ndarray, z: np.ndarray | None = None) -> str | None:
    """Guess whether positions are in metres or millimetres: `"m"`, `"mm"` or `None` (cannot tell).

    A height `z` of the shell centre (its radius, 0.03-1 m) decides if given; otherwise any
    coordinate beyond 20 (a 20 m lab is implausible) means millimetres. Small numbers alone do
    not prove metres (a robot that moved a few mm), so they give `None`.
    """
    if z is not None:
        zz = np.abs(z[np.isfinite(z)])
        if zz.size:
            med = float(np.median(zz))
            if 0.03 <= med <= 1.0:
                return "m"
            if 30.0 <= med <= 1000.0:
                return "mm"
    v = np.abs(np.asarray(values, float))
    v = v[np.isfinite(v)]
    if v.size and float(v.max()) > 20.0:
        return "mm"
    return None


@dataclass(frozen=True)
class UnitRules:
    """What a kind of capture file may declare about its lengths, and the words of its errors.
    The messages are templates of `source`, `declared` (the caller's units), `file` (the file's
    own), `units` (those in force: the file's, else the caller's), `detected`, `words` (the
    detected units in words) and `evidence` (what the detection saw)."""

    choices: tuple[str, ...]
    bad_declared: str
    bad_file: str
    conflict: str
    mismatch: str
    #: where neither the file nor the caller says and the numbers cannot tell; None: metres
    unknown: str | None
    error: type[ValueError] = ValueError
    #: whether a declaration outside `choices` that the file's units contradict is a `conflict`
    #: (rather than a `bad_declared`)
    conflict_first: bool = False


_BAD_FILE = "{source}: the '# units:' line says {file!r}; it must be 'm' or 'mm'."

#: raw exports (Motive, Vicon, QTM, C3D): their own units (a header, a units row), `--units`, the marker spread
EXPORT_UNITS = UnitRules(
    ("auto", "m", "cm", "mm"),
    "{source}: the units (--units) must be auto, m, cm or mm; got {declared!r}.",
    _BAD_FILE,
    "{source}: --units {declared} was given but the file says its lengths are in {file}; drop --units (the file's "
    "units are used) or re-export the file.",
    "{source}: the lengths are declared in {units!r} but the marker spread looks like {words}; pass --units "
    "{detected} if the file is wrong, or check the export scale.",
    "{source}: cannot tell whether lengths are in m or mm; pass --units m or --units mm.",
)
#: trial CSVs: the `# units:` line, `read_trial(units=...)`, the positions' magnitude
TRIAL_UNITS = UnitRules(
    ("auto", "m", "mm"),
    "{source}: the units given must be 'auto', 'm' or 'mm'; got {declared!r}.",
    _BAD_FILE,
    "{source}: the units given ({declared!r}) disagree with the file's '# units:' line ({file!r}); give none (the "
    "file's are used) or fix the file.",
    "{source}: the units given ({units!r}) disagree with the data, which look like {words} ({evidence}); give "
    "{detected!r} (or 'auto') if that is right, or fix the file.",
    None,
    conflict_first=True,
)
#: body-marker CSVs: the `# units:` line, `read_body_markers(units=...)`, the markers' spread
BODY_UNITS = UnitRules(
    ("auto", "m", "mm"),
    "read_body_markers: units must be 'auto', 'm' or 'mm'; got {declared!r}.",
    _BAD_FILE,
    "{source}: the units {declared!r} were declared but the file's '# units:' line says {file!r}.",
    "{source}: the coordinates are declared in {units!r} but the markers lie up to {evidence} from their centroid, "
    "which looks like {words}; fix the numbers or the units.",
    "{source}: the markers lie up to {evidence} from their centroid: neither metres (5 mm-1 m on a robot of this "
    "kind) nor millimetres (5-1000); check the coordinates (platform frame, metres).",
    InputError,
)


def units_in_force(declared: str, file: str | None, source: str, rules: UnitRules) -> str:
    """The units in force: the file's own (`file`), else the `declared` ones (`"auto"` where
    neither says). A declaration outside `rules.choices`, a file's units outside them, or a
    declaration that contradicts the file is a `rules.error`."""
    fields = {"source": source, "declared": declared, "file": file}
    if file is not None and file not in rules.choices:
        raise rules.error(rules.bad_file.format(**fields))
    conflict = file is not None and declared != "auto" and declared != file
    if declared not in rules.choices and not (conflict and rules.conflict_first):
        raise rules.error(rules.bad_declared.format(**fields))
    if conflict:
        raise rules.error(rules.conflict.format(**fields))
    return file if file is not None else declared


def resolve_units(
    declared: str, file: str | None, detected: str | None, source: str, rules: UnitRules, evidence: str = ""
) -> float:
    """Metres per unit of a file's lengths: the file's own units (`file`), else the `declared`
    ones, else the `detected` ones (`units_in_force`). Units that the numbers contradict
    (`detected`) are a `rules.error`, and so are units nobody can tell (unless `rules.unknown`
    is None: metres then). Centimetres come from the file or the declaration only: the spread
    of a marker set in centimetres (0.5-100) looks like metres or millimetres."""
    units = units_in_force(declared, file, source, rules)
    if units == "cm":
        return UNIT_SCALE["cm"]
    fields = {"source": source, "units": units, "detected": detected, "words": _WORDS.get(detected, "")}
    fields["evidence"] = evidence
    if detected is not None and units != "auto" and detected != units:
        raise rules.error(rules.mismatch.format(**fields))
    if units == "auto":
        if detected is None and rules.unknown is not None:
            raise rules.error(rules.unknown.format(**fields))
        units = detected or "m"
    return UNIT_SCALE[units]
