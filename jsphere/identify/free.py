"""Free parameters of a fit: names expanded to scalar components, bounds by reparameterisation.

A fit works on an unconstrained vector `theta (P,)`. `FreeParams` maps it to a `RobotParams`
(`to_params`) and to the physical values of the free names (`physical`), one transform per
free scalar (or one for the whole inertia tensor):

- `log`:       `v = exp(u)`                      (default for masses, inertias, radii, `R_m`)
- `lower`:     `v = lo + exp(u)`;  `upper`: `v = hi - exp(u)`
- `interval`:  `v = lo + (hi - lo) sigmoid(u)`
- `none`:      `v = u`                           (default for `r_m[k]`, off-diagonals of `I`, ...)
- `cholesky`:  the whole field `I` (6 entries) as `I = L L^T`, `L` lower triangular with a
  log-diagonal: every value of `theta` gives a symmetric positive definite tensor.

A fit of onboard-sensor trials may also free the IMU's mounting (`MOUNTING`, `mounting_at`):
`imu_position[k]` [m], and `imu_rotation[k]` [rad], the rotation vector `delta` (IMU axes) of
the correction to the given orientation, `q = q_given exp(delta)` (0 at the start).

Bounds are never enforced by clipping, so gradients and the Gauss-Newton covariance stay
smooth; the covariance in `theta` is mapped to physical units by `d physical / d theta`.
"""

from __future__ import annotations

import dataclasses
import json
import math
import re
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._runtime.errors import InputError
from .._runtime.quick_compile import jit_concrete
from ..model.internal import FIELDS
from ..model.names import MOUNTING, get_value, parse_name, set_value
from ..model.params import RobotParams, number_array
from ..model.rotations import quat_exp, quat_mul

#: fields that must stay > 0 (log transform by default)
POSITIVE = ("R0", "m0", "I0", "Rw", "m", "R_m", "k_tau")
#: fields that must stay >= 0 (log transform by default if the start is > 0, else unbounded)
NONNEGATIVE = ("j", "g", "c_roll", "c_axle")
#: fields whose values scale with mass: with wheel-speed inputs, scaling all of them together
#: leaves every motion unchanged (the servo constraints fix the kinematics, (3.4) is homogeneous)
MASS_LIKE = ("m0", "I0", "m", "I", "j", "c_roll", "c_axle")
#: unit vectors: not supported as free parameters
UNIT_VECTORS = ("wheel_n", "wheel_alpha")


def expand(params: RobotParams, names: str | Sequence[str]) -> list[tuple[str, list[str]]]:
    """`"r_m[2],j,I"` -> `[("r_m[2]", ["r_m[2]"]), ("j", ["j"]), ("I", ["I[0,0]", "I[0,1]", ...])]`.

    A whole field frees all its independent entries (the 6 of the symmetric `I`, row-major
    upper triangle). Raises `ValueError` for unknown names, bad indices, unit-vector fields,
    and names given twice or overlapping (`I` and `I[0,0]`, `R_m` and `r_m[2]`).
    """
    if isinstance(names, str):
        names = _split_names(names)
    out: list[tuple[str, list[str]]] = []
    seen: dict[str, str] = {}
    for given in names:
        given = given.strip()
        if not given:
            continue
        field, index = parse_name(given)
        if field in UNIT_VECTORS:
            raise ValueError(
                f"free parameter {given!r}: {field} holds unit vectors and cannot be fitted component by component; fix it."
            )
        if field not in ("R_m",) + MOUNTING:
            get_value(params, given)  # checks the index
        shape = () if field == "R_m" else (3,) if field in MOUNTING else tuple(getattr(params, field).shape)
        if index or not shape:
            comps = [_canonical(field, index)]
        elif field == "I":
            comps = [f"I[{i},{j}]" for i in range(3) for j in range(i, 3)]
        else:
            comps = [f"{field}[{','.join(map(str, ix))}]" for ix in np.ndindex(*shape)]
        for c in comps:
            if c in seen:
                raise ValueError(f"free parameter {c!r} is named twice (in {seen[c]!r} and {given!r}).")
            seen[c] = given
        out.append((given, comps))
    flat = [c for _, cs in out for c in cs]
    if "R_m" in flat and any(c.startswith("r_m") for c in flat):
        raise ValueError("free parameters 'R_m' and 'r_m[...]' overlap (R_m = |r_m|); free one or the other.")
    if not flat:
        raise ValueError("no free parameters given; name at least one, e.g. 'R_m,j'.")
    return out


def _split_names(s: str) -> list[str]:
    """Split `"I[0,1],j"` at commas outside brackets."""
    return [p.strip() for p in re.split(r",(?![^\[]*\])", s) if p.strip()]


