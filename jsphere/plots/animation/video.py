"""Animations as video: MP4 (H.264 through the ffmpeg binary that the `imageio-ffmpeg` wheel
carries; no system ffmpeg) or GIF (Pillow), written with matplotlib's animation writers.

Built for speed: the figure and its artists are made once (Agg), the geometry of every frame
is computed beforehand with NumPy (`jsphere.plots.animation.scene.body_frames`), and each frame only
moves the artists (`set_data_3d`, `set_verts`, `set_text`) before the writer grabs it. Every
kind of line of a robot (meridians, wheels, ...) is one artist whose polylines are broken by
NaN, so a frame draws a dozen artists per robot."""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np

from ..._runtime.files import atomic_write
from ..._runtime.progress import Progress
from .scene import BodyFrames, Scene, body_frames, frame_times, residual_text, sphere_grid

#: the camera of each view: (elevation, azimuth) [deg]
VIEWS = {"3d": (22.0, -60.0), "top": (90.0, -90.0)}
#: the colours of the robots of a scene (a ghost, the model over a capture, is orange)
COLOURS = ("C0", "C1", "C2", "C4", "C5", "C6", "C8", "C9")
#: the resolution of the videos' figures [dots per inch]
_DPI = 100


def scene_frames(scene: Scene, fps: float, speed: float):
    """The frames of one scene: run times `(F,)`, `BodyFrames` per body, and the residual text
    per frame (a fit's scene) or None."""
    times = frame_times(scene.duration, fps, speed)
    frames = [body_frames(b, scene.params, times) for b in scene.bodies]
    residual = residual_text(frames[0], frames[1]) if scene.residual and len(frames) > 1 else None
    return times, frames, residual


def _limits(scene: Scene, frames: list[BodyFrames]) -> tuple[np.ndarray, np.ndarray]:
    """The floor box `(x0, y0), (x1, y1)` [m] that holds every path, the target and the cloud,
    with a shell radius and a margin around."""
    pts = [f.path for f in frames] + [
        np.asarray(a, float).reshape(-1, 2) for a in (scene.cloud, scene.ellipse) if a is not None
    ]
    if scene.target is not None:
        pts.append(np.asarray(scene.target, float)[None, :2])
    p = np.concatenate(pts)
    p = p[np.all(np.isfinite(p), axis=1)]
    pad = 1.25 * float(scene.params.R0)
    return p.min(0) - pad, p.max(0) + pad


def _status(t: float, f: BodyFrames, k: int) -> str:
    rates = ", ".join(f"{v:+6.1f}" for v in f.chi_dot[k])
    return f"t = {t:5.2f} s   speed {1e3 * f.speed[k]:6.1f} mm/s\nwheel rates chi_dot = ({rates}) rad/s"


#: the lines of a robot, by their `BodyFrames` field, and their style (the robot's colour unless named)
_LINES = {
    "meridians": dict(lw=0.8),
    "equator": dict(color="k", lw=1.0),
    "platform": dict(color="0.25", lw=2.0),
    "wheels": dict(color="C3", lw=1.2),
    "rollers": dict(color="C2", lw=1.5),
    "mast": dict(color="0.4", lw=1.0),
    "com": dict(color="k", marker="o", ls="none", ms=4),
    "path": dict(lw=1.6),
}


class _Robot:
    """The artists of one robot (made once; `show` moves them to a frame)."""

    def __init__(self, ax, template: np.ndarray, colour: str):
        from mpl_toolkits.mplot3d.art3d import Poly3DCollection

        self.template = template
        self.shell = Poly3DCollection(template, facecolor=colour, edgecolor="none", alpha=0.10)
        ax.add_collection3d(self.shell)
        self.lines = {
            k: ax.plot([np.nan], [np.nan], [np.nan], **{"color": colour, **st})[0] for k, st in _LINES.items()
        }
        self.artists = [self.shell, *self.lines.values()]

    def style(self, ghost: bool, colour: str, label: str, crowd: int = 1) -> None:
        a = 0.35 if ghost else 1.0
        lines = self.lines
        for art in self.artists[1:]:
            art.set_alpha(a * (0.8 if art is lines["meridians"] else 1.0))
        self.shell.set_facecolor(colour)
        self.shell.set_alpha((0.05 if ghost else 0.10) / max(1, crowd - 1))  # robots drawn over each other
        lines["meridians"].set_color(colour)
        lines["path"].set_color(colour)
        for k in ("path", "platform"):
            lines[k].set_linestyle("--" if ghost else "-")
        lines["path"].set_label(label)

    def show(self, f: BodyFrames, k: int) -> None:
        self.shell.set_verts(self.template + f.centre[k])
        path = f.path[: k + 1]
        at = {name: getattr(f, name)[k] for name in _LINES if name != "path"}
        at |= {"com": f.com[k][None], "path": np.c_[path, np.zeros(len(path))]}
        for name, pts in at.items():
            self.lines[name].set_data_3d(pts[..., 0], pts[..., 1], pts[..., 2])


