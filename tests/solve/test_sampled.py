"""`jsphere.Sampled`: the cubic table's knot slopes, computed once when the table is made."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jsphere.controls import Sampled


def _three_point_slopes(ts, ys):
    """The slope rule of `Sampled`, knot by knot: central 3-point differences weighted by the
    intervals, one-sided at the ends and beside a jump (a repeated time)."""
    n = len(ts)
    out = np.zeros_like(ys)
    for k in range(n):
        hl = ts[k] - ts[k - 1] if k > 0 else 0.0
        hr = ts[k + 1] - ts[k] if k < n - 1 else 0.0
        dl = (ys[k] - ys[k - 1]) / hl if hl > 0 else None
        dr = (ys[k + 1] - ys[k]) / hr if hr > 0 else None
        if dl is not None and dr is not None:
            out[k] = (hr * dl + hl * dr) / (hl + hr)
        else:
            out[k] = dl if dl is not None else dr
    return out


@pytest.fixture
def table():
    """Uneven knots with a jump at t = 0.5 (a repeated time stamp), two columns."""
    ts = np.array([0.0, 0.1, 0.25, 0.5, 0.5, 0.7, 1.0, 1.2])
    ys = np.stack([np.sin(3 * ts) + (ts >= 0.5), ts**2], axis=1)
    ys[3] = [np.sin(1.5), 0.25]  # the value just before the jump
    return ts, ys


def test_the_slopes_are_the_three_point_rule_at_every_knot(table):
    ts, ys = table
    s = Sampled(jnp.asarray(ts), jnp.asarray(ys))
    np.testing.assert_allclose(np.asarray(s.slopes), _three_point_slopes(ts, ys), rtol=1e-15, atol=1e-15)
    # the interpolant passes through the knots, and its slope there is the knot's
    inner = [1, 2, 5, 6]
    np.testing.assert_allclose(np.asarray(jax.vmap(s)(jnp.asarray(ts[inner]))), ys[inner], rtol=1e-15)
    rate = jax.vmap(jax.jacfwd(s))(jnp.asarray(ts[inner]) + 1e-12)
    np.testing.assert_allclose(np.asarray(rate), np.asarray(s.slopes)[inner], rtol=1e-6)


def test_a_table_made_inside_a_trace_has_the_same_slopes(table):
    ts, ys = table
    eager = Sampled(jnp.asarray(ts), jnp.asarray(ys))
    traced = jax.jit(lambda ts, ys: Sampled(ts, ys).slopes)(jnp.asarray(ts), jnp.asarray(ys))
    np.testing.assert_allclose(np.asarray(traced), np.asarray(eager.slopes), rtol=1e-15, atol=1e-15)
    t = jnp.linspace(-0.1, 1.3, 57)
    made_inside = jax.jit(lambda ts, ys, t: jax.vmap(Sampled(ts, ys))(t))(jnp.asarray(ts), jnp.asarray(ys), t)
    np.testing.assert_allclose(np.asarray(made_inside), np.asarray(jax.vmap(eager)(t)), rtol=1e-15, atol=1e-15)


def test_a_table_made_eagerly_compiles_no_program(table, programs_compiled):
    ts, ys = table
    s = Sampled(jax.device_put(ts), jax.device_put(ys))
    assert s.slopes.shape == ys.shape
    assert programs_compiled == []


def test_linear_and_step_tables_have_no_slopes(table):
    ts, ys = table
    assert Sampled(jnp.asarray(ts), jnp.asarray(ys), "linear").slopes is None
    assert Sampled(jnp.asarray(ts), jnp.asarray(ys), "zoh").slopes is None
