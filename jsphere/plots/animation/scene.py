"""What an animation shows, as NumPy arrays: the robots of a run (`Body`), grouped in `Scene`s,
and the geometry of every frame (`BodyFrames`), computed at once for all frames so that the video
writer and the HTML viewer only move their artists.

Frames: jsphere's fixed frame `OXYZ` (Z up, the floor at `Z = 0`, the shell's centre at
`Z = R0`), metres. Rotation matrices map body components to fixed ones (`rotmat(q)`: rows
`alpha, beta, gamma` for the platform, as `jsphere.State.q`; the shell's as `State.q_shell`).
A capture or a plan table records the platform only: there the shell's attitude is integrated
along the floor path by the rolling constraint (2.3) (`rolling_attitude`, `body_from_poses`)."""

from __future__ import annotations

import dataclasses
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from ...model.params import RobotParams


@dataclasses.dataclass
class Body:
    """One robot along a run, at its own times `t (T,)` [s]: the shell centre `x, y (T,)` [m]
    (fixed frame), the platform's attitude `R (T, 3, 3)` and the shell's `R_shell (T, 3, 3)`
    (body -> fixed components), wheel angles `chi (T, N)` [rad] and rates `chi_dot (T, N)`
    [rad/s]. `label` names it on screen; a `ghost` is drawn translucent over another body (a
    model over the capture)."""

    t: np.ndarray
    x: np.ndarray
    y: np.ndarray
    R: np.ndarray
    R_shell: np.ndarray
    chi: np.ndarray
    chi_dot: np.ndarray
    label: str = ""
    ghost: bool = False

    @property
    def duration(self) -> float:
        return float(self.t[-1] - self.t[0])


@dataclasses.dataclass
class Scene:
    """One run to show: its `bodies` (drawn together, on common times from the first body's
    start), the `params` whose geometry is drawn, a `title`, the `target` `(x, y)` [m] (a plan's)
    or None, and for a Monte-Carlo study the stop points `cloud (M, 2)` [m] and the confidence
    `ellipse (P, 2)` [m], shown over the run's last tenth. `residual`: for a fit, the text of the
    residual of the model (the second body) against the capture (the first) is computed per
    frame when True."""

    bodies: list[Body]
    params: RobotParams
    title: str = ""
    target: tuple[float, float] | None = None
    cloud: np.ndarray | None = None
    ellipse: np.ndarray | None = None
    residual: bool = False

    @property
    def duration(self) -> float:
        return max(b.duration for b in self.bodies)


# ------------------------------------------------------------------------ attitudes from poses


def rolling_attitude(t, x, y, R0: float, spin=None) -> np.ndarray:
    """The shell's attitudes `(T, 3, 3)` (shell -> fixed, the identity at the first sample)
    integrated along the floor path `x, y (T,)` [m] by the rolling constraint (2.3): each step
    turns the shell by the rotation vector `(-dy, dx, 0) / R0 + (0, 0, spin dt)`, `spin (T,)`
    [1/s] the shell's rate about the vertical (zero if None). Over a straight roll of length `d`
    the shell turns by `d / R0`."""
    from scipy.spatial.transform import Rotation

    t, x, y = (np.asarray(a, float) for a in (t, x, y))
    dx, dy = np.diff(x), np.diff(y)
    w = np.zeros((dx.size, 3))
    w[:, 0], w[:, 1] = -dy / R0, dx / R0
    if spin is not None:
        s = np.asarray(spin, float)
        w[:, 2] = 0.5 * (s[1:] + s[:-1]) * np.diff(t)
    steps = Rotation.from_rotvec(w).as_matrix()
    out = np.empty((t.size, 3, 3))
    out[0] = np.eye(3)
    for k in range(dx.size):  # a product of small rotations (T of them; ~1 us each)
        out[k + 1] = steps[k] @ out[k]
    return out