class _Video:
    """A video being written: its figure (made once: the axes, the texts, a `_Robot` per body
    and the scene's markers) and its writer; `scene` sets the figure up for a scene, `frame`
    moves the artists to a frame and hands the picture to the writer."""

    def __init__(self, plt, suffix: str, size: tuple[int, int], fps: float, view: str, R0: float, bodies: int, blit):
        from matplotlib import animation

        W, H = self.size = size
        self.suffix, self.blit, self.palette = suffix, blit, []
        fig = self.fig = plt.figure(figsize=(W / _DPI, H / _DPI), dpi=_DPI)
        small = 7.0 * min(1.0, W / 640.0) + 0.5  # [pt]: the texts keep their place on small pictures
        ax = self.ax = fig.add_axes((0.0, 0.09, 1.0, 0.84), projection="3d", proj_type="ortho")
        ax.view_init(*VIEWS[view])
        ax.set_xlabel("X [m] (fixed frame)", fontsize=7, labelpad=-2)
        ax.set_ylabel("Y [m] (fixed frame)", fontsize=7, labelpad=-2)
        ax.set_zlabel("Z [m]" if view == "3d" else "", fontsize=7, labelpad=-4)
        ax.tick_params(labelsize=6, pad=0)
        if view == "top":
            ax.set_zticks([])
        self.title = fig.text(0.01, 0.985, "", fontsize=small + 0.5, va="top", ha="left")
        self.status = fig.text(0.01, 0.01, "", fontsize=small, va="bottom", ha="left", family="monospace")
        self.extra = fig.text(0.99, 0.93, "", fontsize=small, va="top", ha="right", family="monospace")
        verts, quads = sphere_grid(R0, 14, 8)
        template = verts[quads]
        self.robots = [_Robot(ax, template, COLOURS[i % len(COLOURS)]) for i in range(bodies)]
        nan = [np.nan]
        self.target = ax.plot(nan, nan, nan, "x", color="C3", ms=9, mew=2, label="target")[0]
        self.cloud = ax.plot(nan, nan, nan, ".", color="0.3", ms=2, alpha=0.6, label="stop points")[0]
        self.ellipse = ax.plot(nan, nan, nan, "-", color="C3", lw=1.2, label="95 % ellipse")[0]
        if suffix == ".mp4":
            import imageio_ffmpeg

            plt.rcParams["animation.ffmpeg_path"] = imageio_ffmpeg.get_ffmpeg_exe()
            extra_args = ["-pix_fmt", "yuv420p", "-crf", "23"]
            self.writer = animation.FFMpegWriter(fps=fps, codec="libx264", extra_args=extra_args)
        else:
            self.writer = animation.PillowWriter(fps=fps)
        self.texts, self.markers = [self.title, self.status, self.extra], [self.target, self.cloud, self.ellipse]
        for art in [a for r in self.robots for a in r.artists] + self.markers + self.texts:
            art.set_animated(blit)  # left out of the background, drawn over it each frame

    def scene(self, scene: Scene, frames: list[BodyFrames]) -> None:
        """Set the axes' box, the robots' styles, the markers and the title for `scene`, and draw
        the background (the axes, their panes, ticks and labels: the same for every frame)."""
        ax, n = self.ax, len(scene.bodies)
        lo, hi = _limits(scene, frames)
        R0 = float(scene.params.R0)
        ax.set(xlim=(lo[0], hi[0]), ylim=(lo[1], hi[1]), zlim=(0.0, 2.0 * R0))
        ax.set_box_aspect((hi[0] - lo[0], hi[1] - lo[1], 2.0 * R0), zoom=1.35)
        for i, robot in enumerate(self.robots):
            for art in robot.artists:
                art.set_visible(i < n)
        for i, (robot, b) in enumerate(zip(self.robots, scene.bodies)):
            robot.style(b.ghost, COLOURS[1 if b.ghost else i % len(COLOURS)], b.label, n)
        target = None if scene.target is None else np.asarray([scene.target[:2]], float)
        for art, pts in zip(self.markers, (target, scene.cloud, scene.ellipse)):
            if pts is not None:
                art.set_data_3d(pts[:, 0], pts[:, 1], np.zeros(len(pts)))
        self.target.set_visible(target is not None)
        self.title.set_text(scene.title)
        self.fig.canvas.draw()
        self.background = self.fig.canvas.copy_from_bbox(self.fig.bbox)

    def frame(self, scene: Scene, frames: list[BodyFrames], residual, k: int, t: float, end: float) -> None:
        """Move the artists to frame `k` (run time `t`; the stop points and ellipse are shown from
        `end` on) and hand the picture to the writer: blitted, only the moving artists drawn over
        the background, else the whole figure drawn by the writer."""
        if self.blit:
            self.fig.canvas.restore_region(self.background)
        last = scene.cloud is not None and t >= end
        self.cloud.set_visible(last)
        self.ellipse.set_visible(last and scene.ellipse is not None)
        for robot, f in zip(self.robots, frames):
            robot.show(f, k)
        self.status.set_text(_status(t, frames[0], k))
        self.extra.set_text(residual[k] if residual is not None else "")
        if not self.blit:
            self.writer.grab_frame()
            return
        drawn = self.robots[: len(frames)]
        for robot in drawn:
            robot.shell.do_3d_projection()
        # the shells first (translucent, under every line), then the lines, the markers and the texts
        for art in [r.shell for r in drawn] + [a for r in drawn for a in r.artists[1:]] + self.markers + self.texts:
            self.ax.draw_artist(art)
        self._push()

    def _push(self) -> None:
        """Hand the canvas as it stands to the writer (matplotlib's writers grab a frame by
        drawing the whole figure again; here only the moving artists were drawn)."""
        buf = self.fig.canvas.buffer_rgba()
        if self.suffix == ".mp4":
            self.writer._proc.stdin.write(buf)
            return
        from PIL import Image

        im = Image.frombuffer("RGBA", self.size, bytes(buf), "raw", "RGBA", 0, 1).convert("RGB")
        # one palette for the whole GIF (its first frame's) and no dithering: the frames differ
        # only where the robot moved, and the GIF stores only those differences
        if not self.palette:
            self.palette.append(im.quantize(colors=255, method=Image.Quantize.MEDIANCUT, dither=Image.Dither.NONE))
        self.writer._frames.append(im.quantize(palette=self.palette[0], dither=Image.Dither.NONE))


