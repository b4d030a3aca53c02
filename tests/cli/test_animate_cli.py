"""`jsphere animate` on each kind of input: a trial CSV, a plan CSV, a Monte-Carlo study folder
and a fit with its trials; each writes an MP4 that lasts the run's duration divided by --speed
(within one frame), a GIF and an HTML file, and leaves its inputs as they were."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np
import pytest

from jsphere.cli.app import main

DATA = Path(__file__).resolve().parents[2] / "examples" / "data"
FPS, SPEED = 8, 2.0
SMALL = ["--fps", str(FPS), "--speed", str(SPEED), "--size", "160", "120", "--no-cache", "-q"]

# imageio-ffmpeg's reader and the MP4 writer start ffmpeg by fork and exec at once
pytestmark = pytest.mark.filterwarnings(r"ignore:os\.fork\(\) was called:RuntimeWarning")


def _frames(path: Path) -> int:
    import imageio_ffmpeg

    return imageio_ffmpeg.count_frames_and_secs(str(path))[0]


def _snapshot(folder: Path) -> dict:
    return {
        str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest() for p in folder.rglob("*") if p.is_file()
    }


def _animate_all(source: list[str], tmp: Path, stem: str, duration: float, scenes: int = 1) -> None:
    """MP4 (its length checked: within one frame of each of its `scenes`), GIF and HTML of `source`."""
    from PIL import Image

    for suffix in (".mp4", ".gif", ".html"):
        out = tmp / f"{stem}{suffix}"
        assert main(["animate", *source, "--out", str(out), *SMALL]) == 0
        assert out.stat().st_size > 1000
    n = _frames(tmp / f"{stem}.mp4")
    assert abs(n / FPS - duration / SPEED) <= scenes / FPS
    assert abs(Image.open(tmp / f"{stem}.gif").n_frames / FPS - duration / SPEED) <= scenes / FPS
    html = (tmp / f"{stem}.html").read_text()
    assert "window.jsphereViewer" in html and html.count('"method":"animate"') == n + 2  # steps, play, pause


def test_animate_a_synthetic_trial(tmp_path):
    from jsphere.capture.trial import read_trial

    trial = read_trial(DATA / "ws_01.csv")
    before = _snapshot(DATA)
    _animate_all([str(DATA / "ws_01.csv")], tmp_path, "trial", trial.duration)
    assert _snapshot(DATA) == before


def test_animate_a_plan_table(paper, straight, tmp_path):
    """A plan CSV with its plan.json (the target) beside it."""
    from jsphere.planning.result import Plan

    plan = Plan(
        paper, [], np.zeros((1, 3)), straight, 100.0, np.array([0.25, 0.01, np.nan]), {}, {}, True, [], {}, 0, 0
    )
    plan.to_csv(tmp_path / "plan.csv")
    (tmp_path / "plan.json").write_text(json.dumps({"feasible": True, "target": [0.25, 0.01, None]}))
    _animate_all([str(tmp_path / "plan.csv")], tmp_path, "plan", plan.duration)
    assert (
        main(["animate", str(tmp_path / "plan.csv"), "--view", "top", "--out", str(tmp_path / "top.gif"), *SMALL]) == 0
    )


def _study(tmp: Path, paper) -> Path:
    """A small study folder as `jsphere montecarlo` leaves it (manifest, one batch, stats) and
    its study file beside it."""
    vary = {"r_m[2]": ["normal", -0.0270146, 1e-4]}
    (tmp / "study.toml").write_text(
        'trials = 16\nbatch_size = 16\ngaits = [{kind = "acceleration"}, {kind = "braking"}]\n'
        '[vary]\n"r_m[2]" = ["normal", -0.0270146, 1e-4]\n'
    )
    folder = tmp / "study"
    folder.mkdir()
    rng = np.random.default_rng(0)
    n = 16
    vals = -0.0270146 + 1e-4 * rng.standard_normal((n, 1))
    x, y = 0.2592 + 1e-3 * rng.standard_normal(n), 1e-4 * rng.standard_normal(n)
    status = np.zeros(n, np.int32)
    status[3] = 1  # a failed trial: not drawn
    np.savez(
        folder / "batch_000000.npz",
        vals=vals,
        x=x,
        y=y,
        speed=np.zeros(n),
        status=status,
        gamma3_sd=np.zeros(n),
        reject=np.zeros(n, np.int32),
    )
    (folder / "manifest.json").write_text(
        json.dumps({"fingerprint": "0", "n": n, "seed": 0, "batch_size": n, "vary": vary})
    )
    ok = status == 0
    (folder / "stats.json").write_text(
        json.dumps(
            {
                "n_ok": int(ok.sum()),
                "mean_xy_m": [float(x[ok].mean()), float(y[ok].mean())],
                "ellipse": {"semi_axes_m": [2e-4, 2e-3], "angle_rad": 0.0, "level": 0.95},
            }
        )
    )
    return folder


@pytest.mark.slow
def test_animate_a_montecarlo_folder(paper, straight, tmp_path):
    """A handful of the study's trials (their gaits executed by their drawn robots) and the stop
    points; the study file is found beside the folder or given after it; the folder is input:
    nothing in it changes, and --out inside it is refused."""
    folder = _study(tmp_path, paper)
    before = _snapshot(folder)
    _animate_all([str(folder)], tmp_path, "mc", float(straight.ts[-1]))
    assert main(["animate", str(folder), str(tmp_path / "study.toml"), "--out", str(tmp_path / "b.gif"), *SMALL]) == 0
    assert main(["animate", str(folder), "--out", str(folder / "inside.mp4"), *SMALL]) == 2
    assert _snapshot(folder) == before


def test_montecarlo_scene_draws_the_studys_trials(paper, tmp_path):
    from jsphere.cli.animate import montecarlo_scene

    folder = _study(tmp_path, paper)
    scene = montecarlo_scene(folder, tmp_path / "study.toml")
    assert len(scene.bodies) == 5 and len(scene.cloud) == 15
    assert [b.label for b in scene.bodies] == ["trial 0", "trial 1", "trial 2", "trial 4", "trial 5"]  # 3 failed
    stops = np.array([[b.x[-1], b.y[-1]] for b in scene.bodies])
    assert np.all(np.abs(stops[:, 0] - 0.2592) < 5e-3)  # the straight line's stop, each robot its own
    assert len({round(float(s), 9) for s in stops[:, 0]}) == 5


@pytest.mark.slow
def test_animate_a_fit_with_its_trials(paper, tmp_path):
    """Synthetic trials (`jsphere synth`), a fit.json naming them (the worst first); the fitted
    model replays each trial, ghosted over it; --trial picks one."""
    from jsphere.capture.trial import read_trial

    trials = tmp_path / "fit"
    assert main(["synth", "--out", str(trials), "--trials", "2", "--duration", "1.5", "--no-cache", "-q"]) == 0
    names = sorted(p.stem for p in trials.glob("*.csv"))
    fit = {
        "params": paper.replace(j=2.0e-4).to_dict(),
        "status": "converged",
        "verdict": {"worst_trial": names[1]},
        "trials": [{"name": n} for n in names],
    }
    (trials / "fit.json").write_text(json.dumps(fit))
    before = _snapshot(trials)
    durations = [read_trial(trials / f"{n}.csv").duration for n in names]
    _animate_all([str(trials / "fit.json")], tmp_path, "fit", sum(durations), scenes=2)
    out = tmp_path / "one.mp4"
    assert main(["animate", str(trials / "fit.json"), "--trial", names[0], "--out", str(out), *SMALL]) == 0
    assert abs(_frames(out) / FPS - durations[0] / SPEED) <= 1.0 / FPS
    assert _snapshot(trials) == before

    from jsphere.cli.animate import scenes_from_path

    scenes = scenes_from_path(trials / "fit.json")
    assert [s.bodies[0].label for s in scenes] == [f"{names[1]} (capture)", f"{names[0]} (capture)"]
    assert scenes[0].residual and scenes[0].bodies[1].ghost
