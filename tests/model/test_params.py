"""RobotParams: the paper's values (Section 5), derived k_i, validation, replace, pytree use."""

from __future__ import annotations

import re

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jsphere
from jsphere import RobotParams
from jsphere._runtime.errors import InputError
from jsphere.model.params import RULES, derive, rule_code, rule_reason

SQ2 = np.sqrt(2.0)
PHIS = 2.0 * np.pi * np.arange(3) / 3.0  # phi_i = 2 pi (i - 1)/3

# jitted once: eager op-by-op evaluation of the dynamics is slow
accelerations = jax.jit(jsphere.accelerations)


@pytest.fixture(scope="module")
def paper():
    return RobotParams.paper()


@pytest.fixture(scope="module")
def base(paper):
    """The paper's fields as plain numpy arrays, to build variants from."""
    return {k: np.asarray(v, dtype=np.float64) for k, v in paper.to_dict().items()}


def _geometry(n_wheels):
    phis = 2.0 * np.pi * np.arange(n_wheels) / n_wheels
    c, s, one = np.cos(phis), np.sin(phis), np.ones(n_wheels)
    wheel_r = 0.057 * np.stack([c, s, -one], -1)
    wheel_n = np.stack([c, s, one], -1) / SQ2
    wheel_alpha = np.stack([np.cos(phis - np.pi / 4), np.sin(phis - np.pi / 4), one], -1) / SQ2
    return wheel_r, wheel_n, wheel_alpha


# ----------------------------------------------------------------------- paper values


def test_paper_scalars(paper):
    assert float(paper.R0) == pytest.approx(0.15, abs=1e-15)
    assert float(paper.m0) == pytest.approx(0.8, abs=1e-15)
    assert float(paper.I0) == pytest.approx(0.012, abs=1e-15)
    assert float(paper.Rw) == pytest.approx(0.07, abs=1e-15)
    assert float(paper.m) == pytest.approx(2.5, abs=1e-15)
    assert float(paper.g) == pytest.approx(9.81, abs=1e-15)
    assert paper.n_wheels == 3


def test_paper_is_float64(paper):
    for f in ("R0", "m0", "I0", "Rw", "wheel_r", "wheel_n", "wheel_alpha", "m", "I", "r_m", "j", "g"):
        assert getattr(paper, f).dtype == jnp.float64, f


def test_paper_inertia_tensor(paper):
    np.testing.assert_allclose(np.asarray(paper.I), np.diag([0.016, 0.016, 0.023]), rtol=0, atol=1e-15)


@pytest.mark.parametrize("i", [0, 1, 2])
def test_paper_wheel_geometry(paper, i):
    phi = PHIS[i]
    c, s = np.cos(phi), np.sin(phi)
    np.testing.assert_allclose(np.asarray(paper.wheel_r[i]), 0.057 * np.array([c, s, -1.0]), rtol=0, atol=1e-15)
    np.testing.assert_allclose(np.asarray(paper.wheel_n[i]), np.array([c, s, 1.0]) / SQ2, rtol=0, atol=1e-15)
    np.testing.assert_allclose(
        np.asarray(paper.wheel_alpha[i]),
        np.array([np.cos(phi - np.pi / 4), np.sin(phi - np.pi / 4), 1.0]) / SQ2,
        rtol=0,
        atol=1e-15,
    )
    # unit axes
    assert np.linalg.norm(np.asarray(paper.wheel_n[i])) == pytest.approx(1.0, abs=1e-14)
    assert np.linalg.norm(np.asarray(paper.wheel_alpha[i])) == pytest.approx(1.0, abs=1e-14)


def test_paper_centre_of_mass_and_wheel_inertia(paper):
    r_m = np.asarray(paper.r_m)
    assert r_m[0] == 0.0 and r_m[1] == 0.0 and r_m[2] < 0.0
    assert float(paper.R_m) == pytest.approx(27.0146e-3, abs=1e-7)
    assert -r_m[2] == pytest.approx(float(paper.R_m), rel=1e-15)
    assert float(paper.j) == pytest.approx(2.7395e-4, abs=1e-8)