def render(
    scenes: list[Scene],
    path,
    *,
    fps: float,
    speed: float,
    size=(640, 480),
    view: str = "3d",
    progress=None,
    blit: bool = True,
) -> int:
    """Write the `scenes`, one after the other, as a video to `path` (`.mp4` or `.gif`,
    atomically; checked by `api.check_options`): `fps` frames per second, `speed` the playback factor (a run of `T` s lasts
    `T / speed` s), `size` `(width, height)` [pixels], `view` `"3d"` or `"top"`. `progress`: as
    the library's (`jsphere._runtime.progress`); a bar counts the frames. `blit=False` draws
    each frame in full and lets the writer grab it, as matplotlib's animations do (the
    baseline of `benchmarks/animate.py`). Returns the number of frames written."""
    from ..base import pyplot

    path = Path(path)
    plt = pyplot()
    W, H = (int(v) + int(v) % 2 for v in size)  # H.264 wants even sizes
    prepared = [(s, *scene_frames(s, fps, speed)) for s in scenes]
    total = sum(len(p[1]) for p in prepared)
    R0 = float(prepared[0][0].params.R0)
    video = _Video(plt, path.suffix.lower(), (W, H), fps, view, R0, max(len(s.bodies) for s in scenes), blit)

    def write(tmp):
        with warnings.catch_warnings():
            # ffmpeg is started by fork and exec at once: JAX's threads are not touched in the child
            warnings.filterwarnings("ignore", message=r"os\.fork\(\) was called", category=RuntimeWarning)
            video.writer.setup(video.fig, tmp, _DPI)
        try:
            with Progress(progress).bar(total, "animate", unit="frame") as bar:
                for scene, times, frames, residual in prepared:
                    video.scene(scene, frames)
                    end = 0.9 * times[-1]
                    for k, t in enumerate(times):
                        video.frame(scene, frames, residual, k, t, end)
                        bar.update()
        finally:
            video.writer.finish()

    atomic_write(path, write)
    plt.close(video.fig)
    return total
