"""The torque- and gait-mode vector fields on scalar components ("struct of arrays"), for
batched solves.

Under `jax.vmap` a state stored as one `(16+N,)` array becomes a `(batch, 16+N)` array whose
components are strided, and every 3-vector of (3.4) a `(batch, 3)` array: XLA on CPU then
splits the right-hand side into dozens of small, badly vectorised kernels. Here the state is a
*tuple of scalars*, so that under `vmap` each component is one contiguous `(batch,)` vector,
and (3.4) is written out component by component (measurements: `docs/performance.md`).

For a single trial the same code is slower (every scalar becomes its own small operation in
the integrator's loop), which is why `simulate` uses this layout only when it is batched
(`jsphere.solve.batched.dispatch`). The equations are those of `jsphere.model.dynamics` (docstrings there);
`tests/solve/test_component_layout.py` checks the two implementations against each other to rounding (the gait
field against `jsphere.gaits.gaits._gait_field`).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from ...model.dynamics import applied_torques
from ...model.params import Derived, RobotParams
from ...model.state import Flat

# ------------------------------------------------------------- 3-vectors as tuples of scalars


def _cross(a, b):
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


def _dot(a, b):
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def _mv(M, v):
    """`M v` for `M` given as rows."""
    return tuple(_dot(r, v) for r in M)


def _mtv(M, v):
    """`M^T v` for `M` given as rows."""
    return tuple(M[0][j] * v[0] + M[1][j] * v[1] + M[2][j] * v[2] for j in range(3))


def _rows(A):
    """A constant or traced `(m, n)` array as a tuple of rows of scalars (nested tuples of
    scalars, as the discrete adjoint `jsphere.solve.batched.adjoint` gives them, are returned as they are)."""
    if isinstance(A, tuple):
        return A
    return tuple(tuple(A[i, j] for j in range(A.shape[1])) for i in range(A.shape[0]))


def _add(a, b):
    return tuple(x + y for x, y in zip(a, b))


def _sub(a, b):
    return tuple(x - y for x, y in zip(a, b))


def _scale(s, a):
    return tuple(s * x for x in a)


# --------------------------------------------------------------------------- layout


def to_components(z):
    """`(16+N,)` flat state -> tuple of `16+N` scalars."""
    return tuple(z[..., i] for i in range(z.shape[-1]))


def from_components(c):
    """Tuple of scalars (or of `(T,)` arrays) -> flat state(s) along the last axis."""
    return jnp.stack(c, axis=-1)


# --------------------------------------------------------------------------- the field


def unit(t):
    """A run-time one (NaN at a non-finite `t`), for `kept`."""
    return jnp.where(jnp.isfinite(t), 1.0, jnp.nan).astype(jnp.result_type(t, float))


def kept(tree, one):
    """`tree / one` with `one = unit(t)`: the same values (a division by one is exact), but a
    division is an expensive operation to XLA, so it computes each such value once, in its own
    kernel, instead of again inside every kernel that uses it; a reverse-mode derivative
    divides the value's cotangent by `one` too, with the same effect. Without these points
    XLA recomputes the Schur complement of (3.5) in each acceleration's kernel, and its VJP
    in each cotangent's. `one=None`: `tree` as it is."""
    if one is None:
        return tree
    return jax.tree_util.tree_map(lambda x: x / one, tree)


def adjoint_kept(tree, one, adjoint: bool):
    """`kept(tree, one)` in the form of the field the discrete adjoint differentiates
    (`adjoint`, `jsphere.solve.batched.adjoint`), `tree` as it is otherwise. For values whose
    cotangents feed the robot's parameter cotangents: materialised there, XLA no longer
    recomputes them in each parameter element's kernel; in the forward evaluation the same
    points would cost more than they save (`docs/performance.md`)."""
    return kept(tree, one) if adjoint else tree


