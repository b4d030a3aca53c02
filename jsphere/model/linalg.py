"""Small-vector algebra used on the hot path.

Everything here works on the trailing axes only, so it batches under `jax.vmap` without
reshaping. 3x3 solves use the adjugate (Cramer's rule): for the tiny, well-conditioned,
symmetric positive definite blocks of (3.4) it is exact to rounding and, on CPU, faster than
`jnp.linalg.solve` (`docs/performance.md`).
"""

from __future__ import annotations

import jax.numpy as jnp
from jaxtyping import Array, Float


def cross(a: Float[Array, "... 3"], b: Float[Array, "... 3"]) -> Float[Array, "... 3"]:
    """`a x b`, written out (faster than `jnp.cross` inside vmapped vector fields).

    The components are kept as `(..., 1)` slices and joined by one `concatenate`: 16 primitive
    operations against 22 for indexing and `stack`, the same arithmetic. (A contraction with
    the Levi-Civita tensor is 2 operations but ~1.5x slower vector fields on CPU,
    `docs/performance.md`.)
    """
    a1, a2, a3 = a[..., 0:1], a[..., 1:2], a[..., 2:3]
    b1, b2, b3 = b[..., 0:1], b[..., 1:2], b[..., 2:3]
    return jnp.concatenate([a2 * b3 - a3 * b2, a3 * b1 - a1 * b3, a1 * b2 - a2 * b1], axis=-1)


def dot(a: Float[Array, "... n"], b: Float[Array, "... n"]) -> Float[Array, "..."]:
    return jnp.sum(a * b, axis=-1)


def outer(a: Float[Array, "... 3"], b: Float[Array, "... 3"]) -> Float[Array, "... 3 3"]:
    """`a (x) b` with `(a (x) b)_ij = a_i b_j` (the paper's tensor product)."""
    return a[..., :, None] * b[..., None, :]


def matvec(M: Float[Array, "... m n"], v: Float[Array, "... n"]) -> Float[Array, "... m"]:
    return jnp.sum(M * v[..., None, :], axis=-1)


def inv3(M: Float[Array, "... 3 3"]) -> Float[Array, "... 3 3"]:
    """Inverse of a 3x3 matrix by its adjugate."""
    r0, r1, r2 = M[..., 0, :], M[..., 1, :], M[..., 2, :]
    c0, c1, c2 = cross(r1, r2), cross(r2, r0), cross(r0, r1)
    det = dot(r0, c0)
    adj = jnp.stack([c0, c1, c2], axis=-1)  # columns are the cofactor rows
    return adj / det[..., None, None]


def solve3(M: Float[Array, "... 3 3"], b: Float[Array, "... 3"]) -> Float[Array, "... 3"]:
    """Solve `M x = b` for a 3x3 `M` by Cramer's rule."""
    r0, r1, r2 = M[..., 0, :], M[..., 1, :], M[..., 2, :]
    c0, c1, c2 = cross(r1, r2), cross(r2, r0), cross(r0, r1)
    det = dot(r0, c0)
    x = c0 * b[..., 0:1] + c1 * b[..., 1:2] + c2 * b[..., 2:3]
    return x / det[..., None]


# --------------------------------------------------------------------------- quaternions
