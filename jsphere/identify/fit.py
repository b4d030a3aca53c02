"""System identification: fit `RobotParams` to captured trials.

The model of a trial is `simulate(params, state0(nu), controls)` sampled at the capture times;
the residuals are the captured minus the simulated position and orientation, whitened by
`sigma_pos` [m] and `sigma_rot` [rad]:

    r_pos = (x_sim - x_meas, y_sim - y_meas) / sigma_pos
    r_rot = Log(q_sim^-1 q_meas) / sigma_rot          (rotation vector, platform frame)

with gap frames masked. The cost `1/2 sum r^2` over all trials is minimised over the free
parameters `theta` (see `FreeParams`) and, per trial, the nuisance parameters `nu`:

    wheel speeds: nu = (Omega(0) [3], initial rotation offset [3], x0, y0 offsets [2])
    torques:      nu = (Omega(0) [3], initial rotation offset [3], x0, y0 offsets [2], omega(0) [3])

In wheel-speed mode `omega(0) = Omega(0) + w(0)` follows from the command (2.4), so the
impulsive start of `simulate` changes nothing. All trials run in one compiled function
(vmapped over trials, padded to a common length with masked samples) and all starts in the
same call (vmapped over starts). The Jacobian of each trial's residuals with respect to
`(theta, nu_i)` comes from forward-mode autodiff through diffrax (`ForwardMode`): a few dozen
tangent columns instead of a reverse pass per residual. The normal equations have a block-arrow
structure; the nuisance blocks are eliminated (Schur complement), so the cost of a step grows
linearly with the number of trials.

Optimisation: starts from a Latin hypercube; for long trials multiple shooting first (trials cut
into segments with their own initial states, their continuity defects closed by a rising
weight: `jsphere.identify.shooting`), otherwise a few Adam steps (optax); then Levenberg-Marquardt to
convergence; the noise levels are then estimated from the residuals and LM run again; the best
start is kept; the verdict compares the residuals with the capture's noise floor
(`jsphere.identify.verdict`). Covariance: `s^2 F^-1` with `F` the Gauss-Newton
information of `theta` after eliminating the nuisance parameters, mapped to physical units.
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import json
import math
import sys
import time
import warnings
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import diffrax as dfx
import jax
import jax.numpy as jnp
import numpy as np
import optax

from ..controls import Sampled, Torques, WheelSpeeds
from .._runtime.errors import InputError, SolverFailure
from .._runtime.files import atomic_write, atomic_write_json, remove_stale_temporaries
from ..model.kinematics import relative_rate_from_wheel_speeds
from ..model.rotations import quat_mul, rotmat
from ..model.linalg import dot
from ..model.names import parse_name
from ..model.params import _FIELDS, RobotParams
from . import shooting as _shooting
from .shooting import end_vector
from ..solve.simulate import simulate
from ..model.state import State
from .free import MASS_LIKE, FreeParams, _overlaps, _split_names, apply_fixes

KINDS = ("wheel_speeds", "torques")
#: nuisance parameters per trial, in order
NUISANCE = {
    "wheel_speeds": ("Omega0_x", "Omega0_y", "Omega0_z", "rot0_x", "rot0_y", "rot0_z", "x0", "y0"),
    "torques": ("Omega0_x", "Omega0_y", "Omega0_z", "rot0_x", "rot0_y", "rot0_z", "x0", "y0", "omega0_x", "omega0_y", "omega0_z"),
}
#: typical step of each nuisance parameter (1/s, rad, m): for Adam and the start spread
_NU_SCALE = {"Omega0": 0.05, "rot0": 0.01, "x0": 0.002, "y0": 0.002, "omega0": 0.05}


# ----------------------------------------------------------------------------- quaternions


def quat_exp(v):
    """Unit quaternion of the rotation vector `v` [rad] (smooth at 0)."""
    a2 = dot(v, v)
    small = a2 < 1e-16
    a = jnp.sqrt(jnp.where(small, 1.0, a2))
    s = jnp.where(small, 0.5 - a2 / 48.0, jnp.sin(0.5 * a) / a)
    c = jnp.where(small, 1.0 - a2 / 8.0, jnp.cos(0.5 * a))
    return jnp.concatenate([c[..., None], s[..., None] * v], axis=-1)


def quat_log(q):
    """Rotation vector [rad] of a unit quaternion (the shorter of the two rotations; smooth at 0)."""
    q = jnp.where(q[..., :1] < 0, -q, q)
    w, v = q[..., 0], q[..., 1:]
    n2 = dot(v, v)
    small = n2 < 1e-16
    n = jnp.sqrt(jnp.where(small, 1.0, n2))
    f = jnp.where(small, 2.0 / w, 2.0 * jnp.arctan2(n, w) / n)
    return f[..., None] * v


def quat_conj(q):
    return q * jnp.array([1.0, -1.0, -1.0, -1.0], q.dtype)


# ----------------------------------------------------------------------------- data


@dataclasses.dataclass(frozen=True)
class FitData:
    """Trials packed into arrays of a common length `M` (padded samples are masked).

    `ts (T, M)`: capture times from 0 (padded with the last time); `tc (T, M)`: control knot
    times (padded beyond the end, values held); `u (T, M, N)`: inputs; `t1 (T,)`: durations;
    `x, y (T, M)`, `q (T, M, 4)`: measurements (0 / identity at gaps); `wpos, wrot (T, M)`:
    1.0 where the position / orientation was measured; `xy0 (T, 2)`, `q0 (T, 4)`: the first
    measured pose of each trial.
    """

    ts: np.ndarray
    tc: np.ndarray
    u: np.ndarray
    t1: np.ndarray
    x: np.ndarray
    y: np.ndarray
    q: np.ndarray
    wpos: np.ndarray
    wrot: np.ndarray
    xy0: np.ndarray
    q0: np.ndarray
    kind: str
    names: tuple[str, ...]
    lengths: tuple[int, ...]
    t_start: tuple[float, ...]

    def arrays(self) -> dict[str, jax.Array]:
        return {k: jnp.asarray(getattr(self, k)) for k in ("ts", "tc", "u", "t1", "x", "y", "q", "wpos", "wrot", "xy0", "q0")}

    def fingerprint(self) -> str:
        h = hashlib.sha256(self.kind.encode())
        for k in ("ts", "u", "x", "y", "q", "wpos", "wrot"):
            h.update(np.ascontiguousarray(getattr(self, k)).tobytes())
        return h.hexdigest()


def pack_trials(trials: Sequence, params: RobotParams) -> FitData:
    """Check the trials against `params` and pack them (see `FitData`).

    A trial needs `t (M,)`, `x, y (M,)` [m] (NaN at gaps), `q (M, 4)` (platform -> fixed,
    NaN rows at gaps), `inputs (M, N)`, `kind` and `name` (the `Trial` of `jsphere.capture.trial`).
    """
    trials = list(trials)
    if not trials:
        raise InputError("fit: no trials given.")
    kinds = {getattr(t, "kind", None) for t in trials}
    if len(kinds) != 1 or next(iter(kinds)) not in KINDS:
        raise InputError(f"fit: all trials must have the same input kind, one of {KINDS}; got {sorted(map(str, kinds))}.")
    kind = next(iter(kinds))
    N = params.n_wheels
    M = max(len(np.asarray(t.t)) for t in trials)
    out = {k: [] for k in ("ts", "tc", "u", "t1", "x", "y", "q", "wpos", "wrot", "xy0", "q0")}
    names, lengths, starts = [], [], []
    for k, tr in enumerate(trials):
        name = str(getattr(tr, "name", f"trial{k}"))
        t = np.asarray(tr.t, np.float64)
        u = np.asarray(tr.inputs, np.float64)
        x, y = np.asarray(tr.x, np.float64), np.asarray(tr.y, np.float64)
        q = np.asarray(tr.q, np.float64)
        if u.ndim != 2 or u.shape[1] != N:
            raise InputError(
                f"fit: trial {name!r} has inputs for {u.shape[-1] if u.ndim == 2 else '?'} wheels (shape {u.shape}) but the robot has {N}; use parameters with the same wheel count."
            )
        m = len(t)
        if m < 4 or u.shape[0] != m or x.shape != (m,) or y.shape != (m,) or q.shape != (m, 4):
            raise InputError(
                f"fit: trial {name!r}: t, x, y, q, inputs must have the same number of samples (>= 4); got {m}, {x.shape}, {y.shape}, {q.shape}, {u.shape}."
            )
        if not np.all(np.diff(t) > 0):
            raise InputError(f"fit: trial {name!r}: times must be strictly increasing.")
        if not np.all(np.isfinite(u)):
            raise InputError(f"fit: trial {name!r}: the inputs contain NaN or inf.")
        vp = np.isfinite(x) & np.isfinite(y)
        vr = np.all(np.isfinite(q), axis=1)
        if vp.sum() < 2 or vr.sum() < 2:
            raise InputError(f"fit: trial {name!r} has fewer than 2 measured frames.")
        qn = np.where(vr[:, None], q, [1.0, 0.0, 0.0, 0.0])
        qn = qn / np.linalg.norm(qn, axis=1, keepdims=True)
        t0 = t[0]
        ts = np.concatenate([t - t0, np.full(M - m, t[-1] - t0)])
        dt = (t[-1] - t[0]) / (m - 1)
        tc = np.concatenate([t - t0, t[-1] - t0 + dt * np.arange(1, M - m + 1)])

        def pad(a, v, m=m):
            return np.concatenate([a, np.broadcast_to(v, (M - m,) + a.shape[1:])])

        out["ts"].append(ts)
        out["tc"].append(tc)
        out["u"].append(pad(u, u[-1]))
        out["t1"].append(t[-1] - t0)
        out["x"].append(pad(np.where(vp, x, 0.0), 0.0))
        out["y"].append(pad(np.where(vp, y, 0.0), 0.0))
        out["q"].append(pad(qn, np.array([1.0, 0.0, 0.0, 0.0])))
        out["wpos"].append(pad(vp.astype(np.float64), 0.0))
        out["wrot"].append(pad(vr.astype(np.float64), 0.0))
        out["xy0"].append(np.array([x[vp][0], y[vp][0]]))
        out["q0"].append(qn[vr][0])
        names.append(name)
        lengths.append(m)
        starts.append(float(t0))
    arrs = {k: np.stack(v) for k, v in out.items()}
    return FitData(**arrs, kind=kind, names=tuple(names), lengths=tuple(lengths), t_start=tuple(starts))


def _line_rate(t, y):
    """Slope of a least-squares line through `(t, y)` (y may be (n, d))."""
    tt = t - t.mean()
    return (tt[:, None] * (y - y.mean(0))).sum(0) / max((tt * tt).sum(), 1e-300)


def nuisance_guess(data: FitData, params: RobotParams, *, window: float = 0.1) -> np.ndarray:
    """Initial nuisance parameters `(T, n)` from the first `window` seconds of each trial:
    the platform's angular velocity from the orientations, the horizontal shell rate from
    the rolling velocity `v = R0 Omega x gamma` (2.3); offsets 0."""
    T = data.ts.shape[0]
    n = len(NUISANCE[data.kind])
    nu = np.zeros((T, n))
    R0 = float(params.R0)
    for i in range(T):
        m = data.lengths[i]
        t = data.ts[i, :m]
        sel = t <= t[0] + window
        if sel.sum() < 3:
            sel = np.arange(m) < 3
        pr, rr = sel & (data.wpos[i, :m] > 0), sel & (data.wrot[i, :m] > 0)
        q0 = data.q0[i]
        R = np.asarray(rotmat(jnp.asarray(q0)))  # platform -> fixed
        omega = np.zeros(3)
        if rr.sum() >= 3:
            rv = np.asarray(quat_log(quat_mul(quat_conj(jnp.asarray(q0)), jnp.asarray(data.q[i, :m][rr]))))
            omega = _line_rate(t[rr], rv)
        v = np.zeros(2)
        if pr.sum() >= 3:
            v = _line_rate(t[pr], np.stack([data.x[i, :m][pr], data.y[i, :m][pr]], 1))
        if data.kind == "wheel_speeds":
            w0 = np.asarray(relative_rate_from_wheel_speeds(params, jnp.asarray(data.u[i, 0])))
            nu[i, 0:3] = omega - w0
        else:
            Om_f = np.array([-v[1] / R0, v[0] / R0, (R @ omega)[2]])
            nu[i, 0:3] = R.T @ Om_f
            nu[i, 8:11] = omega
    return nu


# ----------------------------------------------------------------------------- the model


def _trial_outputs(free: FreeParams, kind, rtol, atol, max_steps, adjoint, base, theta, nu, d, sig):
    """Whitened residuals `(5 M,)` of one trial, its solver status, the simulated pose and the
    state at its last sample (`jsphere.identify.shooting.end_vector`)."""
    p = free.to_params(theta, base)
    dt = p.R0.dtype
    q0 = quat_mul(d["q0"], quat_exp(nu[3:6]))
    Omega = nu[0:3]
    table = Sampled(d["tc"], d["u"], "cubic")
    if kind == "wheel_speeds":
        controls = WheelSpeeds(table, ())
        omega = Omega + relative_rate_from_wheel_speeds(p, d["u"][0])
    else:
        controls = Torques(table, ())
        omega = nu[8:11]
    state0 = State(
        q=q0, q_shell=jnp.array([1.0, 0.0, 0.0, 0.0], dt), omega=omega, Omega=Omega,
        x=d["xy0"][0] + nu[6], y=d["xy0"][1] + nu[7], chi=jnp.zeros(p.n_wheels, dt),
    )  # fmt: skip
    tr = simulate(p, state0, controls, d["t1"], ts=d["ts"], rtol=rtol, atol=atol, max_steps=max_steps, throw=False, adjoint=adjoint)
    ex = (tr.x - d["x"]) * d["wpos"] / sig[0]
    ey = (tr.y - d["y"]) * d["wpos"] / sig[0]
    er = quat_log(quat_mul(quat_conj(tr.q), d["q"])) * d["wrot"][:, None] / sig[1]
    res = jnp.concatenate([ex, ey, er.reshape(-1)])
    end = end_vector(tr)
    ok = tr.ok & jnp.all(jnp.isfinite(res)) & jnp.all(jnp.isfinite(end))
    res = jnp.where(ok, res, 0.0)
    end = jnp.where(ok, end, 0.0)
    return res, ok, (tr.x, tr.y, tr.q), end


class _Functions:
    """The compiled functions of one fit configuration (cached: a second fit with the same
    free names, transforms, input kind and shapes does not compile again).

    `jacobian(base, theta (S,P), nu (S,T,n), data, sigmas)`: whitened residuals `(S,T,K)`,
    solver status `(S,T)`, their Jacobian `(S,T,K,P+n)` with respect to `(theta, nu_i)` and
    the simulated poses, vmapped over starts and trials; `step(res, J, lam)`: the LM step of
    single shooting. `segments(...)`: the same for the segments of multiple shooting, with each
    segment's end state and its Jacobian; `assemble(...)`: their normal-equation blocks, cost and
    defects (`jsphere.identify.shooting.assemble`); `solve(blocks, lam)`: the LM step from blocks.
    """

    def __init__(self, free: FreeParams, kind: str, rtol: float, atol: float, max_steps: int):
        P = free.size

        def jac_one(base, th, nu, d, sig):
            def f(z):
                res, ok, pose, end = _trial_outputs(free, kind, rtol, atol, max_steps, dfx.ForwardMode(), base, z[:P], z[P:], d, sig)
                return (res, end), (res, ok, pose, end)

            (J, Je), (res, ok, pose, end) = jax.jacfwd(f, has_aux=True)(jnp.concatenate([th, nu]))
            return res, ok, J, pose, end, Je

        over_trials = lambda f: jax.vmap(f, in_axes=(None, None, 0, 0, None))
        over_starts = lambda f: jax.vmap(f, in_axes=(None, 0, 0, None, None))
        both = jax.jit(over_starts(over_trials(jac_one)))
        self.segments = both
        self.jacobian = jax.jit(lambda *a: both(*a)[:4])
        self.step = jax.jit(jax.vmap(functools.partial(_lm_step, P=P)))

        def assemble(res, J, e, Je, nu, mu, seg, scale):
            return _shooting.assemble(kind, P, res, J, e, Je, nu, mu, seg, scale)

        self.assemble = jax.jit(jax.vmap(assemble, in_axes=(0, 0, 0, 0, 0, None, None, None)))
        self.solve = jax.jit(jax.vmap(_solve_arrow, in_axes=(0, 0)))


_CACHE: dict[Any, _Functions] = {}


def _functions(free: FreeParams, kind: str, rtol: float, atol: float, max_steps: int) -> _Functions:
    key = (free.slots, kind, rtol, atol, max_steps)
    if key not in _CACHE:
        _CACHE[key] = _Functions(free, kind, rtol, atol, max_steps)
    return _CACHE[key]


# ----------------------------------------------------------------------------- Levenberg-Marquardt


def _blocks(res, J, P):
    """Gauss-Newton blocks of the block-arrow normal equations: `Hgg (P,P)`, `Hgn (T,P,n)`,
    `Hnn (T,n,n)`, gradients `gg (P,)`, `gn (T,n)`."""
    Jg, Jn = J[..., :P], J[..., P:]
    Hgg = jnp.einsum("tkp,tkq->pq", Jg, Jg)
    Hgn = jnp.einsum("tkp,tkn->tpn", Jg, Jn)
    Hnn = jnp.einsum("tkn,tkm->tnm", Jn, Jn)
    return Hgg, Hgn, Hnn, jnp.einsum("tkp,tk->p", Jg, res), jnp.einsum("tkn,tk->tn", Jn, res)


def _damp(H, lam):
    d = jnp.diagonal(H, axis1=-2, axis2=-1)
    floor = 1e-12 * jnp.max(d, axis=-1, keepdims=True) + 1e-300
    return H + (lam * d + floor)[..., None] * jnp.eye(H.shape[-1], dtype=H.dtype)


def _solve_arrow(blocks, lam):
    """Levenberg-Marquardt step `(H + lam diag H) delta = -g` of block-arrow normal equations
    (`_blocks`), the nuisance blocks eliminated (Schur complement). Returns
    `(d_theta (P,), d_nu (T,n), predicted cost decrease -(g.delta + delta^T H delta / 2))`."""
    Hgg, Hgn, Hnn, gg, gn = blocks
    Hnn_d = _damp(Hnn, lam)
    Hnn_inv = jnp.linalg.inv(Hnn_d)
    X = jnp.einsum("tpn,tnm->tpm", Hgn, Hnn_inv)
    S = _damp(Hgg, lam) - jnp.einsum("tpm,tqm->pq", X, Hgn)
    rhs = gg - jnp.einsum("tpm,tm->p", X, gn)
    dg = -jnp.linalg.solve(S, rhs)
    dn = -jnp.einsum("tnm,tm->tn", Hnn_inv, gn + jnp.einsum("tpn,p->tn", Hgn, dg))
    g_dot = gg @ dg + jnp.sum(gn * dn)
    quad = dg @ Hgg @ dg + 2.0 * jnp.einsum("p,tpn,tn->", dg, Hgn, dn) + jnp.einsum("tn,tnm,tm->", dn, Hnn, dn)
    return dg, dn, -(g_dot + 0.5 * quad)


def _lm_step(res, J, lam, P: int):
    """The Levenberg-Marquardt step of single shooting (`_solve_arrow` of `_blocks`)."""
    return _solve_arrow(_blocks(res, J, P), lam)


def marginal_information(res, J, P: int) -> np.ndarray:
    """Gauss-Newton information of `theta` with the nuisance parameters eliminated:
    `F = Hgg - sum_t Hgn_t Hnn_t^-1 Hng_t` (numpy, float64)."""
    Hgg, Hgn, Hnn, _, _ = (np.asarray(a) for a in _blocks(res, J, P))
    F = Hgg.copy()
    for t in range(Hnn.shape[0]):
        F -= Hgn[t] @ np.linalg.pinv(Hnn[t], rcond=1e-13, hermitian=True) @ Hgn[t].T
    return 0.5 * (F + F.T)


# ----------------------------------------------------------------------------- results


@dataclasses.dataclass
class FitResult:
    """What `fit` returns. `params`: the fitted `RobotParams` (fixed values included);
    `free`: the expanded free names; `values`, `stderr`: per free name (physical units), and
    for a whole field given as free (`"I"`, `"r_m"`) nested lists of the field's shape;
    `covariance`, `correlation`: of the expanded names (stderr is `inf` along directions the
    data do not determine); `identifiability`: condition number, poorly determined directions,
    warnings; `sigma_pos` [m], `sigma_rot` [rad]: noise levels (estimated unless given);
    `trials`: per trial its RMS residuals, nuisance values and, under `"series"`, the measured
    and simulated paths (for the plots; not written to JSON); `status`, `status_reason`: the
    verdict on the fit (`"converged"`, `"not_converged"` or `"misfit"`, and one sentence: see
    `jsphere.identify.verdict`), `verdict`: the numbers behind it (the capture's noise floor, the
    residual sigmas and their ratios to it, their lag-1 autocorrelations, per trial, the worst
    trial's name)."""

    params: RobotParams
    free: list[str]
    given: list[tuple[str, list[str]]]
    values: dict[str, Any]
    stderr: dict[str, Any]
    covariance: np.ndarray
    correlation: np.ndarray
    cost: float
    iterations: int
    converged: bool
    sigma_pos: float
    sigma_rot: float
    n_residuals: int
    identifiability: dict[str, Any]
    trials: list[dict[str, Any]]
    starts: list[float]
    kind: str
    elapsed_s: float
    status: str = ""
    status_reason: str = ""
    verdict: dict[str, Any] = dataclasses.field(default_factory=dict)
    shooting: dict[str, Any] = dataclasses.field(default_factory=dict)

    def to_json(self) -> dict[str, Any]:
        """The JSON document (`RobotParams.load` reads its `params`)."""
        fin = lambda v: _finite(v)
        return {
            "params": self.params.to_dict(),
            "free": list(self.free),
            "values": fin(self.values),
            "stderr": fin(self.stderr),
            "correlation": fin(np.asarray(self.correlation).tolist()),
            "cost": self.cost,
            "iterations": self.iterations,
            "converged": self.converged,
            "status": self.status,
            "status_reason": self.status_reason,
            "sigma_pos_m": self.sigma_pos,
            "sigma_rot_deg": math.degrees(self.sigma_rot),
            "n_residuals": self.n_residuals,
            "kind": self.kind,
            "identifiability": fin(self.identifiability),
            "verdict": fin(self.verdict),
            "trials": [{k: fin(v) for k, v in t.items() if k != "series"} for t in self.trials],
            "rms_pos_m": [t["rms_pos_m"] for t in self.trials],
            "rms_rot_deg": [t["rms_rot_deg"] for t in self.trials],
            "starts_cost": fin(self.starts),
            "elapsed_s": self.elapsed_s,
            "shooting": fin(self.shooting),
        }

    def save(self, path, *, plots: bool = True) -> list[Path]:
        """Write the JSON atomically and, unless `plots=False`, `<stem>_overlay.png` and
        `<stem>_residuals.png` beside it. Returns the paths written."""
        path = Path(path)
        atomic_write_json(path, self.to_json())
        written = [path]
        if plots:
            from ..plots import fit_figures

            written += fit_figures(self, path.parent, stem=path.stem)
        return written

    def table(self) -> str:
        """A plain-text summary: value +- stderr per free name, noise levels, warnings, and last
        the status with its reason."""
        lines = [f"{'name':<10} {'value':>14} {'stderr':>12} {'rel':>9}"]
        for n in self.free:
            v, s = self.values[n], self.stderr[n]
            rel = abs(s / v) if v else float("inf")
            lines.append(f"{n:<10} {v:>14.6g} {s:>12.3g} {rel:>9.2%}")
        lines.append(
            f"cost {self.cost:.6g} over {self.n_residuals} residuals, {self.iterations} iterations, "
            f"converged: {self.converged}; sigma_pos {self.sigma_pos * 1e3:.3f} mm, sigma_rot {math.degrees(self.sigma_rot):.3f} deg"
        )
        for w in self.identifiability.get("warnings", []):
            lines.append(f"warning: {w}")
        if self.status:
            lines.append(f"status: {self.status}: {self.status_reason}")
        return "\n".join(lines)


def _finite(v):
    """Replace non-finite floats by None (JSON has no inf/NaN)."""
    if isinstance(v, dict):
        return {k: _finite(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_finite(x) for x in v]
    if isinstance(v, (float, np.floating)):
        return float(v) if math.isfinite(v) else None
    if isinstance(v, np.ndarray):
        return _finite(v.tolist())
    return v


def symmetry_directions(names: Sequence[str], values: np.ndarray, params: RobotParams) -> dict[str, np.ndarray]:
    """Directions (physical units, one entry per free name) of two exact invariances of (3.4).

    - `"mass_split"`: the platform mass enters only through `m0 + m` and `m r_m` (its inertia
      `I` is about C), so `m -> m (1+e)`, `m0 -> m0 - e m`, `r_m -> r_m (1-e)` changes nothing.
    - `"mass_scale"`: multiplying every inertia (`I0, I, j`), dampings, `m0 + m` and `m r_m`
      by `1+e` multiplies every force of (3.4) by `1+e`. With wheel-speed inputs (servo
      constraints) the motion is then unchanged; torque inputs fix the scale.
    Only the free names appear; a direction that needs a fixed name to move is no symmetry of
    the fit (the information along it is then large and nothing is reported).
    """
    fields = [parse_name(n)[0] for n in names]
    m_free = "m" in fields
    m, m0 = float(params.m), float(params.m0)
    split, scale = np.zeros(len(names)), np.zeros(len(names))
    for i, f in enumerate(fields):
        v = float(values[i])
        if f == "m":
            split[i], scale[i] = m, m
        elif f == "m0":
            split[i], scale[i] = -m, (m0 if m_free else m0 + m)
        elif f in ("R_m", "r_m"):
            split[i], scale[i] = -v, (0.0 if m_free else v)
        elif f in MASS_LIKE:
            scale[i] = v
    return {"mass_split": split, "mass_scale": scale}


_SYMMETRY_TEXT = {
    "mass_split": "only m0 + m and m r_m enter the model (I is about the shell centre), so m, m0 and R_m (r_m) cannot be told apart: "
    "fix the platform mass, e.g. --fix m=<value>.",
    "mass_scale": "scaling every inertia, the total mass m0 + m and the mass moment m r_m together changes nothing the data can see "
    "(with wheel-speed inputs the motion does not depend on the mass scale; fixing m alone does not set it): "
    "fix a mass or inertia you can measure, e.g. --fix {hint}=<value>, or use torque inputs.",
}


def identifiability(
    free: FreeParams, values: np.ndarray, F_phys: np.ndarray, s2: float, params: RobotParams, *, rel_tol: float = 0.1
) -> dict[str, Any]:
    """Which directions of the free parameters the data determine.

    `F_phys` is the information matrix in physical units. Each name is scaled by its size
    (`|value|`, or a tenth of its field's size for values near 0), so eigenvalues `lam` of the
    scaled information give relative standard deviations `sqrt(s^2/lam)` along their
    eigenvectors. The known invariances (`symmetry_directions`) are checked by name; other
    directions with a relative sd above `rel_tol` are reported with their components.
    """
    names = free.names
    sc = np.maximum(np.abs(values), 0.1 * free.scales())
    Fs = sc[:, None] * F_phys * sc[None, :]
    lam, V = np.linalg.eigh(Fs)
    lam_max = max(float(lam[-1]), 1e-300)
    rel_sd = lambda info: math.sqrt(s2 / info) if info > 1e-14 * lam_max else math.inf
    out: dict[str, Any] = {"condition_number": float(lam_max / max(lam[0], 1e-300 * lam_max)), "symmetries": {}, "directions": [], "warnings": []}
    named = []
    for key, vec in symmetry_directions(names, values, params).items():
        e = vec / sc
        if np.count_nonzero(e) < 2:
            continue
        e = e / np.linalg.norm(e)
        rel = rel_sd(float(e @ Fs @ e))
        out["symmetries"][key] = {"relative_sd": rel, "combination": {n: float(w) for n, w in zip(names, e) if w != 0.0}}
        if rel > rel_tol:
            named.append(e)
            fields = [parse_name(n)[0] for n in names]
            hint = next((f for f in ("m0", "I0", "m") if f in fields), fields[0])
            out["warnings"].append(_SYMMETRY_TEXT[key].format(hint=hint) + f" (relative sd along it {rel:.3g})")
    for k in range(len(lam)):
        rel = rel_sd(float(lam[k]))
        if rel <= rel_tol or any(abs(float(V[:, k] @ e)) > 0.9 for e in named):
            continue
        v = V[:, k] * np.sign(V[np.argmax(np.abs(V[:, k])), k])
        terms = [(names[i], float(v[i])) for i in np.argsort(-np.abs(v)) if abs(v[i]) >= 0.15]
        text = " ".join(f"{w:+.2f} {n}" for n, w in terms)
        out["directions"].append({"relative_sd": rel, "combination": dict(terms), "text": text})
        out["warnings"].append(
            f"the data do not determine the direction {text} (relative changes; relative sd {rel:.3g}): "
            f"fix one of {', '.join(n for n, _ in terms)} or add more exciting trials."
        )
    return out


def _assemble_named(free: FreeParams, per_name: dict[str, float], params: RobotParams, fill: float) -> dict[str, Any]:
    """Add an entry for each whole field given as free (`"I"`: 3x3 nested list), and one per
    name as given where it differs from its canonical spelling (`"I[1,0]"` is `"I[0,1]"`)."""
    out = dict(per_name)
    for given, comps in free.given:
        field, index = parse_name(given)
        if index or len(comps) == 1:
            if given not in out:  # spelled differently from the canonical name (`I[1,0]`, `I[0, 0]`)
                out[given] = per_name[comps[0]]
            continue
        arr = np.full(np.shape(getattr(params, field)), fill)
        for c in comps:
            ix = parse_name(c)[1]
            arr[ix] = per_name[c]
            if field == "I":
                arr[ix[::-1]] = per_name[c]
        out[given] = arr.tolist()
    return out


# ----------------------------------------------------------------------------- the checkpoint

#: version of the checkpoint's contents (part of its fingerprint: a checkpoint written by
#: another version is not resumed)
_CHECKPOINT_FORMAT = 3

#: A test's hook into every checkpoint write: called as `hook(event, path)` with `"written"`
#: when the temporary file is complete but not yet renamed into place, and `"saved"` after the
#: rename. A test raises or kills the process in it to stop a fit at a chosen point.
_checkpoint_hook: Callable[[str, Path], None] | None = None


def _config_fingerprint(data: FitData, free: FreeParams, cfg: dict) -> str:
    h = hashlib.sha256(data.fingerprint().encode())
    h.update(
        json.dumps(
            {"free": free.names, "slots": [dataclasses.astuple(s) for s in free.slots], "base": free.base.to_dict(), **cfg},
            sort_keys=True,
            default=str,
        ).encode()
    )
    return h.hexdigest()


def _checkpoint_layout(stage: int, S: int, P: int, nu_shape: tuple, adam_shapes: Sequence[tuple], evaluation: dict[str, tuple]) -> dict[str, tuple]:
    """The arrays a checkpoint at `stage` holds, with their shapes: everything the optimiser
    reads from one step to the next (`S` starts, `P` free parameters, `nu_shape` the nuisance
    parameters of one start: `(T, n)` per trial, or `(G, n)` per segment in multiple shooting).
    Stage 0 is Adam (its position, moments and best points), stages 1 and 2 the two
    Levenberg-Marquardt stages of single shooting, 4 + k level k of multiple shooting (the
    per-start damping, flags, counters and costs, and the evaluation at the current points,
    shapes `evaluation`: kept, not recomputed, because a vmapped solve's steps and so its
    last digits depend on the other starts it ran with), stage 3 the finished optimisation."""
    out = {"stage": (), "total_it": (), "sig": (2,), "theta": (S, P), "nu": (S, *nu_shape), "max_defect": ()}
    if stage == 0:
        out |= {"adam_k": (), "adam_best_cost": (S,), "adam_best_theta": (S, P), "adam_best_nu": (S, *nu_shape)}
        out |= {f"adam_{i}": tuple(shape) for i, shape in enumerate(adam_shapes)}
    elif stage != 3:
        out |= {"it": (), **{k: (S,) for k in _LM_KEYS}, **{f"out_{k}": v for k, v in evaluation.items()}}
    else:
        out |= {"it": (), "stage_converged": ()}
    return out


def _flat_evaluation(out: dict[str, Any]) -> dict[str, np.ndarray]:
    """An evaluation (`{"res", "J", "pose"}` or `{"blocks", "defect"}`) as named arrays."""
    if "blocks" in out:
        return {**dict(zip(("Hgg", "Hgn", "Hnn", "gg", "gn"), map(np.asarray, out["blocks"]))), "defect": np.asarray(out["defect"])}
    return {"res": np.asarray(out["res"]), "J": np.asarray(out["J"]), **{f"pose_{c}": np.asarray(a) for c, a in zip("xyq", out["pose"])}}


def _unflat_evaluation(a: dict[str, np.ndarray]) -> dict[str, Any]:
    if "Hgg" in a:
        return {"blocks": tuple(jnp.asarray(a[k]) for k in ("Hgg", "Hgn", "Hnn", "gg", "gn")), "defect": a["defect"]}
    return {"res": a["res"], "J": jnp.asarray(a["J"]), "pose": tuple(jnp.asarray(a[f"pose_{c}"]) for c in "xyq")}


#: per-start state of Levenberg-Marquardt: damping, converged, accepted steps without progress,
#: rejections in a row, best cost, cost
_LM_KEYS = ("lam", "converged", "stalled", "rejected", "best_cost", "cost")


def _load_checkpoint(path: Path, fp: str, layout: Callable[[int], dict[str, tuple]]) -> tuple[dict | None, str | None]:
    """`(state, None)` for a checkpoint of this fit; `(None, why)` for one that cannot be used
    (damaged, or from another fit); `(None, None)` where there is none."""
    if not path.exists():
        return None, None
    try:
        with open(path, "rb") as f, np.load(f, allow_pickle=False) as z:  # (np.load leaks the file it opens on a bad zip)
            got = {k: np.asarray(z[k]) for k in z.files}
    except Exception as e:  # noqa: BLE001 - whatever the reader trips on, the file is damaged
        first = (str(e).splitlines() or [""])[0][:100]
        return None, f"cannot be read ({type(e).__name__}{': ' + first if first else ''})"
    if "fingerprint" not in got:
        return None, "is not a checkpoint of jsphere fit (it has no fingerprint)"
    if got["fingerprint"].shape != () or str(got["fingerprint"]) != fp:
        return None, "is from another fit (other trials, options or jsphere version)"
    stage = got.get("stage")
    if stage is None or stage.shape != () or stage.dtype.kind not in "iu" or not 0 <= int(stage) < 4 + len(MU_LEVELS):
        return None, "is damaged (no valid stage)"
    for k, shape in layout(int(stage)).items():
        if k not in got:
            return None, f"is damaged (it has no {k!r})"
        if got[k].shape != shape or got[k].dtype.kind not in "biuf":
            return None, f"is damaged ({k!r} is {got[k].dtype} of shape {got[k].shape}, expected shape {shape})"
    return got, None


def _save_checkpoint(path: Path, fp: str, state: dict[str, Any]) -> None:
    def write(tmp):
        np.savez(tmp, fingerprint=np.array(fp), **state)
        if _checkpoint_hook is not None:
            _checkpoint_hook("written", path)

    atomic_write(path, write)
    if _checkpoint_hook is not None:
        _checkpoint_hook("saved", path)


# ----------------------------------------------------------------------------- the fit


def _first_failure(data: FitData, pose, ok) -> str:
    """Where the first start fails: its first non-finite residual (trial, time, channel), or
    the first trial whose solve did not finish."""
    x, y, q = (np.asarray(a[0]) for a in pose)
    for i in range(data.ts.shape[0]):
        m = data.lengths[i]
        bad = np.stack([~np.isfinite(x[i, :m]), ~np.isfinite(y[i, :m]), ~np.all(np.isfinite(q[i, :m]), -1)])
        hit = np.flatnonzero(bad.any(0))
        if hit.size:
            k = int(hit[0])
            channel = ("x", "y", "orientation")[int(np.argmax(bad[:, k]))]
            t = data.ts[i, k] + data.t_start[i]
            return f"the first non-finite residual is in trial {data.names[i]!r} at t = {t:.6g} s (sample {k}), channel {channel}"
    failed = np.flatnonzero(~np.asarray(ok)[0])
    if failed.size:
        return f"the ODE solve of trial {data.names[int(failed[0])]!r} did not reach its end (max_steps)"
    return "the first start failed, but no trial shows where"


def _check_options(n_starts, max_iter, adam_steps, seed, sigma_pos, sigma_rot) -> None:
    for name, val, least in (("n_starts", n_starts, 1), ("max_iter", max_iter, 1), ("adam_steps", adam_steps, 0)):
        if isinstance(val, bool) or not isinstance(val, (int, np.integer)) or val < least:
            raise InputError(f"fit: {name} must be >= {least} (an integer); got {val!r}.")
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise InputError(f"fit: seed must be an integer >= 0; got {seed!r}.")
    for name, val in (("sigma_pos", sigma_pos), ("sigma_rot", sigma_rot)):
        if val is not None and not (isinstance(val, (int, float, np.number)) and not isinstance(val, bool) and 0 < val < math.inf):
            raise InputError(f"fit: {name} must be a finite number > 0 (or left out to estimate it); got {val!r}.")


#: the longest Levenberg-Marquardt step, in the free parameters' scaled units (`theta_scales`:
#: a factor e^2 for a log-transformed value)
STEP_MAX = 2.0
#: the weights of the continuity defects, one level after the other (multiple shooting)
MU_LEVELS = (1.0, 10.0, 100.0, 1e3, 1e4)
#: the largest defect [noise levels, `jsphere.identify.shooting.defect_scale`] that counts as closed
DEFECT_CLOSED = 0.5
#: a level of the continuation ends when an accepted step changes its cost by less than this
#: (relative), or after 3 rejected steps in a row: its minimiser is only the start of the next
#: level, and single shooting polishes
CONTINUATION_RTOL = 1e-4


def start_design(free: FreeParams, n_starts: int, spread: float, rng: np.random.Generator) -> np.ndarray:
    """`theta (S, P)` of `n_starts` starts: the first at the start values, the others a
    Latin hypercube (space-filling, `scipy.stats.qmc`) over a box: for a name with bounds on
    both sides uniform in the physical value within them; for the others `+- 2 spread` times
    the coordinate's scale about the start (log-transformed values: factors of `e^(+-2 spread)`)."""
    from scipy.stats import qmc

    P = free.size
    theta = np.repeat(free.theta0[None], n_starts, 0)
    if n_starts < 2 or P == 0:
        return theta
    u = qmc.LatinHypercube(d=P, rng=rng).random(n_starts - 1)
    ts = free.theta_scales()
    box = theta[1:] + 2.0 * spread * ts * (2.0 * u - 1.0)
    k = 0
    for sl in free.slots:
        if sl.kind == "interval":
            v = np.clip(u[:, k], 0.02, 0.98)
            box[:, k] = np.log(v / (1.0 - v))
        k += sl.size
    theta[1:] = box
    return theta


def _use_multiple(shooting: str, data: FitData, segment: float) -> bool:
    """`"auto"`: multiple shooting when a trial lasts more than two segments."""
    return shooting == "multiple" or (shooting == "auto" and float(np.max(data.t1)) > 2.0 * segment)


def fit(
    trials: Sequence,
    params: RobotParams,
    free: str | Sequence[str],
    *,
    fix: Mapping[str, Any] | None = None,
    bounds: Mapping[str, Sequence] | None = None,
    n_starts: int = 2,
    spread: float = 0.2,
    seed: int = 0,
    shooting: str = "auto",
    segment: float = 2.0,
    adam_steps: int = 3,
    adam_lr: float = 0.1,
    max_iter: int = 40,
    ftol: float = 1e-10,
    gtol: float = 1e-2,
    noise: float = 1.0,
    sigma_pos: float | None = None,
    sigma_rot: float | None = None,
    rtol: float = 1e-6,
    atol: float = 1e-8,
    max_steps: int = 16384,
    checkpoint: str | Path | None = None,
    restart: bool = False,
    progress: bool | Callable[[str], None] = False,
) -> FitResult:
    """Fit the free parameters of `params` to captured trials (position and orientation).

    **Arguments:**
    - `trials`: `Trial`s (same input kind, wheel count of `params`).
    - `params`: start values of every parameter; `fix` sets some first (`{"m": 2.5}`).
    - `free`: names to fit, `"r_m[2],j,I"` or a list (see `FreeParams`): whole fields free all
      their independent entries (`I`: 6, kept positive definite).
    - `bounds`: `{name: (lo, hi)}` (None for an open end) by reparameterisation.
    - `n_starts`, `spread`, `seed`: starts vmapped together: the first at `params`, the others
      a Latin hypercube over the bounds, or over `+- 2 spread` (relative, for positive values)
      about `params` (`start_design`). The best start is kept.
    - `shooting`, `segment`: `"multiple"` cuts each trial into segments of about `segment`
      seconds with their own initial states, started from the capture, and closes the
      continuity defects between them by raising their weight (`MU_LEVELS`); single shooting
      then polishes the result. `"single"` simulates each trial whole from its start.
      `"auto"` (default): multiple shooting when a trial is longer than two segments.
    - `adam_steps`, `adam_lr`: optax Adam warm-start steps of single shooting (per-coordinate
      scaled units); multiple shooting needs none (its segments start from the capture).
    - `max_iter`, `ftol`, `gtol`, `noise`: Levenberg-Marquardt iterations per stage; a stage
      ends when the predicted decrease of the cost is below `gtol` (in units of chi^2/2: 0.01
      is a step of ~0.14 standard errors along the worst direction), when an accepted step
      changes the cost by less than `ftol` (relative), after 3 accepted steps that do not
      lower the best cost by `gtol`, or after 8 rejected steps in a row. The adaptive ODE
      solver makes the cost piecewise smooth with jumps (~0.1 at `rtol=1e-6` for a few
      thousand samples) while its Jacobian stays accurate, so steps predicted to gain less
      than `noise` are accepted unless the cost rises by more than `noise`.
    - `sigma_pos` [m], `sigma_rot` [rad]: noise levels. If not given they start at 1 mm and
      0.5 deg and are estimated from the residuals after the first stage, and the fit is
      finished with the estimates.
    - `rtol`, `atol`, `max_steps`: the ODE solver's (see `simulate`). The defaults keep the
      simulated positions within ~2 um of a 1e-11 solution over a few seconds of exciting
      input (100 Hz tables: the cubic command has a kink in its rate at every sample, which
      makes tighter tolerances several times slower), far below capture noise.
    - `checkpoint`: a file (`.npz`) written atomically after every Adam and Levenberg-Marquardt
      step with the optimiser's whole state; a fit with the same data and configuration resumes
      from it to the same result, bit for bit, wherever it was stopped (`restart=True` ignores
      it). A checkpoint that cannot be read or belongs to another fit is ignored with a warning.
    - `progress`: `True` prints one line per iteration to stderr (or a callable gets it).

    Returns a `FitResult`. Raises `InputError` (a `ValueError`) for unknown or overlapping
    names, a name both free and fixed, bounds that exclude the start, trials that do not fit
    `params`, bad options; `SolverFailure` when no start gives a finite cost (the checkpoint
    is then removed), naming where the first start fails.
    """
    t_begin = time.perf_counter()
    say = (lambda s: print(s, file=sys.stderr, flush=True)) if progress is True else (progress or (lambda s: None))
    if fix:
        free_list = _split_names(free) if isinstance(free, str) else list(free)
        for fname in fix:
            parse_name(fname)
            for fr in free_list:
                if _overlaps(fname, fr.strip()):
                    raise InputError(f"{fname!r} is both free ({fr!r}) and fixed; choose one.")
    params = apply_fixes(params, fix)
    fp_ = FreeParams(params, free, bounds)
    data = pack_trials(trials, params)
    _check_options(n_starts, max_iter, adam_steps, seed, sigma_pos, sigma_rot)
    if shooting not in ("auto", "single", "multiple"):
        raise InputError(f"fit: shooting must be 'auto', 'single' or 'multiple'; got {shooting!r}.")
    if isinstance(segment, bool) or not isinstance(segment, (int, float, np.number)) or not 0.05 <= segment < math.inf:
        raise InputError(f"fit: segment must be a length in seconds >= 0.05; got {segment!r}.")
    kind = data.kind
    P, T = fp_.size, data.ts.shape[0]
    n_nu = len(NUISANCE[kind])
    S = int(n_starts)
    n_res = int(2 * data.wpos.sum() + 3 * data.wrot.sum())
    if n_res <= P + T * n_nu:
        raise InputError(
            f"fit: the trials hold {n_res} measured values but the fit has {P + T * n_nu} unknowns ({P} free parameters and "
            f"{n_nu} nuisance parameters per trial); give longer trials or fewer free parameters."
        )
    multiple = _use_multiple(shooting, data, float(segment))
    seg = _shooting.segment_trials(data, float(segment)) if multiple else None
    fns = _functions(fp_, kind, float(rtol), float(atol), int(max_steps))
    d = data.arrays()
    base = params
    estimate_sigma = sigma_pos is None or sigma_rot is None
    sig = np.array([sigma_pos or 1e-3, sigma_rot or math.radians(0.5)])
    cfg = {
        "n_starts": S, "spread": spread, "seed": seed, "adam_steps": adam_steps, "adam_lr": adam_lr, "max_iter": max_iter,
        "ftol": ftol, "gtol": gtol, "noise": noise, "sig": sig.tolist(), "estimate_sigma": estimate_sigma, "rtol": rtol,
        "atol": atol, "max_steps": max_steps, "format": _CHECKPOINT_FORMAT, "multiple": multiple, "segment": float(segment),
        "mu": list(MU_LEVELS),
    }  # fmt: skip
    fingerprint = _config_fingerprint(data, fp_, cfg)
    ckpt_path = Path(checkpoint) if checkpoint is not None else None

    # starts: the only random numbers of a fit, drawn from `seed` (part of the fingerprint)
    rng = np.random.default_rng(seed)
    ts_th = fp_.theta_scales()
    theta = start_design(fp_, S, spread, rng)
    nu = np.repeat(nuisance_guess(data, params)[None], S, 0)
    if multiple:
        G = seg.n_segments
        Gmax = seg.slot.shape[1]
        seg_pos = np.concatenate([np.arange(len(c) - 1) for c in seg.boundaries])
        sd, sa = seg.data.arrays(), seg.arrays()
        dscale = jnp.asarray(_shooting.defect_scale(kind, sig, float(params.R0), float(segment)))
        nu_ms = np.repeat(nuisance_guess(seg.data, params)[None], S, 0)
    # Adam works in units of `scale`: z = scale * w
    nu_scale = np.array([_NU_SCALE[n.split("_")[0]] for n in NUISANCE[kind]])
    scale = {"theta": jnp.asarray(np.broadcast_to(ts_th, (S, P))), "nu": jnp.asarray(np.broadcast_to(nu_scale, (S, T, n_nu)))}
    opt = optax.chain(optax.scale_by_adam(), optax.scale(-adam_lr))
    w = jax.tree_util.tree_map(lambda a, s: a / s, {"theta": jnp.asarray(theta), "nu": jnp.asarray(nu)}, scale)
    adam = (w, opt.init(w))  # Adam's position and optimiser state
    adam_leaves, adam_def = jax.tree_util.tree_flatten(adam)
    adam_k, adam_best = 0, None  # steps done; (cost, theta, nu) of the best point of each start
    stage = 4 if multiple else (0 if adam_steps > 0 else 1)
    it, total_it, stage_converged, max_defect = 0, 0, False, math.nan
    lm: dict[str, np.ndarray] | None = None  # Levenberg-Marquardt's per-start state (`_LM_KEYS`)
    current: dict[str, Any] | None = None  # the evaluation (residuals, Jacobian or blocks) at its points

    def nu_shape(st):
        return (G, n_nu) if multiple and st >= 4 else (T, n_nu)

    def layout(st):
        if multiple and st >= 4:
            N = Gmax * n_nu
            ev = {"Hgg": (S, P, P), "Hgn": (S, T, P, N), "Hnn": (S, T, N, N), "gg": (S, P), "gn": (S, T, N), "defect": (S, G, n_nu)}
        else:
            K = 5 * data.ts.shape[1]
            ev = {"res": (S, T, K), "J": (S, T, K, P + n_nu), "pose_x": (S, T, K // 5), "pose_y": (S, T, K // 5), "pose_q": (S, T, K // 5, 4)}
        return _checkpoint_layout(st, S, P, nu_shape(st), [np.shape(a) for a in adam_leaves], ev)

    if ckpt_path is not None:
        remove_stale_temporaries(ckpt_path)
        state, why = (None, None) if restart else _load_checkpoint(ckpt_path, fingerprint, layout)
        if why is not None:
            warnings.warn(f"fit: the checkpoint {ckpt_path} {why}; it is ignored and the fit starts afresh.", stacklevel=2)
        if state is not None:
            stage, total_it = int(state["stage"]), int(state["total_it"])
            sig, theta, max_defect = state["sig"], state["theta"], float(state["max_defect"])
            if stage >= 4:
                nu_ms = state["nu"]
            else:
                nu = state["nu"]
            if stage == 0:
                adam_k = int(state["adam_k"])
                adam = jax.tree_util.tree_unflatten(adam_def, [jnp.asarray(state[f"adam_{i}"], a.dtype) for i, a in enumerate(adam_leaves)])
                adam_best = (state["adam_best_cost"], state["adam_best_theta"], state["adam_best_nu"])
                say(f"fit: resuming from {ckpt_path} (Adam step {adam_k})")
            elif stage == 3:
                it, stage_converged = int(state["it"]), bool(state["stage_converged"])
                say(f"fit: resuming from {ckpt_path} (stage 3: finished)")
            else:
                it = int(state["it"])
                current = _unflat_evaluation({k[4:]: v for k, v in state.items() if k.startswith("out_")})
                lm = {k: state[k] for k in _LM_KEYS}
                lm["converged"] = lm["converged"].astype(bool)
                say(f"fit: resuming from {ckpt_path} (stage {stage}, iteration {it})")

    def save():
        if ckpt_path is None:
            return
        st = {"stage": stage, "total_it": total_it, "sig": sig, "theta": theta, "nu": nu_ms if stage >= 4 else nu, "max_defect": max_defect}
        if stage == 0:
            st |= {"adam_k": adam_k, "adam_best_cost": adam_best[0], "adam_best_theta": adam_best[1], "adam_best_nu": adam_best[2]}
            st |= {f"adam_{i}": a for i, a in enumerate(jax.tree_util.tree_leaves(adam))}
        elif stage == 3:
            st |= {"it": it, "stage_converged": stage_converged}
        else:
            st |= {"it": it, **lm, **{f"out_{k}": v for k, v in _flat_evaluation(current).items()}}
        _save_checkpoint(ckpt_path, fingerprint, {k: np.asarray(v) for k, v in st.items()})

    last: dict[str, Any] = {}  # the simulated poses, solver status and data of the last evaluation

    def evaluate_single(th, n):
        res, ok, J, pose = fns.jacobian(base, jnp.asarray(th), jnp.asarray(n), d, jnp.asarray(sig))
        res, ok = np.asarray(res), np.asarray(ok)
        cost = np.where(ok.all(1), 0.5 * (res * res).sum((1, 2)), np.inf)
        last.update(pose=pose, ok=ok, data=data)
        return cost, {"res": res, "J": J, "pose": pose}

    def solve_single(out, lam):
        dg, dn, pred = fns.step(jnp.asarray(out["res"]), out["J"], jnp.asarray(lam))
        return np.asarray(dg), np.asarray(dn), np.asarray(pred)

    def evaluate_multiple(mu):
        def ev(th, n):
            res, ok, J, pose, e, Je = fns.segments(base, jnp.asarray(th), jnp.asarray(n), sd, jnp.asarray(sig))
            blocks, cost, dfc = fns.assemble(res, J, e, Je, jnp.asarray(n), mu, sa, dscale)
            ok = np.asarray(ok)
            cost = np.where(ok.all(1), np.asarray(cost), np.inf)
            last.update(pose=pose, ok=ok, data=seg.data)
            return cost, {"blocks": blocks, "defect": np.asarray(dfc)}

        return ev

    def solve_multiple(out, lam):
        dg, dn, pred = fns.solve(out["blocks"], jnp.asarray(lam))
        dn = np.asarray(dn).reshape(S, T, Gmax, n_nu)[:, seg.trial, seg_pos]
        return np.asarray(dg), dn, np.asarray(pred)

    def fail(where: str):
        """Every start has failed: nothing later can recover, so stop here and say where."""
        if ckpt_path is not None:
            ckpt_path.unlink(missing_ok=True)
        raise SolverFailure(
            f"fit: every start failed in {where} (no start gives a finite cost); {_first_failure(last['data'], last['pose'], last['ok'])}, "
            "for the first start. Try: check that trial's inputs and capture near that time, start values "
            "nearer the robot (--params, --fix), bounds on the free parameters (--bound), or, in Python, a larger max_steps or a "
            "looser rtol."
        )

    def levenberg_marquardt(evaluate, solve, th, n, label, rel_done=ftol, max_rejected=8):
        """Levenberg-Marquardt on every start from `(th, n)` (or the loaded state) until the best
        start has converged (`rel_done`: the relative change of the cost that ends it;
        `max_rejected` rejections in a row) or `max_iter`; saves after every step. Returns the
        final point, its cost and evaluation."""
        nonlocal lm, it, total_it, current
        if lm is None:
            cost, out = evaluate(th, n)
            current = out
            if not np.isfinite(cost).any():
                fail(f"Levenberg-Marquardt {label}")
            lm = {"lam": np.full(S, 1e-3), "converged": np.zeros(S, bool), "stalled": np.zeros(S, int), "rejected": np.zeros(S, int)}
            lm |= {"best_cost": cost.copy(), "cost": cost}
            it = 0
            save()
        out = current
        lam, converged, stalled, rejected, best_cost = (lm[k] for k in _LM_KEYS[:-1])
        cost = lm["cost"]
        while it < max_iter and not converged[int(np.argmin(cost))]:
            dg, dn, pred_n = solve(out, lam)
            # a step longer than `STEP_MAX` (in the free parameters' scaled units) is shortened:
            # a start far off can otherwise jump to parameters whose motion takes the ODE solver
            # `max_steps` steps, and the whole vmapped batch waits for it
            length = np.max(np.abs(dg) / ts_th, axis=1) if P else np.zeros(S)
            shrink = np.minimum(1.0, STEP_MAX / np.maximum(length, 1e-300))
            dg, dn = dg * shrink[:, None], dn * shrink.reshape((S,) + (1,) * (dn.ndim - 1))
            pred_n = np.where(shrink < 1.0, np.inf, pred_n)  # (the quadratic model's prediction is of the full step)
            th_new, n_new = th + dg, n + dn
            bad = ~np.all(np.isfinite(th_new), 1) | ~np.all(np.isfinite(n_new.reshape(S, -1)), 1)
            th_new = np.where(bad[:, None], th, th_new)
            n_new = np.where(bad[:, None, None], n, n_new)
            cost_n, out_n = evaluate(th_new, n_new)
            # accept a decrease; near the optimum (predicted decrease below `noise`), accept the
            # Gauss-Newton step unless the cost rises by more than the solver's noise floor: its
            # Jacobian is accurate where cost differences are not
            with np.errstate(invalid="ignore"):  # (inf - inf for a start that has failed)
                near = (pred_n < noise) & (cost_n < cost + noise)
                acc = np.isfinite(cost_n) & ((cost_n < cost) | near) & ~converged & ~bad
                rel = (cost - cost_n) / np.maximum(cost, 1e-300)
            # accepted steps that do not lower the best cost by gtol (the solver's noise floor)
            stalled = np.where(acc, np.where(cost_n < best_cost - gtol, 0, stalled + 1), stalled)
            rejected = np.where(acc, 0, rejected + 1)
            best_cost = np.where(acc, np.minimum(best_cost, cost_n), best_cost)
            # done: a negligible predicted or relative decrease, 3 accepted steps without
            # progress, or 8 rejections in a row (lambda grown by 1e8)
            newly = (acc & (np.abs(rel) < rel_done)) | ((pred_n < gtol) & (lam <= 1.0)) | (stalled >= 3) | (rejected >= max_rejected)
            th = np.where(acc[:, None], th_new, th)
            n = np.where(acc[:, None, None], n_new, n)
            out = current = _select(acc, out_n, out)
            cost = np.where(acc, cost_n, cost)
            lam = np.where(acc, np.maximum(lam / 5.0, 1e-12), lam * 10.0)
            converged = converged | newly
            it += 1
            total_it += 1
            lm = dict(zip(_LM_KEYS, (lam, converged, stalled, rejected, best_cost, cost)))
            commit(th, n)
            save()
            step = float(np.max(np.abs(dg) / ts_th)) if P else 0.0
            say(
                f"fit: LM {label} it {it:3d}  cost {np.min(cost):.6e}  lambda {lam[np.argmin(cost)]:.1e}  "
                f"step {step:.2e}  accepted {int(acc.sum())}/{S}  ({time.perf_counter() - t_begin:.1f} s)"
            )
        return th, n, cost, out

    def commit(th, n):
        nonlocal theta, nu, nu_ms
        theta = th
        if stage >= 4:
            nu_ms = n
        else:
            nu = n

    say(f"fit: {T} trials ({kind}), {sum(data.lengths)} samples, {P} free parameters + {n_nu} nuisance per trial, {S} start(s); compiling ...")
    # ---------------------------------------------------------------- stage 4 + k: multiple shooting
    while stage >= 4:
        level = stage - 4
        mu = MU_LEVELS[level]
        if lm is None:
            say(f"fit: multiple shooting: {G} segments of about {segment:g} s, defect weight {mu:g}")
        theta, nu_ms, cost, out = levenberg_marquardt(
            evaluate_multiple(mu), solve_multiple, theta, nu_ms, f"shooting {mu:g}", rel_done=max(ftol, CONTINUATION_RTOL), max_rejected=3
        )
        b = int(np.argmin(cost))
        max_defect = float(np.max(np.abs(out["defect"][b]))) if G > T else 0.0
        lm = None
        if max_defect <= DEFECT_CLOSED or level + 1 == len(MU_LEVELS):
            say(f"fit: multiple shooting: largest defect {max_defect:.3g} noise levels; single shooting from here")
            nu = nu_ms[:, seg.first]
            stage = 1
        else:
            say(f"fit: multiple shooting: largest defect {max_defect:.3g} noise levels; raising the weight")
            stage += 1
    # ---------------------------------------------------------------- stage 0: Adam warm start
    if stage == 0:
        w, ost = adam
        for k in range(adam_k, adam_steps):
            zz = jax.tree_util.tree_map(lambda a, s: a * s, w, scale)
            cost_k, out_k = evaluate_single(zz["theta"], zz["nu"])
            res_k, J_k = out_k["res"], out_k["J"]
            if adam_best is None:
                adam_best = (cost_k.copy(), np.asarray(zz["theta"]).copy(), np.asarray(zz["nu"]).copy())
            else:
                better = cost_k < adam_best[0]
                adam_best = (
                    np.where(better, cost_k, adam_best[0]),
                    np.where(better[:, None], zz["theta"], adam_best[1]),
                    np.where(better[:, None, None], zz["nu"], adam_best[2]),
                )
            if not np.isfinite(adam_best[0]).any():
                fail("the Adam warm start")
            gg = jnp.einsum("stkp,stk->sp", J_k[..., :P], res_k)
            gn = jnp.einsum("stkn,stk->stn", J_k[..., P:], res_k)
            g = {"theta": gg * scale["theta"], "nu": gn * scale["nu"]}
            g = jax.tree_util.tree_map(lambda a: jnp.nan_to_num(a), g)
            upd, ost = opt.update(g, ost)
            w = optax.apply_updates(w, upd)
            adam, adam_k = (w, ost), k + 1
            save()
            say(f"fit: adam {k + 1:3d}/{adam_steps}  cost {np.min(cost_k):.6e}  ({time.perf_counter() - t_begin:.1f} s)")
        if adam_best is not None:
            theta, nu = adam_best[1], adam_best[2]
        stage = 1
    # ---------------------------------------------------------------- stages 1, 2: LM (single shooting)
    while stage in (1, 2):
        theta, nu, cost, out = levenberg_marquardt(evaluate_single, solve_single, theta, nu, f"stage {stage}")
        stage_converged = bool(lm["converged"][int(np.argmin(cost))])
        lm = None
        if stage == 1 and estimate_sigma:
            b = int(np.argmin(cost))
            est = _estimate_sigma(out["res"][b], data, sig, P + T * n_nu)
            # residuals of exactly 0 (noise-free data) give no estimate: keep the level used
            usable = np.isfinite(est) & (est > 0)
            sig = np.where(usable, est, sig)
            stage = 2
            kept = "" if usable.all() else " (residuals of 0 give no estimate: the level used is kept)"
            say(f"fit: noise estimated: sigma_pos {sig[0] * 1e3:.4f} mm, sigma_rot {math.degrees(sig[1]):.4f} deg{kept}; refitting")
        else:
            stage = 3
            save()
    # ---------------------------------------------------------------- result
    cost, out = evaluate_single(theta, nu)
    b = int(np.argmin(cost))
    shooting_info = {"method": "multiple" if multiple else "single"}
    if multiple:
        shooting_info |= {"segment_s": float(segment), "segments": G, "largest_defect": max_defect, "closed": max_defect <= DEFECT_CLOSED}
    result = _result(fp_, data, base, out["pose"], theta, nu, out["res"], out["J"], cost, sig, b, stage_converged, total_it, t_begin)
    return dataclasses.replace(result, shooting=shooting_info)


def _select(acc, new, old):
    """Per start: `new` where accepted, else `old` (pytrees with a leading start axis)."""
    a = jnp.asarray(acc)
    return jax.tree_util.tree_map(lambda x, y: jnp.where(a.reshape((-1,) + (1,) * (x.ndim - 1)), x, y), new, old)


def _estimate_sigma(res_b, data: FitData, sig, n_par: int) -> np.ndarray:
    """Noise levels from the whitened residuals of the best start (dof-corrected; in numpy, whose
    sums do not depend on where the residuals were computed)."""
    res_b = np.asarray(res_b)
    M = data.ts.shape[1]
    pos = res_b[:, : 2 * M] * sig[0]
    rot = res_b[:, 2 * M :] * sig[1]
    n_pos, n_rot = 2 * data.wpos.sum(), 3 * data.wrot.sum()
    frac = 1.0 - n_par / (n_pos + n_rot)
    return np.sqrt(np.array([(pos * pos).sum() / (n_pos * frac), (rot * rot).sum() / (n_rot * frac)]))


def _result(fp_: FreeParams, data, base, pose, theta, nu, res, J, cost, sig, b, converged, iterations, t_begin) -> FitResult:
    P = fp_.size
    T = data.ts.shape[0]
    n_nu = nu.shape[-1]
    th_b = theta[b]
    res_b, J_b = np.asarray(res[b]), J[b]
    n_res = int(2 * data.wpos.sum() + 3 * data.wrot.sum())
    dof = max(n_res - P - T * n_nu, 1)
    s2 = float(2.0 * cost[b] / dof)
    F = marginal_information(jnp.asarray(res_b), J_b, P)  # information of theta (whitened)
    A = np.asarray(jax.jacfwd(fp_.physical)(jnp.asarray(th_b)))
    # (pinv: a transform at the edge of its range, e.g. exp(u) -> 0, has a zero derivative; the
    # name then gets no information, and an infinite standard error)
    Ainv = np.linalg.pinv(A)
    F_phys = Ainv.T @ F @ Ainv
    values = np.asarray(fp_.physical(jnp.asarray(th_b)))
    sc = np.maximum(np.abs(values), 0.1 * fp_.scales())
    Fs = sc[:, None] * F_phys * sc[None, :]
    lam, V = np.linalg.eigh(Fs)
    keep = lam > 1e-14 * max(lam[-1], 1e-300)
    cov_s = (V[:, keep] / lam[keep]) @ V[:, keep].T * s2
    cov = sc[:, None] * cov_s * sc[None, :]
    se = np.sqrt(np.maximum(np.diag(cov), 0.0))
    null_w = np.abs(V[:, ~keep]).max(1) if (~keep).any() else np.zeros(P)
    se = np.where(null_w > 1e-6, np.inf, se)
    with np.errstate(invalid="ignore", divide="ignore"):
        corr = cov / np.outer(se, se)
    corr = np.where(np.isfinite(corr), corr, np.nan)
    np.fill_diagonal(corr, 1.0)
    params = fp_.to_params(jnp.asarray(th_b), base)
    params = RobotParams(**{f: getattr(params, f) for f in _FIELDS}, dtype=base.R0.dtype)
    ident = identifiability(fp_, values, F_phys, s2, params)
    ident["sigma_note"] = "relative sd of each direction; warnings list directions with relative sd > 10%"
    # the fitted trajectories, for the RMS values and the plots
    xs, ys, qs = (np.asarray(a[b]) for a in pose)
    rot_err = np.asarray(quat_log(quat_mul(quat_conj(jnp.asarray(qs)), jnp.asarray(data.q))))
    trials = []
    names_nu = NUISANCE[data.kind]
    for i in range(T):
        m = data.lengths[i]
        wp, wr = data.wpos[i, :m] > 0, data.wrot[i, :m] > 0
        ep = np.stack([xs[i, :m] - data.x[i, :m], ys[i, :m] - data.y[i, :m]], 1)
        er = rot_err[i, :m]
        trials.append(
            {
                "name": data.names[i],
                "samples": m,
                "rms_pos_m": float(np.sqrt((ep[wp] ** 2).sum(1).mean())),
                "rms_rot_deg": float(np.degrees(np.sqrt((er[wr] ** 2).sum(1).mean()))),
                "nuisance": {k: float(v) for k, v in zip(names_nu, nu[b, i])},
                "series": {
                    "t": data.ts[i, :m] + data.t_start[i],
                    "x": np.where(wp, data.x[i, :m], np.nan),
                    "y": np.where(wp, data.y[i, :m], np.nan),
                    "x_sim": xs[i, :m],
                    "y_sim": ys[i, :m],
                    "pos_err": np.where(wp[:, None], ep, np.nan),
                    "rot_err_deg": np.where(wr[:, None], np.degrees(er), np.nan),
                },
            }
        )
    per_val = {n: float(v) for n, v in zip(fp_.names, values)}
    per_se = {n: float(s) for n, s in zip(fp_.names, se)}
    from .verdict import judge, noise_floor

    verdict = judge(
        [t["series"]["pos_err"] for t in trials], [np.radians(t["series"]["rot_err_deg"]) for t in trials], noise_floor(data),
        names=data.names, converged=bool(converged), n_params=P + T * n_nu,
        why_not=f"Levenberg-Marquardt reached max_iter in its last stage, {int(iterations)} iterations in all",
    )  # fmt: skip
    status, status_reason = verdict.pop("status"), verdict.pop("reason")
    return FitResult(
        params=params, free=list(fp_.names), given=fp_.given,
        values=_assemble_named(fp_, per_val, params, np.nan), stderr=_assemble_named(fp_, per_se, params, 0.0),
        covariance=cov, correlation=corr, cost=float(cost[b]), iterations=int(iterations), converged=bool(converged),
        sigma_pos=float(sig[0]), sigma_rot=float(sig[1]), n_residuals=n_res, identifiability=ident, trials=trials,
        starts=[float(c) for c in cost], kind=data.kind, elapsed_s=time.perf_counter() - t_begin,
        status=status, status_reason=status_reason, verdict=verdict,
    )  # fmt: skip


# ----------------------------------------------------------------------------- generic least squares


@dataclasses.dataclass
class LeastSquaresResult:
    """`x`: the solution; `cost = 1/2 |r|^2`; `jac`: `dr/dx` at `x`; `covariance`:
    `s2 (J^T J)^-1` with `s2 = 1` (the residuals are taken as whitened) unless `scale_by_residual`."""

    x: np.ndarray
    cost: float
    jac: np.ndarray
    covariance: np.ndarray
    iterations: int
    converged: bool


def least_squares(
    fun: Callable,
    x0,
    *,
    max_iter: int = 50,
    ftol: float = 1e-14,
    xtol: float = 1e-12,
    jac: str = "rev",
    scale_by_residual: bool = False,
) -> LeastSquaresResult:
    """Levenberg-Marquardt on a small dense problem: minimise `1/2 |fun(x)|^2`.

    `fun` is a pure JAX function of `x (P,)` returning whitened residuals `(K,)`; its
    Jacobian is taken by `jax.jacrev` (`jac="rev"`, for few residuals or simulations with the
    default adjoint) or `jax.jacfwd` (`jac="fwd"`, with `adjoint=diffrax.ForwardMode()`).
    Used by `examples/fit_paper_Rm_j.py` together with `FreeParams`.
    """
    jf = jax.jit(jax.jacrev(fun) if jac == "rev" else jax.jacfwd(fun))
    f = jax.jit(fun)
    x = np.asarray(x0, np.float64)
    r = np.asarray(f(x))
    Jm = np.asarray(jf(x))
    cost = 0.5 * float(r @ r)
    lam, converged, k = 1e-3, False, 0
    for k in range(1, max_iter + 1):
        H = Jm.T @ Jm
        g = Jm.T @ r
        D = np.diag(np.diag(H)) + 1e-300 * np.eye(len(x))
        dx = -np.linalg.solve(H + lam * D, g)
        xn = x + dx
        rn = np.asarray(f(xn))
        cn = 0.5 * float(rn @ rn)
        if np.isfinite(cn) and cn < cost:
            small = (cost - cn) <= ftol * max(cost, 1e-300) or np.max(np.abs(dx) / np.maximum(np.abs(x), 1.0)) < xtol
            x, r, cost = xn, rn, cn
            Jm = np.asarray(jf(x))
            lam = max(lam / 5.0, 1e-15)
            if small or cost == 0.0:
                converged = True
                break
        else:
            lam *= 10.0
            if lam > 1e15:
                converged = True
                break
    s2 = 2 * cost / max(len(r) - len(x), 1) if scale_by_residual else 1.0
    cov = s2 * np.linalg.pinv(Jm.T @ Jm, rcond=1e-14, hermitian=True)
    return LeastSquaresResult(x=x, cost=cost, jac=Jm, covariance=cov, iterations=k, converged=converged)
