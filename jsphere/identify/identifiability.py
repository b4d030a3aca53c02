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
    - `"mass_scale"`: multiplying every inertia (`I0, I, j`), dampings, `m0 + m`, `m r_m` and
      the torque gain `k_tau` by `1+e` multiplies every force of (3.4) by `1+e`, the applied
      torques `k_tau K` included. With wheel-speed inputs (servo constraints, where `k_tau` does
      not enter) the motion is then unchanged; with torque inputs too when `k_tau` is free:
      torques fix the scale only through the torque constant.
    Only the free names appear; a direction that needs a fixed name to move is no symmetry of
    the fit (the information along it is then large and nothing is reported; `exact_symmetries`
    says which directions lie wholly in the free set).
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
        elif f in MASS_LIKE or f == "k_tau":
            scale[i] = v
    return {"mass_split": split, "mass_scale": scale}


def exact_symmetries(names: Sequence[str], params: RobotParams, kind: str) -> tuple[str, ...]:
    """The invariances of `symmetry_directions` that are exact for a fit of these free names on
    trials of input `kind` (`"torques"` or `"wheel_speeds"`): those whose every moving value is
    free. `"mass_split"` needs `m`, `m0` and the platform's centre of mass (`R_m`, or every
    non-zero entry of `r_m`); `"mass_scale"` needs `m0`, `m` or the centre of mass, every
    non-zero inertia and damping (`I0`, the entries of `I`, `j`, `c_roll`, `c_axle`), and with
    torque inputs `k_tau`. Along an exact one the data hold no information at all: the fit
    reports it as not identified (infinite standard errors on its names)."""
    free = set(names)

    def covered(field: str) -> bool:
        v = np.asarray(getattr(params, field), np.float64)
        if v.ndim == 0:
            return field in free or v == 0.0
        for ix in zip(*np.nonzero(v)):
            i = tuple(sorted(ix)) if field == "I" else ix  # I[1,0] is I[0,1]
            if f"{field}[{','.join(map(str, i))}]" not in free:
                return False
        return True

    centre = "R_m" in free or covered("r_m")
    out = []
    if {"m", "m0"} <= free and centre:
        out.append("mass_split")
    inertias = all(covered(f) for f in ("I0", "I", "j", "c_roll", "c_axle"))
    if "m0" in free and ("m" in free or centre) and inertias and (kind != "torques" or "k_tau" in free):
        out.append("mass_scale")
    return tuple(out)


_SYMMETRY_TEXT = {
    "mass_split": "only m0 + m and m r_m enter the model (I is about the shell centre), so m, m0 and R_m (r_m) cannot be told apart: "
    "fix the platform mass, e.g. --fix m=<value>.",
    "mass_scale": "scaling every inertia, the total mass m0 + m and the mass moment m r_m together changes nothing the data can see "
    "(with wheel-speed inputs the motion does not depend on the mass scale; fixing m alone does not set it): "
    "fix a mass or inertia you can measure, e.g. --fix {hint}=<value>, or use torque inputs.",
    "torque_scale": "the torque gain k_tau is free with every inertia, the total mass m0 + m and the mass moment m r_m: "
    "scaling them all together changes no motion (the torques set the scale only through the torque constant), so "
    "the masses and inertias are not identified, only their ratios: fix a mass or inertia you have measured, "
    "e.g. --fix {hint}=<value>, or fix k_tau.",
}


def units_note(names: Sequence[str], params: RobotParams, kind: str) -> str:
    """What the fitted masses and inertias are relative to, in one sentence (the fit report's
    `units_note`): the torque constant (torque inputs, `k_tau` fixed), the fixed masses and
    inertias (`k_tau` free, or wheel-speed inputs), or nothing (an exact mass scale)."""
    k = float(params.k_tau)
    if "mass_scale" in exact_symmetries(names, params, kind):
        return (
            "masses and inertias are not determined in scale (the mass scale direction is not identified): "
            "fix a mass or inertia you have measured."
        )
    if kind == "torques" and "k_tau" not in names:
        return (
            f"masses and inertias are relative to the torque constant (k_tau = {k:g} assumed): a torque gain off by "
            "a factor scales every fitted mass and inertia by it; free k_tau with a mass fixed to fit it."
        )
    if kind == "torques":
        return "masses and inertias are in the units of the fixed masses and inertias; the torque gain k_tau is fitted."
    return (
        "masses and inertias are in the units of the fixed masses and inertias (wheel-speed inputs do not involve "
        "the torques, nor k_tau)."
    )


def identifiability(
    free: FreeParams,
    values: np.ndarray,
    F_phys: np.ndarray,
    s2: float,
    params: RobotParams,
    *,
    rel_tol: float = 0.1,
    kind: str | None = None,
) -> dict[str, Any]:
    """Which directions of the free parameters the data determine.

    `F_phys` is the information matrix in physical units. Each name is scaled by its size
    (`|value|`, or a tenth of its field's size for values near 0), so eigenvalues `lam` of the
    scaled information give relative standard deviations `sqrt(s^2/lam)` along their
    eigenvectors. The known invariances (`symmetry_directions`) are checked by name; those
    exact for the trials' input `kind` (`exact_symmetries`; none when `kind` is None) hold no
    information (relative sd `inf`, whatever rounding leaves in `F_phys`); other directions
    with a relative sd above `rel_tol` are reported with their components.
    """
    names = free.names
    sc, Fs = scaled_information(free, values, F_phys, params, kind)
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
            text = _SYMMETRY_TEXT["torque_scale" if key == "mass_scale" and "k_tau" in fields else key]
            out["warnings"].append(text.format(hint=hint) + f" (relative sd along it {rel:.3g})")
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


def scaled_information(free: FreeParams, values, F_phys, params: RobotParams | None, kind: str | None):
    """`(sc, Fs)`: the size of each free name (`|value|`, or a tenth of its field's size for
    values near 0) and the information in those units, the invariances exact for the trials'
    input `kind` removed (`exact_symmetries`, `project_out`; none without `params` and `kind`)."""
    sc = np.maximum(np.abs(values), 0.1 * free.scales())
    Fs = sc[:, None] * F_phys * sc[None, :]
    if kind is None or params is None:
        return sc, Fs
    dirs = symmetry_directions(free.names, values, params)
    return sc, project_out(Fs, [dirs[k] / sc for k in exact_symmetries(free.names, params, kind)])


def project_out(Fs: np.ndarray, directions: Sequence[np.ndarray]) -> np.ndarray:
    """`P Fs P` with `P` the projector orthogonal to `directions` (scaled units): the information
    with the exact invariances removed, so that rounding cannot give them a finite variance."""
    if not directions:
        return Fs
    Q, _ = np.linalg.qr(np.stack(directions, axis=1))
    P = np.eye(Fs.shape[0]) - Q @ Q.T
    return P @ Fs @ P
