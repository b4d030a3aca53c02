"""Robot parameters (Section 2, 3 and 5 of the paper) and the quantities derived from them.

All quantities are SI (m, kg, kg m^2, s). All vectors are components in the platform frame
`Cxyz` (origin at the shell centre C). See `docs/model.md` for every convention.
"""

from __future__ import annotations

import re
from typing import Any, Callable, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int

from .._runtime.arrays import as_array
from .._runtime.errors import InputError
from .._runtime.files import read_mapping, write_mapping
from .._runtime.precision import x64_enabled
from .linalg import cross, dot, inv3, outer

#: Values of the two parameters the paper omits, inferred from its own numbers
#: (Omega_1 = 0.864 1/s after (5.1) and 0.852 1/s after the turn (5.6)); see docs/model.md.
#: Rounded, R_m = 27.0146 mm and j = 2.7395e-4 kg m^2; the full digits make Omega_1 = 0.864000
#: exactly (the rounded values give 0.8640015).
PAPER_R_M = 27.014555994314536e-3
PAPER_J = 2.739471996359074e-4

_FIELDS = (
    "R0",
    "m0",
    "I0",
    "Rw",
    "wheel_r",
    "wheel_n",
    "wheel_alpha",
    "m",
    "I",
    "r_m",
    "j",
    "g",
    "c_roll",
    "c_axle",
    "k_tau",
)
#: The fields a parameter file may leave out, with the default used and how `load` names it.
#: The others (the geometry, the masses and inertias) are required: a robot has no default mass.
OPTIONAL: dict[str, tuple[float, str]] = {
    "j": (0.0, "j = 0 kg m^2 (massless wheels)"),
    "g": (9.81, "g = 9.81 m/s^2"),
    "c_roll": (0.0, "c_roll = 0 N m s (no rolling resistance)"),
    "c_axle": (0.0, "c_axle = 0 N m s (no axle friction)"),
    "k_tau": (1.0, "k_tau = 1 (torques applied as commanded)"),
}
_OPTIONAL = tuple(OPTIONAL)


def _is_concrete(x: Any) -> bool:
    return not isinstance(x, jax.core.Tracer)


