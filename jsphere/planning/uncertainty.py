"""How uncertain the robot's parameters are, and parameter sets drawn from it (`Uncertainty`).

Two sources: a fit's estimate with its covariance (`Uncertainty.from_fit`: the `values`,
`stderr` and `correlation` of a fit.json, a joint normal distribution), or a Monte-Carlo
study's `vary` table (`Uncertainty.from_vary`: independent normal and uniform entries). Draws
that break a rule of `RobotParams` (a negative mass, a centre of mass outside the shell, ...)
are drawn again, so every set is a robot.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping, Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from .._runtime.errors import InputError
from ..model.names import get_value, parse_name, set_value
from ..model.params import RobotParams, rule_code

#: rounds of redrawing the sets that are no robot before giving up
MAX_REDRAWS = 50


@dataclasses.dataclass(frozen=True)
class Uncertainty:
    """A distribution of some parameters of a robot (the others as in the nominal set).

    `names`: scalar names (`"r_m[2]"`, `"j"`, `"I[2,2]"`); `kinds`: per name `"normal"` (then
    `a` is the mean, `b` the standard deviation) or `"uniform"` (`a` the low, `b` the high end);
    `correlation`: of the normal entries (identity when None), in the order of `names`
    (entries of uniform names are ignored); `source`: where it comes from, for reports.
    """

    names: tuple[str, ...]
    kinds: tuple[str, ...]
    a: np.ndarray
    b: np.ndarray
    correlation: np.ndarray | None = None
    source: str = ""

    def __post_init__(self):
        P = len(self.names)
        if not P:
            raise InputError("Uncertainty: no parameter is uncertain; give at least one name.")
        if len(self.kinds) != P or np.shape(self.a) != (P,) or np.shape(self.b) != (P,):
            raise InputError("Uncertainty: names, kinds, a and b must have one entry per name.")
        for n, k, a, b in zip(self.names, self.kinds, self.a, self.b):
            if k not in ("normal", "uniform"):
                raise InputError(f"Uncertainty[{n!r}]: kind must be 'normal' or 'uniform'; got {k!r}.")
            if not (math.isfinite(a) and math.isfinite(b)) or (k == "normal" and b < 0) or (k == "uniform" and b < a):
                raise InputError(
                    f"Uncertainty[{n!r}]: {k} needs finite numbers with "
                    + ("sd >= 0" if k == "normal" else "low <= high")
                    + f"; got ({a}, {b})."
                )
        if self.correlation is not None:
            C = np.asarray(self.correlation, float)
            if C.shape != (P, P) or not np.all(np.isfinite(C)) or not np.allclose(C, C.T, atol=1e-9):
                raise InputError(f"Uncertainty: the correlation must be a finite symmetric {P} x {P} matrix.")
            if np.min(np.linalg.eigvalsh(C)) < -1e-9:
                raise InputError("Uncertainty: the correlation matrix is not positive semi-definite.")

    # ------------------------------------------------------------------ sources
    @classmethod
    def from_fit(cls, fit: Mapping[str, Any], source: str = "fit") -> Uncertainty:
        """The joint normal distribution of a fit's free parameters: a fit.json's `free`,
        `values`, `stderr` and `correlation` (`jsphere fit --out`). A standard error that is
        missing or not finite (a direction the data do not determine) is an `InputError`."""
        for key in ("free", "values", "stderr", "correlation"):
            if key not in fit:
                raise InputError(f"{source}: a fit result needs {key!r} (as `jsphere fit --out` writes it).")
        names = [str(n) for n in fit["free"]]
        a, b = [], []
        for n in names:
            v, s = fit["values"].get(n), fit["stderr"].get(n)
            if not _finite_number(v):
                raise InputError(f"{source}: values[{n!r}] must be a finite number; got {v!r}.")
            if not _finite_number(s) or s < 0:
                raise InputError(
                    f"{source}: stderr[{n!r}] is {s!r}: the fit did not determine {n}; fix it or refit before "
                    "planning against its uncertainty."
                )
            a.append(float(v))
            b.append(float(s))
        try:
            C = np.asarray(fit["correlation"], float)
        except (TypeError, ValueError):
            raise InputError(
                f"{source}: correlation must be a {len(names)} x {len(names)} matrix of numbers."
            ) from None
        return cls(tuple(names), ("normal",) * len(names), np.asarray(a), np.asarray(b), C, source)

    @classmethod
    def from_vary(cls, entries: Sequence[tuple], source: str = "vary") -> Uncertainty:
        """Independent distributions from a checked `vary` table: `(name, kind, a, b, ...)` per
        entry (`jsphere.montecarlo.study.check_vary`)."""
        names, kinds, a, b = [], [], [], []
        for e in entries:
            names.append(str(e[0]))
            kinds.append(str(e[1]))
            a.append(float(e[2]))
            b.append(float(e[3]))
        return cls(tuple(names), tuple(kinds), np.asarray(a), np.asarray(b), None, source)

    # ------------------------------------------------------------------ draws
    def nominal(self, params: RobotParams) -> RobotParams:
        """`params` with every normal name at its mean (uniform names as in `params`)."""
        p = params
        for n, k, a in zip(self.names, self.kinds, self.a):
            if k == "normal":
                p = set_value(p, n, a)
        return p

    def _raw(self, rng: np.random.Generator, n: int) -> np.ndarray:
        P = len(self.names)
        normal = np.asarray([k == "normal" for k in self.kinds])
        C = np.eye(P) if self.correlation is None else np.asarray(self.correlation, float)
        C = np.where(np.outer(normal, normal), C, np.eye(P))
        w, V = np.linalg.eigh(0.5 * (C + C.T))
        L = V * np.sqrt(np.clip(w, 0.0, None))
        z = rng.standard_normal((n, P)) @ L.T
        u = rng.uniform(size=(n, P))
        return np.where(normal, self.a + self.b * z, self.a + (self.b - self.a) * u)

    def draw(self, params: RobotParams, n: int, seed: int = 0) -> tuple[np.ndarray, RobotParams]:
        """`n` parameter sets: their values of `names` `(n, P)` and `params` with those values,
        stacked along a leading axis (a `RobotParams` pytree to `vmap` over). Sets that are no
        robot (`rule_code`) are drawn again; `InputError` if that keeps failing."""
        for name in self.names:
            field, _ = parse_name(name)
            if field != "R_m":
                try:
                    get_value(params, name)
                except (ValueError, IndexError) as e:
                    raise InputError(f"{self.source}: {e}") from None
        rng = np.random.default_rng(seed)
        vals = self._raw(rng, n)
        for _ in range(MAX_REDRAWS):
            bad = ~_valid(params, self.names, vals)
            if not bad.any():
                break
            vals[bad] = self._raw(rng, int(bad.sum()))
        else:
            raise InputError(
                f"{self.source}: after {MAX_REDRAWS} redraws {int(bad.sum())} of {n} parameter sets are still no "
                "robot (a rule of RobotParams is broken); narrow the distribution."
            )
        return vals, stack_params(params, self.names, vals)


def _finite_number(v) -> bool:
    return isinstance(v, (int, float, np.number)) and not isinstance(v, bool) and math.isfinite(float(v))


def stack_params(params: RobotParams, names: Sequence[str], vals: np.ndarray) -> RobotParams:
    """`params` with `names` set to each row of `vals (n, P)`, stacked along a leading axis."""
    dt = params.R0.dtype

    def one(v):
        p = params
        for j, name in enumerate(names):
            p = set_value(p, name, v[j])
        return p

    return jax.vmap(one)(jnp.asarray(vals, dt))


def _valid(params: RobotParams, names: Sequence[str], vals: np.ndarray) -> np.ndarray:
    """Whether each row of `vals` makes a valid robot (and a positive `R_m` where it is drawn)."""
    code = np.asarray(rule_code(stack_params(params, names, vals)))
    ok = code == 0
    for j, name in enumerate(names):
        if name == "R_m":
            ok &= vals[:, j] > 0
    return ok
