"""Linear-quadratic regulators for the error of `state_error`: the time-varying one along a
plan (backward Riccati recursion over the control intervals) and the terminal one that holds
the target at rest (the infinite-horizon regulator on the controllable part).

**The conserved mode.** The wheel torques are internal: they cancel in the control-free sum of
(3.4), and to first order they conserve the angular momentum about the vertical. Linearised at
rest, the 11-dimensional error has exactly one mode no torque changes: the left null vector `w`
of `[A - I, B]` (a Popov-Belevitch-Hautus test at the eigenvalue 1 of the discrete map; on the
paper's robot `w ~ omega_3 + 0.58 Omega_3`, the momentum about the vertical). The algebraic
Riccati equation of the full error has no stabilising solution. `terminal_regulator` works in
the orthonormal coordinates `y = V^T e` of the complement of `w` (`V^T w = 0`), where the pair
`(V^T A V, V^T B)` is stabilisable, solves the Riccati equation there and returns
`P = V P_y V^T`, `G = G_y V^T`: the conserved mode carries no cost and no feedback. Along the
plan the mode is conserved as well (`w_{k+1}^T B_k = 0` to the integrator's accuracy), so its
weight in `Q` does not change the gains of the recursion, which starts from that `P`.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from ..._runtime.checks import real
from ..._runtime.errors import InputError

#: iterations of the doubling algorithm of `dare` (quadratic convergence)
DOUBLING_STEPS = 60


class Weights(eqx.Module):
    """Weights of the regulator's cost `sum_k e_k^T Q e_k + du_k^T R du_k` per control interval,
    with `Q = diag(q_pos (2), q_att (3), q_rate (6))`, `R = r I`: the inverse squares of the
    error and torque one accepts (Bryson's rule). Defaults: 2 mm, 0.05 rad, 0.5 rad/s, 0.02 N m.

    `expected`: the errors the gains must handle within the torque limit, standard deviations of
    position [m], attitude [rad] and angular velocities [rad/s]: `r` is raised (doubled until
    it holds) so that `|K_ff,i| + |G_i diag(expected)|_2 <= max_torque` on every row and wheel.
    """

    q_pos: float = 2.5e5
    q_att: float = 400.0
    q_rate: float = 4.0
    r: float = 2500.0
    expected: tuple[float, float, float] = (0.005, 0.02, 0.05)

    def __check_init__(self):
        for name in ("q_pos", "q_att", "q_rate", "r"):
            real("Weights", name, getattr(self, name), strict=True)
        if not isinstance(self.expected, (tuple, list)) or len(self.expected) != 3:
            raise InputError(f"Weights.expected must be (position m, attitude rad, rate rad/s); got {self.expected!r}.")
        for v in self.expected:
            real("Weights", "expected", v)

    def Q(self, dtype=jnp.float64) -> Float[Array, "11 11"]:
        return jnp.diag(jnp.asarray([self.q_pos] * 2 + [self.q_att] * 3 + [self.q_rate] * 6, dtype))

    def sigma(self, dtype=jnp.float64) -> Float[Array, " 11"]:
        """The expected errors as an 11-vector (`expected` spread over the error's parts)."""
        e = self.expected
        return jnp.asarray([e[0]] * 2 + [e[1]] * 3 + [e[2]] * 6, dtype)

    def to_json(self) -> dict:
        return {
            "q_pos": self.q_pos,
            "q_att": self.q_att,
            "q_rate": self.q_rate,
            "r": self.r,
            "expected": list(self.expected),
        }


@jax.jit
def riccati(
    A: Float[Array, "M n n"],
    B: Float[Array, "M n m"],
    Q: Float[Array, "n n"],
    R: Float[Array, "m m"],
    P_end: Float[Array, "n n"],
):
    """The finite-horizon discrete Riccati recursion backwards from `P_M = P_end`:
    `G_k = (R + B_k^T P_{k+1} B_k)^-1 B_k^T P_{k+1} A_k`, `P_k = Q + A_k^T P_{k+1} (A_k - B_k G_k)`.
    Returns the gains `G (M, m, n)` (the command `du_k = -G_k e_k`) and `P (M + 1, n, n)`."""

    def back(P, AB):
        A_, B_ = AB
        PB = P @ B_
        G = jnp.linalg.solve(R + B_.T @ PB, PB.T @ A_)
        Pn = Q + A_.T @ P @ (A_ - B_ @ G)
        return 0.5 * (Pn + Pn.T), (G, Pn)

    _, (G, P) = jax.lax.scan(back, P_end, (A, B), reverse=True)
    return G, jnp.concatenate([P, P_end[None]], axis=0)


def dare(A, B, Q, R, steps: int = DOUBLING_STEPS):
    """The stabilising solution `P` of the discrete algebraic Riccati equation
    `P = Q + A^T P A - A^T P B (R + B^T P B)^-1 B^T P A` by the structure-preserving doubling
    algorithm (Chu et al. 2004): `A_{k+1} = A_k (I + G_k H_k)^-1 A_k`,
    `G_{k+1} = G_k + A_k (I + G_k H_k)^-1 G_k A_k^T`, `H_{k+1} = H_k + A_k^T H_k (I + G_k H_k)^-1 A_k`
    from `(A, B R^-1 B^T, Q)`, `H_k -> P` quadratically for a stabilisable, detectable pair."""
    n = A.shape[0]
    eye = jnp.eye(n, dtype=A.dtype)

    def body(_, c):
        Ak, Gk, Hk = c
        W = jnp.linalg.inv(eye + Gk @ Hk)
        An = Ak @ W @ Ak
        Gn = Gk + Ak @ W @ Gk @ Ak.T
        Hn = Hk + Ak.T @ Hk @ W @ Ak
        return An, 0.5 * (Gn + Gn.T), 0.5 * (Hn + Hn.T)

    _, _, P = jax.lax.fori_loop(0, steps, body, (A, B @ jnp.linalg.solve(R, B.T), Q))
    return P


def conserved_direction(A: Float[Array, "n n"], B: Float[Array, "n m"]):
    """The left null vector `w` (unit norm) of `[A - I, B]` and the singular values of that
    matrix, smallest last: the mode of the discrete map at rest that no input changes."""
    M = jnp.concatenate([A - jnp.eye(A.shape[0], dtype=A.dtype), B], axis=1)
    U, s, _ = jnp.linalg.svd(M, full_matrices=True)
    return U[:, -1], s


def complement(w: Float[Array, " n"]) -> Float[Array, "n n-1"]:
    """An orthonormal basis `V` of the complement of the unit vector `w` (`V^T w = 0`)."""
    n = w.shape[0]
    U, _, _ = jnp.linalg.svd(jnp.eye(n, dtype=w.dtype) - jnp.outer(w, w))
    return U[:, : n - 1]


@jax.jit
def terminal_regulator(A, B, Q, R):
    """The infinite-horizon regulator of the map at rest `(A, B)` on the complement of its
    conserved mode (module docstring). Returns `(G (m, n), P (n, n), w (n,), V (n, n-1))`."""
    w, _ = conserved_direction(A, B)
    V = complement(w)
    Ay, By, Qy = V.T @ A @ V, V.T @ B, V.T @ Q @ V
    Py = dare(Ay, By, Qy, R)
    Gy = jnp.linalg.solve(R + By.T @ Py @ By, By.T @ Py @ Ay)
    return Gy @ V.T, V @ Py @ V.T, w, V


def closed_loop_eigenvalues(A, B, G) -> np.ndarray:
    """The eigenvalues of `A - B G`, sorted by modulus, largest first."""
    ev = np.linalg.eigvals(np.asarray(A - B @ G))
    return ev[np.argsort(-np.abs(ev))]