class RobotParams(eqx.Module):
    """Physical parameters of the spherical robot with an internal omniwheel platform.

    A pytree: every field is an array leaf, so parameter sets can be stacked and vmapped
    over, and gradients taken with respect to any field.

    **Fields** (paper symbols; SI units):

    - `R0`: shell radius `R_0` [m].
    - `m0`, `I0`: shell mass [kg] and central moment of inertia (isotropic, `I_0 E`) [kg m^2].
    - `Rw`: omniwheel radius `R_w` [m].
    - `wheel_r`: `(N, 3)` wheel centres `r_i` [m]. Only their direction enters the model.
    - `wheel_n`: `(N, 3)` unit wheel axles `n_i`.
    - `wheel_alpha`: `(N, 3)` unit roller axes `alpha_i` at the contact with the shell.
    - `m`: mass of the platform with wheels [kg].
    - `I`: `(3, 3)` inertia tensor of the platform with wheels about the shell centre C [kg m^2].
    - `r_m`: `(3,)` centre of mass of the platform with wheels [m]; at rest `r_m = -R_m gamma`.
    - `j`: axial moment of inertia of one wheel [kg m^2] (identical wheels).
    - `g`: gravitational acceleration [m/s^2].
    - `c_roll`: optional viscous rolling resistance [N m s]: a torque `-c_roll Omega_h` on the
      shell, `Omega_h` the part of `Omega` perpendicular to the vertical (0 in the paper).
    - `c_axle`: optional viscous friction in each wheel axle [N m s]: a torque `-c_axle chi_dot_i`
      between wheel i and the platform (0 in the paper).
    - `k_tau`: torque gain (dimensionless, default 1): the axle torque applied to wheel i is
      `k_tau K_i` for a commanded `K_i`, so a motor constant that is off by a common factor
      can be fitted (`jsphere fit --free ...,k_tau` with one mass fixed). With torque inputs
      the masses and inertias are identified relative to it: scaling `k_tau` and every mass
      and inertia together changes no motion. Wheel-speed inputs do not involve it.

    Construction validates every field (positive masses and radii, a symmetric positive
    definite `I` whose principal moments meet the triangle inequality, `r_m` off the centre and
    inside the shell, unit axes, `(s_i, n_i)` away from zero, `s_i` spanning 3-space, lengths
    that look like metres: the shapes and the rules of `RULES`) and raises `ValueError` naming
    the field and the expected range. Validation is skipped for traced values (inside `jit`;
    `rule_code` checks those), and pytree operations such as `eqx.tree_at` do not re-validate.

    `dtype` (of every constructor): the fields' float type; default float64 when JAX's float64
    is on (`jsphere.enable_x64()`), else float32, with which the first solve warns once
    (`jsphere.PrecisionWarning`).
    """

    R0: Float[Array, ""]
    m0: Float[Array, ""]
    I0: Float[Array, ""]
    Rw: Float[Array, ""]
    wheel_r: Float[Array, "N 3"]
    wheel_n: Float[Array, "N 3"]
    wheel_alpha: Float[Array, "N 3"]
    m: Float[Array, ""]
    I: Float[Array, "3 3"]
    r_m: Float[Array, "3"]
    j: Float[Array, ""]
    g: Float[Array, ""]
    c_roll: Float[Array, ""]
    c_axle: Float[Array, ""]
    k_tau: Float[Array, ""]

    def __init__(
        self,
        R0,
        m0,
        I0,
        Rw,
        wheel_r,
        wheel_n,
        wheel_alpha,
        m,
        I,
        r_m,
        j=0.0,
        g=9.81,
        c_roll=0.0,
        c_axle=0.0,
        k_tau=1.0,
        *,
        dtype=None,
    ):
        if dtype is None:
            dtype = jnp.float64 if x64_enabled() else jnp.float32  # JAX's float64 switch
        as_ = lambda x: as_array(x, dtype)  # noqa: E731
        self.R0, self.m0, self.I0, self.Rw = as_(R0), as_(m0), as_(I0), as_(Rw)
        self.wheel_r, self.wheel_n, self.wheel_alpha = as_(wheel_r), as_(wheel_n), as_(wheel_alpha)
        self.m, self.I, self.r_m, self.j, self.g = as_(m), as_(I), as_(r_m), as_(j), as_(g)
        self.c_roll, self.c_axle, self.k_tau = as_(c_roll), as_(c_axle), as_(k_tau)

    def __check_init__(self):
        if all(_is_concrete(getattr(self, f)) for f in _FIELDS):
            validate(self)

    @property
    def n_wheels(self) -> int:
        return self.wheel_r.shape[-2]

    @property
    def R_m(self) -> Float[Array, ""]:
        """Distance `R_m = |r_m|` from the shell centre to the platform's centre of mass (2.5)."""
        return jnp.linalg.norm(self.r_m, axis=-1)

    # ------------------------------------------------------------------ constructors

    @classmethod
    def paper(cls, *, R_m: float = PAPER_R_M, j: float = PAPER_J, g: float = 9.81, dtype=None) -> "RobotParams":
        """The experimental robot of Section 5.

        `R0 = 0.15 m, m0 = 0.8 kg, I0 = 0.012 kg m^2, Rw = 0.07 m, m = 2.5 kg,
        I = diag(0.016, 0.016, 0.023) kg m^2`,
        `r_i = 0.057 (cos phi_i, sin phi_i, -1)`, `n_i = (cos phi_i, sin phi_i, 1)/sqrt 2`,
        `alpha_i = (cos(phi_i - pi/4), sin(phi_i - pi/4), 1)/sqrt 2`, `phi_i = 2 pi (i-1)/3`.

        The paper does not give `R_m`, `j` or `g`; the defaults `R_m = 27.0146 mm` and
        `j = 2.7395e-4 kg m^2` reproduce its `Omega_1 = 0.864 1/s` and the `0.852 1/s` after
        the turn (set "P1" of docs/model.md, section 7). `RobotParams.paper(R_m=26.8727e-3, j=0.0)` is
        set "P0".
        """
        phis = 2.0 * np.pi * np.arange(3) / 3.0
        c, s = np.cos(phis), np.sin(phis)
        wheel_r = 0.057 * np.stack([c, s, -np.ones(3)], axis=-1)
        wheel_n = np.stack([c, s, np.ones(3)], axis=-1) / np.sqrt(2.0)
        wheel_alpha = np.stack([np.cos(phis - np.pi / 4), np.sin(phis - np.pi / 4), np.ones(3)], -1) / np.sqrt(2.0)
        return cls(
            R0=0.15,
            m0=0.8,
            I0=0.012,
            Rw=0.07,
            wheel_r=wheel_r,
            wheel_n=wheel_n,
            wheel_alpha=wheel_alpha,
            m=2.5,
            I=np.diag([0.016, 0.016, 0.023]),
            r_m=np.array([0.0, 0.0, -R_m]),
            j=j,
            g=g,
            dtype=dtype,
        )

    def replace(self, **changes) -> "RobotParams":
        """A copy with some fields changed, validated again (e.g. `p.replace(j=0.0)`).

        `R_m=...` is accepted as a shorthand for `r_m = R_m * r_m/|r_m|`.
        """
        kw = {f: getattr(self, f) for f in _FIELDS}
        if "R_m" in changes:
            R_m = changes.pop("R_m")
            kw["r_m"] = kw["r_m"] / jnp.linalg.norm(kw["r_m"], axis=-1, keepdims=True) * jnp.asarray(R_m)[..., None]
        unknown = set(changes) - set(_FIELDS)
        if unknown:
            raise ValueError(f"RobotParams has no field(s) {sorted(unknown)}; fields are {list(_FIELDS)}.")
        kw.update(changes)
        return RobotParams(**kw, dtype=self.R0.dtype)

    def to_dict(self) -> dict[str, Any]:
        """Plain-Python dictionary (numbers and nested lists), e.g. for JSON."""
        return {f: np.asarray(getattr(self, f)).tolist() for f in _FIELDS}

    @classmethod
    def from_dict(cls, d: dict[str, Any], *, dtype=None) -> "RobotParams":
        """Inverse of `to_dict`. Accepts `r`, `n`, `alpha` as aliases of the wheel fields.

        Every field but those of `OPTIONAL` is required; a missing or unknown key is an
        `InputError` naming it."""
        return cls(**_checked_fields(_keys_checked(d, "parameter set")), dtype=dtype)

    def save(self, path) -> None:
        """Write the parameters as TOML or JSON (chosen by the file suffix), atomically."""
        header = "jsphere RobotParams (SI units; vectors in the platform frame)"
        write_mapping(path, self.to_dict(), header=header)

    @classmethod
    def load(cls, path, *, dtype=None) -> "RobotParams":
        """Read parameters from a `.toml` or `.json` file (see `save`), or the `params` of a fit
        result (`jsphere fit --out fit.json`).

        A missing required key, an unknown key (a misspelt field) or a bad value is an
        `InputError` naming the file and the key. The optional keys a file leaves out
        (`OPTIONAL`: `j`, `g`, `c_roll`, `c_axle`, `k_tau`) take their defaults, and one warning
        line on the `jsphere` logger names them with the values used (once per file and
        process). In a fit result, the free parameters' `values` must agree with `params` (the
        copy the robot is read from) to a relative 1e-9, or the file is refused naming the
        parameter and both values: an edit of one copy alone is not taken silently.
        """
        doc = read_mapping(path)
        fit = "params" in doc and isinstance(doc["params"], dict)  # a fit result (`jsphere fit --out`)
        d = doc["params"] if fit else doc
        where = f"{path}: params" if fit else str(path)
        d = _keys_checked(d, where)
        try:
            p = cls(**_checked_fields(d), dtype=dtype)
        except ValueError as e:
            raise InputError(f"{path}: {e}") from None
        if fit and isinstance(doc.get("values"), dict):
            _check_fit_copies(path, doc["values"], p)
        _note_defaults(path, [f for f in OPTIONAL if f not in d])
        return p


