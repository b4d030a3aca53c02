"""jaxtyping's run-time checks of the annotated shapes of the model's functions (beartype as
the checker): every annotation holds on real inputs, and a wrong shape is refused."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jsphere
from jsphere.model import dynamics, kinematics, linalg, rotations

beartype = pytest.importorskip("beartype")
jaxtyping = pytest.importorskip("jaxtyping")


def checked(f):
    return jaxtyping.jaxtyped(typechecker=beartype.beartype)(f)


P = jsphere.RobotParams.paper()
GAMMA = jnp.array([0.05, -0.02, 0.9987])
OMEGA = jnp.array([0.1, 0.2, 0.3])  # platform
SHELL = jnp.array([0.3, -0.1, 0.2])  # shell
K = jnp.array([0.1, -0.2, 0.05])
Q = jnp.array([0.9, 0.1, -0.3, 0.2]) / jnp.linalg.norm(jnp.array([0.9, 0.1, -0.3, 0.2]))

CALLS = {
    "accelerations": lambda check: check(dynamics.accelerations)(P, GAMMA, OMEGA, SHELL, K),
    "wheel_speeds": lambda check: check(kinematics.wheel_speeds)(P, OMEGA, SHELL),
    "relative_rate_from_wheel_speeds": lambda check: check(kinematics.relative_rate_from_wheel_speeds)(P, K),
    "constraint_residuals": lambda check: check(kinematics.constraint_residuals)(
        P, GAMMA, OMEGA, SHELL, kinematics.rolling_velocity(P, GAMMA, SHELL), kinematics.wheel_speeds(P, OMEGA, SHELL)
    ),
    "rolling_velocity": lambda check: check(kinematics.rolling_velocity)(P, GAMMA, SHELL),
    "kinematic_wheel_speeds": lambda check: check(kinematics.kinematic_wheel_speeds)(P, jnp.array([0.1, 0.0])),
    "kinetic_energy": lambda check: check(dynamics.kinetic_energy)(P, GAMMA, OMEGA, SHELL),
    "potential_energy": lambda check: check(dynamics.potential_energy)(P, GAMMA),
    "power": lambda check: check(dynamics.power)(P, OMEGA, SHELL, K),
    "cross": lambda check: check(linalg.cross)(OMEGA, SHELL),
    "dot": lambda check: check(linalg.dot)(OMEGA, SHELL),
    "matvec": lambda check: check(linalg.matvec)(jnp.eye(3), SHELL),
    "solve3": lambda check: check(linalg.solve3)(jnp.eye(3) * 2.0, SHELL),
    "quat_mul": lambda check: check(rotations.quat_mul)(Q, Q),
    "rotmat": lambda check: check(rotations.rotmat)(Q),
    "quat_normalize": lambda check: check(rotations.quat_normalize)(2.0 * Q),
}


@pytest.mark.parametrize("name", sorted(CALLS))
def test_annotations_hold(name):
    """The type-checked call accepts the real inputs and returns what the plain call returns."""
    got, want = CALLS[name](checked), CALLS[name](lambda f: f)
    leaves, ref = jax.tree_util.tree_leaves(got), jax.tree_util.tree_leaves(want)
    assert len(leaves) == len(ref) > 0
    for a, b in zip(leaves, ref):
        assert jnp.shape(a) == jnp.shape(b) and bool(jnp.all(jnp.isfinite(a)))
        np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize(
    "call",
    [
        lambda: checked(dynamics.accelerations)(P, GAMMA, OMEGA, SHELL, K[None]),
        lambda: checked(kinematics.wheel_speeds)(P, OMEGA[:2], SHELL),
        lambda: checked(linalg.cross)(OMEGA, jnp.ones(4)),
        lambda: checked(rotations.rotmat)(Q[:3]),
    ],
    ids=["torques-2d", "rate-2", "cross-4", "quaternion-3"],
)
def test_a_wrong_shape_is_refused(call):
    with pytest.raises(Exception, match="[Tt]ype-check"):
        call()