def test_paper_keyword_overrides():
    p0 = RobotParams.paper(R_m=26.8727e-3, j=0.0)
    assert float(p0.R_m) == pytest.approx(26.8727e-3, rel=1e-12)
    np.testing.assert_allclose(np.asarray(p0.r_m), [0.0, 0.0, -26.8727e-3], atol=1e-15)
    assert float(p0.j) == 0.0


# ---------------------------------------------------------------------- derived


def test_derived_k_paper(paper):
    k = np.asarray(derive(paper).k)
    assert k.shape == (3,)
    np.testing.assert_allclose(k, -53.166, rtol=0, atol=1e-3)
    # the three wheels are identical by symmetry
    assert np.ptp(k) < 1e-10


def test_derived_k_matches_definition(paper, base):
    """k_i = R0 / (Rw (s_i, n_i)), s_i = r_i x alpha_i, computed independently in numpy."""
    s = np.cross(base["wheel_r"], base["wheel_alpha"])
    k = base["R0"] / (base["Rw"] * np.sum(s * base["wheel_n"], axis=-1))
    d = derive(paper)
    np.testing.assert_allclose(np.asarray(d.s), s, rtol=1e-14, atol=1e-16)
    np.testing.assert_allclose(np.asarray(d.k), k, rtol=1e-13)
    np.testing.assert_allclose(np.asarray(d.Sk), k[:, None] * s, rtol=1e-13, atol=1e-15)


# ------------------------------------------------------------------- validation


def _perpendicular_n(base):
    """Unit n_i perpendicular to s_i = r_i x alpha_i (so (s_i, n_i) = 0)."""
    s = np.cross(base["wheel_r"], base["wheel_alpha"])
    n = np.cross(s, base["wheel_alpha"])
    return n / np.linalg.norm(n, axis=-1, keepdims=True)


def _same_direction(base):
    """All three wheels at the same place with the same axes: s_i do not span 3-space."""
    return {f: np.tile(base[f][0], (3, 1)) for f in ("wheel_r", "wheel_n", "wheel_alpha")}


def _nan_entry(x):
    x = np.array(x, dtype=np.float64, copy=True)
    x.flat[1] = np.nan
    return x


