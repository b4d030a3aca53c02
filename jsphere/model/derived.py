"""The quantities of (2.4) and (3.4) that depend on a robot's parameters only (`derive`)."""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, Float

from .._runtime.quick_compile import eager_jit
from .linalg import cross, dot, inv3, outer


class Derived(eqx.Module):
    """Quantities of (2.4) and (3.4) that depend on the parameters only.

    `s (N,3)`: `s_i = r_i x alpha_i`; `k (N,)`: `k_i = R0/(Rw (s_i, n_i))`;
    `Sk (N,3)`: rows `k_i s_i` (so `chi_dot = -Sk (omega - Omega)`, and the torque term of
    (3.4) is `Sk^T K`); `Jss, Jsn, Jns`: the wheel-inertia tensors of (3.4);
    `A`, `A_inv`: the constant `omega`-block `I + Jss - Jns - Jsn` of the mass matrix and its
    inverse; `Sk_pinv (3,N)`: `(Sk^T Sk)^-1 Sk^T` (least-squares inverse of the wheel map);
    `Sk_T_pinv (N,3)`: `Sk (Sk^T Sk)^-1`, giving the least-norm torques `K` of a required
    `Sk^T K`. The constant parts of the blocks of (3.4), so that the vector fields do not
    recompute them: `B0 = Jns - Jss` and `D0 = I0 E + Jss` (`B`, `D` without their
    `gamma`-terms), `mR0 = m R0`, `MR2 = (m + m0) R0^2`, `mg = m g`.
    """

    s: Float[Array, "N 3"]
    k: Float[Array, " N"]
    Sk: Float[Array, "N 3"]
    Jss: Float[Array, "3 3"]
    Jsn: Float[Array, "3 3"]
    Jns: Float[Array, "3 3"]
    A: Float[Array, "3 3"]
    A_inv: Float[Array, "3 3"]
    Sk_pinv: Float[Array, "3 N"]
    Sk_T_pinv: Float[Array, "N 3"]
    B0: Float[Array, "3 3"]
    D0: Float[Array, "3 3"]
    mR0: Float[Array, ""]
    MR2: Float[Array, ""]
    mg: Float[Array, ""]


@eager_jit
def derive(p) -> Derived:
    """Compute the parameter-only quantities of (2.4) and (3.4) once (jit folds them). An eager
    call is one compiled program, not one per operation: a new process's first `derive` costs
    one small compilation instead of about twenty."""
    s = cross(p.wheel_r, p.wheel_alpha)
    k = p.R0 / (p.Rw * dot(s, p.wheel_n))
    j = p.j
    Sk = k[:, None] * s
    Jss = jnp.sum((j * k * k)[:, None, None] * outer(s, s), axis=0)
    Jsn = jnp.sum((j * k)[:, None, None] * outer(s, p.wheel_n), axis=0)
    Jns = jnp.swapaxes(Jsn, -1, -2)
    A = p.I + Jss - Jns - Jsn
    G = inv3(Sk.T @ Sk)
    return Derived(
        s=s,
        k=k,
        Sk=Sk,
        Jss=Jss,
        Jsn=Jsn,
        Jns=Jns,
        A=A,
        A_inv=inv3(A),
        Sk_pinv=G @ Sk.T,
        Sk_T_pinv=Sk @ G,
        B0=Jns - Jss,
        D0=p.I0 * jnp.eye(3, dtype=A.dtype) + Jss,
        mR0=p.m * p.R0,
        MR2=(p.m + p.m0) * p.R0**2,
        mg=p.m * p.g,
    )
