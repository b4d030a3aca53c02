"""Simulation: closed loops between modes, transformations (jit, vmap, grad), precision."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jsphere


@pytest.mark.slow
def test_gait_torques_drive_the_torque_mode(paper):
    """The gait's K(t), fed to the torque-driven simulation, reproduces the gait's motion."""
    tr = jsphere.simulate_gaits(paper, [jsphere.acceleration(), jsphere.braking()], rate=1000)
    sim = jsphere.simulate(
        paper, jsphere.State.at_rest(paper), jsphere.Torques.from_samples(tr.ts, tr.K), 4.0, ts=tr.ts
    )
    assert np.max(np.abs(sim.x - tr.x)) < 1e-6 and np.max(np.abs(sim.y - tr.y)) < 1e-6
    np.testing.assert_allclose(sim.Omega, tr.Omega, atol=1e-7)
    np.testing.assert_allclose(sim.gamma, tr.gamma, atol=1e-7)


@pytest.mark.slow
def test_gait_wheel_speeds_drive_the_wheel_mode(paper):
    """The gait's chi_dot(t), fed to the wheel-speed (servo) mode, reproduces the motion."""
    tr = jsphere.simulate_gaits(paper, [jsphere.acceleration(), jsphere.braking()], rate=1000)
    sim = jsphere.simulate(
        paper, jsphere.State.at_rest(paper), jsphere.WheelSpeeds.from_samples(tr.ts, tr.chi_dot), 4.0, ts=tr.ts
    )
    assert np.max(np.abs(sim.x - tr.x)) < 1e-6 and np.max(np.abs(sim.y - tr.y)) < 1e-6
    np.testing.assert_allclose(sim.chi_dot, tr.chi_dot, atol=1e-6)
    interior = np.abs(np.asarray(tr.ts) % 2.0) > 0.01  # cubic slopes are one-sided at the jumps
    np.testing.assert_allclose(sim.K[interior], tr.K[interior], atol=1e-5)


@pytest.mark.slow
def test_wheel_mode_jump_and_constraints(paper):
    """Starting the kinematic control from rest is an impulse; afterwards (2.4) holds exactly."""
    v = 0.15 * 0.864
    ctrl = jsphere.kinematic_control(paper, jsphere.straight_line(v), t_stop=1.0)
    tr = jsphere.simulate(paper, jsphere.State.at_rest(paper), ctrl, 2.0, ts=jnp.linspace(0.0, 2.0, 201))
    u0 = jsphere.kinematic_wheel_speeds(paper, jnp.array([v, 0.0]))
    np.testing.assert_allclose(tr.chi_dot[0], u0, atol=1e-12)  # command in force from t0
    np.testing.assert_allclose(tr.chi_dot[-1], 0.0, atol=1e-12)  # wheels stopped after t_stop
    res = jsphere.trajectory_residuals(paper, tr)
    assert float(res["wheels"]) < 1e-9 and float(res["gamma_norm"]) < 1e-12
    E = jsphere.energy_along(paper, tr)
    after = np.asarray(tr.ts) > 1.0  # wheels locked: no power, energy conserved
    assert np.ptp(np.asarray(E)[after]) < 1e-7 * abs(float(E[-1]))  # rtol = 1e-8


def test_kinematic_wheel_speeds_realise_the_path(paper):
    """(2.9): the wheel rates give omega - Omega that rolls the shell at the planned velocity."""
    rdot = jnp.array([0.08, -0.05])
    u = jsphere.kinematic_wheel_speeds(paper, rdot, Omega_gamma=0.2, omega_gamma=-0.1, psi=0.4)
    w_minus_W = jsphere.relative_rate_from_wheel_speeds(paper, u)
    c, s = np.cos(0.4), np.sin(0.4)
    Q = np.array([[c, s, 0], [-s, c, 0], [0, 0, 1]])
    gamma = Q[:, 2]
    Omega = 0.2 * gamma + np.cross(gamma, Q @ np.array([0.08, -0.05, 0.0])) / 0.15
    np.testing.assert_allclose(w_minus_W, -0.1 * gamma - Omega, atol=1e-12)
    v = jsphere.rolling_velocity(paper, jnp.asarray(gamma), jnp.asarray(Omega))
    np.testing.assert_allclose((Q.T @ np.asarray(v))[:2], rdot, atol=1e-12)


