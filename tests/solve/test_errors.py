"""Error handling: State and control-table validation, `simulate` argument checks and
run-time failures (NaN, max_steps) with `throw=True/False`, gait and `simulate_gaits` checks.

Run-time failures are raised by equinox from inside the compiled function; their text
carries the stack inside JIT (source lines), so the assertions look only at the lines that
start with "jsphere:" (the package's own messages).
"""

from __future__ import annotations

import re

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jsphere
from jsphere import (
    Gait,
    RobotParams,
    State,
    Torques,
    WheelSpeeds,
    acceleration,
    braking,
    simulate,
    simulate_gaits,
    turn,
)

T1 = 0.5  # short horizon: these tests are about errors, not accuracy


@pytest.fixture(scope="module")
def p():
    return RobotParams.paper()


@pytest.fixture(scope="module")
def s0(p):
    return State.at_rest(p)


class Amp(eqx.Module):
    """Torques `a * sin(t)`: an array-holding control, so that one compiled `simulate` serves
    every amplitude (and `vmap` can map over amplitudes)."""

    a: jax.Array

    def __call__(self, t):
        return self.a * jnp.sin(t)


GOOD = np.array([0.01, 0.02, -0.01])
NAN = np.full(3, np.nan)


def _nan_torques(t):
    return jnp.full(3, jnp.nan)


def _zero_torques(t):
    return jnp.zeros(3)


def jsphere_messages(exc: BaseException) -> str:
    """The package's own message lines in a (possibly equinox run-time) error."""
    lines = re.findall(r"jsphere: [^\n]*", str(exc))
    assert lines, f"no jsphere message in:\n{exc}"
    return "\n".join(lines)


# -------------------------------------------------------------------------- State


def _state_kwargs(s0, **changes):
    kw = {f: np.asarray(getattr(s0, f)) for f in ("q", "q_shell", "omega", "Omega", "x", "y", "chi")}
    kw.update(changes)
    return kw


@pytest.mark.parametrize(
    "field, value",
    [
        ("omega", [0.0, np.nan, 0.0]),
        ("Omega", [np.inf, 0.0, 0.0]),
        ("x", np.nan),
        ("y", -np.inf),
        ("chi", [0.0, 0.0, np.nan]),
        ("q", [np.nan, 0.0, 0.0, 0.0]),
    ],
)
def test_state_non_finite_names_field(s0, field, value):
    with pytest.raises(ValueError, match=rf"State\.{field} must be finite"):
        State(**_state_kwargs(s0, **{field: np.asarray(value, dtype=np.float64)}))


@pytest.mark.parametrize("field", ["q", "q_shell"])
@pytest.mark.parametrize("q", [[1.0, 1.0, 0.0, 0.0], [0.5, 0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 0.0]])
def test_state_non_unit_quaternion_names_field(s0, field, q):
    with pytest.raises(ValueError, match=rf"State\.{field} must be a unit quaternion"):
        State(**_state_kwargs(s0, **{field: np.asarray(q)}))


def test_state_valid_constructions(p, s0):
    State(**_state_kwargs(s0))
    # a unit quaternion within 1e-6 is accepted
    State(**_state_kwargs(s0, q=np.array([1.0 + 5e-7, 0.0, 0.0, 0.0])))
    assert np.linalg.norm(np.asarray(s0.q)) == pytest.approx(1.0, abs=1e-14)
    np.testing.assert_allclose(np.asarray(s0.gamma), [0.0, 0.0, 1.0], atol=1e-14)
    s = State.from_axes(p, (0.0, 1.0, 0.0), (-1.0, 0.0, 0.0), omega=(0.1, 0.0, 0.0))
    np.testing.assert_allclose(np.asarray(s.alpha), [0.0, 1.0, 0.0], atol=1e-14)
    np.testing.assert_allclose(np.asarray(s.beta), [-1.0, 0.0, 0.0], atol=1e-14)


@pytest.mark.parametrize(
    "alpha, beta",
    [((1.0, 0.0, 0.0), (1.0, 0.0, 0.0)), ((2.0, 0.0, 0.0), (0.0, 1.0, 0.0)), ((1.0, 0.0, 0.0), (0.6, 0.8, 0.0))],
)
def test_state_from_axes_not_orthonormal(p, alpha, beta):
    with pytest.raises(ValueError, match="orthonormal"):
        State.from_axes(p, alpha, beta)


# ------------------------------------------------------------------ control tables


CONTROL_CLASSES = pytest.mark.parametrize("cls", [Torques, WheelSpeeds], ids=["Torques", "WheelSpeeds"])


@CONTROL_CLASSES
def test_from_samples_non_monotonic(cls):
    with pytest.raises(ValueError, match=r"non-decreasing.*ts\[2\] = 0\.1 < ts\[1\] = 0\.2"):
        cls.from_samples([0.0, 0.2, 0.1, 0.3], np.zeros((4, 3)))