def torque_field_components(p: RobotParams, d: Derived, K, z, one=None, *, adjoint: bool = False):
    """Rates of the flat state `[q, q_shell, omega, Omega, x, y, chi]` in torque mode, as a tuple.

    (3.4) with (3.5) for `(omega_dot, Omega_dot)` (the Schur complement of the constant
    `omega` block, Cramer's rule for the 3x3 solve, as in `solve_accelerations`), the
    quaternion kinematics of platform and shell, (2.3) for `(x_dot, y_dot)` and (2.4) for
    `chi_dot`. `K` is a tuple of the `N` axle torques; `z` a tuple of the `16+N` state
    components; `one`, if given, `unit(t)` (see `kept`); `adjoint`: the form the discrete
    adjoint differentiates (`adjoint_kept`: the same values). Identical in value to
    `jsphere.solve.fields._torque_field` (to rounding).
    """
    n = len(K)
    w, W = tuple(z[Flat.omega]), tuple(z[Flat.Omega])
    R = _platform_rows(z[Flat.q])
    g = R[2]
    B, D, r1, r2 = _blocks_and_forces(p, d, g, w, W, one, adjoint)
    Ainv, Sk = _rows(d.A_inv), _rows(d.Sk)
    # axle torques (torque gain, optional axle friction: `applied_torques`) and their moment Sk^T K
    dw = _sub(w, W)
    Ke = tuple(applied_torques(p, K[i], _dot(Sk[i], dw)) for i in range(n))
    tau = tuple(sum(Ke[i] * Sk[i][j] for i in range(n)) for j in range(3))
    r1, r2 = kept(_sub(r1, tau), one), _add(r2, tau)
    # Schur complement S = D - B^T A^-1 B (symmetric: its upper triangle), then
    # Omega_dot = S^-1 (r2 - B^T A^-1 r1), omega_dot = A^-1 (r1 - B Omega_dot). Each level is
    # kept before the next reads it; X = A^-1 B and the attitude rows are cheaper recomputed
    # where used than kept (a kernel and a divide per trial each).
    X = tuple(tuple(sum(Ainv[i][k] * B[k][j] for k in range(3)) for j in range(3)) for i in range(3))
    a1 = kept(_mv(Ainv, r1), one)
    Su = kept({(i, j): D[i][j] - sum(B[k][i] * X[k][j] for k in range(3)) for i in range(3) for j in range(i, 3)}, one)
    S = tuple(tuple(Su[min(i, j), max(i, j)] for j in range(3)) for i in range(3))
    rhs = kept(_sub(r2, _mtv(B, a1)), one)
    Wd = kept(_solve3(S, rhs), one)
    wd = _sub(a1, _mv(X, Wd))
    return _kinematic_rates(p, d, z, R, g, w, W, wd, Wd)


def _blocks_and_forces(p: RobotParams, d: Derived, g, w, W, one=None, adjoint=False):
    """`B`, `D` (`mass_blocks`) and `r1`, `r2` (`forces`) of (3.4) as tuples, for the attitude
    `g = gamma` and the rates `w = omega`, `W = Omega` (3-tuples of scalars); `one`, `adjoint`:
    see `adjoint_kept`, applied to these and to `I omega`, `J_ns (Omega - omega)`."""
    rm = tuple(p.r_m[i] for i in range(3))
    Jns, Jss, I = _rows(d.Jns), _rows(d.Jss), _rows(p.I)
    mR0 = p.m * p.R0
    MR2 = (p.m + p.m0) * p.R0**2
    grm, gg = _dot(g, rm), _dot(g, g)
    B = tuple(
        tuple(Jns[i][j] - Jss[i][j] + mR0 * ((grm if i == j else 0.0) - g[i] * rm[j]) for j in range(3))
        for i in range(3)
    )
    D = tuple(
        tuple((p.I0 if i == j else 0.0) + Jss[i][j] + MR2 * ((gg if i == j else 0.0) - g[i] * g[j]) for j in range(3))
        for i in range(3)
    )
    B, D = adjoint_kept((B, D), one, adjoint)
    gWxw = _cross(g, _cross(W, w))
    Iw, Jv = adjoint_kept((_mv(I, w), _mv(Jns, _sub(W, w))), one, adjoint)
    r1 = _sub(
        _sub(_add(_scale(-1.0, _cross(w, Iw)), _cross(Jv, w)), _scale(mR0, _cross(rm, gWxw))),
        _scale(p.m * p.g, _cross(rm, g)),
    )
    Wg = _dot(W, g)
    r2 = _sub(
        _sub(
            _sub(_scale(-MR2, _cross(g, gWxw)), _scale(mR0, _cross(g, _cross(w, _cross(w, rm))))),
            _scale(p.I0, _cross(w, W)),
        ),
        _scale(p.c_roll, _sub(W, _scale(Wg, g))),
    )
    return (B, D, *adjoint_kept((r1, r2), one, adjoint))


