"""Markers -> pose -> trial: `rigid_body_pose` turns each frame's markers (`MarkerData`) into
the body frame's pose (Kabsch/Umeyama without scale), `markers_to_trial` adds the inputs and
makes a `Trial`; `ConvertOptions` gives the conventions of the body frame."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from .._runtime.errors import InputError
from ..model.rotations import quat_from_rotmat_np, rotmat_np
from .body import _match_body_markers, estimate_body_markers
from .inputs import interpolate_inputs, read_inputs_csv
from .markers import MarkerData
from .options import ConvertOptions, with_keywords
from .trial import Trial
from .validation import _checked, sign_continuous, warn, warn_implausible

#: the fields of `ConvertOptions` that `markers_to_trial` accepts as keywords (deprecated)
_KEYWORDS = ("body_markers", "alignment", "body_offset", "max_rms", "time_offset", "name", "max_gap_fraction")
_KEYWORDS += ("allow_truncated", "keep_suspect")
#: smallest second singular value of the centred present markers [m] for a pose (not collinear)
MIN_SPREAD = 1e-3


def rigid_body_pose(
    markers: np.ndarray, body_markers: np.ndarray, *, max_rms: float = np.inf
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The rigid motion that best maps `body_markers` `(K, 3)` [m] onto each frame's `markers`
    `(M, K, 3)` [m, NaN where missing]: over the markers present, the `R`, `p` minimising
    `sum_k |R b_k + p - m_k|^2` (Kabsch/Umeyama without scale: SVD of the cross-covariance, its
    determinant fixed to +1 so that no reflection is returned).

    Returns `(q, p, rms)`: `(M, 4)` quaternions (w, x, y, z) body -> fixed, sign-continuous;
    `(M, 3)` the body-frame origin; `(M,)` RMS residuals [m]. Frames with fewer than 3 markers,
    markers (nearly) collinear (second singular value of the centred body markers below
    `MIN_SPREAD`) or a residual above `max_rms` are NaN (gaps).
    """
    m = np.asarray(markers, float)
    b = np.asarray(body_markers, float)
    if m.ndim != 3 or m.shape[2] != 3 or b.shape != (m.shape[1], 3):
        raise ValueError(
            f"rigid_body_pose: markers must be (M, K, 3) and body_markers (K, 3); got {m.shape} and {b.shape}."
        )
    if not np.all(np.isfinite(b)):
        raise ValueError("rigid_body_pose: body_markers must be finite.")
    w = np.all(np.isfinite(m), axis=2).astype(float)  # (M, K)
    n = w.sum(1)
    mz = np.where(w[..., None] > 0, m, 0.0)
    nn = np.maximum(n, 1.0)[:, None]
    mc = (w[..., None] * mz).sum(1) / nn  # (M, 3) centroid of present markers
    bc = (w[..., None] * b[None]).sum(1) / nn  # (M, 3) centroid of their body coordinates
    db = w[..., None] * (b[None] - bc[:, None])  # (M, K, 3), zero where missing
    dm = w[..., None] * (mz - mc[:, None])
    H = np.einsum("mki,mkj->mij", db, dm)  # sum_k b_k m_k^T
    U, _, Vt = np.linalg.svd(H)
    V, Ut = np.swapaxes(Vt, 1, 2), np.swapaxes(U, 1, 2)
    d = np.where(np.linalg.det(V @ Ut) < 0, -1.0, 1.0)  # V diag(1, 1, d) U^T: never a reflection
    R = (V * np.stack([np.ones_like(d), np.ones_like(d), d], axis=1)[:, None, :]) @ Ut
    p = mc - np.einsum("mij,mj->mi", R, bc)
    fit = np.einsum("mij,kj->mki", R, b) + p[:, None]
    res2 = np.where(w > 0, np.sum((fit - mz) ** 2, axis=2), 0.0)
    rms = np.sqrt(res2.sum(1) / nn[:, 0])
    spread = np.linalg.svd(db, compute_uv=False)[:, 1]
    ok = (n >= 3) & (spread >= MIN_SPREAD) & (rms <= max_rms)
    q = quat_from_rotmat_np(R)
    q[~ok], p[~ok], rms[~ok] = np.nan, np.nan, np.nan
    return sign_continuous(q), p, rms


