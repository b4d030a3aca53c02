"""Trials of both kinds in one fit: captured poses (`FitData`) and the robot's own sensors
(`OnboardData`), sharing the free parameters.

Each part keeps its own model, nuisance values and noise levels (`sigma_pos, sigma_rot` then
`sigma_gyro, sigma_acc, sigma_encoder`); the fit sees one stack of trials, the pose trials
first. A trial's residuals and nuisance values are padded to the stack's common sizes: `n`
nuisance values and `K` residuals per trial, where a part with `n_k < n` nuisance values gets
`n - n_k` anchor residuals `r = nu_j` (Jacobian 1) for the values it does not have. They start
at 0 and stay there, add nothing to the cost, and keep the block-arrow normal equations
(`jsphere.numerics.lm`) regular; the information of the free parameters is unchanged by them.
"""

from __future__ import annotations

import dataclasses
import hashlib
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np

from .._runtime.arrays import to_jax
from .._runtime.errors import InputError
from .data import FitData
from .onboard import OnboardData
from .robust import reweigh


@dataclasses.dataclass(frozen=True)
class MixedData:
    """Pose trials and onboard trials fitted together (module docstring); the onboard trials'
    input kind is the pose trials'."""

    pose: FitData
    onboard: OnboardData

    @property
    def parts(self) -> tuple[FitData, OnboardData]:
        return self.pose, self.onboard

    @property
    def kind(self) -> str:
        return self.pose.kind

    @property
    def measure(self) -> str:
        return "mixed:" + self.onboard.measure

    @property
    def max_offset(self) -> float:
        return self.pose.max_offset

    @property
    def channels(self) -> tuple[str, ...]:
        return self.pose.channels + self.onboard.channels

    @property
    def names(self) -> tuple[str, ...]:
        return self.pose.names + self.onboard.names

    @property
    def lengths(self) -> tuple[int, ...]:
        return self.pose.lengths + self.onboard.lengths

    @property
    def n_pose(self) -> int:
        """The pose trials, first in the stack."""
        return self.pose.ts.shape[0]

    @property
    def n_nu(self) -> int:
        """The nuisance values of a trial in the stack (the larger part's)."""
        return max(len(p.nuisance) for p in self.parts)

    @property
    def n_measured(self) -> int:
        return sum(p.n_measured for p in self.parts)

    @property
    def sizes(self) -> tuple[int, int]:
        """The residuals of a pose trial and of an onboard trial, without anchors."""
        return self.pose.width * self.pose.ts.shape[1], self.onboard.width * self.onboard.ts.shape[1]

    @property
    def n_res(self) -> int:
        """`K`: the residuals of a trial in the stack, anchors included."""
        return max(k + self.n_nu - len(p.nuisance) for k, p in zip(self.sizes, self.parts))

    def aux_shapes(self) -> tuple[tuple[tuple[int, ...], ...], ...]:
        return tuple(p.aux_shapes() for p in self.parts)

    def arrays(self) -> dict[str, dict[str, jax.Array]]:
        return {"pose": self.pose.arrays(), "onboard": self.onboard.arrays()}

    def fingerprint(self) -> str:
        return hashlib.sha256("".join(p.fingerprint() for p in self.parts).encode()).hexdigest()

    def split(self, a: np.ndarray, axis: int = 0) -> tuple[np.ndarray, np.ndarray]:
        """An array over the stack's trials (`axis`) cut into the pose trials' and the onboard
        trials' (their residuals or nuisance values without padding where `a` holds them:
        `unpad`)."""
        return np.split(np.asarray(a), [self.n_pose], axis=axis)

    def unpad(self, a: np.ndarray, part: int, last: str = "res") -> np.ndarray:
        """A part's own residuals (`last="res"`) or nuisance values (`"nu"`) of `a (..., K)` or
        `(..., n)`, whose trials are that part's."""
        n = self.sizes[part] if last == "res" else len(self.parts[part].nuisance)
        return np.asarray(a)[..., :n]