@CONTROL_CLASSES
@pytest.mark.parametrize("bad", [np.nan, np.inf])
def test_from_samples_non_finite_row(cls, bad):
    vals = np.zeros((4, 3))
    vals[2, 1] = bad
    with pytest.raises(ValueError, match=r"row 2 \(t = 0\.2\) is not finite"):
        cls.from_samples([0.0, 0.1, 0.2, 0.3], vals)


@CONTROL_CLASSES
def test_from_samples_non_finite_times(cls):
    with pytest.raises(ValueError, match=r"Sampled\.ts contains NaN"):
        cls.from_samples([0.0, np.nan, 0.2], np.zeros((3, 3)))


@CONTROL_CLASSES
@pytest.mark.parametrize("n", [0, 1])
def test_from_samples_too_few(cls, n):
    with pytest.raises(ValueError, match="at least 2 times"):
        cls.from_samples(np.zeros(n), np.zeros((n, 3)))


@CONTROL_CLASSES
def test_from_samples_row_count_mismatch(cls):
    with pytest.raises(ValueError, match="2 rows for 3 times"):
        cls.from_samples([0.0, 0.1, 0.2], np.zeros((2, 3)))


@CONTROL_CLASSES
def test_from_samples_triple_time_stamp(cls):
    with pytest.raises(ValueError, match="more than twice"):
        cls.from_samples([0.0, 0.1, 0.1, 0.1, 0.2], np.zeros((5, 3)))


@CONTROL_CLASSES
def test_from_samples_bad_kind(cls):
    with pytest.raises(ValueError, match="'spline'"):
        cls.from_samples([0.0, 0.1], np.zeros((2, 3)), kind="spline")


def test_wheel_speeds_zoh_rejected():
    with pytest.raises(ValueError, match="zoh"):
        WheelSpeeds.from_samples([0.0, 0.1, 0.2], np.zeros((3, 3)), kind="zoh")


@CONTROL_CLASSES
def test_from_samples_jump_is_accepted(cls):
    c = cls.from_samples([0.0, 0.1, 0.1, 0.2], np.array([[0.0] * 3, [0.0] * 3, [1.0] * 3, [1.0] * 3]), kind="linear")
    assert c.jump_ts == (0.1,)


def test_from_samples_scalar_values():
    with pytest.raises(ValueError, match="Sampled.values"):
        Torques.from_samples([0.0, 1.0], 0.5)


@CONTROL_CLASSES
def test_control_needs_a_callable(cls):
    with pytest.raises(TypeError, match="function of time"):
        cls(3.0)


# ------------------------------------------------------------ simulate: arguments


@pytest.mark.parametrize("bad", ["flat", None, "dict"])
def test_simulate_state0_type(p, s0, bad):
    state0 = {"flat": s0.flatten(), None: None, "dict": {"q": s0.q}}[bad]
    with pytest.raises(TypeError, match="state0 must be a jsphere.State"):
        simulate(p, state0, Torques(_zero_torques), T1)


@pytest.mark.parametrize("bad", ["function", "array", "Amp"])
def test_simulate_controls_type(p, s0, bad):
    controls = {"function": _zero_torques, "array": jnp.zeros(3), "Amp": Amp(jnp.asarray(GOOD))}[bad]
    with pytest.raises(TypeError, match="controls must be jsphere.Torques"):
        simulate(p, s0, controls, T1)


@pytest.mark.parametrize(
    "ts", [[0.0, 0.3, 0.2], [0.5, 0.0], [0.0, np.nan, 0.5], [[0.0, 0.5]]], ids=["decreasing", "reversed", "nan", "2d"]
)
def test_simulate_bad_ts(p, s0, ts):
    with pytest.raises(ValueError, match="ts must be a finite, non-decreasing 1-D array"):
        simulate(p, s0, Torques(_zero_torques), T1, ts=ts)


def test_simulate_wheel_count_mismatch(p):
    s4 = State.from_axes(p, chi=np.zeros(4))
    with pytest.raises(ValueError, match="4 wheels but params has 3"):
        simulate(p, s4, Torques(_zero_torques), T1)


def test_simulate_control_width_mismatch(p, s0):
    with pytest.raises(ValueError, match="wheel"):
        simulate(p, s0, Torques(lambda t: jnp.zeros(2)), T1)


# --------------------------------------------------------- simulate: run-time errors


def test_simulate_nan_controls_raise(p, s0):
    with pytest.raises(Exception, match="NaN") as ei:
        simulate(p, s0, Torques(_nan_torques), T1)
    msg = jsphere_messages(ei.value)
    assert "NaN" in msg
    assert "throw=False" in msg  # tells the user how to get Trajectory.ok instead


def test_simulate_nan_controls_throw_false(p, s0):
    tr = simulate(p, s0, Torques(Amp(jnp.asarray(NAN))), T1, throw=False)
    assert tr.ok.shape == ()
    assert not bool(tr.ok)
    # the same compiled function on a finite control succeeds
    tr = simulate(p, s0, Torques(Amp(jnp.asarray(GOOD))), T1, throw=False)
    assert bool(tr.ok)
    assert np.all(np.isfinite(np.asarray(tr.omega)))
    assert int(tr.num_steps) > 5


