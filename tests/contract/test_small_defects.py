"""What a new user reads first: `jsphere design` prints the D-optimal criterion in its natural
sign, named as such; the HTML viewer opens at t = 0.00 s with each slider label the time of its
frame; `jsphere montecarlo --gather` prints the workers' compute time as the study's, and its
own apart."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest
from viewer_html import frame_time, viewer_figure

import jsphere
from jsphere.cli.app import main

NAME = "log det of the information matrix (D-optimal criterion, larger is better)"


def test_design_prints_the_criterion_itself_not_the_penalised_objective(paper, monkeypatch):
    """The search's best point so far breaks a limit: its objective (criterion less 1000 x the
    penalty) is -9.3086, its criterion 19.2719. The step line prints the criterion, positive,
    named; the result's table prints `criterion` as design.json holds it."""
    from jsphere._runtime.progress import Progress
    from jsphere.design import excitation
    from jsphere.design.information import Grid, Noise, problem
    from jsphere.design.inputs import Spec
    from jsphere.design.result import DesignResult
    from jsphere.identify.free import FreeParams

    phi, pen = 19.2719, 0.0285805

    def search(z0s, pr, lim, *, steps, learning_rate=0.05, on_step=None):
        obj = np.array([phi - 1e3 * pen])
        for k in range(steps + 1):
            if on_step is not None:
                on_step(k, obj, np.array([phi]), np.array([pen]))
        return np.asarray(z0s), obj, np.array([phi]), np.array([pen])

    monkeypatch.setattr(excitation, "maximise", search)
    spec = Spec(kind="K", trials=1, wheels=3, n_freqs=2, duration=1.0, f_max=1.0, ramp=0.5, limit=0.1)
    free = FreeParams(paper, "j")
    pr = problem(paper, free, spec, Noise(), Grid(rate=5.0, substeps=1))
    lines = []
    o = excitation.DesignOptions(restarts=1, steps=2, seed=0, learning_rate=0.02)
    excitation._optimise(Progress(lines.append), pr, jsphere.Limits(), free, o)
    steps = [x for x in lines if "step" in x and "/2" in x]
    assert len(steps) == 3 and all(NAME in x for x in steps)
    printed = [float(re.search(re.escape(NAME) + r" (-?[0-9.]+)", x).group(1)) for x in steps]
    assert printed == [phi] * 3 and phi > 0
    assert not any("-9.3" in x or "objective" in x for x in lines)

    result = DesignResult(
        kind="K", free=["j"], values={"j": 2.74e-4}, duration=1.0, rate=20.0, tables=[], baseline_tables=[],
        criterion={"design": 27.776, "baseline": 26.626}, criterion_model={"design": phi, "baseline": 18.0},
        stderr_predicted={"j": 1e-5}, stderr_predicted_baseline={"j": 2e-5}, rms={"design": 0.01, "baseline": 0.01},
        limits={}, limits_baseline={}, limits_model={}, baseline_equal_rms=None,
        restarts=[{"start": 3.0, "final": phi - 1e3 * pen, "penalty": pen, "criterion": phi}], settings={},
        elapsed_s=1.0,
    )  # fmt: skip
    last = result.table().splitlines()[-1]
    assert last.startswith(f"{NAME}: design 27.776, baseline 26.626")
    assert result.to_json()["criterion"] == {"design": 27.776, "baseline": 26.626}


def test_viewer_opens_at_t_zero_and_each_slider_label_is_its_frames_time(paper, tmp_path):
    """A synthetic wheel-speed trial shown with `jsphere animate --out x.html`: exit 0; the
    slider starts on step 0, labelled `0.00 s`, the page does not play on its own, and step `k`
    is labelled with the time frame `k` shows."""
    c = jsphere.random_inputs(paper, 2.0, kind="wheel_speeds", seed=1)
    jsphere.write_trial(tmp_path / "trial.csv", jsphere.synthetic_trial(paper, c, 2.0, seed=1, name="t1"))
    out = tmp_path / "trial.html"
    assert main(["animate", str(tmp_path / "trial.csv"), "--out", str(out), "--size", "200", "150", "-q"]) == 0
    _, layout, frames = viewer_figure(out)
    slider = layout["sliders"][0]
    labels = [s["label"] for s in slider["steps"]]
    assert slider["active"] == 0 and labels[0] == "0.00 s" and frame_time(frames[0]) == "0.00"
    assert labels[1] == f"{2.0 / (len(frames) - 1):.2f} s" != labels[0]  # 15 frames a second, from 0 to 2 s
    assert labels == [f"{float(frame_time(f)):.2f} s" for f in frames]
    assert [s["args"][0] for s in slider["steps"]] == [[f["name"]] for f in frames]
    assert "Plotly.animate(" not in out.read_text()


STUDY = (
    'trials = 128\nseed = 3\nbatch_size = 64\ngaits = [{kind = "acceleration"}, {kind = "braking"}]\n'
    '[vary]\n"r_m[2]" = ["normal", -0.0270146, 1e-4]\n'
)


def test_gather_prints_the_workers_compute_time_as_the_studys(tmp_path, capsys):
    """`--worker` then `--gather` on 128 trials: exit 0 each; the gather's first line gives the
    sum of the compute times the worker recorded (time_*.json), its own time a line apart.
    Without the records it gives no study time at all rather than its own."""
    cfg = tmp_path / "study.toml"
    cfg.write_text(STUDY)
    out = tmp_path / "study"
    assert main(["montecarlo", str(cfg), "--out", str(out), "--worker", "-q"]) == 0
    capsys.readouterr()
    recorded = sum(json.loads((out / f"time_{k:06d}.json").read_text())["compute_s"] for k in range(2))
    assert recorded > 0
    assert main(["montecarlo", str(cfg), "--out", str(out), "--gather", "--no-plots", "-q"]) == 0
    lines = capsys.readouterr().out.splitlines()
    study = re.fullmatch(r"jsphere montecarlo: 128 trials in (\S+) s of the workers' compute: 128 ok, .*", lines[0])
    assert study and float(study.group(1)) == pytest.approx(recorded, abs=0.05)
    assert lines[1].startswith("  2 batch(es) by 1 process(es), ")
    assert re.fullmatch(r"  gathered in \S+ s \(joining the batch files\)", lines[2])
    for k in range(2):
        (out / f"time_{k:06d}.json").unlink()
    assert main(["montecarlo", str(cfg), "--out", str(out), "--gather", "--no-plots", "-q"]) == 0
    first = capsys.readouterr().out.splitlines()[0]
    assert first.startswith("jsphere montecarlo: 128 trials (the batches' compute time is not recorded")
    assert " s:" not in first
