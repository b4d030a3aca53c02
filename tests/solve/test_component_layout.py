"""The component ("struct of arrays") layout used by batched torque-mode solves.

`simulate` runs a flat `(16+N,)` state for a single trial and a tuple of scalar components
under `vmap` (jsphere.solve.batched.components, chosen by `custom_vmap`). These tests check that the two layouts
compute the same field and the same motions, and that every transformation a user may wrap
around `simulate` still works and gives the same derivatives.
"""

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from robots import random_robot

import jsphere
import jsphere.solve.batched.layout as L
from jsphere.model.params import derive
from jsphere.solve.batched.components import from_components, to_components
from jsphere.solve.field_args import FieldArgs
from jsphere.solve.fields import _torque_field, _torque_field_soa

PH = jnp.array([0.0, 2.1, 4.2])


@pytest.fixture(autouse=True)
def _component_layout_for_small_batches(monkeypatch):
    """The batches here are a few trials; let them take the component layout (by default only
    batches of `COMPONENT_MIN_BATCH` and more do) ..."""
    monkeypatch.setattr(L, "COMPONENT_MIN_BATCH", 1)
    # ... with per-trial step sizes: the layouts must agree to rounding (the shared step
    # sequence of `batch_steps="shared"` is tested in test_ensemble.py)
    monkeypatch.setattr(L, "SHARED_MIN_BATCH", 10**9)


class Sines(eqx.Module):
    a: jax.Array

    def __call__(self, t):
        return self.a * jnp.sin(jnp.pi * t + PH)


def _random_robot(seed, n_wheels, damping):
    p = random_robot(jax.random.PRNGKey(seed), n_wheels)
    return p.replace(c_roll=0.01, c_axle=0.002) if damping else p


@pytest.mark.parametrize("n_wheels,damping", [(3, False), (3, True), (4, True)])
def test_component_field_equals_flat_field(n_wheels, damping):
    rng = np.random.default_rng(n_wheels + 10 * damping)
    p = _random_robot(n_wheels + 10 * damping, n_wheels, damping)
    d = derive(p)
    for _ in range(5):
        q = rng.normal(size=4)
        qs = rng.normal(size=4)
        z = jnp.asarray(
            np.concatenate(
                [q / np.linalg.norm(q), qs / np.linalg.norm(qs), rng.normal(size=6) * 3, rng.normal(size=2 + n_wheels)]
            )
        )
        K = jnp.asarray(rng.normal(size=n_wheels) * 0.05)
        ctrl = jsphere.Torques(lambda t, K=K: K)
        args = FieldArgs(params=p, derived=d, control=ctrl, t_start=0.0, t_end=10.0)
        flat = _torque_field(0.3, z, args)
        comp = from_components(_torque_field_soa(0.3, to_components(z), args))
        np.testing.assert_allclose(comp, flat, rtol=1e-11, atol=1e-13 * float(jnp.max(jnp.abs(flat))))


@pytest.mark.parametrize("n_wheels,damping", [(3, True), (4, False)])
def test_gait_component_field_equals_flat_field(n_wheels, damping):
    """The gait-mode field on components (batched `simulate_gaits`) against `_gait_field`."""
    from jsphere.gaits.gaits import _gait_field, _gait_field_soa
    from jsphere.model.kinematics import rest_attitude
    from jsphere.model.rotations import rotation_between

    rng = np.random.default_rng(7 + n_wheels)
    p = _random_robot(20 + n_wheels, n_wheels, damping)
    d = derive(p)
    Qm = rotation_between(jnp.array([0.0, 0.0, 1.0]), rest_attitude(p))
    gait = jsphere.Gait(theta=jsphere.SinSquared(0.12), phi=0.4, omega_gamma=lambda t: 0.3 * jnp.sin(t), T=2.0)
    for t in (0.1, 0.7, 1.9):
        q, qs = rng.normal(size=4), rng.normal(size=4)
        z = jnp.asarray(
            np.concatenate(
                [q / np.linalg.norm(q), qs / np.linalg.norm(qs), rng.normal(size=6) * 3, rng.normal(size=2 + n_wheels)]
            )
        )
        args = FieldArgs(params=p, derived=d, control=(gait, Qm), t_start=0.5, t_end=2.5)
        flat = _gait_field(t, z, args)
        comp = from_components(_gait_field_soa(t, to_components(z), args))
        np.testing.assert_allclose(comp, flat, rtol=1e-11, atol=1e-13 * float(jnp.max(jnp.abs(flat))))
    # the component kinematics, for the base class and for a subclass with its own gamma
    for g in (gait, jsphere.smooth_gait(jnp.array([[0.1, 0.02], [-0.05, 0.03]]), jnp.array([0.2]), T=2.0)):
        for t in (0.3, 1.4):
            want = jnp.concatenate(g.kinematics(Qm, t))
            np.testing.assert_allclose(jnp.stack(g.kinematics_components(Qm, t)), want, rtol=1e-12, atol=1e-14)


