"""Robots the tests share: `random_robot(key, n_wheels)`, a random but valid robot.

Importable from any test folder as `from robots import random_robot` (pytest puts `tests/`,
the folder of the root `conftest.py`, on the import path)."""

import jax
import jax.numpy as jnp

import jsphere


def random_robot(key, n_wheels=3):
    """A random but valid robot: arbitrary wheel directions, full inertia tensor, offset r_m."""
    ks = jax.random.split(key, 8)
    R0 = 0.1 + 0.2 * jax.random.uniform(ks[0])
    dirs = jax.random.normal(ks[1], (n_wheels, 3))
    r = 0.4 * R0 * dirs / jnp.linalg.norm(dirs, axis=1, keepdims=True)
    n = jax.random.normal(ks[2], (n_wheels, 3))
    n = n / jnp.linalg.norm(n, axis=1, keepdims=True)
    a = jax.random.normal(ks[3], (n_wheels, 3))
    a = a / jnp.linalg.norm(a, axis=1, keepdims=True)
    L = 0.05 * jax.random.normal(ks[4], (3, 3))
    S = L @ L.T  # a second moment of mass: its inertia tensor satisfies the triangle inequality
    I = jnp.trace(S) * jnp.eye(3) - S + 0.01 * jnp.eye(3)
    rm = 0.2 * R0 * jax.random.normal(ks[5], (3,)) / jnp.sqrt(3.0)
    return jsphere.RobotParams(
        R0=R0,
        m0=0.5 + jax.random.uniform(ks[6]),
        I0=0.01,
        Rw=0.3 * R0,
        wheel_r=r,
        wheel_n=n,
        wheel_alpha=a,
        m=1.0 + 2.0 * jax.random.uniform(ks[7]),
        I=I,
        r_m=rm,
        j=3e-4,
        g=9.81,
    )


def unseen_robot():
    """A robot 5-20 % away from the paper's in the seven usual free parameters
    (`r_m[2], j, I[0,0], I[1,1], I[2,2], m0, I0`): the user-contract tests fit and score it
    from the paper's values."""
    import numpy as np

    return jsphere.RobotParams.paper().replace(
        m0=0.85, I0=0.0105, j=3.2e-4, r_m=np.array([0.0, 0.0, -0.031]), I=np.diag([0.018, 0.0145, 0.026])
    )


def torque_trials(robot, durations, rate=100.0, seed=0, **kw):
    """Capture-like trials of `robot` driven by three sinusoidal torques per wheel at 0.3-0.7 Hz,
    1 mm and 0.5 deg noise, one per duration [s], named `t0`, `t1`, ..."""
    out = []
    for i, t1 in enumerate(durations):
        u = jsphere.random_inputs(robot, t1, kind="torques", f_min=0.3, f_max=0.7, seed=seed * 100 + i)
        out.append(jsphere.synthetic_trial(robot, u, t1, rate=rate, seed=seed * 100 + i, name=f"t{i}", **kw))
    return out
