"""What the animation draws: the shell's meridians turn as the rolling constraint says, the
attitudes read back from a plan table are the plan's own, and the videos last as long as the run
divided by the playback factor."""

from __future__ import annotations

import re

import numpy as np
import pytest

import jsphere
from jsphere.planning.result import Plan
from jsphere.plots.animation.scene import Scene, body_frames, body_from_poses, body_from_trajectory, rolling_attitude

# the test reads the videos back with imageio-ffmpeg's reader: a subprocess, started by fork and exec at once
pytestmark = pytest.mark.filterwarnings(r"ignore:os\.fork\(\) was called:RuntimeWarning")


def _drawn_turn(frames, first: int, last: int, axis=None) -> float:
    """The angle [rad] of the rotation that carries the drawn meridians (about the shell's
    centre) from frame `first` to frame `last` (Kabsch); with `axis`, its rotation vector's
    component along that unit axis."""
    a = frames.meridians[first] - frames.centre[first]
    b = frames.meridians[last] - frames.centre[last]
    ok = np.all(np.isfinite(a), axis=1)
    u, _, vt = np.linalg.svd(b[ok].T @ a[ok])
    R = u @ np.diag([1.0, 1.0, np.linalg.det(u @ vt)]) @ vt
    assert np.allclose(R @ a[ok].T, b[ok].T, atol=1e-9)  # a rigid turn of the drawn lines
    if axis is not None:
        from scipy.spatial.transform import Rotation

        return float(Rotation.from_matrix(R).as_rotvec() @ axis)
    return float(np.arccos(np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0)))


def test_meridians_turn_by_distance_over_R0_along_a_straight_roll(paper, straight):
    """The paper's straight line (acceleration 5.1, braking 5.3): the shell's attitude is the
    state's `q_shell`; over the roll of length d the drawn meridians turn by d / R0 about the
    horizontal axis perpendicular to the path (the shell's small spin about the vertical
    aside)."""
    body = body_from_trajectory(straight)
    times = body.t[np.linspace(0, body.t.size - 1, 9).astype(int)] - body.t[0]  # samples: no interpolation
    f = body_frames(body, paper, times)
    R0 = float(paper.R0)
    for k in range(1, len(times)):
        dx, dy = f.path[k] - f.path[0]
        d = np.hypot(dx, dy)
        axis = np.array([-dy, dx, 0.0]) / d
        assert _drawn_turn(f, 0, k, axis) == pytest.approx(d / R0, rel=1e-5, abs=1e-6)
    assert d / R0 > 1.5  # the check spans most of a half turn


def test_rolling_attitude_of_a_captured_straight_path(paper):
    """A path without the shell's attitude (a capture): the integrated attitude turns by d / R0."""
    t = np.linspace(0.0, 3.0, 301)
    s = 0.3 * (1 - np.cos(np.pi * t / 3.0)) / 2
    x, y = s * np.cos(0.6), s * np.sin(0.6)
    R = np.repeat(np.eye(3)[None], t.size, axis=0)
    body = body_from_poses(paper, t, x, y, R)
    f = body_frames(body, paper, np.array([0.0, 1.0, 3.0]))
    assert _drawn_turn(f, 0, 2) == pytest.approx(0.3 / float(paper.R0), rel=1e-9)
    # the axis: horizontal, perpendicular to the path, turning the top of the shell forwards
    Rs = rolling_attitude(t, x, y, float(paper.R0))[-1]
    top = Rs @ np.array([0.0, 0.0, 1.0])
    assert np.dot(top[:2], [np.cos(0.6), np.sin(0.6)]) > 0


def _plan_of(paper, straight) -> Plan:
    """A `Plan` holding the paper's straight line, as `jsphere plan` would write it."""
    end = np.array([float(straight.x[-1]), float(straight.y[-1]), np.nan])
    return Plan(
        params=paper,
        gaits=[jsphere.acceleration(), jsphere.braking()],
        legs=np.zeros((1, 3)),
        trajectory=straight,
        rate=100.0,
        target=end,
        errors={},
        limits_report={},
        feasible=True,
        shortfall=[],
        iterations={},
        elapsed_s=0.0,
        loss=0.0,
    )