def markers_to_trial(
    data: MarkerData, inputs, options: ConvertOptions = ConvertOptions(), *, format: str | None = None, **kwargs
) -> Trial:
    """A `Trial` from raw marker data (`data`, from a reader such as `read_motive_csv`) and the
    `inputs`: an inputs table's path (`read_inputs_csv`) or a tuple `(t, values, kind)`,
    interpolated linearly to the capture times `t_capture + time_offset`; frames outside the
    inputs' time range are dropped, with a `CaptureWarning` saying how many.

    `options` (`ConvertOptions`): its fields `body_markers`, `alignment`, `body_offset`,
    `max_rms`, `keep_suspect`, `time_offset`, `name`, `max_gap_fraction` and `allow_truncated`
    apply (as keywords they still work, with a `DeprecationWarning`). `format`: the format of
    `convert_raw` that `data` came from, for the advice of the plausibility warnings.

    The exporter's rigid-body pose (`data.rb_q`), where there is one, is the body frame's. An
    `InputError` where more than half of the frames with a marker fit would be left out
    (`max_rms`, suspect: not one rigid body), or where given body markers lie more than 10%
    nearer or farther apart than the export's. Each finding of `implausible` is a
    `CaptureWarning`.
    """
    o = with_keywords(options, kwargs, "markers_to_trial", _KEYWORDS)
    body_offset, time_offset, max_rms = o.body_offset, o.time_offset, o.max_rms
    source = data.source
    off = np.asarray(body_offset, float)
    if off.size != 3 or not np.all(np.isfinite(off)):
        raise InputError(
            f"{source}: the body offset (--body-offset X Y Z) must be 3 finite numbers, x, y, z in the platform frame "
            f"in metres; got {body_offset!r}."
        )
    if not math.isfinite(time_offset):
        raise InputError(
            f"{source}: the time offset (--time-offset) must be a finite number of seconds; got {time_offset!r}."
        )
    if not max_rms > 0:  # NaN too
        raise InputError(
            f"{source}: the largest marker fit residual kept must be a positive number of metres; got {max_rms!r}."
        )
    if isinstance(inputs, (str, Path)):
        t_in, u_in, kind, _ = read_inputs_csv(inputs, allow_truncated=o.allow_truncated)
    else:
        t_in, u_in, kind = inputs
        t_in, u_in = np.asarray(t_in, float), np.asarray(u_in, float).reshape(len(t_in), -1)
    A = np.eye(3) if o.alignment is None else np.asarray(o.alignment, float)
    if A.shape != (3, 3) or not np.allclose(A @ A.T, np.eye(3), atol=1e-6) or np.linalg.det(A) < 0:
        raise ValueError(f"{source}: alignment must be a 3x3 rotation matrix (platform -> body frame).")
    q_body, p_body = (
        (data.rb_q, data.rb_p) if data.rb_q is not None else _body_pose(data, o.body_markers, max_rms, o.keep_suspect)
    )
    q, centre = _platform_pose(q_body, p_body, A, off.reshape(3))
    t = data.t + time_offset
    keep = _overlap(t, t_in, source)
    u = interpolate_inputs(t_in, u_in, t[keep])
    lines = None if data.lines is None else data.lines[keep]
    tt, x, y, qq, uu, z = _checked(
        t[keep],
        centre[keep, 0],
        centre[keep, 1],
        q[keep],
        u,
        kind,
        centre[keep, 2],
        source=source,
        lines=lines,
        max_gap_fraction=o.max_gap_fraction,
    )
    warn_implausible(tt, x, y, qq, source, z, from_markers=True, **_hints(format))
    return Trial(tt, x, y, qq, uu, kind, z, name=o.name or Path(source).stem)


