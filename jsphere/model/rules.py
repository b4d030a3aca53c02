"""The rules every robot's parameter set meets (`RULES`): checked with NumPy when a
`RobotParams` is made (`validate`), and with `jax.numpy` inside compiled code (`rule_code`, for
the parameter sets `monte_carlo` draws)."""

from __future__ import annotations

from typing import Any, Callable, NamedTuple

import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Int

from .._runtime.errors import InputError
from .fields import FIELDS, TABLE


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


def _any_core(xp, x, k: int):
    """`x` reduced with `any` over its last `k` dimensions (all of them if it has fewer)."""
    k = min(k, x.ndim)
    return xp.any(x, axis=tuple(range(-k, 0))) if k else x


def _finite_rule(f: str) -> Rule:
    return Rule(
        f,
        f"{f} not finite",
        lambda xp, a: _any_core(xp, ~xp.isfinite(a[f]), TABLE[f].ndim),
        lambda a: "must be finite (got NaN or inf).",
    )


def _sign_rule(f: str, strict: bool, what: str) -> Rule:
    """`f` must be `> 0` (`strict`) or `>= 0`; `what` starts the message."""
    return Rule(
        f,
        f"{f} {'<=' if strict else '<'} 0",
        (lambda xp, a: a[f] <= 0) if strict else (lambda xp, a: a[f] < 0),
        lambda a: f"{what}; got {a[f]}.",
    )


def _metres_rule(f: str) -> Rule:
    return Rule(
        f,
        f"{f} > 10 m",
        lambda xp, a: a[f] > 10.0,
        lambda a: "is larger than 10 m: lengths are in metres, not millimetres.",
    )


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
    *(_finite_rule(f) for f in FIELDS),
    *(
        _sign_rule(f, True, f"must be > 0 {u}")
        for f, u in (("R0", "m"), ("Rw", "m"), ("m0", "kg"), ("m", "kg"), ("I0", "kg m^2"))
    ),
    _sign_rule("j", False, "wheel axial inertia must be >= 0 kg m^2"),
    *(_sign_rule(f, False, "damping must be >= 0 N m s") for f in ("c_roll", "c_axle")),
    _sign_rule("k_tau", True, "torque gain (applied over commanded axle torque) must be > 0 (1: as commanded)"),
    _sign_rule("g", False, "must be >= 0 m/s^2 (use 9.81)"),
    _metres_rule("R0"),
    _metres_rule("Rw"),
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
_N_FINITE = len(FIELDS)


def _fail(field: str, msg: str):
    raise InputError(f"RobotParams.{field}: {msg}")


def _check_rules(rules, a: dict) -> None:
    for rule in rules:
        with np.errstate(divide="ignore", invalid="ignore"):
            broken = np.any(rule.broken(np, a))
        if broken:
            _fail(rule.field, rule.message(a))


def validate(p) -> None:
    """Check every field of a concrete `RobotParams`; raise `InputError` (a `ValueError`) naming
    the field: the shapes, then every rule of `RULES`.

    Leading batch dimensions (stacked parameter sets) are allowed on every field.
    """
    a = {f: np.asarray(getattr(p, f), dtype=np.float64) for f in FIELDS}
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


def rule_code(p) -> Int[Array, "..."]:
    """0 where the parameter set `p` meets every rule of `RULES`, else `1 +` the index of the
    first rule it breaks (the one `validate` would report): `RULES[code - 1].reason` names it.

    Pure `jax.numpy` (traceable and vmappable; one code per set of stacked sets), for
    parameter sets made inside compiled code, which `validate` cannot see. Shapes are not
    checked (they come from a validated set).
    """
    a = {f: getattr(p, f) for f in FIELDS}
    code = jnp.zeros(jnp.shape(a["R0"]), jnp.int32)
    for k in reversed(range(len(RULES))):
        code = jnp.where(RULES[k].broken(jnp, a), k + 1, code)
    return code


def rule_reason(code: int) -> str:
    """The short name of the rule broken by a set of `rule_code` `code` (`"valid"` for 0)."""
    return "valid" if code == 0 else RULES[int(code) - 1].reason