# (id, function base -> changes, field the message must name, optional extra regex)
INVALID = [
    ("m<0", lambda b: {"m": -2.5}, "m", None),
    ("m=0", lambda b: {"m": 0.0}, "m", None),
    ("m0<0", lambda b: {"m0": -0.8}, "m0", None),
    ("R0<0", lambda b: {"R0": -0.15}, "R0", None),
    ("Rw<0", lambda b: {"Rw": -0.07}, "Rw", None),
    ("I0<0", lambda b: {"I0": -0.012}, "I0", None),
    ("I0=0", lambda b: {"I0": 0.0}, "I0", None),
    ("j<0", lambda b: {"j": -1e-5}, "j", None),
    ("g<0", lambda b: {"g": -9.81}, "g", None),
    ("k_tau=0", lambda b: {"k_tau": 0.0}, "k_tau", "torque gain"),
    ("k_tau<0", lambda b: {"k_tau": -1.0}, "k_tau", None),
    ("I-not-symmetric", lambda b: {"I": [[0.016, 0.002, 0.0], [0.0, 0.016, 0.0], [0.0, 0.0, 0.023]]}, "I", "symmetric"),
    ("I-not-posdef", lambda b: {"I": np.diag([0.016, -0.016, 0.023])}, "I", "positive definite"),
    ("I-singular", lambda b: {"I": np.diag([0.016, 0.0, 0.023])}, "I", "positive definite"),
    ("wheel_n-not-unit", lambda b: {"wheel_n": 1.1 * b["wheel_n"]}, "wheel_n", "unit"),
    ("wheel_alpha-not-unit", lambda b: {"wheel_alpha": 0.9 * b["wheel_alpha"]}, "wheel_alpha", "unit"),
    ("s.n=0", lambda b: {"wheel_n": _perpendicular_n(b)}, "wheel_n", r"\(s_i, n_i\)"),
    ("s-not-spanning", _same_direction, "wheel_r", "span"),
    (
        "alpha-parallel-r",
        lambda b: {"wheel_alpha": b["wheel_r"] / np.linalg.norm(b["wheel_r"], axis=-1, keepdims=True)},
        "wheel_alpha",
        "parallel",
    ),
    ("m-nan", lambda b: {"m": np.nan}, "m", "finite"),
    ("R0-inf", lambda b: {"R0": np.inf}, "R0", "finite"),
    ("wheel_r-nan", lambda b: {"wheel_r": _nan_entry(b["wheel_r"])}, "wheel_r", "finite"),
    ("I-nan", lambda b: {"I": _nan_entry(b["I"])}, "I", "finite"),
    ("r_m-nan", lambda b: {"r_m": _nan_entry(b["r_m"])}, "r_m", "finite"),
    ("R0-in-mm", lambda b: {"R0": 150.0}, "R0", "millimetres"),
    ("Rw-in-mm", lambda b: {"Rw": 70.0}, "Rw", "millimetres"),
    ("Rw>=R0", lambda b: {"Rw": 0.15}, "Rw", "R0"),
    ("|r_m|=R0", lambda b: {"r_m": [0.0, 0.0, -0.15]}, "r_m", "inside the shell"),
    ("|r_m|>R0", lambda b: {"r_m": [0.1, 0.0, -0.2]}, "r_m", "inside the shell"),
    ("wheel_r-outside-shell", lambda b: {"wheel_r": 3.0 * b["wheel_r"]}, "wheel_r", "inside the shell"),
    ("wheel_r-zero", lambda b: {"wheel_r": np.vstack([np.zeros(3), b["wheel_r"][1:]])}, "wheel_r", "non-zero"),
    ("2-wheels", lambda b: {f: b[f][:2] for f in ("wheel_r", "wheel_n", "wheel_alpha")}, "wheel_r", "N >= 3"),
    ("wheel_r-1d", lambda b: {"wheel_r": b["wheel_r"][0]}, "wheel_r", "shape"),
    ("wheel_r-Nx2", lambda b: {"wheel_r": b["wheel_r"][:, :2]}, "wheel_r", "shape"),
    ("wheel_n-fewer-rows", lambda b: {"wheel_n": b["wheel_n"][:2]}, "wheel_n", "shape"),
    (
        "wheel_alpha-more-rows",
        lambda b: {"wheel_alpha": np.vstack([b["wheel_alpha"], b["wheel_alpha"][:1]])},
        "wheel_alpha",
        "shape",
    ),
    ("I-vector", lambda b: {"I": np.array([0.016, 0.016, 0.023])}, "I", "3x3"),
    ("I-2x2", lambda b: {"I": np.eye(2) * 0.016}, "I", "3x3"),
    ("r_m-2", lambda b: {"r_m": [0.0, -0.02]}, "r_m", "3-vector"),
    ("I-triangle", lambda b: {"I": np.diag([0.005, 0.005, 0.023])}, "I", "triangle inequality"),
    ("r_m-zero", lambda b: {"r_m": [0.0, 0.0, 0.0]}, "r_m", "off the shell centre"),
]


@pytest.mark.parametrize("make, field, extra", [c[1:] for c in INVALID], ids=[c[0] for c in INVALID])
def test_invalid_params_raise_naming_field(base, make, field, extra):
    kw = dict(base)
    kw.update(make(base))
    # the message starts with "RobotParams.<field>:" (exact field name: `m` is not `m0`)
    with pytest.raises(ValueError, match=rf"RobotParams\.{re.escape(field)}:") as ei:
        RobotParams(**kw)
    if extra is not None:
        assert re.search(extra, str(ei.value)), str(ei.value)


def test_valid_variants_construct(base):
    """Sanity: the variants above differ from a valid set only in the broken field; the valid
    sets keep the values given and break no rule."""
    plain = RobotParams(**base)
    still = RobotParams(**{**base, "j": 0.0, "g": 0.0})
    coupled = RobotParams(**{**base, "I": [[0.016, 0.001, 0.0], [0.001, 0.016, 0.0], [0.0, 0.0, 0.023]]})
    assert float(still.j) == 0.0 and float(still.g) == 0.0
    assert float(coupled.I[0, 1]) == 0.001 and float(coupled.I[1, 0]) == 0.001
    assert [int(rule_code(p)) for p in (plain, still, coupled)] == [0, 0, 0]


@pytest.fixture(scope="module")
def rule_codes():
    """`rule_code` compiled once, vmapped over stacked parameter sets."""
    return jax.jit(jax.vmap(rule_code))


