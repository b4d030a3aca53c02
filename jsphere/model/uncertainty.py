"""How uncertain a robot's parameters are, and robots drawn from it (`Uncertainty`).

One type, built from its fields (`Uncertainty(names, kinds, a, b, correlation, source,
truncate)`: a Monte-Carlo study's `vary` table, independent normal and uniform entries), or read
from a fit's estimate with its covariance (`Uncertainty.from_fit`: the `values`, `stderr` and
`correlation` of a fit.json, a joint normal distribution). Every draw is checked against the rules of `RobotParams` (`rule_code`, and a
drawn `R_m` must be a positive distance); a "truncated" name is drawn again while its set is
no robot, which truncates its distribution to the valid robots.

Random numbers are JAX's, from one key per draw and name: draw `i` with seed `s` draws name
`j` from `fold_in(fold_in(PRNGKey(s), i), j)`, and its `k`-th redraw from that key folded with
`k`. A draw is therefore the same whatever the batch it is made in (`docs/decisions/random-numbers.md`).
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Mapping, Sequence
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int

from .._runtime.checks import is_number, is_traced
from .._runtime.errors import InputError
from .names import get_value, parse_name, set_value
from .params import RULES, RobotParams, rule_code

#: redraws of a truncated name before a draw that is still no robot is rejected
MAX_REDRAWS = 100
#: why a draw is rejected, by `draw_code`: 0 valid, then every rule of `RobotParams`
#: (`jsphere.model.params.RULES`), then a drawn `R_m` that is not a positive distance
REASONS: tuple[str, ...] = ("valid", *(rule.reason for rule in RULES), "R_m <= 0")
KINDS = ("normal", "uniform")


def draw_key(seed, i) -> jax.Array:
    """The key of draw `i`: `fold_in(PRNGKey(seed), i)`."""
    return jax.random.fold_in(jax.random.PRNGKey(seed), i)


def with_values(params: RobotParams, names: Sequence[str], vals) -> RobotParams:
    """`params` with each of `names` set to its value in `vals`."""
    p = params
    for j, name in enumerate(names):
        p = set_value(p, name, vals[j])
    return p


def stack_params(params: RobotParams, names: Sequence[str], vals) -> RobotParams:
    """`params` with `names` set to each row of `vals (n, P)`, stacked along a leading axis."""
    return jax.vmap(lambda v: with_values(params, names, v))(jnp.asarray(vals, params.R0.dtype))


def draw_code(params: RobotParams, names: Sequence[str], vals) -> Int[Array, ""]:
    """0 if `params` with `names` set to `vals` is a robot, else the first broken rule
    (`REASONS`)."""
    code = rule_code(with_values(params, names, vals))
    for j, name in enumerate(names):
        if name == "R_m":
            code = jnp.where(vals[j] <= 0, len(REASONS) - 1, code)
    return code


def _finite(v) -> bool:
    return is_number(v) and math.isfinite(v)


class Uncertainty(eqx.Module):
    """A distribution of some parameters of a robot (the others as in the nominal set).

    `names`: scalar names (`"r_m[2]"`, `"j"`, `"I[2,2]"`, `"R_m"`); `kinds`: per name `"normal"`
    (then `a` is the mean, `b` the standard deviation) or `"uniform"` (`a` the low, `b` the high
    end); `correlation`: of the normal entries (independent when None), in the order of `names`
    (entries of uniform names are ignored); `source`: where it comes from, for reports;
    `truncate`: per name, whether it is drawn again while its set is no robot (all when None).
    """

    names: tuple[str, ...] = eqx.field(static=True)
    kinds: tuple[str, ...] = eqx.field(static=True)
    a: Float[Array, " v"]
    b: Float[Array, " v"]
    correlation: Float[Array, "v v"] | None = None
    source: str = eqx.field(static=True, default="")
    truncate: Bool[Array, " v"] | None = None

    def __check_init__(self):
        P = len(self.names)
        if len(self.kinds) != P or np.shape(self.a) != (P,) or np.shape(self.b) != (P,):
            raise InputError("Uncertainty: names, kinds, a and b must have one entry per name.")
        for n, k in zip(self.names, self.kinds):
            if k not in KINDS:
                raise InputError(f"Uncertainty[{n!r}]: kind must be 'normal' or 'uniform'; got {k!r}.")
        if is_traced(self.a, self.b):
            return
        for n, k, a, b in zip(self.names, self.kinds, np.asarray(self.a), np.asarray(self.b)):
            if not (math.isfinite(a) and math.isfinite(b)) or (k == "normal" and b < 0) or (k == "uniform" and b < a):
                raise InputError(
                    f"Uncertainty[{n!r}]: {k} needs finite numbers with "
                    + ("sd >= 0" if k == "normal" else "low <= high")
                    + f"; got ({a}, {b})."
                )
        if self.correlation is not None and not is_traced(self.correlation):
            C = np.asarray(self.correlation, float)
            if C.shape != (P, P) or not np.all(np.isfinite(C)) or not np.allclose(C, C.T, atol=1e-9):
                raise InputError(f"Uncertainty: the correlation must be a finite symmetric {P} x {P} matrix.")
            if np.min(np.linalg.eigvalsh(C)) < -1e-9:
                raise InputError("Uncertainty: the correlation matrix is not positive semi-definite.")

    # ------------------------------------------------------------------ sources
    @classmethod
    def from_fit(cls, fit: Mapping[str, Any], source: str = "fit") -> Uncertainty:
        """The joint normal distribution of a fit's free parameters (its estimate and covariance):
        a fit.json's `free`, `values`, `stderr` and `correlation` (`jsphere fit --out`). A
        standard error that is missing or not finite (a direction the data do not determine) is
        an `InputError`."""
        for key in ("free", "values", "stderr", "correlation"):
            if key not in fit:
                raise InputError(f"{source}: a fit result needs {key!r} (as `jsphere fit --out` writes it).")
        names = [str(n) for n in fit["free"]]
        a, b = [], []
        for n in names:
            v, s = fit["values"].get(n), fit["stderr"].get(n)
            if not _finite(v):
                raise InputError(f"{source}: values[{n!r}] must be a finite number; got {v!r}.")
            if not _finite(s) or s < 0:
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
        if not names:
            raise InputError(f"{source}: the fit has no free parameter; nothing is uncertain.")
        return cls(tuple(names), ("normal",) * len(names), np.asarray(a), np.asarray(b), C, source)

    @classmethod
    def from_vary(cls, entries: Sequence[tuple], source: str = "vary") -> Uncertainty:
        """Independent distributions, every name truncated to the valid robots, from `(name,
        kind, a, b, ...)` entries: `Uncertainty(names, kinds, a, b, source=source)`. Kept for
        one release, with a `DeprecationWarning`."""
        warnings.warn(
            "Uncertainty.from_vary(entries) is deprecated; pass Uncertainty(names, kinds, a, b, source=...).",
            DeprecationWarning,
            stacklevel=2,
        )
        if not entries:
            raise InputError(f"{source}: no parameter is uncertain; give at least one name.")
        ab = np.array([[float(e[2]), float(e[3])] for e in entries])
        return cls(
            tuple(str(e[0]) for e in entries), tuple(str(e[1]) for e in entries), ab[:, 0], ab[:, 1], None, source
        )

    # ------------------------------------------------------------------ draws
    def nominal(self, params: RobotParams) -> RobotParams:
        """`params` with every normal name at its mean (uniform names as in `params`)."""
        p = params
        for n, k, a in zip(self.names, self.kinds, np.asarray(self.a)):
            if k == "normal":
                p = set_value(p, n, float(a))
        return p

    def _sample(self, keys, dtype) -> Float[Array, " v"]:
        """One value per name, name `j` from `keys[j]`."""
        normal = np.array([k == "normal" for k in self.kinds])
        s = jnp.stack([(jax.random.normal if n else jax.random.uniform)(k, dtype=dtype) for k, n in zip(keys, normal)])
        if self.correlation is not None:
            # correlated normals: `L z` with `L L^T = C` on the normal names (eigen-decomposition,
            # so a semi-definite `C` is accepted)
            C = jnp.where(
                np.outer(normal, normal), jnp.asarray(self.correlation, dtype), jnp.eye(len(normal), dtype=dtype)
            )
            w, V = jnp.linalg.eigh(0.5 * (C + C.T))
            s = jnp.where(normal, (V * jnp.sqrt(jnp.clip(w, 0.0, None))) @ jnp.where(normal, s, 0.0), s)
        a, b = jnp.asarray(self.a, dtype), jnp.asarray(self.b, dtype)
        return jnp.where(normal, a + b * s, a + (b - a) * s)

    def draw_one(self, params: RobotParams, seed, i) -> tuple[Float[Array, " v"], Int[Array, ""]]:
        """Values of every name for draw `i` (deterministic in `(seed, i)` only, `draw_key`) and
        their `draw_code`. While the set is no robot, the truncated names are drawn again from
        their keys folded with the attempt number (at most `MAX_REDRAWS` times), so a set of draws
        that are all valid is the same with or without truncation (pure JAX: jit and vmap)."""
        dtype = params.R0.dtype
        if not self.kinds:
            return jnp.zeros((0,), dtype), jnp.zeros((), jnp.int32)
        keys = [jax.random.fold_in(draw_key(seed, i), j) for j in range(len(self.kinds))]
        truncate = jnp.ones(len(self.kinds), bool) if self.truncate is None else self.truncate
        vals = self._sample(keys, dtype)
        code = draw_code(params, self.names, vals)

        def cond(c):
            attempt, _, code = c
            return (code != 0) & jnp.any(truncate) & (attempt < MAX_REDRAWS)

        def body(c):
            attempt, vals, _ = c
            attempt = attempt + 1
            new = self._sample([jax.random.fold_in(k, attempt) for k in keys], dtype)
            vals = jnp.where(truncate, new, vals)
            return attempt, vals, draw_code(params, self.names, vals)

        _, vals, code = jax.lax.while_loop(cond, body, (jnp.zeros((), jnp.int32), vals, code))
        return vals, code

    def draw(self, params: RobotParams, n: int, seed: int = 0) -> tuple[np.ndarray, RobotParams]:
        """`n` robots: their values of `names` `(n, P)` and `params` with those values, stacked
        along a leading axis (a `RobotParams` pytree to `vmap` over); draw `i` is `draw_one(params,
        seed, i)`. `InputError` if a name is not a parameter of `params`, or if a set is still no
        robot after `MAX_REDRAWS` redraws."""
        for name in self.names:
            if parse_name(name)[0] != "R_m":
                try:
                    get_value(params, name)
                except (ValueError, IndexError) as e:
                    raise InputError(f"{self.source}: {e}") from None
        vals, code = _draw_many(self, params, seed, n)
        bad = int(np.sum(np.asarray(code) != 0))
        if bad:
            raise InputError(
                f"{self.source}: after {MAX_REDRAWS} redraws {bad} of {n} parameter sets are still no robot "
                "(a rule of RobotParams is broken); narrow the distribution."
            )
        vals = np.asarray(vals)
        return vals, stack_params(params, self.names, vals)

    def robot(self, params: RobotParams, vals, valid) -> RobotParams:
        """The robot of a draw, or the nominal one `params` for an invalid draw (only the drawn
        leaves change), so that an invalid draw's solve is an ordinary one."""
        p = with_values(params, self.names, vals)
        if self.names:
            p = jax.tree_util.tree_map(lambda a, b: a if a is b else jnp.where(valid, a, b), p, params)
        return p


@eqx.filter_jit
def _draw_many(unc: Uncertainty, params: RobotParams, seed, n: int):
    return jax.vmap(lambda i: unc.draw_one(params, seed, i))(jnp.arange(n))