def _hints(format: str | None) -> dict[str, str]:
    """What the plausibility warnings advise for poses of `format` (`convert_raw`'s): options
    that apply to it, or, for a ROS bag, whose frames are its publisher's, plain words."""
    if format == "rosbag":
        return {
            "units_hint": "the publisher may send millimetres (ROS's REP 103 says metres)",
            "up_hint": "is the pose topic's world frame Z-up (REP 103), and its child frame the platform?",
        }
    return {
        "units_hint": "give the export's units (--units mm)",
        "up_hint": "is the export's up axis right? (--up-axis: 'y' is Motive's default, 'z' that of Vicon, QTM and C3D)",
    }


def _body_pose(
    data: MarkerData, body_markers, max_rms: float, keep_suspect: bool = False
) -> tuple[np.ndarray, np.ndarray]:
    """The body frame's pose `(q (M, 4), p (M, 3))` from the markers (`rigid_body_pose`), with
    the body markers given, matched by name or estimated; frames of a suspect marker fit are
    gaps unless `keep_suspect` (`suspect_frames`)."""
    source = data.source
    if len(data.names) < 3:
        raise ValueError(f"{source}: {len(data.names)} marker(s) {list(data.names)}; a pose needs at least 3 markers.")
    if body_markers is None:
        body_markers, _ = estimate_body_markers(data.markers, source)
    elif isinstance(body_markers, dict):
        body_markers = _match_body_markers(body_markers, data.names, source)
    body_markers = np.asarray(body_markers, float)
    if body_markers.shape != (len(data.names), 3):
        raise ValueError(
            f"{source}: the body markers must be {len(data.names)} rows of x, y, z, one per marker {list(data.names)}."
        )
    known = np.all(np.isfinite(body_markers), axis=1)  # markers left out of a body_markers dict
    _check_body_scale(data.markers[:, known], body_markers[known], source)
    q_body, p_body, rms = rigid_body_pose(data.markers[:, known], body_markers[known])
    fitted = np.isfinite(rms)
    over = fitted & (np.where(fitted, rms, 0.0) > max_rms)
    rms_in = np.where(over, np.nan, rms)
    error = data.marker_error
    suspect = suspect_frames(rms_in, error)
    out = over | (suspect & (not keep_suspect))
    n_fit = int(fitted.sum())
    if n_fit and out.sum() > 0.5 * n_fit:
        raise InputError(
            f"{source}: the markers do not move as one rigid body: {int(out.sum())} of the {n_fit} frames with a "
            f"marker fit would be left out ({int(over.sum())} with a residual above {max_rms * 1e3:g} mm, "
            f"{int((suspect & ~over).sum()) if not keep_suspect else 0} far above the take's noise; median residual "
            f"{np.nanmedian(rms) * 1e3:.3g} mm): the markers belong to a person or to several bodies, not one robot; "
            "give --body-markers FILE listing only the robot's markers (the others are then left out of the fit)."
        )
    q_body[out], p_body[out] = np.nan, np.nan  # (fresh arrays of `rigid_body_pose`)
    if over.any():
        warn(
            f"{source}: {int(over.sum())} of {len(rms)} frame(s) are left out as missing: their marker fit residual is "
            f"above {max_rms * 1e3:g} mm (up to {np.nanmax(rms[over]) * 1e3:.3g} mm; the take's median is "
            f"{np.nanmedian(rms) * 1e3:.3g} mm): a marker far from where the others put it (a swapped, merged or ghost "
            f"marker), first at t = {data.t[np.flatnonzero(over)[0]]:.6g} s."
        )
    if suspect.any():
        limit = suspect_limit(rms_in)
        first = float(data.t[np.flatnonzero(suspect)[0]])
        what = "kept, as --keep-suspect asks" if keep_suspect else "left out as missing (--keep-suspect keeps them)"
        warn(
            f"{source}: {int(suspect.sum())} of {len(rms)} frame(s) whose marker fit residual stands out of the take's "
            f"noise (above {limit * 1e3:.3g} mm: {limit / np.nanmedian(rms_in):.3g}x the median "
            f"{np.nanmedian(rms_in) * 1e3:.3g} mm, from the residuals' spread, at least {SUSPECT:g}x"
            + (f", and above {SUSPECT_ERROR:g}x the export's own marker error" if error is not None else "")
            + f"; up to {np.nanmax(rms_in[suspect]) * 1e3:.3g} mm, first at t = {first:.6g} s) are {what}: a swapped or "
            "ghost marker."
        )
    return q_body, p_body