def _unchecked(paper, changes):
    """`paper` with fields replaced without validation (as a parameter set made inside
    compiled code is)."""
    fields = list(changes)
    return eqx.tree_at(
        lambda p: [getattr(p, f) for f in fields], paper, [jnp.asarray(changes[f], jnp.float64) for f in fields]
    )


def test_rule_code_and_validate_share_the_rules(base, paper, rule_codes):
    """Every value rule `RobotParams` checks has a code from the traceable `rule_code` (under
    jit and vmap) naming the same field, with the same message."""
    cases = [(name, make(base), field) for name, make, field, _ in INVALID]
    cases = [c for c in cases if all(np.shape(v) == np.shape(base[f]) for f, v in c[1].items())]
    assert len(cases) >= 28
    sets = [_unchecked(paper, changes) for _, changes, _ in cases] + [paper]
    codes = np.asarray(rule_codes(jax.tree_util.tree_map(lambda *x: jnp.stack(x), *sets)))
    assert codes[-1] == 0 and rule_reason(0) == "valid"
    for (name, changes, field), code in zip(cases, codes[:-1]):
        assert code > 0, name
        rule = RULES[code - 1]
        with pytest.raises(ValueError) as ei:
            RobotParams(**{**base, **changes})
        assert str(ei.value).startswith(f"RobotParams.{rule.field}: "), (name, rule.reason, str(ei.value))
        assert rule.field == field, name
        a = {f: np.asarray(v, np.float64) for f, v in {**base, **changes}.items()}
        assert str(ei.value) == f"RobotParams.{rule.field}: {rule.message(a)}", name
        assert rule_reason(int(code)) == rule.reason


def test_rule_code_float32_paper_is_valid(paper):
    """The nominal robot in float32 meets the rules evaluated in float32."""
    p32 = RobotParams.paper(dtype=jnp.float32)
    assert int(jax.jit(rule_code)(p32)) == 0


def test_inertia_triangle_inequality_and_centre_of_mass_off_centre(base):
    """An inertia tensor no body has (principal moments breaking the triangle inequality) and a
    centre of mass at the shell centre (no rest attitude) are refused; a flat body (equality)
    is allowed."""
    with pytest.raises(ValueError, match=r"RobotParams\.I: .*triangle inequality"):
        RobotParams(**{**base, "I": np.diag([0.01, 0.01, 0.0201])})
    RobotParams(**{**base, "I": np.diag([0.01, 0.013, 0.023])})  # a plate: I3 = I1 + I2
    with pytest.raises(ValueError, match=r"RobotParams\.r_m: .*off the shell centre"):
        RobotParams(**{**base, "r_m": np.zeros(3)})


def test_four_wheel_robot(base):
    r, n, a = _geometry(4)
    p4 = RobotParams(**{**base, "wheel_r": r, "wheel_n": n, "wheel_alpha": a})
    assert p4.n_wheels == 4
    d = derive(p4)
    assert d.k.shape == (4,) and d.Sk.shape == (4, 3) and d.Sk_T_pinv.shape == (4, 3)
    np.testing.assert_allclose(np.asarray(d.k), -53.166, atol=1e-3)
    # the least-squares inverse of the wheel map is a left inverse
    np.testing.assert_allclose(np.asarray(d.Sk_pinv @ d.Sk), np.eye(3), atol=1e-12)
    gamma = jnp.array([0.0, 0.0, 1.0])
    wd, Wd = accelerations(p4, gamma, jnp.zeros(3), jnp.zeros(3), jnp.array([0.01, 0.0, -0.01, 0.0]))
    assert np.all(np.isfinite(np.asarray(wd))) and np.all(np.isfinite(np.asarray(Wd)))
    assert jsphere.State.at_rest(p4).chi.shape == (4,)


# ------------------------------------------------------------------------ replace


def test_replace_R_m(paper):
    q = paper.replace(R_m=0.02)
    assert float(q.R_m) == pytest.approx(0.02, rel=1e-14)
    np.testing.assert_allclose(np.asarray(q.r_m), [0.0, 0.0, -0.02], atol=1e-16)
    for f in ("R0", "m0", "I0", "Rw", "wheel_r", "wheel_n", "wheel_alpha", "m", "I", "j", "g"):
        np.testing.assert_array_equal(np.asarray(getattr(q, f)), np.asarray(getattr(paper, f)), err_msg=f)
    # the original is untouched
    assert float(paper.R_m) == pytest.approx(27.0146e-3, abs=1e-7)