def body_rates(t, R) -> np.ndarray:
    """The platform's angular velocity `omega (T, 3)` [1/s] in platform components, from its
    attitudes `R (T, 3, 3)`: `[omega]_x = R^T dR/dt` (central differences)."""
    dR = np.gradient(np.asarray(R), np.asarray(t), axis=0)
    W = np.einsum("tji,tjk->tik", R, dR)
    return 0.5 * np.stack([W[:, 2, 1] - W[:, 1, 2], W[:, 0, 2] - W[:, 2, 0], W[:, 1, 0] - W[:, 0, 1]], axis=-1)


def body_from_poses(params: RobotParams, t, x, y, R, *, chi_dot=None, label: str = "", ghost: bool = False) -> Body:
    """A `Body` from platform poses (a capture, a plan's table): frames with a missing pose
    (NaN) are left out; the shell's attitude is integrated by `rolling_attitude`, with the spin
    about the vertical that the wheel rates `chi_dot (T, N)` [rad/s] give through (2.4) when
    they are known (else none). Without wheel rates (torque inputs), the wheel rates are those
    (2.4) gives for that shell motion; the wheel angles integrate the rates."""
    from ...model.params import derive

    t, x, y, R = (np.asarray(a, float) for a in (t, x, y, R))
    ok = np.isfinite(x) & np.isfinite(y) & np.all(np.isfinite(R), axis=(1, 2))
    later = np.flatnonzero(ok)
    ok[later[:-1][np.diff(t[later]) <= 0]] = False  # a repeated time (a jump in a table): its last row
    if chi_dot is not None:
        chi_dot = np.asarray(chi_dot, float)[ok]
    t, x, y, R = t[ok], x[ok], y[ok], R[ok]
    if t.size < 2:
        raise ValueError(f"{label or 'the run'}: fewer than two frames with a pose; nothing to animate.")
    d, omega, R0, spin = derive(params), body_rates(t, R), float(params.R0), None
    if chi_dot is not None:  # (2.4): omega - Omega = -Sk^+ chi_dot, in platform components
        rel = -np.einsum("ij,tj->ti", np.asarray(d.Sk_pinv), chi_dot)
        spin = np.einsum("tij,tj->ti", R, omega - rel)[:, 2]
    R_shell = rolling_attitude(t, x, y, R0, spin)
    if chi_dot is None:  # the rates (2.4) of this shell motion: Omega (fixed) from the path
        vx, vy = np.gradient(x, t), np.gradient(y, t)
        Om_fixed = np.stack([-vy / R0, vx / R0, np.zeros_like(vx)], axis=-1)
        Om = np.einsum("tji,tj->ti", R, Om_fixed)
        chi_dot = -np.einsum("ij,tj->ti", np.asarray(d.Sk), omega - Om)
    inc = 0.5 * (chi_dot[1:] + chi_dot[:-1]) * np.diff(t)[:, None]  # the wheel angles: the rates integrated
    chi = np.concatenate([np.zeros((1, chi_dot.shape[1])), np.cumsum(inc, axis=0)])
    return Body(t, x, y, R, R_shell, chi, chi_dot, label, ghost)


def body_from_trajectory(traj, *, label: str = "", ghost: bool = False) -> Body:
    """A `Body` from a `Trajectory`: the shell's attitude is the state's `q_shell`, the wheel
    angles and rates the state's `chi`, `chi_dot`."""
    from ...model.rotations import rotmat_np

    ts = np.asarray(traj.ts, float)
    keep = np.concatenate([np.diff(ts) > 0, [True]])  # a repeated time (a jump): its last value
    R = np.stack([np.asarray(traj.alpha), np.asarray(traj.beta), np.asarray(traj.gamma)], axis=-2)
    arrays = (ts, traj.x, traj.y, R, rotmat_np(np.asarray(traj.q_shell, float)), traj.chi, traj.chi_dot)
    return Body(*(np.asarray(a, float)[keep] for a in arrays), label, ghost)


