"""Robot parameters (Section 2, 3 and 5 of the paper): `RobotParams`, its constructors and its
files.

All quantities are SI (m, kg, kg m^2, s). All vectors are components in the platform frame
`Cxyz` (origin at the shell centre C). See `docs/model.md` for every convention. The fields'
table is `jsphere.model.fields`, their rules `jsphere.model.rules`, the quantities derived from
them `jsphere.model.derived`, the reading of files `jsphere.model.param_files`.
"""

from __future__ import annotations

from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from .._runtime.arrays import as_array
from .._runtime.errors import InputError
from .._runtime.files import read_mapping, write_mapping
from .._runtime.precision import x64_enabled

# the names the rest of the package imports from here
from .derived import Derived as Derived
from .derived import derive as derive
from .fields import FIELDS
from .fields import OPTIONAL as OPTIONAL
from .param_files import check_fit_copies, checked_fields, keys_checked, note_defaults
from .param_files import number_array as number_array
from .rules import RULES as RULES
from .rules import rule_code as rule_code
from .rules import rule_reason as rule_reason
from .rules import validate

#: Values of the two parameters the paper omits, inferred from its own numbers
#: (Omega_1 = 0.864 1/s after (5.1) and 0.852 1/s after the turn (5.6)); see docs/model.md.
#: Rounded, R_m = 27.0146 mm and j = 2.7395e-4 kg m^2; the full digits make Omega_1 = 0.864000
#: exactly (the rounded values give 0.8640015).
PAPER_R_M = 27.014555994314536e-3
PAPER_J = 2.739471996359074e-4


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
        given = locals()
        if dtype is None:
            dtype = jnp.float64 if x64_enabled() else jnp.float32  # JAX's float64 switch
        for f in FIELDS:
            setattr(self, f, as_array(given[f], dtype))

    def __check_init__(self):
        if all(_is_concrete(getattr(self, f)) for f in FIELDS):
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
        kw = {f: getattr(self, f) for f in FIELDS}
        if "R_m" in changes:
            R_m = changes.pop("R_m")
            kw["r_m"] = kw["r_m"] / jnp.linalg.norm(kw["r_m"], axis=-1, keepdims=True) * jnp.asarray(R_m)[..., None]
        unknown = set(changes) - set(FIELDS)
        if unknown:
            raise ValueError(f"RobotParams has no field(s) {sorted(unknown)}; fields are {list(FIELDS)}.")
        kw.update(changes)
        return RobotParams(**kw, dtype=self.R0.dtype)

    def to_dict(self) -> dict[str, Any]:
        """Plain-Python dictionary (numbers and nested lists), e.g. for JSON."""
        return {f: np.asarray(getattr(self, f)).tolist() for f in FIELDS}

    @classmethod
    def from_dict(cls, d: dict[str, Any], *, dtype=None) -> "RobotParams":
        """Inverse of `to_dict`. Accepts `r`, `n`, `alpha` as aliases of the wheel fields.

        Every field but those of `OPTIONAL` is required; a missing or unknown key is an
        `InputError` naming it."""
        return cls(**checked_fields(keys_checked(d, "parameter set")), dtype=dtype)

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
        d = keys_checked(d, where)
        try:
            p = cls(**checked_fields(d), dtype=dtype)
        except ValueError as e:
            raise InputError(f"{path}: {e}") from None
        if fit and isinstance(doc.get("values"), dict):
            check_fit_copies(path, doc["values"], p)
        note_defaults(path, [f for f in OPTIONAL if f not in d])
        return p
