"""Gaits and sampled controls built inside a user's `jit` (traced, not compiled here:
`jax.eval_shape` traces exactly as `jit` does)."""

import jax
import numpy as np
import pytest

import jsphere


def test_gaits_built_inside_jit_keep_their_durations(paper):
    out = jax.eval_shape(lambda: jsphere.simulate_gaits(paper, [jsphere.acceleration(), jsphere.braking()]))
    assert out.x.shape == (402,)  # each gait at 100 Hz on its own [start, end]


def test_sampled_torques_built_inside_jit(paper):
    ts = np.array([0.0, 0.5, 0.5, 1.0])  # a jump at 0.5 s
    K = np.zeros((4, 3))
    out = jax.eval_shape(
        lambda K: jsphere.simulate(
            paper, jsphere.State.at_rest(paper), jsphere.Torques.from_samples(ts, K), 1.0, ts=ts
        ),
        K,
    )
    assert out.x.shape == (4,)
    assert jsphere.Torques.from_samples(ts, K).jump_ts == (0.5,)
    assert jsphere.Torques.from_samples(ts, K, kind="zoh").jump_ts == (0.5, 0.5)


def test_traced_time_stamps_are_refused():
    with pytest.raises(ValueError, match="time stamps are traced"):
        jax.eval_shape(lambda ts: jsphere.Torques.from_samples(ts, np.zeros((3, 3))), np.linspace(0.0, 1.0, 3))
