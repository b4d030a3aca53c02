"""`jsphere.least_squares`: Rosenbrock's valley, linear problems against `numpy.linalg.lstsq`
(full rank and rank-deficient), both Jacobian modes, the covariance and the result's fields."""

from __future__ import annotations

import dataclasses

import jax.numpy as jnp
import numpy as np
import pytest

import jsphere


def rosenbrock(x):
    return jnp.stack([10.0 * (x[1] - x[0] ** 2), 1.0 - x[0]])


@pytest.mark.parametrize("jac", ["rev", "fwd"])
def test_rosenbrock_reaches_the_minimum_from_the_classic_start(jac):
    res = jsphere.least_squares(rosenbrock, jnp.array([-1.2, 1.0]), jac=jac, max_iter=200)
    assert res.converged
    np.testing.assert_allclose(res.x, [1.0, 1.0], atol=1e-8)
    assert res.cost < 1e-20
    assert 5 < res.iterations < 200


def test_an_iteration_budget_too_small_ends_unconverged():
    res = jsphere.least_squares(rosenbrock, jnp.array([-1.2, 1.0]), max_iter=2)
    assert not res.converged and res.iterations == 2
    assert res.cost < 0.5 * float(np.sum(np.asarray(rosenbrock(jnp.array([-1.2, 1.0]))) ** 2))


def _linear(A, b):
    A, b = jnp.asarray(A), jnp.asarray(b)
    return lambda x: A @ x - b


def test_a_linear_problem_matches_lstsq_and_its_covariance():
    rng = np.random.default_rng(0)
    A = rng.normal(size=(40, 4))
    b = A @ np.array([1.0, -2.0, 0.5, 3.0]) + 0.1 * rng.normal(size=40)
    x_ref, ssr, _, _ = np.linalg.lstsq(A, b, rcond=None)
    res = jsphere.least_squares(_linear(A, b), np.zeros(4))
    assert res.converged
    np.testing.assert_allclose(res.x, x_ref, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(res.cost, 0.5 * ssr[0], rtol=1e-10)
    np.testing.assert_allclose(res.jac, A, rtol=1e-14)
    np.testing.assert_allclose(res.covariance, np.linalg.inv(A.T @ A), rtol=1e-8)
    scaled = jsphere.least_squares(_linear(A, b), np.zeros(4), scale_by_residual=True)
    np.testing.assert_allclose(scaled.covariance, ssr[0] / (40 - 4) * np.linalg.inv(A.T @ A), rtol=1e-8)


def test_a_rank_deficient_problem_reaches_the_least_squares_fit():
    """Two equal columns: the solution is not unique, the fit `A x` and the cost are; the
    covariance (a pseudo-inverse) stays finite."""
    rng = np.random.default_rng(1)
    B = rng.normal(size=(30, 2))
    A = np.column_stack([B[:, 0], B[:, 1], B[:, 1]])
    b = rng.normal(size=30)
    x_ref, _, rank, _ = np.linalg.lstsq(A, b, rcond=None)
    assert rank == 2
    res = jsphere.least_squares(_linear(A, b), np.zeros(3))
    assert res.converged
    np.testing.assert_allclose(A @ res.x, A @ x_ref, rtol=1e-8, atol=1e-10)
    np.testing.assert_allclose(res.cost, 0.5 * np.sum((A @ x_ref - b) ** 2), rtol=1e-10)
    assert np.all(np.isfinite(res.covariance))


def test_the_result_fields():
    res = jsphere.least_squares(_linear(np.eye(3), np.ones(3)), np.zeros(3))
    assert [f.name for f in dataclasses.fields(res)] == ["x", "cost", "jac", "covariance", "iterations", "converged"]
    assert isinstance(res, jsphere.LeastSquaresResult)
    assert res.x.shape == (3,) and res.jac.shape == (3, 3) and res.covariance.shape == (3, 3)
    assert isinstance(res.cost, float) and isinstance(res.iterations, int) and isinstance(res.converged, bool)
    np.testing.assert_allclose(res.x, np.ones(3), rtol=1e-12)
    assert res.cost < 1e-25