def test_replace_j_zero(paper):
    q = paper.replace(j=0.0)
    assert float(q.j) == 0.0
    assert q.j.dtype == jnp.float64
    assert float(paper.j) > 0.0
    d = derive(q)
    np.testing.assert_array_equal(np.asarray(d.Jss), np.zeros((3, 3)))
    np.testing.assert_allclose(np.asarray(d.A), np.asarray(paper.I), atol=0)


def test_replace_several_and_validates(paper):
    q = paper.replace(R_m=0.03, j=0.0, m=3.0)
    assert float(q.m) == 3.0 and float(q.j) == 0.0 and float(q.R_m) == pytest.approx(0.03)
    with pytest.raises(ValueError, match=r"RobotParams\.m:"):
        paper.replace(m=-1.0)
    with pytest.raises(ValueError, match=r"RobotParams\.r_m:"):
        paper.replace(R_m=0.2)


def test_replace_unknown_field(paper):
    with pytest.raises(ValueError, match="mass"):
        paper.replace(mass=3.0)


def test_replace_R_m_on_stacked_params(paper):
    """`replace(R_m=...)` on stacked parameter sets should set each set's |r_m|."""
    P = jax.tree_util.tree_map(lambda *x: jnp.stack(x), paper, paper.replace(R_m=0.02))
    Q = P.replace(R_m=0.025)
    np.testing.assert_allclose(np.asarray(Q.R_m), [0.025, 0.025], rtol=1e-12)


# ----------------------------------------------------------- pytree, vmap and jit


def test_is_pytree_with_array_leaves(paper):
    leaves = jax.tree_util.tree_leaves(paper)
    assert len(leaves) == 15  # the 12 fields of the paper + the optional c_roll, c_axle, k_tau
    assert all(isinstance(x, jax.Array) for x in leaves)


def test_vmap_over_stacked_params(paper):
    p2 = paper.replace(R_m=0.02, j=0.0, m=3.0)
    P = jax.tree_util.tree_map(lambda *x: jnp.stack(x), paper, p2)
    assert P.R0.shape == (2,) and P.wheel_r.shape == (2, 3, 3)
    gamma = jnp.array([0.1, -0.05, 0.99])
    gamma = gamma / jnp.linalg.norm(gamma)
    omega, Omega = jnp.array([0.1, 0.2, 0.3]), jnp.array([0.3, -0.1, 0.2])
    K = jnp.array([0.01, -0.02, 0.03])
    wd, Wd = jax.jit(jax.vmap(jsphere.accelerations, in_axes=(0, None, None, None, None)))(P, gamma, omega, Omega, K)
    assert wd.shape == (2, 3) and Wd.shape == (2, 3)
    for i, p in enumerate((paper, p2)):
        wd_i, Wd_i = accelerations(p, gamma, omega, Omega, K)
        np.testing.assert_allclose(np.asarray(wd[i]), np.asarray(wd_i), rtol=1e-12, atol=1e-14)
        np.testing.assert_allclose(np.asarray(Wd[i]), np.asarray(Wd_i), rtol=1e-12, atol=1e-14)
    # the two parameter sets really give different answers
    assert not np.allclose(np.asarray(wd[0]), np.asarray(wd[1]))


def test_stacked_construction_is_validated_per_set(base, paper):
    d2 = {k: np.asarray(v) for k, v in paper.replace(R_m=0.02).to_dict().items()}
    stacked = {f: np.stack([base[f], d2[f]]) for f in base}
    P = RobotParams(**stacked)
    np.testing.assert_allclose(np.asarray(P.R_m), [float(paper.R_m), 0.02], rtol=1e-12)
    stacked["m"] = np.array([2.5, -1.0])
    with pytest.raises(ValueError, match=r"RobotParams\.m:"):
        RobotParams(**stacked)