#: what each required field is, for the message that names a missing one
_MEANING = {
    "R0": "the shell radius [m]",
    "m0": "the shell mass [kg]",
    "I0": "the shell's moment of inertia [kg m^2]",
    "Rw": "the omniwheel radius [m]",
    "wheel_r": "the wheel centres, one row per wheel [m]",
    "wheel_n": "the unit axle directions, one row per wheel",
    "wheel_alpha": "the unit roller axes, one row per wheel",
    "m": "the platform mass with wheels [kg]",
    "I": "the platform's inertia tensor about the shell centre [kg m^2]",
    "r_m": "the platform's centre of mass [m]",
}
#: the files whose left-out keys have been named, with those keys (`_note_defaults`)
_NOTED: set[tuple[str, tuple[str, ...]]] = set()


def _keys_checked(d: Any, where: str) -> dict[str, Any]:
    """`d` with the wheel aliases resolved, after checking that it holds every required field
    and nothing else (`InputError` starting with `where`, naming the key)."""
    import difflib

    if not isinstance(d, dict):
        raise InputError(f"{where}: a parameter set must be a table of fields {list(_FIELDS)}; got {type(d).__name__}.")
    d = dict(d)
    for alias, field in (("r", "wheel_r"), ("n", "wheel_n"), ("alpha", "wheel_alpha")):
        if alias in d and field not in d:
            d[field] = d.pop(alias)
    unknown = sorted(set(d) - set(_FIELDS), key=str)
    if unknown:
        k = unknown[0]
        close = difflib.get_close_matches(str(k), _FIELDS, n=1)
        hint = f" (did you mean {close[0]!r}?)" if close else ""
        raise InputError(
            f"{where}: unknown key {k!r}{hint}; the keys of a robot are {', '.join(_FIELDS)} "
            "(examples/robot.toml lists them)."
        )
    missing = [f for f in _FIELDS if f not in d and f not in OPTIONAL]
    if missing:
        which = ", ".join(f"{f!r} ({_MEANING[f]})" for f in missing)
        raise InputError(
            f"{where}: missing required key{'s' if len(missing) > 1 else ''} {which}; add "
            f"{'them' if len(missing) > 1 else 'it'} (examples/robot.toml shows every key, docs/robot.md how to measure it)."
        )
    return d


