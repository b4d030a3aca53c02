"""Rotations: quaternions `(w, x, y, z)`, scalar first, and rotation matrices.

`rotmat(q)` rotates *body* components into *fixed* components (the convention of the trial CSV
format).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from .linalg import cross, dot


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
