"""Rotations: quaternions `(w, x, y, z)`, scalar first, rotation vectors and rotation matrices.

`rotmat(q)` rotates *body* components into *fixed* components (the convention of the trial CSV
format). The JAX functions serve the model and the fit; the `_np` twins at the end do the same in
float64 NumPy for the capture readers and the verdict.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
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
    vx = jnp.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]], dtype=jnp.result_type(a, b))
    return jnp.eye(3, dtype=vx.dtype) + vx + (vx @ vx) / (1.0 + c)


def quat_conj(q: Float[Array, "... 4"]) -> Float[Array, "... 4"]:
    """Conjugate (the inverse of a unit quaternion)."""
    return q * jnp.array([1.0, -1.0, -1.0, -1.0], q.dtype)


def quat_exp(v: Float[Array, "... 3"]) -> Float[Array, "... 4"]:
    """Unit quaternion of the rotation vector `v` [rad] (smooth at 0)."""
    a2 = dot(v, v)
    small = a2 < 1e-16
    a = jnp.sqrt(jnp.where(small, 1.0, a2))
    s = jnp.where(small, 0.5 - a2 / 48.0, jnp.sin(0.5 * a) / a)
    c = jnp.where(small, 1.0 - a2 / 8.0, jnp.cos(0.5 * a))
    return jnp.concatenate([c[..., None], s[..., None] * v], axis=-1)


def quat_log(q: Float[Array, "... 4"]) -> Float[Array, "... 3"]:
    """Rotation vector [rad] of a unit quaternion (the shorter of the two rotations; smooth at 0)."""
    q = jnp.where(q[..., :1] < 0, -q, q)
    w, v = q[..., 0], q[..., 1:]
    n2 = dot(v, v)
    small = n2 < 1e-16
    n = jnp.sqrt(jnp.where(small, 1.0, n2))
    f = jnp.where(small, 2.0 / w, 2.0 * jnp.arctan2(n, w) / n)
    return f[..., None] * v


# ----------------------------------------------------------------------------- NumPy twins
# float64 NumPy versions for the capture readers and the verdict, which work on whole files
# outside JAX (the same conventions as the JAX functions above). Conversions go through
# `scipy.spatial.transform.Rotation` (imported when first used); the product and the logarithm
# stay here, since they must carry the NaN of a capture gap through element by element.


def _stacked(a, tail: tuple[int, ...], out: tuple[int, ...], convert) -> np.ndarray:
    """`convert` (a `scipy.spatial.transform.Rotation` conversion, imported when first used) of
    the `(..., *tail)` array `a` as one stack, shaped back to `(..., *out)`."""
    from scipy.spatial.transform import Rotation

    a = np.asarray(a, float)
    lead = a.shape[: a.ndim - len(tail)]
    a = a.reshape((-1, *tail))
    return np.zeros((*lead, *out)) if a.shape[0] == 0 else convert(Rotation, a).reshape((*lead, *out))


def quat_mul_np(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Hamilton product `p (x) q` of `(..., 4)` scalar-first quaternions (NumPy twin of `quat_mul`)."""
    pw, px, py, pz = np.moveaxis(p, -1, 0)
    qw, qx, qy, qz = np.moveaxis(q, -1, 0)
    return np.stack(
        [
            pw * qw - px * qx - py * qy - pz * qz,
            pw * qx + px * qw + py * qz - pz * qy,
            pw * qy - px * qz + py * qw + pz * qx,
            pw * qz + px * qy - py * qx + pz * qw,
        ],
        axis=-1,
    )


def quat_conj_np(q: np.ndarray) -> np.ndarray:
    """Conjugates of `(..., 4)` quaternions (NumPy twin of `quat_conj`)."""
    return np.asarray(q) * np.array([1.0, -1.0, -1.0, -1.0])


def quat_from_rotvec_np(r: np.ndarray) -> np.ndarray:
    """Unit quaternion of the rotation by `|r|` [rad] about `r/|r|` (`(..., 3)` -> `(..., 4)`;
    NumPy twin of `quat_exp`: `Rotation.from_rotvec`)."""
    return _stacked(r, (3,), (4,), lambda R, r: R.from_rotvec(r).as_quat(scalar_first=True))


def quat_log_np(q: np.ndarray) -> np.ndarray:
    """Rotation vector [rad] of unit quaternions `(..., 4)` (the shorter rotation; NumPy twin of
    `quat_log`)."""
    q = np.where(q[..., :1] < 0, -q, q)
    w, v = q[..., 0], q[..., 1:]
    n = np.linalg.norm(v, axis=-1)
    big = n > 1e-12
    f = np.where(big, 2.0 * np.arctan2(n, w) / np.where(big, n, 1.0), 2.0 / w)
    return f[..., None] * v


def quat_from_rotmat_np(R: np.ndarray) -> np.ndarray:
    """Unit quaternions `(..., 4)` (w >= 0) of rotation matrices `(..., 3, 3)` (NumPy twin of
    `quat_from_rotmat`, for stacks of matrices: `Rotation.from_matrix`)."""
    q = _stacked(R, (3, 3), (4,), lambda R, m: R.from_matrix(m).as_quat(scalar_first=True))
    return np.where(q[..., :1] < 0, -q, q) + 0.0  # (+ 0.0: no negative zeros in written files)


def rotmat_np(q: np.ndarray) -> np.ndarray:
    """Rotation matrices `(..., 3, 3)` of quaternions `(..., 4)` (w, x, y, z), body -> fixed
    (NumPy twin of `rotmat`: `Rotation.from_quat`)."""
    return _stacked(q, (4,), (3, 3), lambda R, q: R.from_quat(q, scalar_first=True).as_matrix())