def _note_defaults(path, left_out: list[str]) -> None:
    """One warning line on the `jsphere` logger naming the optional keys a file leaves out and
    the defaults used, once per file and set of keys in a process."""
    import logging
    import os

    key = (os.path.abspath(os.fspath(path)), tuple(left_out))
    if not left_out or key in _NOTED:
        return
    _NOTED.add(key)
    logging.getLogger("jsphere").warning(
        f"warning: {path} leaves out {', '.join(left_out)}; using {', '.join(OPTIONAL[f][1] for f in left_out)}. "
        "Write the key(s) in the file to use your robot's value (docs/robot.md)."
    )


def _check_fit_copies(path, values: dict[str, Any], p: "RobotParams") -> None:
    """Refuse a fit result whose `values` (the free parameters) disagree with its `params`
    beyond a relative 1e-9 (`InputError` naming the parameter and both values)."""
    for name, v in values.items():
        try:
            have = np.asarray(get_value(p, str(name)), np.float64)
        except ValueError:
            raise InputError(
                f"{path}: values has an unknown parameter {name!r}; it names no field of params."
            ) from None
        try:
            want = np.asarray(
                np.vectorize(lambda x: np.nan if x is None else x, otypes=[np.float64])(np.asarray(v, dtype=object)),
                np.float64,
            )
        except (TypeError, ValueError):
            raise InputError(f"{path}: values[{name!r}] must be a number (or lists of numbers); got {v!r}.") from None
        if want.shape != have.shape:
            raise InputError(f"{path}: values[{name!r}] has shape {want.shape}, params has {have.shape} for it.")
        scale = float(np.max(np.abs(have))) if have.size else 0.0
        tol = 1e-9 * np.maximum(np.abs(want), np.abs(have)) + 1e-12 * scale
        bad = np.flatnonzero(np.isfinite(want) & ~(np.abs(want - have) <= tol))
        if bad.size:
            i = int(bad[0])
            a, b = float(want.flat[i]), float(have.flat[i])
            sub = "" if want.ndim == 0 else f"[{','.join(map(str, np.unravel_index(i, want.shape)))}]"
            raise InputError(
                f"{path}: values[{name!r}]{sub} = {a!r} disagrees with params ({name}{sub} = {b!r}), the copy the "
                "robot is read from; edit params (and values to match), or delete values."
            )


# ------------------------------------------------------------------------- validation

#: the shape each field of a parameter set must have (`from_dict`), in words
_SHAPE_TEXT = {
    "I": "a 3x3 nested list (shape (3, 3))",
    "r_m": "a list of 3 numbers (shape (3,))",
    "wheel_r": "a list of N >= 3 rows of 3 numbers (shape (N, 3))",
    "wheel_n": "a list of N rows of 3 numbers, one per wheel of wheel_r (shape (N, 3))",
    "wheel_alpha": "a list of N rows of 3 numbers, one per wheel of wheel_r (shape (N, 3))",
}


def _not_a_number(v: Any) -> str | None:
    """Why `v` (a number or nested lists of numbers) is not numeric, or None if it is."""
    if isinstance(v, (list, tuple)):
        return next((r for r in map(_not_a_number, v) if r is not None), None)
    if isinstance(v, (bool, np.bool_)):
        return f"not a boolean ({str(bool(v)).lower()})"
    if isinstance(v, (int, float, np.integer, np.floating)):
        return None
    if isinstance(v, str):
        return f"not a string ({v!r}; write numbers without quotes)"
    if hasattr(v, "dtype") and hasattr(v, "shape"):  # NumPy and JAX arrays
        return None if np.dtype(v.dtype).kind in "iuf" else f"not an array of {np.dtype(v.dtype)}"
    return "not null" if v is None else f"not a {type(v).__name__}"


