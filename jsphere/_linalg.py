"""Small-vector algebra used on the hot path.

Everything here works on the trailing axes only, so it batches under `jax.vmap` without
reshaping. 3x3 solves use the adjugate (Cramer's rule): on CPU this is several times faster
than `jnp.linalg.solve` for the tiny systems of (3.4), and it is exact to rounding for the
well-conditioned, symmetric positive definite blocks that occur there.

Quaternions are `(w, x, y, z)`, scalar first. `rotmat(q)` rotates *body* components into
*fixed* components (the convention of the trial CSV format).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float


def as_array(x, dtype) -> Array:
    """`jnp.asarray(x, dtype)`, except that a Python or NumPy value is converted by NumPy first.

    Converting a Python float with `jnp.asarray` is an XLA program (a weak-to-strong
    `convert_element_type`): compiled once, then loaded from the persistent cache by every new
    process, ~50 ms each in a second `jsphere reproduce` (benchmarks/NOTES.md, session 11).
    JAX arrays and tracers go through `jnp.asarray` unchanged.
    """
    if isinstance(x, (jax.Array, jax.core.Tracer)):
        return jnp.asarray(x, dtype=dtype)
    if isinstance(x, (list, tuple)) and any(isinstance(v, (jax.Array, jax.core.Tracer)) for v in jax.tree_util.tree_leaves(x)):
        return jnp.asarray(x, dtype=dtype)
    return jax.device_put(np.asarray(x, dtype=dtype))  # (`jnp.asarray` would lower a copy program)


def to_jax(x) -> Array:
    """`jnp.asarray(x)` (dtype and weak type alike) without the copy program `jnp.asarray` lowers
    for a Python or NumPy value (see `as_array`)."""
    if isinstance(x, (jax.Array, jax.core.Tracer)):
        return x
    if isinstance(x, (bool, int, float, complex, np.ndarray, np.generic)):
        return jax.device_put(x)
    return jnp.asarray(x)


def under_jit() -> bool:
    """Whether this code is being traced by `jax.jit` (a constant made here is then a tracer).

    A NumPy scalar becomes a device array without compiling anything, unlike an eager JAX
    operation (e.g. `jnp.zeros(()) + 0.0`, one more small program per process).
    """
    return isinstance(jax.device_put(np.float32(0.0)), jax.core.Tracer)


def cross(a: Float[Array, "... 3"], b: Float[Array, "... 3"]) -> Float[Array, "... 3"]:
    """`a x b`, written out (faster than `jnp.cross` inside vmapped vector fields)."""
    a1, a2, a3 = a[..., 0], a[..., 1], a[..., 2]
    b1, b2, b3 = b[..., 0], b[..., 1], b[..., 2]
    return jnp.stack([a2 * b3 - a3 * b2, a3 * b1 - a1 * b3, a1 * b2 - a2 * b1], axis=-1)


def dot(a: Float[Array, "... n"], b: Float[Array, "... n"]) -> Float[Array, "..."]:
    return jnp.sum(a * b, axis=-1)


def outer(a: Float[Array, "... 3"], b: Float[Array, "... 3"]) -> Float[Array, "... 3 3"]:
    """`a (x) b` with `(a (x) b)_ij = a_i b_j` (the paper's tensor product)."""
    return a[..., :, None] * b[..., None, :]


def matvec(M: Float[Array, "... m n"], v: Float[Array, "... n"]) -> Float[Array, "... m"]:
    return jnp.sum(M * v[..., None, :], axis=-1)


def det3(M: Float[Array, "... 3 3"]) -> Float[Array, "..."]:
    return dot(M[..., 0, :], cross(M[..., 1, :], M[..., 2, :]))


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


def quat_mul(p: Float[Array, "... 4"], q: Float[Array, "... 4"]) -> Float[Array, "... 4"]:
    """Hamilton product `p (x) q`."""
    pw, pv = p[..., :1], p[..., 1:]
    qw, qv = q[..., :1], q[..., 1:]
    w = pw * qw - dot(pv, qv)[..., None]
    v = pw * qv + qw * pv + cross(pv, qv)
    return jnp.concatenate([w, v], axis=-1)


def quat_rate_body(q: Float[Array, "... 4"], w: Float[Array, "... 3"]) -> Float[Array, "... 4"]:
    """`q_dot = q (x) (0, w) / 2` for an angular velocity `w` in body components."""
    zero = jnp.zeros_like(w[..., :1])
    return 0.5 * quat_mul(q, jnp.concatenate([zero, w], axis=-1))


def quat_rate_fixed(q: Float[Array, "... 4"], w: Float[Array, "... 3"]) -> Float[Array, "... 4"]:
    """`q_dot = (0, w) (x) q / 2` for an angular velocity `w` in fixed components."""
    zero = jnp.zeros_like(w[..., :1])
    return 0.5 * quat_mul(jnp.concatenate([zero, w], axis=-1), q)


def quat_normalize(q: Float[Array, "... 4"]) -> Float[Array, "... 4"]:
    return q / jnp.sqrt(dot(q, q))[..., None]


def rotmat(q: Float[Array, "... 4"]) -> Float[Array, "... 3 3"]:
    """Rotation matrix of a (not necessarily unit) quaternion; body -> fixed components.

    For the platform quaternion this is `Q^T` of (2.1): its rows are `alpha, beta, gamma`.
    """
    q = quat_normalize(q)
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    r0 = jnp.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1)
    r1 = jnp.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1)
    r2 = jnp.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1)
    return jnp.stack([r0, r1, r2], axis=-2)


@jax.jit  # one compiled program when called eagerly (State constructors), not ~25 small ones
def quat_from_rotmat(R: Float[Array, "3 3"]) -> Float[Array, "4"]:
    """Unit quaternion (w >= 0) of a rotation matrix (Shepperd's method, branch-free)."""
    R = jnp.asarray(R)
    tr = R[0, 0] + R[1, 1] + R[2, 2]
    cands = jnp.stack(
        [
            jnp.stack([1 + tr, R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]]),
            jnp.stack([R[2, 1] - R[1, 2], 1 + 2 * R[0, 0] - tr, R[0, 1] + R[1, 0], R[0, 2] + R[2, 0]]),
            jnp.stack([R[0, 2] - R[2, 0], R[0, 1] + R[1, 0], 1 + 2 * R[1, 1] - tr, R[1, 2] + R[2, 1]]),
            jnp.stack([R[1, 0] - R[0, 1], R[0, 2] + R[2, 0], R[1, 2] + R[2, 1], 1 + 2 * R[2, 2] - tr]),
        ]
    )
    k = jnp.argmax(jnp.stack([tr, R[0, 0], R[1, 1], R[2, 2]]))
    q = cands[k]
    q = q / jnp.linalg.norm(q)
    return jnp.where(q[0] < 0, -q, q)


@jax.jit
def rotation_between(a: Float[Array, "3"], b: Float[Array, "3"]) -> Float[Array, "3 3"]:
    """The smallest rotation taking unit vector `a` onto unit vector `b` (Rodrigues).

    Singular only for `b = -a`.
    """
    v = cross(a, b)
    c = dot(a, b)
    vx = jnp.array(
        [[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]], dtype=jnp.result_type(a, b)
    )
    return jnp.eye(3, dtype=vx.dtype) + vx + (vx @ vx) / (1.0 + c)