def body_from_trial(params: RobotParams, trial, *, label: str | None = None, ghost: bool = False) -> Body:
    """A `Body` from a `Trial` (`body_from_poses`; its wheel speeds, if those are its inputs)."""
    from ...model.rotations import rotmat_np

    if not np.any(trial.valid):
        raise ValueError(f"trial {trial.name!r} has no frame with a pose; nothing to animate.")
    if trial.n_wheels != params.n_wheels:
        raise ValueError(
            f"trial {trial.name!r} has {trial.n_wheels} wheels but the robot drawn has {params.n_wheels}; "
            "give its parameter file with --params."
        )
    R = rotmat_np(np.where(np.isfinite(trial.q), trial.q, np.array([1.0, 0, 0, 0])))
    R[~trial.valid] = np.nan
    chi_dot = trial.inputs if trial.kind == "wheel_speeds" else None
    label = trial.name if label is None else label
    return body_from_poses(params, trial.t, trial.x, trial.y, R, chi_dot=chi_dot, label=label, ghost=ghost)


def platform_from_table(params: RobotParams, gamma, heading) -> np.ndarray:
    """Platform attitudes `(T, 3, 3)` from a plan table's `gamma_1..3` and `heading` (the
    precession angle `psi` of (2.6)-(2.8) about the vertical): the attitude with third row
    `gamma` nearest the rest attitude turned by `heading`."""
    from scipy.spatial.transform import Rotation

    g = np.asarray(gamma, float)
    g = g / np.linalg.norm(g, axis=-1, keepdims=True)
    gm = -np.asarray(params.r_m, float) / np.linalg.norm(np.asarray(params.r_m, float))
    e3 = np.array([0.0, 0.0, 1.0])

    def between(a, b):  # the smallest rotations taking a to b, (T, 3, 3)
        a, b = np.broadcast_to(a, b.shape), b
        axis = np.cross(a, b)
        s, c = np.linalg.norm(axis, axis=-1), np.einsum("ti,ti->t", a, b)
        ang = np.arctan2(s, c)
        unit = np.where(s[:, None] > 1e-15, axis / np.maximum(s, 1e-300)[:, None], 0.0)
        return Rotation.from_rotvec(unit * ang[:, None]).as_matrix()

    # M = R Qm has third row the fixed vertical seen from a frame at rest (gamma_m -> e3); its
    # tilt is the smallest rotation taking e3 to M^T e3, its heading the yaw in front of it
    Qm = between(e3[None], gm[None])[0]
    gM = g @ Qm  # = Qm^T gamma, the vertical seen in the rest-aligned frame
    B = np.swapaxes(between(e3[None], gM), -1, -2)  # B^T e3 = gM
    yaw0 = np.arctan2(B[:, 1, 0], B[:, 0, 0])
    c, s = np.cos(np.asarray(heading) - yaw0), np.sin(np.asarray(heading) - yaw0)
    Z = np.zeros((g.shape[0], 3, 3))
    Z[:, 0, 0], Z[:, 0, 1], Z[:, 1, 0], Z[:, 1, 1], Z[:, 2, 2] = c, -s, s, c, 1.0
    return Z @ B @ Qm.T


# ------------------------------------------------------------------------------------- frames


def frame_times(duration: float, fps: float, speed: float) -> np.ndarray:
    """The run times [s] of the frames of a clip: `round(duration / speed * fps)` frames (at
    least 2) from the start to the end, so that the clip lasts `duration / speed` within one
    frame."""
    n = max(2, int(round(duration / speed * fps)))
    return np.linspace(0.0, duration, n)


def _slerp(t, R, at) -> np.ndarray:
    from scipy.spatial.transform import Rotation, Slerp

    from ...model.rotations import quat_from_rotmat_np

    return Slerp(t, Rotation.from_quat(quat_from_rotmat_np(R), scalar_first=True))(np.clip(at, t[0], t[-1])).as_matrix()


def _lerp(t, v, at) -> np.ndarray:
    v = np.asarray(v, float)
    if v.ndim == 1:
        return np.interp(at, t, v)
    return np.stack([np.interp(at, t, v[:, i]) for i in range(v.shape[1])], axis=-1)


def _circle(n: int) -> np.ndarray:
    a = np.linspace(0.0, 2.0 * np.pi, n)
    return np.stack([np.cos(a), np.sin(a)], axis=-1)