def _canonical(field: str, index: tuple[int, ...]) -> str:
    if not index:
        return field
    if field == "I" and index[0] > index[1]:
        index = index[::-1]  # I[1,0] is I[0,1]
    return f"{field}[{','.join(map(str, index))}]"


def _overlaps(a: str, b: str) -> bool:
    """Whether two names (fields or components) refer to a common number."""
    fa, ia = parse_name(a)
    fb, ib = parse_name(b)
    if {fa, fb} == {"R_m", "r_m"}:
        return True
    if fa != fb:
        return False
    if not ia or not ib:
        return True
    return _canonical(fa, ia) == _canonical(fb, ib)


def parse_fix_value(name: str, value: Any, expected: str = "a number (or a list of numbers for a whole field)") -> Any:
    """A value for `--fix NAME=VALUE`: a number, or (nested) lists of numbers for a whole field.
    Strings are parsed as JSON (`"2.5"`, `"[[0.016,0,0],...]"`). Booleans, strings inside the
    JSON and ragged lists are refused, naming `expected` (the shape wanted, in words)."""
    v = value
    if isinstance(v, str):
        try:
            v = json.loads(v)
        except json.JSONDecodeError:
            raise InputError(
                f"--fix {name}={value}: the value must be a number (or a JSON list of numbers for a whole field)."
            ) from None
    arr = np.asarray(number_array(v, f"--fix {name}={value}", expected))
    if not np.all(np.isfinite(arr)):
        raise InputError(f"--fix {name}={value!r}: the value must be finite.")
    return arr


def apply_fixes(params: RobotParams, fix: Mapping[str, Any] | None) -> RobotParams:
    """`params` with every `fix` name set (validated again: a bad value raises `ValueError`
    naming the field)."""
    if not fix:
        return params
    p = params
    for name, value in fix.items():
        field, _ = parse_name(name)
        shape = () if field == "R_m" else tuple(get_value(params, name).shape)
        want = "a number" if not shape else f"a value of shape {shape}"
        arr = parse_fix_value(name, value, want)
        if field == "R_m" and arr.shape != ():
            raise InputError(f"--fix {name}: R_m is a scalar; got shape {arr.shape}.")
        if arr.shape not in ((), shape):
            raise InputError(f"--fix {name}: expected {want}; got shape {arr.shape}.")
        p = set_value(p, name, arr)
    try:
        return RobotParams(**{f: getattr(p, f) for f in FIELDS}, dtype=params.R0.dtype)
    except ValueError as e:
        raise InputError(f"after --fix: {e}") from None


@dataclasses.dataclass(frozen=True)
class Slot:
    """One block of `theta`: a scalar name with its transform, or the whole `I` (cholesky)."""

    names: tuple[str, ...]
    kind: str  # log | lower | upper | interval | none | cholesky
    lo: float = -math.inf
    hi: float = math.inf
    scale: float = 1.0  # typical size of the physical value (for steps, spreads, reports)

    @property
    def size(self) -> int:
        return len(self.names)


def _forward(kind: str, lo: float, hi: float, u):
    if kind == "log":
        return jnp.exp(u)
    if kind == "lower":
        return lo + jnp.exp(u)
    if kind == "upper":
        return hi - jnp.exp(u)
    if kind == "interval":
        return lo + (hi - lo) * jax.nn.sigmoid(u)
    return u


def _inverse(kind: str, lo: float, hi: float, v: float) -> float:
    if kind == "log":
        return math.log(v)
    if kind == "lower":
        return math.log(v - lo)
    if kind == "upper":
        return math.log(hi - v)
    if kind == "interval":
        s = (v - lo) / (hi - lo)
        return math.log(s / (1.0 - s))
    return v


_TRIU = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))


def _chol_to_I(u):
    L = jnp.zeros((3, 3), u.dtype)
    L = L.at[0, 0].set(jnp.exp(u[0])).at[1, 0].set(u[1]).at[1, 1].set(jnp.exp(u[2]))
    L = L.at[2, 0].set(u[3]).at[2, 1].set(u[4]).at[2, 2].set(jnp.exp(u[5]))
    return L @ L.T


def _I_to_chol(I) -> list[float]:
    L = np.linalg.cholesky(np.asarray(I, np.float64))
    return [math.log(L[0, 0]), L[1, 0], math.log(L[1, 1]), L[2, 0], L[2, 1], math.log(L[2, 2])]


#: `FreeParams.compiled` by slots
_COMPILED: dict[tuple[Slot, ...], tuple[Callable, Callable]] = {}


