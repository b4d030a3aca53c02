"""`jsphere.numerics.trig`: sine and cosine in elementwise arithmetic, against the C library's."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jsphere.numerics import trig

ULP_ONE = np.spacing(1.0)  # 2.2e-16


@pytest.mark.parametrize("lo, hi", [(0.0, 1.0), (1.0, 100.0), (100.0, 1e4), (1e4, 2.0**20)])
def test_values_agree_with_the_c_library_to_one_unit_of_one(lo, hi):
    """Up to `LIMIT`, in a jitted batch and element by element (XLA may or may not fuse the
    reduction's products with their differences; both must be exact)."""
    rng = np.random.default_rng(0)
    x = rng.uniform(lo, hi, 200_000) * rng.choice([-1.0, 1.0], 200_000)
    s, c = (np.asarray(a) for a in jax.jit(trig.sincos)(x))
    assert s.dtype == c.dtype == np.float64
    assert np.max(np.abs(s - np.sin(x))) <= ULP_ONE
    assert np.max(np.abs(c - np.cos(x))) <= ULP_ONE
    few = x[:: len(x) // 7][:7]
    for xi in few:  # one at a time
        si, ci = (float(a) for a in trig.sincos(np.float64(xi)))
        assert abs(si - np.sin(xi)) <= ULP_ONE and abs(ci - np.cos(xi)) <= ULP_ONE


def test_within_two_units_in_the_last_place_of_the_value_on_the_first_quadrants():
    x = np.random.default_rng(1).uniform(-np.pi, np.pi, 200_000)
    x = x[np.abs(np.sin(x)) > 1e-3]
    s, c = (np.asarray(a) for a in trig.sincos(x))
    assert np.max(np.abs(s - np.sin(x)) / np.spacing(np.abs(np.sin(x)))) <= 2.0
    keep = np.abs(np.cos(x)) > 1e-3
    assert np.max(np.abs(c - np.cos(x))[keep] / np.spacing(np.abs(np.cos(x[keep])))) <= 2.0


def test_small_angles_keep_their_relative_accuracy():
    x = 10.0 ** np.random.default_rng(2).uniform(-12, -1, 10_000)
    np.testing.assert_allclose(np.asarray(trig.sin(x)), np.sin(x), rtol=3e-16, atol=0)
    np.testing.assert_allclose(np.asarray(trig.sin(-x)), -np.sin(x), rtol=3e-16, atol=0)


def test_beyond_the_limit_the_values_are_nan_not_wrong_numbers():
    x = np.array([trig.LIMIT, -trig.LIMIT, 1.01 * trig.LIMIT, 1e12, -1e20, 1e300])
    s, c = (np.asarray(a) for a in trig.sincos(x))
    np.testing.assert_allclose(s[:2], np.sin(x[:2]), rtol=0, atol=ULP_ONE)
    np.testing.assert_allclose(c[:2], np.cos(x[:2]), rtol=0, atol=ULP_ONE)
    assert np.all(np.isnan(s[2:])) and np.all(np.isnan(c[2:]))


def test_special_values():
    x = np.array([0.0, np.pi / 2, np.pi, 2 * np.pi, -np.pi / 2, np.inf, -np.inf, np.nan])
    s, c = (np.asarray(a) for a in trig.sincos(x))
    np.testing.assert_allclose(s[:5], np.sin(x[:5]), rtol=0, atol=ULP_ONE)
    np.testing.assert_allclose(c[:5], np.cos(x[:5]), rtol=0, atol=ULP_ONE)
    assert s[0] == 0.0 and c[0] == 1.0
    assert np.all(np.isnan(s[5:])) and np.all(np.isnan(c[5:]))


def test_derivatives_of_every_order_are_the_other_function():
    x = jnp.linspace(-7.0, 7.0, 57)
    d1 = jax.vmap(jax.grad(trig.sin))(x)
    d2 = jax.vmap(jax.grad(jax.grad(trig.sin)))(x)
    d3 = jax.vmap(jax.grad(jax.grad(jax.grad(trig.cos))))(x)
    np.testing.assert_allclose(d1, np.cos(x), rtol=0, atol=2 * ULP_ONE)
    np.testing.assert_allclose(d2, -np.sin(x), rtol=0, atol=2 * ULP_ONE)
    np.testing.assert_allclose(d3, np.sin(x), rtol=0, atol=2 * ULP_ONE)
    s, ds = jax.jvp(lambda x: trig.sincos(x), (x,), (2.0 * jnp.ones_like(x),))
    np.testing.assert_allclose(ds[0], 2 * np.cos(x), rtol=0, atol=4 * ULP_ONE)
    np.testing.assert_allclose(ds[1], -2 * np.sin(x), rtol=0, atol=4 * ULP_ONE)


def test_other_dtypes_use_jax_s_own_functions():
    x32 = jnp.linspace(-3.0, 3.0, 11, dtype=jnp.float32)
    assert trig.sin(x32).dtype == jnp.float32
    np.testing.assert_array_equal(trig.sin(x32), jnp.sin(x32))
    np.testing.assert_array_equal(trig.cos(x32), jnp.cos(x32))
    assert float(trig.sin(1.0)) == pytest.approx(np.sin(1.0), abs=ULP_ONE)  # a Python float: float64


def test_a_batched_gait_solve_matches_the_single_solves():
    """The gait kinematics use these functions in single and batched solves alike."""
    import jsphere

    p = jsphere.RobotParams.paper()
    th = jnp.array([0.05, 0.08, 0.1, 0.12] * 8)  # 32 trials: the batch loop's shared steps

    def end(t):
        tr = jsphere.simulate_gaits(p, [jsphere.acceleration(theta_max=t), jsphere.braking(theta_max=t)])
        return tr.x[-1]

    batched = jax.jit(jax.vmap(end))(th)
    single = np.array([float(end(t)) for t in th[:4]])
    np.testing.assert_allclose(np.asarray(batched[:4]), single, rtol=0, atol=1e-8)


def test_the_gait_kinematics_of_batched_solves_use_them_and_single_solves_xla_s():
    """Batched solves' kinematics (`kinematics_components`) are traced with these polynomials,
    a single solve's (`kinematics`) with XLA's `sin` and `cos`; the values agree."""
    import jsphere

    gait = jsphere.acceleration(theta_max=0.1, phi=0.3)
    Qm, t = jnp.eye(3), jnp.asarray(0.37)
    single = jnp.concatenate(gait.kinematics(Qm, t))
    batched = jnp.stack(gait.kinematics_components(Qm, t))
    np.testing.assert_allclose(batched, single, rtol=0, atol=1e-15)

    def primitives(jaxpr) -> set:
        found = set()
        for e in jaxpr.eqns:
            found.add(e.primitive.name)
            for v in e.params.values():
                for sub in v if isinstance(v, (tuple, list)) else (v,):
                    if hasattr(sub, "eqns") or hasattr(sub, "jaxpr"):
                        found |= primitives(getattr(sub, "jaxpr", sub))
        return found

    assert "sin" in primitives(jax.make_jaxpr(lambda t: gait.kinematics(Qm, t))(t).jaxpr)
    assert not {"sin", "cos"} & primitives(jax.make_jaxpr(lambda t: gait.kinematics_components(Qm, t))(t).jaxpr)
    assert "sin" in primitives(jax.make_jaxpr(lambda t: gait.kinematics(Qm, t))(t).jaxpr)  # nothing left switched