#: a frame is suspect where the logarithm of its marker fit residual is above the take's median
#: by more than this many robust standard deviations (1.4826 x the median absolute deviation of
#: the logarithms: a residual's spread grows with its size) ...
SUSPECT_SPREAD = 3.0
#: ... and more than this many times the take's median ...
SUSPECT = 5.0
#: ... and above this [m]: a capture resolves about 0.1 mm, so a take of residuals near 0 does
#: not make every frame suspect ...
SUSPECT_FLOOR = 2e-4
#: ... and, where the export reports its own marker error for the frame (Motive's `Mean Marker
#: Error`, a mean distance over the markers), more than this many times it
SUSPECT_ERROR = 2.0


def suspect_limit(rms: np.ndarray) -> float:
    """The take's threshold of `suspect_frames` [m] (before the per-frame floor of the export's
    marker error): `max(median * exp(SUSPECT_SPREAD * s), SUSPECT * median, SUSPECT_FLOOR)`
    over the finite positive residuals `rms`, with `s` = 1.4826 x the median absolute deviation
    of their logarithms; inf where there are none."""
    r = np.asarray(rms, float)
    r = r[np.isfinite(r) & (r > 0)]
    if r.size == 0:
        return math.inf
    log = np.log(r)
    centre = float(np.median(log))
    s = 1.4826 * float(np.median(np.abs(log - centre)))
    return max(math.exp(centre + SUSPECT_SPREAD * s), SUSPECT * math.exp(centre), SUSPECT_FLOOR)


def suspect_frames(rms: np.ndarray, marker_error: np.ndarray | None = None) -> np.ndarray:
    """Frames whose RMS marker fit residual `rms (M,)` [m] (NaN at gaps) stands out of the take's
    own noise (`suspect_limit`): a marker swapped with another or a ghost marker taken for one.

    White marker noise gives squared residuals of chi^2 with `3 K - 6` degrees of freedom (`K`
    markers): their 99.99 % point is 2.3x the median residual for 4 markers, 3x for 3, below
    `SUSPECT`. A take whose noise varies from frame to frame spreads log-normally: by `s` = 1,
    0.3 % of its frames lie above the threshold (19x the median), by `s` = 1.5, 0.2 % (90x). A
    frame whose residual is within `SUSPECT_ERROR` times the export's own marker error
    (`marker_error (M,)` [m], NaN where not reported) is noisy, not swapped (an RMS over `K`
    markers is at most `sqrt(K)` times their mean distance)."""
    r = np.asarray(rms, float)
    ok = np.isfinite(r)
    if not ok.any():
        return np.zeros(r.shape, bool)
    out = ok & (np.where(ok, r, 0.0) > suspect_limit(r))
    if marker_error is not None:
        e = np.asarray(marker_error, float)
        out &= ~(np.isfinite(e) & (np.where(ok, r, 0.0) <= SUSPECT_ERROR * np.where(np.isfinite(e), e, 0.0)))
    return out