def test_simulate_max_steps_raises(p, s0):
    with pytest.raises(Exception) as ei:
        simulate(p, s0, Torques(Amp(jnp.asarray(GOOD))), T1, max_steps=5)
    jsphere_messages(ei.value)  # a jsphere message, not a bare diffrax/XLA error


def test_simulate_max_steps_message_mentions_max_steps(p, s0):
    with pytest.raises(Exception) as ei:
        simulate(p, s0, Torques(Amp(jnp.asarray(GOOD))), T1, max_steps=5)
    msg = jsphere_messages(ei.value)
    assert "max_steps" in msg
    assert "produced NaN" not in msg


def test_simulate_max_steps_throw_false(p, s0):
    tr = simulate(p, s0, Torques(Amp(jnp.asarray(GOOD))), T1, max_steps=5, throw=False)
    assert not bool(tr.ok)
    assert int(tr.num_steps) <= 5


@pytest.mark.slow
def test_simulate_vmap_ok_per_trial(p, s0):
    amps = jnp.asarray(np.stack([GOOD, NAN]))

    @jax.vmap
    def run(a):
        return simulate(p, s0, Torques(Amp(a)), T1, throw=False)

    tr = run(amps)
    np.testing.assert_array_equal(np.asarray(tr.ok), [True, False])
    assert np.all(np.isfinite(np.asarray(tr.omega[0])))


# -------------------------------------------------------------------- gaits


def test_simulate_gaits_empty(p):
    with pytest.raises(TypeError, match="non-empty list"):
        simulate_gaits(p, [])


def test_simulate_gaits_not_gaits(p):
    with pytest.raises(TypeError, match="jsphere.Gait"):
        simulate_gaits(p, [acceleration(), "braking"])


@pytest.mark.parametrize(
    "alpha0, beta0",
    [((1.0, 0.0, 0.0), (1.0, 0.0, 0.0)), ((1.0, 0.0, 0.0), (0.0, 2.0, 0.0)), ((1.0, 0.1, 0.0), (0.0, 1.0, 0.0))],
)
def test_simulate_gaits_axes_not_orthonormal(p, alpha0, beta0):
    with pytest.raises(ValueError, match="orthonormal"):
        simulate_gaits(p, [acceleration()], alpha0=alpha0, beta0=beta0)


def test_simulate_gaits_axes_not_at_rest_attitude(p):
    # orthonormal, but alpha0 x beta0 = (0, -1, 0) is not the first gait's gamma(0) = (0, 0, 1)
    with pytest.raises(ValueError, match=r"gamma\(0\)"):
        simulate_gaits(p, [acceleration()], alpha0=(1.0, 0.0, 0.0), beta0=(0.0, 0.0, 1.0))


@pytest.mark.parametrize("reset", [[True, True], [], [None, False, True]], ids=["2-for-1", "0-for-1", "3-for-1"])
def test_simulate_gaits_reset_length(p, reset):
    with pytest.raises(ValueError, match=rf"one entry per gait boundary \(1\); got {len(reset)}"):
        simulate_gaits(p, [acceleration(), braking()], reset=reset)


def test_simulate_gaits_reset_not_a_3_vector(p):
    with pytest.raises(ValueError, match="Omega 3-vector"):
        simulate_gaits(p, [acceleration(), braking()], reset=[(1.0, 2.0)])


def test_simulate_gaits_reset_not_a_3_vector_among_several(p):
    with pytest.raises(ValueError, match="reset"):
        simulate_gaits(p, [acceleration(), braking(), turn()], reset=[False, (1.0, 2.0)])


@pytest.mark.parametrize(
    "make, T",
    [(acceleration, 1.5), (braking, 2.5), (turn, 0.5), (acceleration, 0.0)],
    ids=["acceleration-1.5", "braking-2.5", "turn-0.5", "acceleration-0"],
)
def test_gait_T_not_multiple_of_period(make, T):
    with pytest.raises(ValueError, match="whole multiple of the sin\\^2 period"):
        make(T=T)


def test_gait_period_mismatch():
    with pytest.raises(ValueError, match="period 0.75"):
        acceleration(T=2.0, period=0.75)
    g = acceleration(T=1.5, period=0.75)  # 2 periods: fine
    assert float(g.T) == 1.5
    assert float(acceleration(T=3.0).T) == 3.0


@pytest.mark.parametrize("T", [-1.0, 0.0, np.nan])
def test_gait_T_must_be_positive(T):
    with pytest.raises(ValueError, match="Gait.T must be a positive duration"):
        Gait(theta=lambda t: 0.1 * jnp.sin(jnp.pi * t) ** 2, T=T)


def test_public_names():
    """The entry points these tests use are exported at the top level."""
    for name in ("simulate", "simulate_gaits", "Torques", "WheelSpeeds", "State", "RobotParams", "Gait"):
        assert hasattr(jsphere, name)
