"""The interactive viewer: one self-contained HTML file (plotly, its offline bundle embedded,
nothing fetched from the network; docs/decisions/viewer.md) with the 3-D scene to rotate and
zoom, play/pause, a time slider, and the overlays of the video (time, speed, wheel rates, a
fit's residual, a plan's target, a study's stop points and ellipse).

Each frame of the slider holds the geometry that `jsphere.plots.animation.scene.body_frames` computed
for the video, rounded to 0.1 mm, and the slider's step `k` is labelled with frame `k`'s run
time. The page opens on the first frame, paused (`t = 0.00 s`). It sets `window.jsphereViewer`
to the plot's element (for scripts and the browser test)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..._runtime.files import atomic_write_text
from .scene import Scene, sphere_grid
from .video import COLOURS, _limits, _status, scene_frames

#: the traces of one robot, in order
_PARTS = ("shell", "meridians", "equator", "platform", "wheels", "rollers", "mast", "path")


def _xyz(pts: np.ndarray, kind: str = "scatter3d") -> dict:
    """Plotly's `x, y, z` of points `(P, 3)` [m], 0.1 mm steps, NaN as gaps (None), for a trace of
    type `kind`."""
    out = {"type": kind}
    for i, key in enumerate("xyz"):
        v = np.round(np.asarray(pts[..., i], float), 4)
        out[key] = [None if not np.isfinite(a) else float(a) for a in v]
    return out


#: the most points of a path in one frame (the path drawn so far, thinned evenly)
PATH_POINTS = 80


def _traces(go, n_bodies: int, triangles) -> list:
    """The figure's traces, styled and named (the frames hold their data): `_PARTS` of each of
    `n_bodies` robots (`triangles`: the shell mesh's), then the target, the stop points and the
    ellipse."""
    from matplotlib.colors import to_hex

    ti, tj, tk = triangles
    shell, hidden = dict(opacity=0.12, hoverinfo="skip", showlegend=False), dict(mode="lines", showlegend=False)
    com = dict(mode="lines+markers", line=dict(color="#666666", width=3), marker=dict(size=[0, 5], color="black"))
    traces = []
    for b in range(n_bodies):
        c = to_hex(COLOURS[b % len(COLOURS)])  # the video's
        lines = {f"meridians {b + 1}": (c, 3), "equator": ("black", 3), "platform": ("#444444", 6)}
        lines |= {"omniwheels": ("#d62728", 4), "roller axes": ("#2ca02c", 5)}
        traces.append(go.Mesh3d(i=ti, j=tj, k=tk, color=c, name=f"shell {b + 1}", **shell))
        traces += [go.Scatter3d(line=dict(color=co, width=w), name=nm, **hidden) for nm, (co, w) in lines.items()]
        traces.append(go.Scatter3d(**com, name="centre of mass", showlegend=False))
        traces.append(go.Scatter3d(mode="lines", line=dict(color=c, width=5), name=f"path {b + 1}"))
    return traces + [
        go.Scatter3d(mode="markers", marker=dict(symbol="x", size=6, color="#d62728"), name="target"),
        go.Scatter3d(mode="markers", marker=dict(size=2, color="#555555"), name="stop points"),
        go.Scatter3d(mode="lines", line=dict(color="#d62728", width=4), name="95 % ellipse"),
    ]


def _frame_data(scene: Scene, fr: list, n_bodies: int, verts: np.ndarray, k: int, show_end: bool) -> list[dict]:
    """The data of every trace (`_traces` order: `_PARTS` per robot, then the markers) at frame `k`
    of `scene` (`fr`: its bodies' frames; `show_end`: the stop points and ellipse are shown)."""
    empty = {"type": "scatter3d", "x": [], "y": [], "z": []}
    data = []
    keep = np.unique(np.linspace(0, k, min(k + 1, PATH_POINTS)).round().astype(int))  # the path so far, thinned
    for b in range(n_bodies):
        if b >= len(fr):
            data += [{"type": "mesh3d", "x": [], "y": [], "z": []}] + [empty] * (len(_PARTS) - 1)
            continue
        f = fr[b]
        path = np.concatenate([f.path[keep], np.zeros((keep.size, 1))], axis=1)
        lines = [getattr(f, name)[k] for name in _PARTS[1:6]] + [np.concatenate([f.mast[k], f.com[k][None]]), path]
        parts = [_xyz(verts + f.centre[k], "mesh3d")] + [_xyz(pts) for pts in lines]
        if scene.bodies[b].ghost:  # the model over the capture: fainter
            parts = [p | {"opacity": 0.06 if i == 0 else 0.45} for i, p in enumerate(parts)]
        data += parts
    tgt, el = scene.target, scene.ellipse
    data.append(_xyz(np.array([[tgt[0], tgt[1], 0.0]])) if tgt is not None else empty)
    data.append(_xyz(np.c_[scene.cloud, np.zeros(len(scene.cloud))]) if show_end else empty)
    data.append(_xyz(np.c_[el, np.zeros(len(el))]) if show_end and el is not None else empty)
    return data


def _frames(go, prepared: list, n_bodies: int, verts: np.ndarray) -> tuple[list, list[str]]:
    """The slider's frames of the `prepared` scenes (`(scene, times, frames, residual)`) and the
    run time that labels each."""
    frames, run_times = [], []
    for s_idx, (scene, times, fr, residual) in enumerate(prepared):
        end = 0.9 * times[-1]
        for k, t in enumerate(times):
            data = _frame_data(scene, fr, n_bodies, verts, k, scene.cloud is not None and t >= end)
            text = _status(t, fr[0], k).replace("\n", "<br>") + (f"<br>{residual[k]}" if residual is not None else "")
            layout = {"annotations": [_note(scene.title.replace("\n", "<br>"), 1.0), _note(text, 0.0)]}
            frames.append(go.Frame(name=f"{len(frames)}", data=data, traces=list(range(len(data))), layout=layout))
            run_times.append(f"{s_idx + 1}:{t:.2f} s" if len(prepared) > 1 else f"{t:.2f} s")
    return frames, run_times


def _controls(fps: float, frames: list, run_times: list[str]) -> dict:
    """The layout's play/pause buttons and time slider over `frames` (labelled `run_times`)."""
    # a slider step waits for the frames drawn before it ("afterall"): interrupted, plotly's
    # animation promise rejects unhandled (a console error at each click on the rail)
    after = dict(mode="afterall", frame=dict(duration=0, redraw=True), transition=dict(duration=0))
    play = dict(frame=dict(duration=1000.0 / fps, redraw=True), transition=dict(duration=0), fromcurrent=True)
    stop = dict(mode="immediate", frame=dict(duration=0, redraw=False), transition=dict(duration=0))
    buttons = [
        dict(label="play", method="animate", args=[None, play]),
        dict(label="pause", method="animate", args=[[None], stop]),
    ]
    menu = dict(type="buttons", direction="left", x=0.0, y=0.0, xanchor="left", yanchor="top", buttons=buttons)
    steps = [dict(label=lab, method="animate", args=[[f.name], after]) for f, lab in zip(frames, run_times)]
    current = dict(prefix="t = ", font=dict(size=11))
    slider = dict(active=0, x=0.12, y=0.0, len=0.86, yanchor="top", currentvalue=current, steps=steps)
    return dict(updatemenus=[menu], sliders=[slider])


def write_html(scenes: list[Scene], path, *, fps: float, speed: float, size=(900, 700), view: str = "3d") -> int:
    """Write the viewer of `scenes` (one after the other on the slider) to `path` (atomically):
    frames at `fps` per second of playback, `speed` the playback factor, `size` `(width, height)`
    [pixels] of the plot, `view` the starting camera (`"3d"` or `"top"`). Returns the number of
    frames."""
    import plotly.graph_objects as go

    path = Path(path)
    prepared = [(s, *scene_frames(s, fps, speed)) for s in scenes]
    n_bodies = max(len(s.bodies) for s in scenes)
    R0 = float(scenes[0].params.R0)
    verts, q = sphere_grid(R0, 16, 10)
    triangles = (np.r_[q[:, 0], q[:, 0]], np.r_[q[:, 1], q[:, 2]], np.r_[q[:, 2], q[:, 3]])
    lo = np.min([_limits(s, f)[0] for s, _, f, _ in prepared], axis=0)
    hi = np.max([_limits(s, f)[1] for s, _, f, _ in prepared], axis=0)
    frames, run_times = _frames(go, prepared, n_bodies, verts)
    fig = go.Figure(data=_traces(go, n_bodies, triangles), frames=frames)
    for tr, d in zip(fig.data, frames[0].data):
        tr.update(d)
    eye = dict(x=1.3, y=-1.6, z=0.9) if view == "3d" else dict(x=0.0, y=0.0, z=2.5)
    up = dict(x=0, y=1, z=0) if view == "top" else dict(x=0, y=0, z=1)
    span = hi - lo
    axes = dict(
        xaxis=dict(title="X [m] (fixed frame)", range=[lo[0], hi[0]]),
        yaxis=dict(title="Y [m] (fixed frame)", range=[lo[1], hi[1]]),
        zaxis=dict(title="Z [m]", range=[0.0, 2.0 * R0]),
    )
    ratio = dict(x=1.0, y=span[1] / span[0], z=2.0 * R0 / span[0])
    scene = dict(**axes, aspectmode="manual", aspectratio=ratio, camera=dict(eye=eye, up=up))
    fig.update_layout(
        width=int(size[0]),
        height=int(size[1]),
        margin=dict(l=0, r=0, t=40, b=0),
        annotations=list(frames[0].layout.annotations),
        scene=scene,
        legend=dict(x=0.0, y=0.9, font=dict(size=10)),
        **_controls(fps, frames, run_times),
    )
    post = "window.jsphereViewer = document.getElementById('{plot_id}');"
    # opens on the first frame, paused: plotly's auto-play would start at its own default pace
    # (500 ms a frame), the slider already past the first frame once the page is drawn
    html = fig.to_html(
        include_plotlyjs=True, full_html=True, post_script=post, config=dict(displaylogo=False), auto_play=False
    )
    atomic_write_text(path, html)
    return len(frames)


def _note(text: str, y: float) -> dict:
    """A text at the plot's left, at its top (`y = 1`) or bottom (`y = 0`)."""
    where = dict(x=0.01, y=y, xref="paper", yref="paper", xanchor="left", yanchor="top" if y > 0.5 else "bottom")
    return dict(text=text, showarrow=False, align="left", font=dict(size=11, family="monospace"), **where)
