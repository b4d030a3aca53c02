"""Multiple shooting for the fit: trials cut into segments, each with its own initial state.

Over a long trial, small errors of the start values grow (a heading error turns into a
position error that grows with the distance rolled), and the cost of single shooting has many
wrong valleys. Multiple shooting (Bock's method) cuts each trial into segments of a few
seconds that start at captured frames. Each segment gets its own nuisance parameters: the
initial state of the segment, in the same form as a trial's (`jsphere.identify.data.NUISANCE`), started
from the capture. The continuity defects between consecutive segments of a trial,

    d_s = state(end of segment s) (-) state0(segment s+1)
        = (Omega_end - Omega0', Log(q_end^-1 q0'), x_end - x0', y_end - y0' [, omega_end - omega0']
           [, offset - offset'])

each component divided by the change that one noise level makes over a segment (`defect_scale`),
become residuals of weight `mu`. The fit raises `mu` until the defects vanish, which is a
continuation from independent segments to one trajectory per trial. A fitted clock offset
(`jsphere.identify.data.TIME_OFFSET`) is a nuisance value of every segment, its defect the
difference from the next segment's; each segment's table of inputs then reaches far enough
beyond its ends for the largest offset.

Given the parameters `theta`, segments are independent, so they are simulated in one vmapped
batch. The normal equations are an arrow over trials whose nuisance block per trial is block
tridiagonal (a defect couples consecutive segments). It is assembled as a dense
`(G n, G n)` block per trial (`G` segments of at most `n` nuisance parameters) and eliminated as
in single shooting (`jsphere.numerics.lm.solve_arrow`).
"""

from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np

from ..model.rotations import quat_conj, quat_exp, quat_log, quat_mul
from .data import NUISANCE, FitData

#: the end state of a segment as one vector: q (4), x, y, Omega (3), omega (3)
END_SIZE = 13
#: the weights of the continuity defects, one level after the other
MU_LEVELS = (1.0, 10.0, 100.0, 1e3, 1e4)
#: the largest defect [noise levels, `defect_scale`] that counts as closed
DEFECT_CLOSED = 0.5
#: a level of the continuation ends when an accepted step changes its cost by less than this
#: (relative), or after 3 rejected steps in a row: its minimiser is only the start of the next
#: level, and single shooting polishes
CONTINUATION_RTOL = 1e-4


@dataclasses.dataclass(frozen=True)
class Segments:
    """Trials cut into segments. `data` holds the segments as trials of their own (a
    `FitData`, padded to a common length; the sample at a segment's end is the first sample of
    the next, simulated but not counted in the residuals). `trial (G,)`: the trial of each
    segment; `slot (T, Gmax)`: the segments of each trial in order (`G` where there is none);
    `has_next (G,)`: whether a segment of the same trial follows; `next_xy0 (G, 2)`,
    `next_q0 (G, 4)`: the captured pose at the start of the following segment; `first (T,)`:
    the first segment of each trial; `boundaries`: per trial the sample indices where its
    segments start, and its last sample."""

    data: FitData
    trial: np.ndarray
    slot: np.ndarray
    has_next: np.ndarray
    next_xy0: np.ndarray
    next_q0: np.ndarray
    first: np.ndarray
    boundaries: tuple[tuple[int, ...], ...]

    @property
    def n_segments(self) -> int:
        return int(self.trial.shape[0])

    def arrays(self) -> dict[str, jax.Array]:
        return {
            "has_next": jnp.asarray(self.has_next, jnp.float64),
            "next_xy0": jnp.asarray(self.next_xy0),
            "next_q0": jnp.asarray(self.next_q0),
            "slot": jnp.asarray(self.slot),
        }


def boundaries(t: np.ndarray, both: np.ndarray, segment: float) -> list[int]:
    """Sample indices where the segments of one trial start, and its last sample.

    The trial is cut into `round(duration / segment)` (at least 1) segments of equal length;
    each cut moves to the nearest frame where position and orientation were both captured (a
    segment starts from a captured pose), at least 3 samples from the previous cut."""
    m = len(t)
    n_seg = max(1, round((t[-1] - t[0]) / segment))
    good = np.flatnonzero(both)
    cuts = [0]
    for k in range(1, n_seg):
        target = t[0] + k * (t[-1] - t[0]) / n_seg
        cand = good[(good > cuts[-1] + 2) & (good < m - 3)]
        if cand.size == 0:
            break
        cuts.append(int(cand[np.argmin(np.abs(t[cand] - target))]))
    return cuts + [m - 1]


