"""An independent plain-numpy right-hand side of the equations of motion (3.4) for the
scipy baseline of `run.py`.

Written from the paper's formulas (as documented at the top of `jsphere/model/dynamics.py`),
without importing anything from jsphere: only the *numbers* of the parameter set are taken
from a `RobotParams` (as plain arrays), every derived quantity is recomputed here.

State (12 components): `[q (w,x,y,z), omega (3), Omega (3), x, y]`, with `q` the platform
quaternion rotating platform components into fixed ones (rotation matrix `R`, rows
`alpha, beta, gamma`), `omega`, `Omega` the platform and shell angular velocities in platform
components.

    gamma      = R[2]
    M [w'; W'] = [r1 - Sk^T K; r2 + Sk^T K],   M = [[A, B], [B^T, D]]   (numpy.linalg.solve, 6x6)
    x', y'     = (R v)[:2],  v = R0 Omega x gamma                        (2.2), (2.3)
    q'         = q (x) (0, omega) / 2
"""

from __future__ import annotations

import numpy as np


def _cross(a, b):
    # np.cross is slow for single 3-vectors; this is the same product written out.
    return np.array([a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]])


class NumpyRobot:
    """Parameter-only quantities of (2.4), (3.4), recomputed in numpy."""

    def __init__(self, R0, m0, I0, Rw, wheel_r, wheel_n, wheel_alpha, m, I, r_m, j, g):
        f = lambda x: np.asarray(x, dtype=np.float64)  # noqa: E731
        self.R0, self.m0, self.I0, self.Rw = float(R0), float(m0), float(I0), float(Rw)
        self.m, self.j, self.g = float(m), float(j), float(g)
        self.I, self.r_m = f(I), f(r_m)
        r, n, al = f(wheel_r), f(wheel_n), f(wheel_alpha)
        s = np.cross(r, al)  # s_i = r_i x alpha_i
        k = self.R0 / (self.Rw * np.einsum("ij,ij->i", s, n))  # k_i = R0 / (Rw (s_i, n_i))
        self.n = n
        self.Sk = k[:, None] * s  # rows k_i s_i
        jk = self.j * k
        self.Jss = np.einsum("i,ia,ib->ab", jk * k, s, s)
        self.Jsn = np.einsum("i,ia,ib->ab", jk, s, n)
        self.Jns = self.Jsn.T.copy()
        self.A = self.I + self.Jss - self.Jns - self.Jsn
        self.E = np.eye(3)

    @classmethod
    def from_params(cls, p) -> "NumpyRobot":
        """From any object with the `RobotParams` field names (values converted to numpy)."""
        names = ("R0", "m0", "I0", "Rw", "wheel_r", "wheel_n", "wheel_alpha", "m", "I", "r_m", "j", "g")
        return cls(**{k: np.asarray(getattr(p, k)) for k in names})

    # ------------------------------------------------------------------ model pieces
    @staticmethod
    def rotmat(q):
        """Rotation matrix (platform -> fixed) of the normalised quaternion `q = (w, x, y, z)`."""
        w, x, y, z = q / np.sqrt(q @ q)
        return np.array(
            [
                [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
            ]
        )

    def mass_matrix(self, gamma):
        B = self.Jns - self.Jss + self.m * self.R0 * ((gamma @ self.r_m) * self.E - np.outer(gamma, self.r_m))
        D = (
            self.I0 * self.E
            + self.Jss
            + (self.m + self.m0) * self.R0**2 * ((gamma @ gamma) * self.E - np.outer(gamma, gamma))
        )
        return np.block([[self.A, B], [B.T, D]])

    def forces(self, gamma, w, W):
        p = self
        Wxw = _cross(W, w)
        r1 = (
            -_cross(w, p.I @ w)
            + _cross(p.Jns @ (W - w), w)
            - p.m * p.R0 * _cross(p.r_m, _cross(gamma, Wxw))
            - p.m * p.g * _cross(p.r_m, gamma)
        )
        r2 = (
            -(p.m + p.m0) * p.R0**2 * _cross(gamma, _cross(gamma, Wxw))
            - p.m * p.R0 * _cross(gamma, _cross(w, _cross(w, p.r_m)))
            - p.I0 * _cross(w, W)
        )
        return r1, r2

    def rhs(self, t, y, torque_fn):
        """`dy/dt` of the 12-component state for torques `K = torque_fn(t)`."""
        q, w, W = y[0:4], y[4:7], y[7:10]
        R = self.rotmat(q)
        gamma = R[2]
        r1, r2 = self.forces(gamma, w, W)
        tau = torque_fn(t) @ self.Sk  # Sk^T K = sum_i k_i s_i K_i
        acc = np.linalg.solve(self.mass_matrix(gamma), np.concatenate([r1 - tau, r2 + tau]))
        v = self.R0 * _cross(W, gamma)
        xy_dot = (R @ v)[:2]
        # q (x) (0, omega) / 2
        qw, qv = q[0], q[1:]
        q_dot = 0.5 * np.concatenate([[-(qv @ w)], qw * w + _cross(qv, w)])
        return np.concatenate([q_dot, acc, xy_dot])

    # ------------------------------------------------------------------ checks
    def energy(self, y):
        """Total energy (3.2) + (3.3), written from the kinetic energy term by term."""
        q, w, W = y[0:4], y[4:7], y[7:10]
        gamma = self.rotmat(q)[2]
        v = self.R0 * _cross(W, gamma)
        chi_dot = -self.Sk @ (w - W)
        T = (
            0.5 * (self.m + self.m0) * (v @ v)
            + 0.5 * self.I0 * (W @ W)
            + 0.5 * w @ self.I @ w
            + self.m * v @ _cross(w, self.r_m)
            + self.j * np.sum(chi_dot * (self.n @ w))
            + 0.5 * self.j * np.sum(chi_dot**2)
        )
        return T + self.m * self.g * (self.r_m @ gamma)

    def power(self, y, K):
        """Motor power `sum_i K_i chi_dot_i`, `chi_dot = -Sk (omega - Omega)` (2.4)."""
        return K @ (-self.Sk @ (y[4:7] - y[7:10]))


def initial_state(q0, x0=0.0, y0=0.0):
    """At rest with platform quaternion `q0`."""
    return np.concatenate([np.asarray(q0, float), np.zeros(6), [x0, y0]])