def number_array(value: Any, what: str, expected: str) -> Any:
    """`value` (a number or nested lists of numbers) as a float64 NumPy array; a JAX array is
    returned as it is. Raises `InputError` starting with `what` for a boolean, a string or
    another non-number anywhere in `value`, and for ragged lists (naming `expected`, the shape
    wanted in words)."""
    from .._runtime.errors import InputError

    why = _not_a_number(value)
    if why is not None:
        raise InputError(f"{what}: the value must be a number, {why}.")
    if isinstance(value, (jax.Array, jax.core.Tracer)):
        return value
    try:
        return np.asarray(value, dtype=np.float64)
    except ValueError:
        raise InputError(f"{what}: a ragged list (rows of different lengths); expected {expected}.") from None


def _checked_fields(d: dict[str, Any]) -> dict[str, Any]:
    """The fields of a parameter set as arrays, each checked to be numbers of its field's shape
    (`InputError` naming the field and the expected shape)."""
    from .._runtime.errors import InputError

    out = {}
    for f in sorted(d, key=_FIELDS.index):  # wheel_r before the fields whose shape follows it
        v = d[f]
        expected = _SHAPE_TEXT.get(f, "a number")
        a = number_array(v, f"RobotParams.{f}", expected)
        shape = tuple(np.shape(a))
        if f in ("wheel_n", "wheel_alpha") and "wheel_r" in out:
            ok = shape == tuple(np.shape(out["wheel_r"]))
        elif f == "wheel_r":
            ok = len(shape) == 2 and shape[1] == 3 and shape[0] >= 3
        else:
            ok = shape == {"I": (3, 3), "r_m": (3,)}.get(f, ())
        if not ok:
            raise InputError(f"RobotParams.{f}: expected {expected}; got shape {shape}.")
        out[f] = a
    return out


class Rule(NamedTuple):
    """One rule every parameter set meets (`RULES`).

    `field`: the field a broken rule names; `reason`: a short name of the breach (e.g.
    `"m0 <= 0"`, as counted by `MonteCarloResult.stats`); `broken(xp, a)`: `True` for each set
    that breaks it (`a`: the fields by name, arrays of `xp` = `numpy` or `jax.numpy`; leading
    batch dimensions give one answer per set); `message(a)`: the sentence `validate` raises
    (NumPy values).
    """

    field: str
    reason: str
    broken: Callable[[Any, dict], Any]
    message: Callable[[dict], str]


#: trailing dimensions of each field (the rest are batch dimensions of stacked sets)
_CORE_NDIM = {"wheel_r": 2, "wheel_n": 2, "wheel_alpha": 2, "I": 2, "r_m": 1}


def _any_core(xp, x, k: int):
    """`x` reduced with `any` over its last `k` dimensions (all of them if it has fewer)."""
    k = min(k, x.ndim)
    return xp.any(x, axis=tuple(range(-k, 0))) if k else x


def _finite_rule(f: str) -> Rule:
    return Rule(
        f,
        f"{f} not finite",
        lambda xp, a: _any_core(xp, ~xp.isfinite(a[f]), _CORE_NDIM.get(f, 0)),
        lambda a: "must be finite (got NaN or inf).",
    )


def _positive_rule(f: str, unit: str) -> Rule:
    return Rule(f, f"{f} <= 0", lambda xp, a: a[f] <= 0, lambda a: f"must be > 0 {unit}; got {a[f]}.")


def _eig(xp, a):
    return xp.linalg.eigvalsh(a["I"])


def _s(xp, a):
    """`s_i = r_i x alpha_i` and `|s_i|`."""
    s = xp.cross(a["wheel_r"], a["wheel_alpha"])
    return s, xp.linalg.norm(s, axis=-1)


def _s_dot_n(xp, a):
    s, s_norm = _s(xp, a)
    return xp.sum(s * a["wheel_n"], axis=-1) / s_norm


def _s_conditioning(xp, a):
    """Smallest over largest singular value of the unit vectors `s_i / |s_i|`."""
    s, s_norm = _s(xp, a)
    sv = xp.linalg.svd(s / s_norm[..., None], compute_uv=False)
    return sv[..., -1] / sv[..., 0]


def _unit_error(xp, a, f):
    return xp.abs(xp.linalg.norm(a[f], axis=-1) - 1.0)