class Sines(eqx.Module):
    """`K_i(t) = a_i sin(pi t + 2.1 (i - 1))`: a control holding arrays, so one compiled
    simulation serves every amplitude (a new lambda per call would recompile)."""

    a: jax.Array

    def __call__(self, t):
        return self.a * jnp.sin(jnp.pi * t + jnp.array([0.0, 2.1, 4.2]))


ZERO = jsphere.Torques(lambda t: jnp.zeros(3))


def _problem1(p, a):
    return jsphere.simulate(p, jsphere.State.at_rest(p), jsphere.Torques(Sines(a)), 1.0, rtol=1e-8, atol=1e-10)


@pytest.mark.slow
def test_jit_vmap_over_inputs_params_and_states(paper):
    A = jnp.array([[0.05, 0.05, 0.05], [0.04, 0.06, 0.05]])
    f = jax.jit(jax.vmap(lambda a: _problem1(paper, a)))
    out = f(A)
    for i in range(2):
        single = _problem1(paper, A[i])
        np.testing.assert_allclose(out.x[i, -1], single.x[-1], rtol=1e-12, atol=1e-15)
    # vmap over parameter sets
    ps = [paper, paper.replace(R_m=0.025), paper.replace(j=0.0)]
    stacked = jax.tree_util.tree_map(lambda *x: jnp.stack(x), *ps)
    outp = jax.jit(jax.vmap(lambda p: _problem1(p, A[0])))(stacked)
    for i, p in enumerate(ps):
        np.testing.assert_allclose(outp.x[i, -1], _problem1(p, A[0]).x[-1], rtol=1e-10, atol=1e-14)
    # vmap over initial states
    s0 = [jsphere.State.at_rest(paper, x=0.1), jsphere.State.from_axes(paper, Omega=(0.0, 0.5, 0.0))]
    S = jax.tree_util.tree_map(lambda *x: jnp.stack(x), *s0)
    outs = jax.vmap(lambda s: jsphere.simulate(paper, s, ZERO, 1.0))(S)
    for i, s in enumerate(s0):
        np.testing.assert_allclose(outs.x[i, -1], jsphere.simulate(paper, s, ZERO, 1.0).x[-1], rtol=1e-12, atol=1e-15)


def _fd(f, x, h):
    return (f(x + h) - f(x - h)) / (2 * h)


@pytest.mark.slow
def test_grad_of_final_position_wrt_params(paper):
    """Reverse-mode gradient of a torque-driven final x with respect to R_m, j and I vs finite differences."""
    a = jnp.array([0.05, 0.045, 0.055])

    def final_x(p):
        return _problem1(p, a).x[-1]

    g = jax.jit(jax.grad(final_x))(paper)
    checks = [
        ("r_m[2]", lambda p, v: eqx.tree_at(lambda q: q.r_m, p, p.r_m.at[2].set(v)), paper.r_m[2], g.r_m[2]),
        ("j", lambda p, v: eqx.tree_at(lambda q: q.j, p, v), paper.j, g.j),
        ("I[0,0]", lambda p, v: eqx.tree_at(lambda q: q.I, p, p.I.at[0, 0].set(v)), paper.I[0, 0], g.I[0, 0]),
        ("I[2,2]", lambda p, v: eqx.tree_at(lambda q: q.I, p, p.I.at[2, 2].set(v)), paper.I[2, 2], g.I[2, 2]),
    ]
    fx = jax.jit(final_x)
    for name, setter, v0, gv in checks:
        h = 1e-4 * abs(float(v0))
        fd = _fd(lambda v: float(fx(setter(paper, v))), float(v0), h)
        assert abs(float(gv) - fd) <= 1e-4 * abs(fd) + 1e-9, (name, float(gv), fd)