def _gaps(parts: np.ndarray) -> np.ndarray:
    """Polylines `(F, L, P, 3)` as one polyline per frame `(F, L (P + 1), 3)`, NaN between them
    (drawn as one artist, broken at the NaN)."""
    F, L, P, _ = parts.shape
    out = np.full((F, L, P + 1, 3), np.nan)
    out[:, :, :P] = parts
    return out.reshape(F, L * (P + 1), 3)


@dataclasses.dataclass
class BodyFrames:
    """The drawn geometry of one `Body` at every frame, fixed frame [m]: `centre (F, 3)`,
    `meridians (F, P, 3)` (great circles through the shell's poles, one polyline with NaN gaps),
    `equator (F, P, 3)`, `platform (F, P, 3)` (the polygon through the wheel centres),
    `wheels (F, P, 3)` (each omniwheel's rim and spokes turned by its angle `chi_i`),
    `rollers (F, P, 3)` (the roller axis `alpha_i` at each wheel's contact), `com (F, 3)` and the
    `mast (F, P, 3)` from the centre to it; `path (F, 2)` the floor point, `speed (F,)` [m/s],
    `chi_dot (F, N)` [rad/s], `R_shell (F, 3, 3)`."""

    centre: np.ndarray
    meridians: np.ndarray
    equator: np.ndarray
    platform: np.ndarray
    wheels: np.ndarray
    rollers: np.ndarray
    com: np.ndarray
    mast: np.ndarray
    path: np.ndarray
    speed: np.ndarray
    chi_dot: np.ndarray
    R_shell: np.ndarray
    R: np.ndarray


def sphere_grid(R0: float, n_lon: int, n_lat: int) -> tuple[np.ndarray, np.ndarray]:
    """The vertices `(V, 3)` of a sphere of radius `R0` about the origin on a longitude-latitude
    grid (each stored once) and its quadrilaterals `(n_lon n_lat, 4)` as vertex indices."""
    lon = np.linspace(0.0, 2 * np.pi, n_lon, endpoint=False)
    lat = np.linspace(-np.pi / 2, np.pi / 2, n_lat + 1)
    Lo, La = np.meshgrid(lon, lat, indexing="ij")
    verts = R0 * np.stack([np.cos(La) * np.cos(Lo), np.cos(La) * np.sin(Lo), np.sin(La)], -1).reshape(-1, 3)
    a, b = (g.ravel() for g in np.meshgrid(np.arange(n_lon), np.arange(n_lat), indexing="ij"))
    idx = lambda a, b: (a % n_lon) * (n_lat + 1) + b
    return verts, np.stack([idx(a, b), idx(a + 1, b), idx(a + 1, b + 1), idx(a, b + 1)], axis=-1)


#: great circles through the shell's poles (meridians) and points per circle
MERIDIANS, CIRCLE_POINTS = 6, 41


def shell_lines(R_shell: np.ndarray, centre: np.ndarray, R0: float) -> tuple[np.ndarray, np.ndarray]:
    """The shell's meridians and equator `(F, P, 3)` [m] for attitudes `R_shell (F, 3, 3)` and
    centres `(F, 3)`: `MERIDIANS` great circles through the shell's own poles `+-e3` and its
    equator, carried by the shell's rotation."""
    c = _circle(CIRCLE_POINTS)
    phi = np.pi * np.arange(MERIDIANS)[:, None] / MERIDIANS
    cx, cz = c[:, 0], np.broadcast_to(c[:, 1], (MERIDIANS, len(c)))
    local = R0 * np.stack([np.cos(phi) * cx, np.sin(phi) * cx, cz], axis=-1)  # (L, P, 3)
    eq = R0 * np.stack([c[:, 0], c[:, 1], np.zeros(len(c))], axis=-1)[None]
    m = np.einsum("fij,lpj->flpi", R_shell, local) + centre[:, None, None]
    e = np.einsum("fij,lpj->flpi", R_shell, eq) + centre[:, None, None]
    return _gaps(m), _gaps(e)