#: Every rule on the values of a parameter set, in the order `validate` checks them: the
#: first broken rule is the one reported. `validate` evaluates them with NumPy (and checks the
#: shapes in between, after finiteness); `rule_code` with `jax.numpy`, traceable and
#: vmappable, for parameter sets made inside compiled code (the draws of `monte_carlo`).
RULES: tuple[Rule, ...] = (
    *(_finite_rule(f) for f in _FIELDS),
    *(_positive_rule(f, unit) for f, unit in (("R0", "m"), ("Rw", "m"), ("m0", "kg"), ("m", "kg"), ("I0", "kg m^2"))),
    Rule("j", "j < 0", lambda xp, a: a["j"] < 0, lambda a: f"wheel axial inertia must be >= 0 kg m^2; got {a['j']}."),
    Rule(
        "c_roll",
        "c_roll < 0",
        lambda xp, a: a["c_roll"] < 0,
        lambda a: f"damping must be >= 0 N m s; got {a['c_roll']}.",
    ),
    Rule(
        "c_axle",
        "c_axle < 0",
        lambda xp, a: a["c_axle"] < 0,
        lambda a: f"damping must be >= 0 N m s; got {a['c_axle']}.",
    ),
    Rule(
        "k_tau",
        "k_tau <= 0",
        lambda xp, a: a["k_tau"] <= 0,
        lambda a: f"torque gain (applied over commanded axle torque) must be > 0 (1: as commanded); got {a['k_tau']}.",
    ),
    Rule("g", "g < 0", lambda xp, a: a["g"] < 0, lambda a: f"must be >= 0 m/s^2 (use 9.81); got {a['g']}."),
    Rule(
        "R0",
        "R0 > 10 m",
        lambda xp, a: a["R0"] > 10.0,
        lambda a: "is larger than 10 m: lengths are in metres, not millimetres.",
    ),
    Rule(
        "Rw",
        "Rw > 10 m",
        lambda xp, a: a["Rw"] > 10.0,
        lambda a: "is larger than 10 m: lengths are in metres, not millimetres.",
    ),
    Rule(
        "Rw",
        "Rw >= R0",
        lambda xp, a: a["Rw"] >= a["R0"],
        lambda a: f"wheel radius must be smaller than the shell radius R0; got Rw={a['Rw']}, R0={a['R0']}.",
    ),
    Rule(
        "I",
        "I not symmetric",
        lambda xp, a: _any_core(
            xp, xp.abs(a["I"] - xp.swapaxes(a["I"], -1, -2)) > 1e-12 + 1e-9 * xp.abs(xp.swapaxes(a["I"], -1, -2)), 2
        ),
        lambda a: "inertia tensor must be symmetric.",
    ),
    Rule(
        "I",
        "I not positive definite",
        lambda xp, a: _any_core(xp, _eig(xp, a) <= 0, 1),
        lambda a: f"inertia tensor must be positive definite; eigenvalues {np.linalg.eigvalsh(a['I'])}.",
    ),
    Rule(
        "I",
        "I breaks the triangle inequality",
        lambda xp, a: (lambda e: e[..., 2] - e[..., 0] - e[..., 1] > 1e-6 * xp.sum(e, axis=-1))(_eig(xp, a)),
        lambda a: (
            "the principal moments of inertia must satisfy the triangle inequality (the largest at most the sum "
            f"of the other two, as for any body); eigenvalues {np.linalg.eigvalsh(a['I'])}."
        ),
    ),
    Rule(
        "r_m",
        "|r_m| >= R0",
        lambda xp, a: xp.linalg.norm(a["r_m"], axis=-1) >= a["R0"],
        lambda a: (
            f"centre of mass must lie inside the shell, |r_m| < R0; got |r_m| = {np.linalg.norm(a['r_m'], axis=-1)} m."
        ),
    ),
    Rule(
        "r_m",
        "r_m = 0",
        lambda xp, a: xp.linalg.norm(a["r_m"], axis=-1) <= 0,
        lambda a: "centre of mass must be off the shell centre (the rest attitude is gamma = -r_m/|r_m|); got r_m = 0.",
    ),
    Rule(
        "wheel_r",
        "wheel_r = 0",
        lambda xp, a: _any_core(xp, xp.linalg.norm(a["wheel_r"], axis=-1) <= 0, 1),
        lambda a: "wheel positions must be non-zero (their direction defines s_i = r_i x alpha_i).",
    ),
    Rule(
        "wheel_r",
        "|wheel_r| >= R0",
        lambda xp, a: _any_core(xp, xp.linalg.norm(a["wheel_r"], axis=-1) >= a["R0"][..., None], 1),
        lambda a: (
            f"wheel centres must lie inside the shell, |r_i| < R0; got |r_i| = {np.linalg.norm(a['wheel_r'], axis=-1)} m."
        ),
    ),
    *(
        Rule(
            f,
            f"{f} not unit",
            lambda xp, a, f=f: _any_core(xp, _unit_error(xp, a, f) > 1e-6, 1),
            lambda a, f=f: (
                f"axes must be unit vectors (|v| = 1 within 1e-6); got norms {np.linalg.norm(a[f], axis=-1)}."
            ),
        )
        for f in ("wheel_n", "wheel_alpha")
    ),
    Rule(
        "wheel_alpha",
        "alpha_i parallel to r_i",
        lambda xp, a: _any_core(xp, _s(xp, a)[1] < 1e-9, 1),
        lambda a: "roller axis alpha_i is parallel to r_i, so s_i = r_i x alpha_i = 0.",
    ),
    Rule(
        "wheel_n",
        "(s_i, n_i) = 0",
        lambda xp, a: _any_core(xp, xp.abs(_s_dot_n(xp, a)) < 1e-3, 1),
        lambda a: (
            "(s_i, n_i)/|s_i| must be away from zero (|.| >= 1e-3) or the wheel cannot drive the shell "
            f"(k_i = R0/(Rw (s_i, n_i)) is infinite); got {_s_dot_n(np, a)}."
        ),
    ),
    Rule(
        "wheel_r",
        "s_i do not span 3-space",
        lambda xp, a: _s_conditioning(xp, a) < 1e-6,
        lambda a: "the vectors s_i = r_i x alpha_i do not span 3-space: the wheels cannot set omega - Omega.",
    ),
)
#: the rules that need no particular shapes (checked before the shapes)
_N_FINITE = len(_FIELDS)