class Flip(eqx.Module):
    """`K = a` before t = 1 s, `-a` after: a jump (the solve restarts there)."""

    a: jax.Array

    def __call__(self, t):
        return jnp.where(t < 1.0, self.a, -self.a)


@pytest.mark.slow
def test_batched_equals_single_and_chooses_the_layout():
    """jit(vmap) of the public API with a closure (problem 1 of benchmarks/) against one trial at
    a time: the two layouts agree far below the solver tolerance, and every field comes back."""
    p = jsphere.RobotParams.paper()
    A = 0.05 * (1 + 0.1 * jax.random.normal(jax.random.PRNGKey(0), (4, 3)))

    def final(a):  # the lambda closes over the vmapped amplitude
        tr = jsphere.simulate(p, jsphere.State.at_rest(p), jsphere.Torques(lambda t: a * jnp.sin(jnp.pi * t + PH)), 2.0)
        return jnp.stack([tr.x[-1], tr.y[-1]])

    batched = jax.jit(jax.vmap(final))(A)
    single = jax.jit(final)
    for i in range(A.shape[0]):
        # rounding differs between the layouts, so a marginal step may be taken or rejected
        # differently: agreement to ~1e-10 m, 1e4 times below the 1e-3 mm the tolerances aim at
        np.testing.assert_allclose(batched[i], single(A[i]), rtol=0, atol=1e-9)
    # a full trajectory under vmap: every field, several samples, a jump in the torques
    ts = jnp.linspace(0.0, 2.0, 7)
    sim = lambda a: jsphere.simulate(p, jsphere.State.at_rest(p), jsphere.Torques(Flip(a), jump_ts=(1.0,)), 2.0, ts=ts)  # noqa: E731
    trb = jax.vmap(sim)(A[:2])
    for i in range(2):
        tr1 = sim(A[i])
        for name in ("x", "y", "gamma", "omega", "Omega", "chi", "chi_dot", "K", "q", "q_shell"):
            np.testing.assert_allclose(getattr(trb, name)[i], getattr(tr1, name), rtol=1e-8, atol=1e-9, err_msg=name)
        assert int(trb.status[i]) == 0 and int(trb.segment[i, -1]) == 1


@pytest.mark.slow
def test_vmap_over_module_controls_params_and_nested():
    p = jsphere.RobotParams.paper()
    A = jnp.array([[0.05, 0.05, 0.05], [0.04, 0.06, 0.05]])
    run = lambda p, a: jsphere.simulate(p, jsphere.State.at_rest(p), jsphere.Torques(Sines(a)), 1.0).x[-1]  # noqa: E731
    xs = jax.vmap(lambda a: run(p, a))(A)  # eager vmap, batched Module leaves
    ps = jax.tree_util.tree_map(lambda *x: jnp.stack(x), p, p.replace(R_m=0.025))
    xp = jax.jit(jax.vmap(lambda q: run(q, A[0])))(ps)  # batched parameters
    xn = jax.jit(jax.vmap(jax.vmap(run, in_axes=(None, 0)), in_axes=(0, None)))(ps, A)  # nested
    for i in range(2):
        assert abs(float(xs[i] - run(p, A[i]))) < 1e-10
        assert abs(float(xn[0, i] - xs[i])) < 1e-10
        assert abs(float(xn[i, 0] - xp[i])) < 1e-10
    assert abs(float(xp[1] - run(p.replace(R_m=0.025), A[0]))) < 1e-10


