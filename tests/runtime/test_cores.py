"""One CPU device per core (`use_cpu_cores`) and batches split over the devices
(`shard_trials`): the split batch gives the one-device batch's results, on every device."""

import os
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jsphere


def test_the_device_count_is_set_before_jax_starts_or_not_at_all():
    jax.devices()  # this process's JAX has started (with its one CPU device)
    have = len(jax.devices("cpu"))
    assert jsphere.use_cpu_cores(have) == have  # the same count again: nothing to do
    with pytest.raises(RuntimeError, match=rf"already runs with {have} CPU device.*right after `import jax`"):
        jsphere.use_cpu_cores(have + 1)
    with pytest.raises(ValueError, match="at least 1"):
        jsphere.use_cpu_cores(0)


def test_shard_trials_places_arrays_and_names_a_batch_that_does_not_divide():
    x = {"a": jnp.arange(6.0), "tag": "kept as it is"}
    out = jsphere.shard_trials(x)
    assert out["tag"] == "kept as it is" and np.array_equal(out["a"], np.arange(6.0))
    assert out["a"].sharding.device_set == set(jax.devices())
    two = jax.devices()[:1] * 2  # two entries: the batch must split in two
    with pytest.raises(ValueError, match="7 trials cannot be split over 2 devices"):
        jsphere.shard_trials(jnp.arange(7.0), two)
    with pytest.raises(ValueError, match="a scalar cannot be split"):
        jsphere.shard_trials(jnp.float64(1.0))


SCRIPT = """
import numpy as np, jax, jax.numpy as jnp, jsphere
jsphere.enable_x64()
assert jsphere.use_cpu_cores(2) == 2 and len(jax.devices()) == 2
from jsphere.solve.batched import layout
layout.BATCH_CHUNK = __CHUNK__
p = jsphere.RobotParams.paper()

def final(a):
    tr = jsphere.simulate(p, jsphere.State.at_rest(p),
                          jsphere.Torques(lambda t: a * jnp.sin(jnp.pi * t + jnp.array([0.0, 2.1, 4.2]))), 0.5)
    return jnp.stack([tr.x[-1], tr.y[-1]])

A = 0.05 * (1 + 0.1 * jax.random.normal(jax.random.PRNGKey(0), (__TRIALS__, 3)))
f = jax.jit(jax.vmap(final))
one, split = f(A), f(jsphere.shard_trials(A))
hlo = f.lower(jsphere.shard_trials(A)).compile().as_text()
assert "all-gather" not in hlo and "all-to-all" not in hlo  # every device keeps its trials
assert split.sharding.device_set == set(jax.devices()) and not split.sharding.is_fully_replicated, split.sharding
assert np.max(np.abs(np.asarray(split) - np.asarray(one))) < 1e-9
if __GRAD__:
    g = jax.jit(jax.grad(lambda A: jnp.sum(jax.vmap(final)(A) ** 2)))
    g2 = g(jsphere.shard_trials(A))
    assert not g2.sharding.is_fully_replicated, g2.sharding
    g1, g2 = np.asarray(g(A)), np.asarray(g2)
    assert np.max(np.abs(g2 - g1)) < 1e-7 * np.max(np.abs(g1)), np.max(np.abs(g2 - g1))
try:
    jsphere.use_cpu_cores(3)
    raise SystemExit("use_cpu_cores(3) after the start was accepted")
except RuntimeError as e:
    assert "already runs with 2 CPU device(s)" in str(e), e
print("OK")
"""


def _run(trials: int, chunk: int, grad: bool) -> None:
    env = dict(os.environ, JAX_PLATFORMS="cpu")
    env.pop("XLA_FLAGS", None)
    script = SCRIPT.replace("__CHUNK__", str(chunk)).replace("__GRAD__", str(grad)).replace("__TRIALS__", str(trials))
    out = subprocess.run([sys.executable, "-c", script], env=env, capture_output=True, text=True, timeout=600)
    assert out.returncode == 0 and out.stdout.strip().endswith("OK"), out.stderr[-3000:]


def test_a_batch_split_over_two_cpu_devices_gives_the_one_device_results():
    """64 trials with shared steps on two devices: the same step sequence (its error norm
    reduced across the devices), the one-device results, the output split as the input."""
    _run(trials=64, chunk=1024, grad=False)


@pytest.mark.slow
def test_chunks_of_a_split_batch_and_their_gradient_stay_on_both_devices():
    """A batch above the chunk size, split over two devices: every chunk takes trials from both
    halves, so forward pass and discrete adjoint give the one-device values."""
    _run(trials=128, chunk=32, grad=True)