@pytest.mark.slow
def test_grad_wrt_gait_amplitude_and_params(paper):
    ts = jnp.array([0.0, 4.0])

    def stop(th, Rm):
        p = eqx.tree_at(lambda q: q.r_m, paper, jnp.array([0.0, 0.0, -Rm]))
        tr = jsphere.simulate_gaits(p, [jsphere.acceleration(theta_max=th), jsphere.braking(theta_max=th)], ts=ts)
        return tr.x[-1]

    f = jax.jit(stop)
    g_th, g_rm = jax.jit(jax.grad(stop, argnums=(0, 1)))(0.1, 0.027)
    fd_th = _fd(lambda v: float(f(v, 0.027)), 0.1, 1e-5)
    fd_rm = _fd(lambda v: float(f(0.1, v)), 0.027, 1e-6)
    assert abs(float(g_th) - fd_th) < 1e-6 * abs(fd_th)
    assert abs(float(g_rm) - fd_rm) < 1e-5 * abs(fd_rm)
    # the stop distance grows with R_m: dOmega_1/dR_m = +0.036 (1/s)/mm (docs/model.md, section 7)
    assert 1e-3 * float(g_rm) == pytest.approx(2 * 0.15 * 0.036, rel=0.05)


@pytest.mark.slow
def test_float32_on_request(paper):
    p32 = jsphere.RobotParams.paper(dtype=jnp.float32)
    # without tolerances, float32 parameters get float32 ones (1e-5, 1e-7): float64's 1e-10
    # made these gaits fail at max_steps, and a trial of problem 1 at 1e-8 took ~7,000 steps
    tr = jsphere.simulate_gaits(p32, [jsphere.acceleration(), jsphere.braking()])
    assert tr.x.dtype == jnp.float32 and bool(tr.ok)
    assert abs(float(tr.x[-1]) - 0.259199) < 1e-5 and abs(float(tr.y[-1]) - 0.003594) < 1e-5

    ph = jnp.array([0.0, 2.1, 4.2], jnp.float32)
    A = 0.05 * (1 + 0.1 * np.random.default_rng(0).standard_normal((64, 3)))

    def finals(p, A, **kw):
        run = lambda a: jsphere.simulate(
            p,
            jsphere.State.at_rest(p),
            jsphere.Torques(lambda t: a * jnp.sin(jnp.pi * t + ph.astype(a.dtype))),
            4.0,
            **kw,
        )  # noqa: E731
        return jax.jit(jax.vmap(run))(A)

    t32, t64 = finals(p32, jnp.asarray(A, jnp.float32)), finals(paper, jnp.asarray(A))
    assert t32.x.dtype == jnp.float32 and bool(jnp.all(t32.ok))
    assert int(t32.num_steps[0]) < 100  # shared steps; 64 measured (float64 at 1e-8: 128)
    err = np.hypot(
        np.asarray(t32.x[:, -1], float) - np.asarray(t64.x[:, -1]),
        np.asarray(t32.y[:, -1], float) - np.asarray(t64.y[:, -1]),
    )
    assert err.max() < 3e-5  # [m]; 9e-6 measured over 1024 trials

    with pytest.warns(UserWarning, match=r"rtol=1e-08 with float32 parameters"):
        jsphere.simulate(p32, jsphere.State.at_rest(p32), jsphere.Torques(lambda t: ph), 0.1, rtol=1e-8, atol=1e-10)


@pytest.mark.slow
def test_jacfwd_with_forward_mode_adjoint(paper):
    import diffrax

    def final_xy(a):
        tr = jsphere.simulate(
            paper, jsphere.State.at_rest(paper), jsphere.Torques(Sines(a)), 1.0, adjoint=diffrax.ForwardMode()
        )
        return jnp.stack([tr.x[-1], tr.y[-1]])

    a0 = jnp.array([0.05, 0.045, 0.055])
    J = jax.jacfwd(final_xy)(a0)
    f = jax.jit(lambda a: (lambda tr: jnp.stack([tr.x[-1], tr.y[-1]]))(_problem1(paper, a)))
    h = 1e-6
    J_fd = np.stack([(f(a0 + h * e) - f(a0 - h * e)) / (2 * h) for e in np.eye(3)], axis=1)
    np.testing.assert_allclose(J, J_fd, rtol=1e-5, atol=1e-9)