def _sines_final(p, a, t1=1.0, **kw):
    tr = jsphere.simulate(p, jsphere.State.at_rest(p), jsphere.Torques(Sines(a)), t1, **kw)
    return jnp.stack([tr.x[-1], tr.y[-1]])


A3 = jnp.array([[0.05, 0.045, 0.055], [0.04, 0.06, 0.05], [0.055, 0.05, 0.045]])


@pytest.mark.slow
def test_grad_under_vmap_against_finite_differences(monkeypatch):
    """Problem 3 of benchmarks/: reverse mode of a batch-summed loss w.r.t. parameters goes
    through the custom VJP around the batched layout (here the large-batch path: component
    layout forward, the flat VJP recomputed in chunks of 2, the last one padded); checked
    against central differences."""
    monkeypatch.setattr(L, "GRAD_CHUNK", 2)
    p = jsphere.RobotParams.paper()

    def loss(j, rm):
        q = eqx.tree_at(lambda q: (q.j, q.r_m), p, (j, p.r_m.at[2].set(rm)))
        xy = jax.vmap(lambda a: _sines_final(q, a))(A3)
        return jnp.sum(xy**2)

    gj, grm = jax.jit(jax.grad(loss, argnums=(0, 1)))(p.j, p.r_m[2])
    f = jax.jit(loss)
    hj, hr = 1e-3 * float(p.j), 1e-3 * abs(float(p.r_m[2]))
    fd_j = (float(f(p.j + hj, p.r_m[2])) - float(f(p.j - hj, p.r_m[2]))) / (2 * hj)
    fd_r = (float(f(p.j, p.r_m[2] + hr)) - float(f(p.j, p.r_m[2] - hr))) / (2 * hr)
    assert abs(float(gj) - fd_j) < 1e-5 * abs(fd_j)
    assert abs(float(grm) - fd_r) < 1e-5 * abs(fd_r)


@pytest.mark.slow
def test_forward_mode_under_vmap_against_finite_differences():
    p = jsphere.RobotParams.paper()
    e = jnp.array([1.0, -0.5, 0.25])
    jv = jax.jit(
        jax.vmap(lambda a: jax.jvp(lambda b: _sines_final(p, b, adjoint=diffrax.ForwardMode()), (a,), (e,))[1])
    )(A3)
    f = jax.jit(jax.vmap(lambda a: _sines_final(p, a)))
    h = 1e-6
    fd = (f(A3 + h * e) - f(A3 - h * e)) / (2 * h)
    np.testing.assert_allclose(jv, fd, rtol=1e-5, atol=1e-9)


@pytest.mark.slow
@pytest.mark.parametrize("min_batch", [1, 10**6])
def test_derivatives_under_vmap_match_unbatched(monkeypatch, min_batch):
    """Per-trial reverse-mode gradients w.r.t. a batched input and parameters, and forward-mode
    Jacobians, batched against one trial at a time (flat layout). `min_batch` 1: the large-batch
    paths (component layout, recomputed backward pass); 10**6: the small-batch paths (flat
    layout, the pullback's residuals kept)."""
    monkeypatch.setattr(L, "COMPONENT_MIN_BATCH", min_batch)
    p = jsphere.RobotParams.paper()

    def loss(p, a):
        xy = _sines_final(p, a)
        return xy[0] ** 2 + xy[1] ** 2

    ga = jax.jit(jax.vmap(jax.grad(loss, argnums=1), in_axes=(None, 0)))(p, A3)
    gp = jax.jit(jax.grad(lambda q: jnp.sum(jax.vmap(lambda a: loss(q, a))(A3))))(p)
    ga1 = jax.jit(jax.grad(loss, argnums=1))
    gp1 = jax.jit(jax.grad(loss))
    np.testing.assert_allclose(ga, np.stack([ga1(p, a) for a in A3]), rtol=1e-7)
    gps = [gp1(p, a) for a in A3]
    for name in ("j", "I", "r_m", "m0", "I0"):
        want = sum(getattr(g, name) for g in gps)
        np.testing.assert_allclose(
            getattr(gp, name), want, rtol=1e-7, atol=1e-12 * float(jnp.max(jnp.abs(want))), err_msg=name
        )
    fm = lambda a: _sines_final(p, a, adjoint=diffrax.ForwardMode())  # noqa: E731
    J = jax.jit(jax.vmap(jax.jacfwd(fm)))(A3[:2])
    J1 = jax.jit(jax.jacfwd(fm))
    for i in range(2):
        np.testing.assert_allclose(J[i], J1(A3[i]), rtol=1e-7, atol=1e-12)