def segment_trials(data: FitData, segment: float) -> Segments:
    """Cut the trials of a `FitData` into segments of about `segment` seconds (`Segments`)."""
    T = data.ts.shape[0]
    pieces, cut_list = [], []  # (trial, first sample, last sample, last segment of its trial)
    for i in range(T):
        m = data.lengths[i]
        cuts = boundaries(data.ts[i, :m], (data.wpos[i, :m] > 0) & (data.wrot[i, :m] > 0), segment)
        cut_list.append(tuple(cuts))
        pieces += [(i, cuts[s], cuts[s + 1], s == len(cuts) - 2) for s in range(len(cuts) - 1)]
    L = max(b - a + 1 for _, a, b, _ in pieces)
    extra = 2
    if data.max_offset > 0:
        dt = float(np.median(np.diff(data.tc[0, : data.lengths[0]])))
        extra += int(math.ceil(data.max_offset / dt))
    rows = [_segment(data, i, a, b, last, L, extra) for i, a, b, last in pieces]
    G = len(pieces)
    trial_of = np.asarray([p[0] for p in pieces])
    slot = np.full((T, max(len(c) - 1 for c in cut_list)), G, np.int32)
    for i in range(T):
        idx = np.flatnonzero(trial_of == i)
        slot[i, : idx.size] = idx
    has_next, nxt_xy0, nxt_q0 = zip(*(r["next"] for r in rows))
    return Segments(
        data=FitData.stacked(rows, data.kind, data.max_offset),
        trial=trial_of,
        slot=slot,
        has_next=np.asarray(has_next),
        next_xy0=np.stack(nxt_xy0),
        next_q0=np.stack(nxt_q0),
        first=slot[:, 0].copy(),
        boundaries=tuple(cut_list),
    )


def _segment(data: FitData, i: int, a: int, b: int, last: bool, L: int, extra: int = 2) -> dict:
    """Samples `a..b` of trial `i` as a trial of its own, padded to `L` samples: its arrays (as
    `FitData`'s), name, length, start time, and `next`: whether a segment follows and the
    captured pose where it starts. The segment's table of inputs holds `extra` more knots on
    each side (2: the cubic table is the trial's; more for a fitted clock offset)."""
    Lc = L + 2 * extra
    m = b - a + 1
    t0 = data.ts[i, a]
    ts = data.ts[i, a : b + 1] - t0
    # knots a-extra .. b+extra of the trial's table (its padding continues past its end)
    lo = max(a - extra, 0)
    kn = np.arange(lo, lo + Lc)
    kn_c = np.minimum(kn, data.tc.shape[1] - 1)
    tc = data.tc[i, kn_c] - t0
    over = kn - kn_c  # beyond the trial's padded table: continue its spacing
    dt = (data.tc[i, -1] - data.tc[i, -2]) if data.tc.shape[1] > 1 else 1.0
    wp = data.wpos[i, a : b + 1].copy()
    wr = data.wrot[i, a : b + 1].copy()
    if not last:  # the next segment's first sample: simulated for the defect, counted there
        wp[-1] = wr[-1] = 0.0
    pad = lambda v, fill: np.concatenate([v, np.broadcast_to(fill, (L - m,) + v.shape[1:])])
    vp, vr = data.wpos[i, a : b + 1] > 0, data.wrot[i, a : b + 1] > 0
    nxt = (
        (True, np.array([data.x[i, b], data.y[i, b]]), data.q[i, b])
        if not last
        else (False, np.zeros(2), np.array([1.0, 0.0, 0.0, 0.0]))
    )
    return {
        "ts": np.concatenate([ts, np.full(L - m, ts[-1])]),
        "tc": tc + over * dt,
        "u": data.u[i, kn_c],
        "t1": ts[-1],
        "x": pad(data.x[i, a : b + 1], 0.0),
        "y": pad(data.y[i, a : b + 1], 0.0),
        "q": pad(data.q[i, a : b + 1], np.array([1.0, 0.0, 0.0, 0.0])),
        "wpos": pad(wp, 0.0),
        "wrot": pad(wr, 0.0),
        "xy0": np.array([data.x[i, a : b + 1][vp][0], data.y[i, a : b + 1][vp][0]]) if vp.any() else data.xy0[i],
        "q0": data.q[i, a : b + 1][vr][0] if vr.any() else data.q0[i],
        "name": f"{data.names[i]}[{t0:.2f}s]",
        "length": m,
        "start": data.t_start[i] + float(t0),
        "next": nxt,
    }