def stack(outs, nu, P: int, n_pose: int, own: tuple[int, int], n_res: int):
    """The outputs `(res (S,T_k,K_k), ok, J (S,T_k,K_k,P+n_k), aux)` of each part's trials
    (`outs`: pose, onboard) as one stack: residuals padded to `n_res` with the anchors `nu_j` of
    the nuisance values a part does not have (module docstring), Jacobians to `(n_res, P + n)`;
    `nu (S, T, n)`, `own`: each part's `n_k`."""
    n = nu.shape[-1]
    res, Js = [], []
    for (r, _, J, _), n_k, nu_k in zip(outs, own, (nu[:, :n_pose], nu[:, n_pose:])):
        lead, dt = r.shape[:-1], r.dtype
        anchors, pad = n - n_k, n_res - r.shape[-1] - (n - n_k)
        res.append(jnp.concatenate([r, nu_k[..., n_k:], jnp.zeros(lead + (pad,), dt)], axis=-1))
        J = jnp.concatenate([J, jnp.zeros(J.shape[:-1] + (anchors,), dt)], axis=-1)
        eye = jnp.broadcast_to(jnp.eye(anchors, P + n, P + n_k, dtype=dt), lead + (anchors, P + n))
        Js.append(jnp.concatenate([J, eye, jnp.zeros(lead + (pad, P + n), dt)], axis=-2))
    ok = jnp.concatenate([o[1] for o in outs], axis=1)
    return jnp.concatenate(res, 1), ok, jnp.concatenate(Js, 1), tuple(o[3] for o in outs)


def mixed_data(pose: FitData, onboard: OnboardData) -> MixedData:
    """Pose and onboard trials packed together; `InputError` where their input kinds differ."""
    if pose.kind != onboard.kind:
        raise InputError(
            f"fit: the motion-capture trials' inputs are {pose.kind} and the onboard-sensor trials' {onboard.kind}; "
            "trials fitted together share one input kind."
        )
    return MixedData(pose, onboard)


def parts_of(data) -> tuple:
    """The parts of a fit's data: `MixedData.parts`, or the data itself alone."""
    return data.parts if isinstance(data, MixedData) else (data,)


def n_nuisance(data) -> int:
    """The nuisance values of a trial in the fit's stack (`MixedData.n_nu`)."""
    return data.n_nu if isinstance(data, MixedData) else len(data.nuisance)


def n_res(data) -> int:
    """The residuals of a trial in the fit's stack (`MixedData.n_res`)."""
    return data.n_res if isinstance(data, MixedData) else data.width * data.ts.shape[1]


def stacked(data, per_part: Callable[[object], np.ndarray], fill: float) -> np.ndarray:
    """`per_part(data)`, or for `MixedData` each part's `(T_k, n_k)` padded with `fill` to the
    stack's `n` and stacked, the pose trials first."""
    if not isinstance(data, MixedData):
        return np.asarray(per_part(data))
    n = data.n_nu
    rows = [np.asarray(per_part(d)) for d in data.parts]
    return np.concatenate([np.pad(r, ((0, 0), (0, n - r.shape[1])), constant_values=fill) for r in rows])


def weighted(data, loss: str, res, J):
    """The residuals and Jacobian reweighted for a robust `loss`
    (`jsphere.identify.robust.reweigh`): the pose trials', whole or in a `MixedData` stack;
    onboard trials' are least squares."""
    if loss == "l2" or data.measure != "pose" and not isinstance(data, MixedData):
        return res, J
    if not isinstance(data, MixedData):
        return reweigh(loss, to_jax(res), J)
    Tp, Kp = data.n_pose, data.sizes[0]
    res, J = to_jax(res), jnp.asarray(J)
    rp, Jp = reweigh(loss, res[:, :Tp, :Kp], J[:, :Tp, :Kp])
    res = jnp.concatenate([jnp.concatenate([rp, res[:, :Tp, Kp:]], -1), res[:, Tp:]], 1)
    J = jnp.concatenate([jnp.concatenate([Jp, J[:, :Tp, Kp:]], -2), J[:, Tp:]], 1)
    return res, J