def _fail(field: str, msg: str):
    raise InputError(f"RobotParams.{field}: {msg}")


def _check_rules(rules, a: dict) -> None:
    for rule in rules:
        with np.errstate(divide="ignore", invalid="ignore"):
            broken = np.any(rule.broken(np, a))
        if broken:
            _fail(rule.field, rule.message(a))


def validate(p: RobotParams) -> None:
    """Check every field of a concrete `RobotParams`; raise `InputError` (a `ValueError`) naming
    the field: the shapes, then every rule of `RULES`.

    Leading batch dimensions (stacked parameter sets) are allowed on every field.
    """
    a = {f: np.asarray(getattr(p, f), dtype=np.float64) for f in _FIELDS}
    _check_rules(RULES[:_N_FINITE], a)
    wr = a["wheel_r"]
    if wr.ndim < 2 or wr.shape[-1] != 3 or wr.shape[-2] < 3:
        _fail("wheel_r", f"must have shape (N, 3) with N >= 3 wheels; got {wr.shape}.")
    N = wr.shape[-2]
    for f in ("wheel_n", "wheel_alpha"):
        if a[f].shape[-2:] != (N, 3):
            _fail(f, f"must have shape ({N}, 3) like wheel_r; got {a[f].shape}.")
    if a["I"].shape[-2:] != (3, 3):
        _fail("I", f"must be a 3x3 inertia tensor; got shape {a['I'].shape}.")
    if a["r_m"].shape[-1:] != (3,):
        _fail("r_m", f"must be a 3-vector; got shape {a['r_m'].shape}.")
    _check_rules(RULES[_N_FINITE:], a)


def rule_code(p: RobotParams) -> Int[Array, "..."]:
    """0 where the parameter set `p` meets every rule of `RULES`, else `1 +` the index of the
    first rule it breaks (the one `validate` would report): `RULES[code - 1].reason` names it.

    Pure `jax.numpy` (traceable and vmappable; one code per set of stacked sets), for
    parameter sets made inside compiled code, which `validate` cannot see. Shapes are not
    checked (they come from a validated set).
    """
    a = {f: getattr(p, f) for f in _FIELDS}
    code = jnp.zeros(jnp.shape(a["R0"]), jnp.int32)
    for k in reversed(range(len(RULES))):
        code = jnp.where(RULES[k].broken(jnp, a), k + 1, code)
    return code


def rule_reason(code: int) -> str:
    """The short name of the rule broken by a set of `rule_code` `code` (`"valid"` for 0)."""
    return "valid" if code == 0 else RULES[int(code) - 1].reason


# ------------------------------------------------------------------ derived quantities