def _platform_pose(
    q_body: np.ndarray, p_body: np.ndarray, A: np.ndarray, off: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The platform's orientation `q (M, 4)` (NaN where the body's is) and the shell centre
    `(M, 3)`: `R_platform = R_body A`, `r_centre = p_body + R_platform off`."""
    R_body = rotmat_np(np.where(np.isfinite(q_body), q_body, 1.0))
    R = R_body @ A  # platform -> fixed
    centre = p_body + np.einsum("mij,j->mi", R, off)
    q = quat_from_rotmat_np(R)
    q[~np.all(np.isfinite(q_body), axis=1)] = np.nan
    return q, centre


def _overlap(t: np.ndarray, t_in: np.ndarray, source: str) -> np.ndarray:
    """The capture frames within the inputs table's time range (`(M,)` bool); a `CaptureWarning`
    where the table's times look like milliseconds, and one counting the frames left out, before
    the table's start and after its end."""
    keep = (t >= t_in[0] - 1e-9) & (t <= t_in[-1] + 1e-9)
    if not np.any(keep):
        raise ValueError(
            f"{source}: the capture times [{t[0]:g}, {t[-1]:g}] s do not overlap the inputs' [{t_in[0]:g}, {t_in[-1]:g}] s; "
            "the two must share a clock (--time-offset SECONDS shifts the capture's)."
        )
    span_in, span = float(t_in[-1] - t_in[0]), float(t[keep][-1] - t[keep][0])
    if span_in >= 100.0 * max(span, 1e-9) and float(np.median(np.diff(t_in))) >= 100.0 * float(np.median(np.diff(t))):
        warn(
            f"{source}: the inputs table spans {span_in:g} s with steps of {float(np.median(np.diff(t_in))):g} s, the capture "
            f"{span:g} s with steps of {float(np.median(np.diff(t))):g} s: are the inputs' times in milliseconds? Give them in "
            "seconds."
        )
    before, after = int(np.sum(~keep & (t < t_in[0]))), int(np.sum(~keep & (t > t_in[-1])))
    if before or after:
        parts = [f"{n} before its start" for n in (before,) if n] + [f"{n} after its end" for n in (after,) if n]
        warn(
            f"{source}: {before + after} of {t.size} capture frame(s) are left out: they lie outside the inputs "
            f"table's time range [{t_in[0]:.6g}, {t_in[-1]:.6g}] s ({' and '.join(parts)}; the capture runs "
            f"[{t[0]:.6g}, {t[-1]:.6g}] s after the time offset)."
        )
    return keep


def _check_body_scale(markers: np.ndarray, body: np.ndarray, source: str) -> None:
    """Raise `InputError` if the distances between the body markers differ from those between
    the export's markers by more than 10% (median over marker pairs of the ratio of the body's
    distance to the export's median over frames): body markers in millimetres, or another
    marker set, would give no pose at all ("too few valid frames")."""
    K = body.shape[0]
    i, j = np.triu_indices(K, 1)
    d_data = np.linalg.norm(markers[:, i] - markers[:, j], axis=2)  # (M, pairs), NaN where missing
    seen = np.sum(np.isfinite(d_data), axis=0) > 0
    if not np.any(seen):
        return
    d_data = np.nanmedian(d_data[:, seen], axis=0)
    d_body = np.linalg.norm(body[i] - body[j], axis=1)[seen]
    ok = d_data > 0
    if not np.any(ok):
        return
    ratio = float(np.median(d_body[ok] / d_data[ok]))
    if abs(ratio - 1.0) <= 0.1:
        return
    hint = (
        "the body markers look like millimetres: give them in metres (or add '# units: mm' to their file)"
        if 500.0 <= ratio <= 2000.0
        else "the body markers look like metres while the export is read in millimetres"
        if 5e-4 <= ratio <= 2e-3
        else "check that they belong to this marker set, and their units (metres)"
    )
    raise InputError(
        f"{source}: the body markers are {ratio:.4g} times as far apart as the markers in the export (median over "
        f"marker pairs); {hint}."
    )