def _solve3(M, r):
    """`M^-1 r` for a 3x3 `M` given as rows (Cramer's rule, as `jsphere.model.rotations.solve3`)."""
    c0, c1, c2 = _cross(M[1], M[2]), _cross(M[2], M[0]), _cross(M[0], M[1])
    idet = 1.0 / _dot(M[0], c0)
    return tuple((c0[i] * r[0] + c1[i] * r[1] + c2[i] * r[2]) * idet for i in range(3))


def _platform_rows(q):
    """Rows alpha, beta, gamma of `Q^T` (the rotation matrix of the normalised quaternion)."""
    qw, qx, qy, qz = q
    inv = 1.0 / jnp.sqrt(qw * qw + qx * qx + qy * qy + qz * qz)
    a, b, c, e = qw * inv, qx * inv, qy * inv, qz * inv
    return (
        (1 - 2 * (c * c + e * e), 2 * (b * c - a * e), 2 * (b * e + a * c)),
        (2 * (b * c + a * e), 1 - 2 * (b * b + e * e), 2 * (c * e - a * b)),
        (2 * (b * e - a * c), 2 * (c * e + a * b), 1 - 2 * (b * b + c * c)),
    )


def _kinematic_rates(p: RobotParams, d: Derived, z, R, g, w, W, wd, Wd):
    """The flat state's rates from the accelerations `wd`, `Wd`: the quaternion kinematics of
    platform and shell, (2.3) for `(x_dot, y_dot)` (with the attitude `g`) and (2.4)."""
    qw, qx, qy, qz, sw, sx, sy, sz = z[Flat.quats]
    # q_dot = q (x) (0, omega) / 2, q_shell_dot = (0, Q^T Omega) (x) q_shell / 2
    w0, w1, w2 = w
    dq = (
        0.5 * (-qx * w0 - qy * w1 - qz * w2),
        0.5 * (qw * w0 + qy * w2 - qz * w1),
        0.5 * (qw * w1 + qz * w0 - qx * w2),
        0.5 * (qw * w2 + qx * w1 - qy * w0),
    )
    f0, f1, f2 = _mv(R, W)
    dqs = (
        0.5 * (-f0 * sx - f1 * sy - f2 * sz),
        0.5 * (f0 * sw + f1 * sz - f2 * sy),
        0.5 * (f1 * sw + f2 * sx - f0 * sz),
        0.5 * (f2 * sw + f0 * sy - f1 * sx),
    )
    vf = _mv(R, _scale(p.R0, _cross(W, g)))  # (2.3) in fixed components
    Sk = _rows(d.Sk)
    dw = _sub(w, W)
    chi_dot = tuple(-_dot(Sk[i], dw) for i in range(len(Sk)))
    return dq + dqs + tuple(wd) + tuple(Wd) + (vf[0], vf[1]) + chi_dot


def gait_field_components(p: RobotParams, d: Derived, kin, z, one=None):
    """Rates of the flat state in gait mode (`jsphere.gaits.gaits._gait_field`), as a tuple.

    `kin` is the 9-tuple `(gamma, omega, omega_dot)` the gait prescribes at this time;
    `Omega_dot` from the control-free sum of (3.4), `(B + D) Omega_dot = r1 + r2 - (A + B^T)
    omega_dot` (`free_Omega_dot`), then the kinematics with the prescribed `gamma`; `one` as
    in `torque_field_components`.
    """
    g, w, wd = tuple(kin[0:3]), tuple(kin[3:6]), tuple(kin[6:9])
    W = tuple(z[Flat.Omega])
    B, D, r1, r2 = _blocks_and_forces(p, d, g, w, W)
    M = tuple(_add(Bi, Di) for Bi, Di in zip(B, D))
    M, rhs = kept((M, _sub(_add(r1, r2), _add(_mv(_rows(d.A), wd), _mtv(B, wd)))), one)
    Wd = kept(_solve3(M, rhs), one)
    return _kinematic_rates(p, d, z, kept(_platform_rows(z[Flat.q]), one), g, w, W, wd, Wd)