def test_construct_from_traced_values_under_jit(base, paper):
    gamma = jnp.array([0.0, 0.1, 0.995])
    gamma = gamma / jnp.linalg.norm(gamma)
    K = jnp.array([0.01, 0.02, -0.01])

    @jax.jit
    def f(m, R0):
        p = RobotParams(**{**base, "m": m, "R0": R0})
        return jsphere.accelerations(p, gamma, jnp.zeros(3), jnp.zeros(3), K)

    wd, Wd = f(2.5, 0.15)
    wd_ref, Wd_ref = accelerations(paper, gamma, jnp.zeros(3), jnp.zeros(3), K)
    np.testing.assert_allclose(np.asarray(wd), np.asarray(wd_ref), rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(np.asarray(Wd), np.asarray(Wd_ref), rtol=1e-12, atol=1e-14)

    # validation is skipped for traced values: an invalid (negative) mass does not raise
    @jax.jit
    def g(m):
        return RobotParams(**{**base, "m": m}).m * 2.0

    assert float(g(-1.0)) == -2.0
    # ... while the same value outside jit does
    with pytest.raises(ValueError, match=r"RobotParams\.m:"):
        RobotParams(**{**base, "m": -1.0})


def test_tree_at_does_not_revalidate(paper):
    q = eqx.tree_at(lambda p: p.m, paper, jnp.asarray(-1.0))
    assert float(q.m) == -1.0


# ----------------------------------------------------------------------- parameter sets (from_dict)


@pytest.mark.parametrize(
    "field, value, says",
    [
        ("m", True, "RobotParams.m: the value must be a number, not a boolean (true)"),
        ("m", "2.5", "RobotParams.m: the value must be a number, not a string ('2.5'; write numbers without quotes)"),
        ("m", None, "RobotParams.m: the value must be a number, not null"),
        ("j", {"value": 1e-4}, "RobotParams.j: the value must be a number, not a dict"),
        (
            "I",
            [[0.016, 0, 0], [0, 0.016, 0], [0, 0, False]],
            "RobotParams.I: the value must be a number, not a boolean (false)",
        ),
        (
            "I",
            [[0.016, 0, 0], [0, 0.016], [0, 0, 0.023]],
            "RobotParams.I: a ragged list (rows of different lengths); expected a 3x3 nested list (shape (3, 3))",
        ),
        ("I", [0.016, 0.016, 0.023], "RobotParams.I: expected a 3x3 nested list (shape (3, 3)); got shape (3,)"),
        ("r_m", [0.0, -0.027], "RobotParams.r_m: expected a list of 3 numbers (shape (3,)); got shape (2,)"),
        ("m", [2.5], "RobotParams.m: expected a number; got shape (1,)"),
        (
            "wheel_r",
            [[0.05, 0, -0.05]] * 2,
            "RobotParams.wheel_r: expected a list of N >= 3 rows of 3 numbers (shape (N, 3)); got shape (2, 3)",
        ),
        (
            "wheel_n",
            [[1.0, 0, 0]] * 4,
            "RobotParams.wheel_n: expected a list of N rows of 3 numbers, one per wheel of wheel_r (shape (N, 3)); got shape (4, 3)",
        ),
    ],
)
def test_from_dict_refuses_what_is_not_numbers_of_the_field_s_shape(paper, field, value, says):
    d = paper.to_dict()
    d[field] = value
    with pytest.raises(InputError) as e:
        RobotParams.from_dict(d)
    assert str(e.value) == says + "."


def test_parameter_file_with_a_boolean_or_a_string_names_the_file_and_the_field(paper, tmp_path):
    text = jsphere._runtime.files.dumps_toml(paper.to_dict())
    for line, says in (
        ("m = true", "RobotParams.m: the value must be a number, not a boolean"),
        ('m = "2.5"', "RobotParams.m: the value must be a number, not a string ('2.5'"),
    ):
        path = tmp_path / "robot.toml"
        path.write_text(re.sub(r"(?m)^m = .*$", line, text))
        with pytest.raises(ValueError, match=re.escape(f"{path}: {says}")):
            RobotParams.load(path)


def test_from_dict_takes_numpy_values_and_integers(paper):
    d = {k: np.asarray(v) for k, v in paper.to_dict().items()}
    d["m"] = 2  # an integer is a number
    p = RobotParams.from_dict(d)
    assert float(p.m) == 2.0 and p.m.dtype == jnp.float64