def body_frames(body: Body, params: RobotParams, times: np.ndarray) -> BodyFrames:
    """`BodyFrames` of `body` at the run times `times (F,)` [s] from the body's start (held at
    its last pose after its end)."""
    t, at = body.t, body.t[0] + np.asarray(times, float)
    x, y = _lerp(t, body.x, at), _lerp(t, body.y, at)
    R0, Rw = float(params.R0), float(params.Rw)
    centre = np.stack([x, y, np.full(at.size, R0)], axis=-1)
    R, R_shell = _slerp(t, body.R, at), _slerp(t, body.R_shell, at)
    chi, chi_dot = _lerp(t, body.chi, at), _lerp(t, body.chi_dot, at)
    meridians, equator = shell_lines(R_shell, centre, R0)

    unit = lambda v: v / np.linalg.norm(v, axis=-1, keepdims=True)
    rhat, n = unit(np.asarray(params.wheel_r, float)), unit(np.asarray(params.wheel_n, float))
    centres = (R0 - Rw) * rhat  # each wheel touches the shell along r_i (platform frame)
    # the rim in the wheel's plane (normal n_i) and two spokes, turned by chi_i about n_i
    u = unit(rhat - np.einsum("ni,ni->n", rhat, n)[:, None] * n)
    w = np.cross(n, u)
    c = _circle(25)
    rim = centres[:, None] + Rw * (c[None, :, :1] * u[:, None] + c[None, :, 1:] * w[:, None])  # (N, P, 3)
    ang = chi[:, :, None] + np.array([0.0, np.pi / 2, np.pi, 3 * np.pi / 2])[None, None]  # (F, N, 4)
    tips = centres[None, :, None] + Rw * (
        np.cos(ang)[..., None] * u[None, :, None] + np.sin(ang)[..., None] * w[None, :, None]
    )
    gap = np.full_like(tips[:, :, 0], np.nan)
    spokes = np.stack([tips[:, :, 0], tips[:, :, 2], gap, tips[:, :, 1], tips[:, :, 3]], axis=2)
    contact, a = R0 * rhat, np.asarray(params.wheel_alpha, float)
    roller = np.stack([contact - 0.35 * Rw * a, contact + 0.35 * Rw * a], axis=1)  # (N, 2, 3)
    # platform components -> fixed: p_fixed = centre + R p
    rot = lambda pts: np.einsum("fij,...j->f...i", R, pts)
    rims = rot(rim) + centre[:, None, None]  # (F, N, P, 3)
    spk = np.einsum("fij,fnpj->fnpi", R, spokes) + centre[:, None, None]
    wheels = np.concatenate([_gaps(rims), _gaps(spk)], axis=1)
    rollers = _gaps(rot(roller) + centre[:, None, None])
    ring = np.concatenate([centres, centres[:1]], axis=0)
    platform = rot(ring) + centre[:, None]
    com = rot(np.asarray(params.r_m, float)) + centre
    mast = np.stack([centre, com], axis=1)
    h = 0.05  # [s]: the speed is the mean over 0.1 s about each frame (captures are noisy)
    lo, hi = np.clip(at - h, t[0], t[-1]), np.clip(at + h, t[0], t[-1])
    span = np.maximum(hi - lo, 1e-12)
    speed = np.hypot(_lerp(t, body.x, hi) - _lerp(t, body.x, lo), _lerp(t, body.y, hi) - _lerp(t, body.y, lo)) / span
    path = np.stack([x, y], -1)
    return BodyFrames(
        centre, meridians, equator, platform, wheels, rollers, com, mast, path, speed, chi_dot, R_shell, R
    )


def residual_text(measured: BodyFrames, model: BodyFrames) -> list[str]:
    """Per frame: the model's position [mm] and attitude [deg] residual against the capture."""
    from scipy.spatial.transform import Rotation

    d = 1e3 * np.linalg.norm(model.path - measured.path, axis=-1)
    rel = np.einsum("fji,fjk->fik", measured.R, model.R)
    ang = np.degrees(np.linalg.norm(Rotation.from_matrix(rel).as_rotvec(), axis=-1))
    return [f"residual {a:6.2f} mm, {b:5.2f} deg" for a, b in zip(d, ang)]