class FreeParams:
    """The free parameters of a fit and their transforms (static configuration, not a pytree).

    **Arguments:**
    - `params`: the start values (with fixed values already set, see `apply_fixes`).
    - `free`: names, comma-separated or a list: fields (`"j"`, `"I"`: all 6 entries,
      `"r_m"`: all 3), components (`"I[0,0]"`, `"r_m[2]"`), or the derived `"R_m"`.
    - `bounds`: `{name: (lo, hi)}` with `None` for an open end, for scalar free names (as
      expanded: `"I[0,0]"`); the start must lie strictly inside. Defaults: `> 0` for masses,
      inertias, radii, `R_m`, the torque gain `k_tau` and the diagonal of `I`; `>= 0` (open at 0) for `j`, `g`,
      `c_roll`, `c_axle` when they start above 0; none otherwise.

    - `mounting`: the IMU's `jsphere.Mounting` where the fit's trials are onboard-sensor
      trials: `free` may then name `imu_position` and `imu_rotation` (`MOUNTING`, module
      docstring), which `mounting_at` applies.

    `names` lists the expanded physical names in `theta` order; `given` the names as given
    with their components (for reports of whole fields).
    """

    def __init__(
        self,
        params: RobotParams,
        free: str | Sequence[str],
        bounds: Mapping[str, Sequence] | None = None,
        mounting=None,
    ):
        self.base = params
        self.mounting = mounting
        self.given = expand(params, free)
        on_imu = [g for g, _ in self.given if parse_name(g)[0] in MOUNTING]
        if on_imu and mounting is None:
            raise InputError(
                f"free parameter {on_imu[0]!r} is the IMU's mounting: it is fitted from onboard-sensor trials only."
            )
        bounds = dict(bounds or {})
        flat = [c for _, cs in self.given for c in cs]
        for b in bounds:
            parse_name(b)
            canon = _canonical(*parse_name(b))
            if canon not in flat:
                raise ValueError(f"bounds given for {b!r}, which is not a free parameter (free: {', '.join(flat)}).")
        bounds = {_canonical(*parse_name(k)): v for k, v in bounds.items()}
        slots: list[Slot] = []
        for given, comps in self.given:
            field, index = parse_name(given)
            if field == "I" and not index:
                if any(c in bounds for c in comps):
                    raise ValueError(
                        "bounds on entries of a whole free 'I' are not supported (it is kept positive definite by a Cholesky factor); free the entries one by one to bound them."
                    )
                I = np.asarray(params.I, np.float64)
                slots.append(Slot(tuple(comps), "cholesky", scale=float(np.max(np.abs(I)))))
                continue
            for c in comps:
                slots.append(self._scalar_slot(params, c, bounds.get(c), self._value(params, c)))
        self.slots = tuple(slots)
        self.names = [n for s in self.slots for n in s.names]
        self.theta0 = np.asarray(self.to_theta(params))

    def _value(self, params: RobotParams, name: str) -> float:
        """The start value of a scalar name (the mounting's rotation: 0, no correction)."""
        field, index = parse_name(name)
        if field == "imu_position":
            return float(np.asarray(self.mounting.position)[index[0]])
        return 0.0 if field == "imu_rotation" else float(get_value(params, name))

    @staticmethod
    def _scalar_slot(params: RobotParams, name: str, bound, v: float) -> Slot:
        field, index = parse_name(name)
        if field in MOUNTING:  # a centimetre, or a hundredth of a radian
            fv = np.full(1, 0.01)
        else:
            fv = np.abs(np.asarray(getattr(params, field) if field != "R_m" else params.R_m, np.float64))
        scale = max(abs(v), 0.1 * float(np.max(fv)) if fv.size else 0.0, 1e-12)
        diag = field == "I" and index[0] == index[1]
        if bound is None:
            if field in POSITIVE or diag:
                return Slot((name,), "log", 0.0, math.inf, scale)
            if field in NONNEGATIVE and v > 0:
                return Slot((name,), "log", 0.0, math.inf, scale)
            return Slot((name,), "none", scale=scale)
        if not isinstance(bound, (tuple, list)) or len(bound) != 2:
            raise ValueError(f"bounds[{name!r}] must be (lo, hi) with None for an open end; got {bound!r}.")
        lo = -math.inf if bound[0] is None else float(bound[0])
        hi = math.inf if bound[1] is None else float(bound[1])
        if not lo < hi:
            raise ValueError(f"bounds[{name!r}] = ({lo}, {hi}): the lower bound must be below the upper bound.")
        if not lo < v < hi:
            raise ValueError(
                f"bounds[{name!r}] = ({lo}, {hi}) exclude the start value {v}; move the start (e.g. --fix/--params) or widen the bounds."
            )
        if math.isfinite(lo) and math.isfinite(hi):
            kind = "interval"
        elif math.isfinite(lo):
            kind = "log" if lo == 0.0 else "lower"
        elif math.isfinite(hi):
            kind = "upper"
        else:
            kind = "none"
        return Slot((name,), kind, lo, hi, scale)

    # ------------------------------------------------------------------ maps
    @property
    def size(self) -> int:
        return len(self.names)

    def to_theta(self, params: RobotParams) -> np.ndarray:
        """The unconstrained vector of `params` (inverse of `to_params` on the free names)."""
        out: list[float] = []
        for s in self.slots:
            if s.kind == "cholesky":
                try:
                    out += _I_to_chol(params.I)
                except np.linalg.LinAlgError:
                    raise ValueError("the start value of I is not positive definite.") from None
            else:
                out.append(_inverse(s.kind, s.lo, s.hi, self._value(params, s.names[0])))
        return np.asarray(out, np.float64)

    def physical(self, theta) -> jax.Array:
        """Physical values of `names` (SI units) at `theta` (pure JAX)."""
        vals, k = [], 0
        for s in self.slots:
            u = theta[k : k + s.size]
            if s.kind == "cholesky":
                I = _chol_to_I(u)
                vals += [I[i, j] for i, j in _TRIU]
            else:
                vals.append(_forward(s.kind, s.lo, s.hi, u[0]))
            k += s.size
        return jnp.stack(vals)

    def to_params(self, theta, base: RobotParams | None = None) -> RobotParams:
        """The `RobotParams` at `theta`: `base` (default: the start values) with the free ones
        replaced (pure JAX, differentiable; not re-validated)."""
        p, k = (self.base if base is None else base), 0
        for s in self.slots:
            u = theta[k : k + s.size]
            if s.kind == "cholesky":
                p = eqx.tree_at(lambda q: q.I, p, _chol_to_I(u))
            elif parse_name(s.names[0])[0] not in MOUNTING:
                p = set_value(p, s.names[0], _forward(s.kind, s.lo, s.hi, u[0]))
            k += s.size
        return p

    def mounting_at(self, theta, position, rotation) -> tuple[jax.Array, jax.Array]:
        """The IMU's `(position (3,), rotation (4,))` at `theta`: `position` and `rotation` (the
        given mounting) with the free `imu_position` components replaced and the free
        `imu_rotation` correction applied, `rotation exp(delta)` (pure JAX, differentiable)."""
        delta, k = jnp.zeros(3, position.dtype), 0
        for s in self.slots:
            field, index = parse_name(s.names[0])
            if field in MOUNTING:
                v = _forward(s.kind, s.lo, s.hi, theta[k])
                if field == "imu_position":
                    position = position.at[index[0]].set(v)
                else:
                    delta = delta.at[index[0]].set(v)
            k += s.size
        return position, quat_mul(rotation, quat_exp(delta))

    @property
    def frees_mounting(self) -> bool:
        """Whether a name of the IMU's mounting is free."""
        return any(parse_name(n)[0] in MOUNTING for n in self.names)

    def compiled(self) -> tuple[Callable, Callable]:
        """`(physical_and_jacobian(theta), to_params(theta, base))`, compiled once per process
        for the `slots` they depend on: the physical values with `d physical / d theta`, and
        `to_params` with its `base` given."""
        if self.slots not in _COMPILED:
            jacobian = jax.jacfwd(self.physical)
            _COMPILED[self.slots] = (
                jit_concrete(lambda th: (self.physical(th), jacobian(th))),
                jit_concrete(self.to_params),
            )
        return _COMPILED[self.slots]

    def physical_covariance(self, theta, cov_theta) -> np.ndarray:
        """Map a covariance of `theta` to the physical values: `A C A^T`, `A = d physical/d theta`."""
        A = np.asarray(self.compiled()[0](jnp.asarray(theta, jnp.float64))[1])
        return A @ np.asarray(cov_theta) @ A.T

    def scales(self) -> np.ndarray:
        """Typical size of each physical value (for relative reports and start spreads)."""
        return np.asarray([s.scale for s in self.slots for _ in s.names])

    def theta_scales(self) -> np.ndarray:
        """Typical step in each `theta` coordinate: 1 where the transform is logarithmic or
        logistic, the physical scale where it is the identity."""
        out = []
        for s in self.slots:
            if s.kind == "cholesky":
                o = 0.1 * math.sqrt(s.scale)
                out += [1.0, o, 1.0, o, o, 1.0]
            else:
                out.append(s.scale if s.kind == "none" else 1.0)
        return np.asarray(out)
