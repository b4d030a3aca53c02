"""Which directions of the free parameters the data determine: the known exact invariances of the
equations of motion (3.4) and the poorly determined directions of the information matrix."""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np

from ..model.names import parse_name
from ..model.params import RobotParams
from .free import MASS_LIKE, FreeParams


def symmetry_directions(names: Sequence[str], values: np.ndarray, params: RobotParams) -> dict[str, np.ndarray]:
    """Directions (physical units, one entry per free name) of two exact invariances of (3.4).

    - `"mass_split"`: the platform mass enters only through `m0 + m` and `m r_m` (its inertia
      `I` is about C), so `m -> m (1+e)`, `m0 -> m0 - e m`, `r_m -> r_m (1-e)` changes nothing.
    - `"mass_scale"`: multiplying every inertia (`I0, I, j`), dampings, `m0 + m` and `m r_m`
      by `1+e` multiplies every force of (3.4) by `1+e`. With wheel-speed inputs (servo
      constraints) the motion is then unchanged; torque inputs fix the scale.
    Only the free names appear; a direction that needs a fixed name to move is no symmetry of
    the fit (the information along it is then large and nothing is reported).
    """
    fields = [parse_name(n)[0] for n in names]
    m_free = "m" in fields
    m, m0 = float(params.m), float(params.m0)
    split, scale = np.zeros(len(names)), np.zeros(len(names))
    for i, f in enumerate(fields):
        v = float(values[i])
        if f == "m":
            split[i], scale[i] = m, m
        elif f == "m0":
            split[i], scale[i] = -m, (m0 if m_free else m0 + m)
        elif f in ("R_m", "r_m"):
            split[i], scale[i] = -v, (0.0 if m_free else v)
        elif f in MASS_LIKE:
            scale[i] = v
    return {"mass_split": split, "mass_scale": scale}


_SYMMETRY_TEXT = {
    "mass_split": "only m0 + m and m r_m enter the model (I is about the shell centre), so m, m0 and R_m (r_m) cannot be told apart: "
    "fix the platform mass, e.g. --fix m=<value>.",
    "mass_scale": "scaling every inertia, the total mass m0 + m and the mass moment m r_m together changes nothing the data can see "
    "(with wheel-speed inputs the motion does not depend on the mass scale; fixing m alone does not set it): "
    "fix a mass or inertia you can measure, e.g. --fix {hint}=<value>, or use torque inputs.",
}


def identifiability(
    free: FreeParams, values: np.ndarray, F_phys: np.ndarray, s2: float, params: RobotParams, *, rel_tol: float = 0.1
) -> dict[str, Any]:
    """Which directions of the free parameters the data determine.

    `F_phys` is the information matrix in physical units. Each name is scaled by its size
    (`|value|`, or a tenth of its field's size for values near 0), so eigenvalues `lam` of the
    scaled information give relative standard deviations `sqrt(s^2/lam)` along their
    eigenvectors. The known invariances (`symmetry_directions`) are checked by name; other
    directions with a relative sd above `rel_tol` are reported with their components.
    """
    names = free.names
    sc = np.maximum(np.abs(values), 0.1 * free.scales())
    Fs = sc[:, None] * F_phys * sc[None, :]
    lam, V = np.linalg.eigh(Fs)
    lam_max = max(float(lam[-1]), 1e-300)
    rel_sd = lambda info: math.sqrt(s2 / info) if info > 1e-14 * lam_max else math.inf
    out: dict[str, Any] = {
        "condition_number": float(lam_max / max(lam[0], 1e-300 * lam_max)),
        "symmetries": {},
        "directions": [],
        "warnings": [],
    }
    named = []
    for key, vec in symmetry_directions(names, values, params).items():
        e = vec / sc
        if np.count_nonzero(e) < 2:
            continue
        e = e / np.linalg.norm(e)
        rel = rel_sd(float(e @ Fs @ e))
        out["symmetries"][key] = {
            "relative_sd": rel,
            "combination": {n: float(w) for n, w in zip(names, e) if w != 0.0},
        }
        if rel > rel_tol:
            named.append(e)
            fields = [parse_name(n)[0] for n in names]
            hint = next((f for f in ("m0", "I0", "m") if f in fields), fields[0])
            out["warnings"].append(_SYMMETRY_TEXT[key].format(hint=hint) + f" (relative sd along it {rel:.3g})")
    for k in range(len(lam)):
        rel = rel_sd(float(lam[k]))
        if rel <= rel_tol or any(abs(float(V[:, k] @ e)) > 0.9 for e in named):
            continue
        v = V[:, k] * np.sign(V[np.argmax(np.abs(V[:, k])), k])
        terms = [(names[i], float(v[i])) for i in np.argsort(-np.abs(v)) if abs(v[i]) >= 0.15]
        text = " ".join(f"{w:+.2f} {n}" for n, w in terms)
        out["directions"].append({"relative_sd": rel, "combination": dict(terms), "text": text})
        out["warnings"].append(
            f"the data do not determine the direction {text} (relative changes; relative sd {rel:.3g}): "
            f"fix one of {', '.join(n for n, _ in terms)} or add more exciting trials."
        )
    return out