@pytest.mark.slow
def test_failures_are_reported_per_trial_under_vmap():
    p = jsphere.RobotParams.paper()
    A = jnp.array([[0.05, 0.05, 0.05], [jnp.nan, 0.05, 0.05]])
    tr = jax.vmap(lambda a: jsphere.simulate(p, jsphere.State.at_rest(p), jsphere.Torques(Sines(a)), 1.0, throw=False))(
        A
    )
    assert tr.ok.tolist() == [True, False]
    few = jax.vmap(
        lambda a: jsphere.simulate(
            p, jsphere.State.at_rest(p), jsphere.Torques(Sines(a)), 1.0, throw=False, max_steps=5
        )
    )(A[:1])
    assert int(few.status[0]) == 1
    # throw=True under vmap: equinox raises at run time, or poisons the output with NaN where
    # equinox's on-error mode is "nan" (as the CLI sets it; an earlier test may have)
    try:
        x = jax.vmap(
            lambda a: jsphere.simulate(p, jsphere.State.at_rest(p), jsphere.Torques(Sines(a)), 1.0, max_steps=5)
        )(A[:1]).x
        assert not np.all(np.isfinite(np.asarray(x)))
    except Exception as e:  # noqa: BLE001
        assert "max_steps" in str(e)


def test_large_batches_are_chunked_for_the_platform_they_run_on(monkeypatch):
    """Chunks of `BATCH_CHUNK` trials on a CPU, of `ACCELERATOR_BATCH_CHUNK` on a GPU (the
    platform of the default device where one is set, else the default backend)."""
    assert L.batch_chunk() == L.BATCH_CHUNK == 1024
    monkeypatch.setattr(jax, "default_backend", lambda: "gpu")
    assert L.batch_chunk() == L.ACCELERATOR_BATCH_CHUNK
    with jax.default_device(jax.devices("cpu")[0]):
        assert L.batch_chunk() == L.BATCH_CHUNK


@pytest.mark.slow
def test_chunked_batches_and_the_small_batch_threshold(monkeypatch):
    """A batch above `BATCH_CHUNK` runs as chunks (padded), one below `COMPONENT_MIN_BATCH` in the
    flat layout: both give the per-trial results."""
    p = jsphere.RobotParams.paper()
    A = 0.05 * (1 + 0.1 * jax.random.normal(jax.random.PRNGKey(3), (5, 3)))
    single = jax.jit(lambda a: _sines_final(p, a, 0.5))
    want = np.stack([single(a) for a in A])
    monkeypatch.setattr(L, "BATCH_CHUNK", 2)  # 5 trials -> 3 chunks of 2, the last padded
    np.testing.assert_allclose(jax.jit(jax.vmap(lambda a: _sines_final(p, a, 0.5)))(A), want, rtol=0, atol=1e-9)
    monkeypatch.setattr(L, "COMPONENT_MIN_BATCH", 256)  # flat layout under vmap: same arithmetic
    np.testing.assert_allclose(jax.jit(jax.vmap(lambda a: _sines_final(p, a, 0.5)))(A), want, rtol=0, atol=1e-12)