def defect_scale(kind: str, sig, R0: float, segment: float, time_offset: bool = False) -> np.ndarray:
    """The size of each defect component that counts as one noise level: `sigma_rot` for the
    orientation, `sigma_pos` for the position, and for the velocities the error that moves the
    pose by one noise level over a segment (`sigma_pos / (R0 tau)` for the shell's rolling rate
    `Omega`, `sigma_rot / tau` for the platform's `omega`), `tau` the segment length; for a
    fitted clock offset `sigma_pos / R0` seconds (the time in which a shell rolling at 1 rad/s
    moves by one noise level)."""
    sp, sr = float(sig[0]), float(sig[1])
    tau = max(float(segment), 1e-3)
    out = [sp / (R0 * tau)] * 3 + [sr] * 3 + [sp] * 2
    if kind == "torques":
        out += [sr / tau] * 3
    if time_offset:
        out += [sp / R0]
    return np.asarray(out)


def end_vector(traj) -> jax.Array:
    """The state at a segment's last sample as one vector (`END_SIZE`)."""
    return jnp.concatenate([traj.q[-1], traj.x[-1:], traj.y[-1:], traj.Omega[-1], traj.omega[-1]])


def defect(kind: str, end, nu_next, next_xy0, next_q0, scale):
    """Continuity defect between a segment's end state `end` (`end_vector`, then the segment's
    clock offset where it is fitted) and the initial state of the next segment (its nuisance
    `nu_next` and captured pose), divided by `scale`."""
    q_end, x_end, y_end, Om_end = end[0:4], end[4], end[5], end[6:9]
    q0n = quat_mul(next_q0, quat_exp(nu_next[3:6]))
    parts = [
        Om_end - nu_next[0:3],
        quat_log(quat_mul(quat_conj(q_end), q0n)),
        jnp.stack([x_end - (next_xy0[0] + nu_next[6]), y_end - (next_xy0[1] + nu_next[7])]),
    ]
    if kind == "torques":
        parts.append(end[9:12] - nu_next[8:11])
    if nu_next.shape[0] > len(NUISANCE[kind]):  # the clock offset, last
        parts.append(end[-1:] - nu_next[-1:])  # end: `end_vector`, then the offset
    return jnp.concatenate(parts) / scale


