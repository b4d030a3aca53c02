"""Sine and cosine in elementwise arithmetic, for float64 code on batches.

XLA's CPU backend evaluates a float64 `sin` or `cos` one element at a time, at about 8 ns
per element on this project's machines, against about 0.3 ns for a multiply; in batched
gait solves the kinematics' sines and cosines of each trial's angles took a sixth (shared
steps) to almost half (per-trial steps) of the time
(`docs/decisions/sine-and-cosine-in-elementwise-arithmetic.md`). Here they are polynomials,
which XLA vectorises and fuses into the surrounding kernels (about 1 ns per element):

- **Reduction** (Cody and Waite): `x = k pi/2 + r`, `k = round(2 x / pi)`, with `pi/2` split
  into three parts of which the first two have 33 significant bits, so that `k * PIO2_1` and
  `k * PIO2_2` are exact for `|k| < 2^20` (`|x| <= LIMIT = 2^20`), whether or not XLA fuses a
  product with its difference, and `r` is accurate to a few units in the last place of
  `|r| <= pi/4`.
- **Kernels** on `[-pi/4, pi/4]`: the minimax polynomials of fdlibm's `__kernel_sin` and
  `__kernel_cos` (Sun Microsystems, 1993; their coefficients below), of degree 13 and 14.
- **Quadrant**: `k mod 4` picks `+-sin r` or `+-cos r`.

Against the C library (`tests/numerics/test_trig.py`): within one unit in the last place of
1 (2.2e-16) for every `|x| <= LIMIT` tried, and within 2 units in the last place of the value
on `[-pi, pi]`; small angles keep their relative accuracy. Beyond `LIMIT` (about 1.05e6) the
reduction would lose digits (every one of them near 1e16), so there both are NaN rather than a
wrong number; the gaits' angles and times are far below it. Their
derivatives are each other (`jax.custom_jvp`), so a `jvp` or `grad` through them is the same
polynomials again. Other dtypes use `jnp.sin`, `jnp.cos`.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

#: the largest `|x|` evaluated; beyond, NaN (module docstring)
LIMIT = 2.0**20
#: `pi/2 = PIO2_1 + PIO2_2 + PIO2_3` (fdlibm's split: 33 + 33 + 53 significant bits)
PIO2_1 = 1.57079632673412561417e00
PIO2_2 = 6.07710050630396597660e-11
PIO2_3 = 2.02226624871116645580e-21
#: `sin r = r + r^3 (S1 + r^2 S2 + ... + r^10 S6)` on `|r| <= pi/4` (fdlibm's `__kernel_sin`)
_S = (
    -1.66666666666666324348e-01,
    8.33333333332248946124e-03,
    -1.98412698298579493134e-04,
    2.75573137070700676789e-06,
    -2.50507602534068634195e-08,
    1.58969099521155010221e-10,
)
#: `cos r = 1 - r^2 / 2 + r^4 (C1 + r^2 C2 + ... + r^10 C6)` (fdlibm's `__kernel_cos`)
_C = (
    4.16666666666666019037e-02,
    -1.38888888888741095749e-03,
    2.48015872894767294178e-05,
    -2.75573143513906633035e-07,
    2.08757232129817482790e-09,
    -1.13596475577881948265e-11,
)


def _horner(z, coeffs):
    acc = coeffs[-1]
    for c in coeffs[-2::-1]:
        acc = c + z * acc
    return acc


@jax.custom_jvp
def _sincos64(x):
    k = jnp.round(x * (2.0 / math.pi))
    r = ((x - k * PIO2_1) - k * PIO2_2) - k * PIO2_3
    z = r * r
    s = r + r * z * _horner(z, _S)
    c = 1.0 - 0.5 * z + z * z * _horner(z, _C)
    q = k - 4.0 * jnp.floor(0.25 * k)  # the quadrant, 0 ... 3
    odd = (q == 1.0) | (q == 3.0)
    sin = jnp.where(odd, c, s)
    cos = jnp.where(odd, s, c)
    sin = jnp.where(q >= 2.0, -sin, sin)
    cos = jnp.where((q == 1.0) | (q == 2.0), -cos, cos)
    inside = jnp.abs(x) <= LIMIT
    return jnp.where(inside, sin, jnp.nan), jnp.where(inside, cos, jnp.nan)


@_sincos64.defjvp
def _sincos64_jvp(primals, tangents):
    (x,), (dx,) = primals, tangents
    s, c = _sincos64(x)
    return (s, c), (c * dx, -s * dx)


def sincos(x: Float[ArrayLike, "..."]) -> tuple[Float[Array, "..."], Float[Array, "..."]]:
    """`(sin x, cos x)` elementwise: one reduction for both (module docstring)."""
    x = jnp.asarray(x)
    if x.dtype != jnp.float64:
        return jnp.sin(x), jnp.cos(x)
    return _sincos64(x)


def sin(x: Float[ArrayLike, "..."]) -> Float[Array, "..."]:
    """`sin x` elementwise (module docstring); for float64 a polynomial that XLA vectorises."""
    return sincos(x)[0]


def cos(x: Float[ArrayLike, "..."]) -> Float[Array, "..."]:
    """`cos x` elementwise (module docstring); for float64 a polynomial that XLA vectorises."""
    return sincos(x)[1]