def test_plan_table_gives_back_the_plans_attitudes(paper, straight, tmp_path):
    """A plan CSV holds `gamma` and the heading: the platform's attitude read from it is the
    plan's, and the shell's attitude integrated from its path and wheel rates is the state's."""
    from jsphere.cli.animate import plan_table_scene

    plan = _plan_of(paper, straight)
    plan.to_csv(tmp_path / "plan.csv")
    scene = plan_table_scene(tmp_path / "plan.csv", paper)
    read, truth = scene.bodies[0], body_from_trajectory(straight)
    times = np.linspace(0.0, truth.duration, 41)
    a, b = body_frames(read, paper, times), body_frames(truth, paper, times)
    assert np.max(np.abs(a.R - b.R)) < 1e-9
    assert np.max(np.abs(a.R_shell - b.R_shell)) < 2e-3
    assert np.max(np.abs(a.chi_dot - b.chi_dot)) < 1e-9
    assert scene.target == pytest.approx((float(straight.x[-1]), float(straight.y[-1])))


@pytest.mark.parametrize("suffix", [".mp4", ".gif", ".html"])
def test_animate_a_plan_object(paper, straight, tmp_path, suffix):
    """`jsphere.animate` on a `Plan`: the MP4 lasts the run's duration / speed within a
    frame, the GIF holds as many frames, the HTML file one slider step per frame."""
    import imageio_ffmpeg
    from PIL import Image

    from jsphere.plots.animation import animate

    plan = _plan_of(paper, straight)
    out = animate(plan, tmp_path / f"plan{suffix}", fps=8, speed=2.0, size=(160, 120), progress=False)
    expected = plan.duration / 2.0
    if suffix == ".mp4":
        n, _ = imageio_ffmpeg.count_frames_and_secs(str(out))
        assert abs(n / 8 - expected) <= 1 / 8
    elif suffix == ".gif":
        im = Image.open(out)
        assert abs(im.n_frames / 8 - expected) <= 1 / 8
        assert im.size == (160, 120)
    else:
        html = out.read_text()
        assert html.count('"method":"animate"') >= round(expected * 8)
        assert not re.search(r"<(script|link)[^>]+(src|href)=", html)  # plotly's bundle inline, nothing loaded


def test_viewer_opens_on_the_first_frame_and_labels_each_slider_step_with_its_frames_time(paper, straight, tmp_path):
    """The viewer's figure read from the HTML file: slider step `k` shows frame `k` and is
    labelled with that frame's run time (`frame_times`), as the frame's own status line says;
    the page opens paused on the first frame, `t = 0.00 s` (no auto-play)."""
    from viewer_html import frame_time, viewer_figure

    from jsphere.plots.animation import animate
    from jsphere.plots.animation.scene import frame_times

    out = animate(_plan_of(paper, straight), tmp_path / "plan.html", fps=15, speed=1.0, size=(160, 120))
    data, layout, frames = viewer_figure(out)
    slider = layout["sliders"][0]
    steps = slider["steps"]
    times = frame_times(float(straight.ts[-1] - straight.ts[0]), 15.0, 1.0)
    assert len(steps) == len(frames) == len(times) > 2
    assert [s["args"][0] for s in steps] == [[f["name"]] for f in frames]
    assert [s["label"] for s in steps] == [f"{t:.2f} s" for t in times]
    assert [f"{float(frame_time(f)):.2f} s" for f in frames] == [s["label"] for s in steps]
    assert (slider["active"], slider["currentvalue"]["prefix"] + steps[0]["label"]) == (0, "t = 0.00 s")
    assert data[0]["x"] == frames[0]["data"][0]["x"] and data[0]["x"] != frames[1]["data"][0]["x"]
    assert layout["annotations"][1]["text"] == frames[0]["layout"]["annotations"][1]["text"]
    assert "Plotly.animate(" not in out.read_text()  # paused until play is pressed


def test_a_video_shows_the_robot_move(paper, straight, tmp_path):
    """Frames of the MP4 differ where the robot moves and the first frame is not blank."""
    import imageio_ffmpeg

    from jsphere.plots.animation import animate

    scene = Scene([body_from_trajectory(straight, label="gaits")], paper, title="straight line", target=(0.26, 0.0))
    out = animate(scene, tmp_path / "s.mp4", fps=4, speed=1.0, size=(200, 150), view="top", progress=False)
    reader = imageio_ffmpeg.read_frames(str(out))
    meta = next(reader)
    frames = [np.frombuffer(f, np.uint8).reshape(meta["size"][1], meta["size"][0], 3) for f in reader]
    assert frames[0].std() > 10
    assert np.abs(frames[0].astype(int) - frames[len(frames) // 2]).mean() > 0.5