def assemble(kind: str, P: int, res, J, e, Je, nu, mu, seg: dict, scale):
    """Normal-equation blocks of the multiple-shooting problem, per trial.

    `res (G, K)`, `J (G, K, P + n)`: the whitened residuals of each segment and their Jacobian
    with respect to `(theta, nu_s)`; `e (G, END_SIZE)`, `Je (G, END_SIZE, P + n)`: each
    segment's end state and its Jacobian; `nu (G, n)`; `mu`: the weight of the defects.
    Returns `(Hgg (P, P), Hgn (T, P, Gmax n), Hnn (T, Gmax n, Gmax n), gg (P,), gn (T, Gmax n))`,
    the cost `1/2 |r|^2 + mu/2 |d|^2`, and the defects `(G, n)` (unweighted)."""
    G, n = nu.shape
    slot = seg["slot"]
    T, Gmax = slot.shape
    has = seg["has_next"]
    # the next segment of each segment (itself where there is none: masked out)
    nxt = jnp.minimum(jnp.arange(G) + 1, G - 1)
    nu_next = nu[nxt]

    def one(e_s, nu_n, xy0, q0):
        return defect(kind, e_s, nu_n, xy0, q0, scale)

    d = jax.vmap(one)(e, nu_next, seg["next_xy0"], seg["next_q0"])
    De = jax.vmap(jax.jacfwd(one, argnums=0))(e, nu_next, seg["next_xy0"], seg["next_q0"])  # (G, n, END)
    Dn = jax.vmap(jax.jacfwd(one, argnums=1))(e, nu_next, seg["next_xy0"], seg["next_q0"])  # (G, n, n)
    w = jnp.sqrt(mu) * has
    d = d * has[:, None]
    dw = d * w[:, None]
    Dz = jnp.einsum("gne,gez->gnz", De, Je) * w[:, None, None]  # w.r.t. (theta, nu_s)
    Dn = Dn * w[:, None, None]  # w.r.t. nu_{s+1}
    Jg, Jn = J[..., :P], J[..., P:]
    Dg, Da = Dz[..., :P], Dz[..., P:]
    # global blocks
    Hgg = jnp.einsum("gkp,gkq->pq", Jg, Jg) + jnp.einsum("gkp,gkq->pq", Dg, Dg)
    gg = jnp.einsum("gkp,gk->p", Jg, res) + jnp.einsum("gkp,gk->p", Dg, dw)
    # per segment: its diagonal block, its coupling to theta and its gradient; the defect of
    # segment s adds to the blocks of s and s+1 and to the off-diagonal block (s, s+1)
    Hss = jnp.einsum("gkn,gkm->gnm", Jn, Jn) + jnp.einsum("gkn,gkm->gnm", Da, Da)
    Hgs = jnp.einsum("gkp,gkn->gpn", Jg, Jn) + jnp.einsum("gkp,gkn->gpn", Dg, Da)
    gs = jnp.einsum("gkn,gk->gn", Jn, res) + jnp.einsum("gkn,gk->gn", Da, dw)
    Hnext = jnp.einsum("gkn,gkm->gnm", Dn, Dn)  # to the block of s+1
    Hgnext = jnp.einsum("gkp,gkn->gpn", Dg, Dn)
    gnext = jnp.einsum("gkn,gk->gn", Dn, dw)
    Hoff = jnp.einsum("gkn,gkm->gnm", Da, Dn)  # (s, s+1)
    # move the "next" contributions to the segment they belong to (segment s+1 = index s+1)
    shift = lambda a: jnp.concatenate([jnp.zeros_like(a[:1]), a[:-1]], axis=0)
    Hss = Hss + shift(Hnext)
    Hgs = Hgs + shift(Hgnext)
    gs = gs + shift(gnext)
    # per trial, dense: slot (T, Gmax) -> segment (G: an empty slot, identity block, no gradient)
    eye = jnp.eye(n, dtype=res.dtype)
    pad1 = lambda a, fill: jnp.concatenate([a, fill[None]], axis=0)
    Hd = pad1(Hss, eye)[slot]  # (T, Gmax, n, n)
    Ho = pad1(Hoff, jnp.zeros_like(eye))[slot[:, :-1]]  # (T, Gmax-1, n, n): (g, g+1)
    Hgn = pad1(Hgs, jnp.zeros_like(Hgs[0]))[slot]  # (T, Gmax, P, n)
    gn = pad1(gs, jnp.zeros_like(gs[0]))[slot]  # (T, Gmax, n)
    ar = jnp.arange(Gmax)
    H = jnp.zeros((T, Gmax, Gmax, n, n), res.dtype)
    H = H.at[:, ar, ar].set(Hd)
    if Gmax > 1:
        H = H.at[:, ar[:-1], ar[1:]].set(Ho)
        H = H.at[:, ar[1:], ar[:-1]].set(jnp.swapaxes(Ho, -1, -2))
    Hnn = jnp.transpose(H, (0, 1, 3, 2, 4)).reshape(T, Gmax * n, Gmax * n)
    Hgn = jnp.transpose(Hgn, (0, 2, 1, 3)).reshape(T, P, Gmax * n)
    gn = gn.reshape(T, Gmax * n)
    cost = 0.5 * jnp.sum(res * res) + 0.5 * jnp.sum(dw * dw)
    return (Hgg, Hgn, Hnn, gg, gn), cost, d