class Derived(eqx.Module):
    """Quantities of (2.4) and (3.4) that depend on the parameters only.

    `s (N,3)`: `s_i = r_i x alpha_i`; `k (N,)`: `k_i = R0/(Rw (s_i, n_i))`;
    `Sk (N,3)`: rows `k_i s_i` (so `chi_dot = -Sk (omega - Omega)`, and the torque term of
    (3.4) is `Sk^T K`); `Jss, Jsn, Jns`: the wheel-inertia tensors of (3.4);
    `A`, `A_inv`: the constant `omega`-block `I + Jss - Jns - Jsn` of the mass matrix and its
    inverse; `Sk_pinv (3,N)`: `(Sk^T Sk)^-1 Sk^T` (least-squares inverse of the wheel map);
    `Sk_T_pinv (N,3)`: `Sk (Sk^T Sk)^-1`, giving the least-norm torques `K` of a required
    `Sk^T K`. The constant parts of the blocks of (3.4), so that the vector fields do not
    recompute them: `B0 = Jns - Jss` and `D0 = I0 E + Jss` (`B`, `D` without their
    `gamma`-terms), `mR0 = m R0`, `MR2 = (m + m0) R0^2`, `mg = m g`.
    """

    s: Float[Array, "N 3"]
    k: Float[Array, " N"]
    Sk: Float[Array, "N 3"]
    Jss: Float[Array, "3 3"]
    Jsn: Float[Array, "3 3"]
    Jns: Float[Array, "3 3"]
    A: Float[Array, "3 3"]
    A_inv: Float[Array, "3 3"]
    Sk_pinv: Float[Array, "3 N"]
    Sk_T_pinv: Float[Array, "N 3"]
    B0: Float[Array, "3 3"]
    D0: Float[Array, "3 3"]
    mR0: Float[Array, ""]
    MR2: Float[Array, ""]
    mg: Float[Array, ""]


def derive(p: RobotParams) -> Derived:
    """Compute the parameter-only quantities of (2.4) and (3.4) once (jit folds them)."""
    s = cross(p.wheel_r, p.wheel_alpha)
    k = p.R0 / (p.Rw * dot(s, p.wheel_n))
    j = p.j
    Sk = k[:, None] * s
    Jss = jnp.sum((j * k * k)[:, None, None] * outer(s, s), axis=0)
    Jsn = jnp.sum((j * k)[:, None, None] * outer(s, p.wheel_n), axis=0)
    Jns = jnp.swapaxes(Jsn, -1, -2)
    A = p.I + Jss - Jns - Jsn
    G = inv3(Sk.T @ Sk)
    return Derived(
        s=s,
        k=k,
        Sk=Sk,
        Jss=Jss,
        Jsn=Jsn,
        Jns=Jns,
        A=A,
        A_inv=inv3(A),
        Sk_pinv=G @ Sk.T,
        Sk_T_pinv=Sk @ G,
        B0=Jns - Jss,
        D0=p.I0 * jnp.eye(3, dtype=A.dtype) + Jss,
        mR0=p.m * p.R0,
        MR2=(p.m + p.m0) * p.R0**2,
        mg=p.m * p.g,
    )


# ----------------------------------------------------------------------------- names of parameters

_NAME = re.compile(r"^\s*([A-Za-z_][A-Za-z0-9_]*)\s*(?:\[\s*([0-9\s,]+)\s*\])?\s*$")
#: derived names: `R_m = |r_m|` (scales r_m along its direction)
DERIVED = ("R_m",)


def parse_name(name: str) -> tuple[str, tuple[int, ...]]:
    """`"I[0,1]"` -> `("I", (0, 1))`; `"j"` -> `("j", ())`. Raises `ValueError` naming the
    fields when the name is unknown or the index does not fit the field's shape."""
    if not isinstance(name, str):
        raise ValueError(f"a parameter name must be a string such as 'j' or 'I[0,0]'; got {name!r}.")
    m = _NAME.match(name)
    if not m:
        raise ValueError(
            f"cannot parse parameter name {name!r}; use a field ({', '.join(_FIELDS)}), a component such as 'I[0,0]' or 'r_m[2]', or 'R_m'."
        )
    field, idx = m.group(1), m.group(2)
    index = tuple(int(i) for i in idx.split(",") if i.strip()) if idx else ()
    if field not in _FIELDS and field not in DERIVED:
        raise ValueError(f"unknown parameter {field!r} in {name!r}; fields are {', '.join(_FIELDS)} (and 'R_m').")
    if field in DERIVED and index:
        raise ValueError(f"{field} is a scalar; got {name!r}.")
    return field, index


def check_index(params: "RobotParams", field: str, index: tuple[int, ...], name: str):
    shape = getattr(params, field).shape
    if len(index) not in (0, len(shape)) or any(i >= s for i, s in zip(index, shape)):
        raise ValueError(f"{name!r}: index {list(index)} does not fit {field} of shape {shape}.")


def get_value(params: "RobotParams", name: str):
    """The value a name refers to (an array for a whole field)."""
    field, index = parse_name(name)
    if field == "R_m":
        return params.R_m
    check_index(params, field, index, name)
    v = getattr(params, field)
    return v[index] if index else v
