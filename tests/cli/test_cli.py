"""The command line's conventions: `--version`, help with a description, examples and exit codes,
quick answers without JAX, `NAME=VALUE` options that leave the trial files alone, `-q`/`-v`, and
the progress helper shared by `fit`, `plan` and `monte_carlo`."""

from __future__ import annotations

import io
import logging
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from jsphere._runtime import progress as progress_module
from jsphere._runtime.errors import ExitCode
from jsphere._runtime.progress import Progress
from jsphere.cli.app import COMMANDS, main, parser, version

ROOT = Path(__file__).resolve().parents[2]
DATA = ROOT / "examples" / "data"


def _python(code: str, *args: str) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    return subprocess.run([sys.executable, "-c", code, *args], capture_output=True, text=True, env=env, timeout=120)


def test_version(capsys):
    with pytest.raises(SystemExit) as e:
        main(["--version"])
    assert e.value.code == 0
    assert capsys.readouterr().out.strip() == f"jsphere {version()}"
    import jsphere

    assert version().split("+")[0] == jsphere.__version__


@pytest.mark.parametrize("name", [c.NAME for c in COMMANDS])
def test_every_command_has_a_description_examples_exit_codes_and_q_v(name, capsys):
    with pytest.raises(SystemExit) as e:
        main([name, "--help"])
    assert e.value.code == 0
    text = capsys.readouterr().out
    assert "examples:\n  jsphere " + name in text
    assert "exit codes:\n  0    success" in text and f"{int(ExitCode.INTERRUPTED)}  interrupted" in text
    assert "-q, --quiet" in text and "-v, --verbose" in text
    assert ("3    plan:" in text) == (name == "plan") and ("5    fit:" in text) == (name == "fit")
    sub = parser()._subparsers._group_actions[0].choices[name]
    assert len(sub.description) > 80  # a sentence, not the one-line help


def test_help_version_and_argument_errors_import_no_jax():
    """Through the real package (`jsphere/__init__.py` included): nothing heavy is imported."""
    code = (
        "import sys\n"
        "from jsphere.cli.app import main\n"
        "for argv in (['--help'], ['--version'], ['fit', '--help'], ['plan'], ['synth', '--trials']):\n"
        "    try:\n"
        "        main(argv)\n"
        "    except SystemExit:\n"
        "        pass\n"
        "print(sorted(m for m in ('jax', 'numpy', 'equinox', 'tqdm') if m in sys.modules))\n"
    )
    done = _python(code)
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip().splitlines()[-1] == "[]", done.stdout[-500:]


def test_import_jsphere_is_light_and_every_name_resolves():
    code = (
        "import sys, jsphere\n"
        "print('jax' in sys.modules)\n"
        "from jsphere import fit, RobotParams, ExitCode\n"
        "missing = [n for n in jsphere.__all__ if getattr(jsphere, n, None) is None]\n"
        "print(missing, set(jsphere.__all__) <= set(dir(jsphere)), jsphere.model.params.RobotParams is RobotParams)\n"
    )
    done = _python(code)
    assert done.returncode == 0, done.stderr
    assert done.stdout.split("\n")[:2] == ["False", "[] True True"], done.stdout


@pytest.mark.parametrize(
    "argv, fix, bound, trials",
    [
        (["--free", "j", "--fix", "m=2.5", "a.csv", "--out", "f.json"], ["m=2.5"], None, ["a.csv"]),
        (["a.csv", "--free", "j", "--fix", "m=2.5", "m0=0.8", "b.csv"], ["m=2.5", "m0=0.8"], None, ["a.csv", "b.csv"]),
        (
            ["--fix", "m=2.5,I[0,0]=0.02", "--fix", "j=1e-4", "a.csv", "--free", "R_m"],
            ["m=2.5", "I[0,0]=0.02", "j=1e-4"],
            None,
            ["a.csv"],
        ),
        (
            ["--fix", "r_m=[0,0,-0.02]", "--bound", "j=0:1e-3", "R_m=0.01:", "a.csv", "--free", "j"],
            ["r_m=[0,0,-0.02]"],
            ["j=0:1e-3", "R_m=0.01:"],
            ["a.csv"],
        ),
        (["--free", "j", "--fix", "m", "a.csv"], ["m"], None, ["a.csv"]),  # a wrong first value is reported as such
    ],
)
def test_fix_and_bound_are_repeatable_and_leave_the_trials(argv, fix, bound, trials):
    args = parser().parse_args(["fit", *argv])
    assert args.fix == fix and args.bound == bound
    assert [*args.trials, *(args.trials_after_options or [])] == trials


def test_a_trial_file_named_like_an_assignment_is_a_file(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    Path("j=1.csv").write_text("")
    args = parser().parse_args(["fit", "--free", "j", "--fix", "m=2.5", "j=1.csv"])
    assert args.fix == ["m=2.5"] and args.trials_after_options == ["j=1.csv"]


def test_cli_defaults_match_the_library():
    import inspect

    import jsphere

    assert parser().parse_args(["plan", "--to", "1", "0"]).restarts == jsphere.PlanOptions().restarts
    for f in (jsphere.fit, jsphere.plan, jsphere.plan_many, jsphere.plan_route, jsphere.monte_carlo):
        assert inspect.signature(f).parameters["progress"].default is None, f.__name__


def test_montecarlo_overrides_and_summary():
    from jsphere.cli.montecarlo import summary

    args = parser().parse_args(["montecarlo", "s.toml", "--seed", "3", "--batch-size", "256", "-q", "--frame", "paper"])
    assert (args.seed, args.batch_size, args.quiet, args.frame) == (3, 256, True, "paper")
    st = {
        "n_ok": 98,
        "n_rejected": 1,
        "n_failed": 1,
        "mean_xy_m": [0.2588, 0.0035],
        "sd_xy_m": [1e-4, 2e-5],
        "planned_stop_m": [0.25877, 0.00359],
    }
    text = summary(st, 100, 12.34, [Path("out/stats.json")])
    assert text.splitlines() == [
        "jsphere montecarlo: 100 trials in 12.3 s: 98 ok, 1 rejected, 1 failed",
        "  stop point (jsphere frame): mean (258.800, 3.500) mm, sd (0.100, 0.020) mm",
        "  planned stop: (258.770, 3.590) mm",
        f"  wrote {Path('out/stats.json')}",
    ]


# ------------------------------------------------------------------ -q / -v through logging


@pytest.mark.parametrize("flag, shown", [([], {"info"}), (["-q"], set()), (["-v"], {"info", "debug"})])
def test_quiet_and_verbose_set_the_jsphere_logger(flag, shown, tmp_path, capsys, monkeypatch):
    """The `synth` command logs nothing itself: a stand-in run shows what the handler passes."""
    from jsphere.cli import synth

    def run(args):
        log = logging.getLogger("jsphere.test")
        log.info("info")
        log.debug("debug")
        log.warning("warning")
        return 0

    monkeypatch.setattr(synth, "run", run)
    assert main(["synth", "--out", str(tmp_path), "--no-cache", *flag]) == 0
    out, err = capsys.readouterr()
    assert out == "" and set(err.split()) == shown | {"warning"}
    assert not logging.getLogger("jsphere").handlers  # removed after the command


# ------------------------------------------------------------------ the progress helper


class _Terminal(io.StringIO):
    def isatty(self):
        return True


def test_progress_forms(capsys, monkeypatch):
    lines = []
    p = Progress(lines.append)
    p.say("stage")
    with p.bar(3, "work") as bar:
        bar.update(1)
        p.step("step 1")
    assert lines == ["stage", "step 1"] and p.bars is False
    Progress(False).say("nothing")
    Progress(None).say("nothing either")  # not a terminal: the logger only (no handler here)
    assert capsys.readouterr().err == ""
    Progress(True).step("a line")  # not a terminal: lines on stderr
    assert capsys.readouterr().err == "a line\n"
    with pytest.raises(TypeError, match="progress must be"):
        Progress("yes")


def test_bars_on_a_terminal_with_the_compilation_left_out(monkeypatch, tmp_path):
    pytest.importorskip("tqdm")
    term = _Terminal()
    monkeypatch.setattr(sys, "stderr", term)
    monkeypatch.setattr(progress_module, "_cache_dir", lambda: tmp_path)
    p = Progress(None)
    assert p.bars
    with p.bar(4, "jsphere test", "trial") as bar:
        with p.compiling("montecarlo", "test-program", "jsphere test"):
            pass
        bar.update(2, "cost 1")
        p.step("not on the terminal: the bar shows it")
        bar.done()
    text = term.getvalue()
    assert "jsphere test: compiling (first call, ~45 s)" in text
    assert "jsphere test: 100%" in text and "2/2" in text and "not on the terminal" not in text
    record = progress_module._read_record(tmp_path)["montecarlo"]
    assert len(record["keys"]) == 1 and record["last_s"] is None  # too quick to have compiled
    before = term.getvalue()
    with p.compiling("montecarlo", "test-program", "jsphere test"):  # compiled: no note
        pass
    assert term.getvalue() == before


def test_the_first_call_estimate_comes_from_the_cache_record(tmp_path, monkeypatch):
    monkeypatch.setattr(progress_module, "_cache_dir", lambda: tmp_path)
    key = progress_module._full_key("plan", "p")
    assert progress_module.expected_compile_s("plan", key) == progress_module.FIRST_CALL_S["plan"]
    progress_module._record("plan", "other", 12.3)
    assert progress_module.expected_compile_s("plan", key) == 12.3
    progress_module._record("plan", "cached", 0.2)  # served by JAX's cache: not an estimate
    assert progress_module.expected_compile_s("plan", key) == 12.3
    progress_module._record("plan", key, 20.0)
    assert progress_module.expected_compile_s("plan", key) is None


# ------------------------------------------------------------------ figures in jsphere's frame


def test_stop_points_figure_is_in_jsphere_frame_unless_asked(monkeypatch, tmp_path):
    from jsphere.montecarlo.result import MonteCarloResult
    from jsphere.plots import montecarlo as figures
    from jsphere.plots.base import pyplot

    rng = np.random.default_rng(0)
    n = 200
    res = MonteCarloResult(
        n=n,
        seed=0,
        samples={},
        x_final=0.2588 + 1e-4 * rng.normal(size=n),
        y_final=0.0035 + 1e-5 * rng.normal(size=n),
        speed_final=np.zeros(n),
        status=np.zeros(n, np.int32),
        gamma3_sd_after=np.zeros(n),
        elapsed_s=1.0,
        reject_code=np.zeros(n, np.int32),
    )
    drawn = {}

    def keep(fig, path, margins=None):
        ax = fig.axes[0]
        drawn[path.name] = (ax.get_xlabel(), ax.get_ylabel(), np.asarray(ax.lines[0].get_xydata()).mean(0))
        pyplot().close(fig)

    monkeypatch.setattr(figures, "finish", keep)
    figures.montecarlo_figure(res, tmp_path / "ours.png", planned=(0.2588, 0.0036))
    figures.montecarlo_figure(res, tmp_path / "paper.png", planned=(0.2588, 0.0036), frame="paper")
    xl, yl, mean = drawn["ours.png"]
    assert "jsphere frame" in xl and "jsphere frame" in yl
    assert mean == pytest.approx([258.8, 3.5], abs=0.05)
    xl, yl, mean = drawn["paper.png"]
    assert "paper's figure frame" in xl and "paper's figure frame" in yl
    assert mean == pytest.approx([-3.5, 258.8], abs=0.05)
    with pytest.raises(ValueError, match="frame must be"):
        figures.montecarlo_figure(res, tmp_path / "x.png", frame="figure")


@pytest.mark.parametrize("robust", [False, True])
def test_plan_passes_its_fast_start_to_the_verifications(robust, tmp_path, monkeypatch, capsys):
    """`jsphere plan` runs `plan` (and `plan_robust` with `--robust`) with its cache's `FastStart`
    running their programs, as `fit` and `reproduce` do, so that the verification's program is
    kept for the next run."""
    from jsphere._runtime import quick_compile
    from jsphere._runtime.errors import InputError
    from jsphere._runtime.fast_start import FastStart
    from jsphere.planning import plan as plan_module
    from jsphere.planning import robust as robust_module

    seen = []

    def record(*args, options=None, **kw):
        seen.append(quick_compile._RUNNER[0])
        if robust and len(seen) == 1:
            return "nominal"
        raise InputError("recorded")

    monkeypatch.setattr(plan_module, "plan", record)
    monkeypatch.setattr(robust_module, "plan_robust", record)
    extra = []
    if robust:
        vary = tmp_path / "study.toml"
        vary.write_text('[vary]\n"r_m[2]" = ["normal", -0.0270146, 1e-4]\n')
        extra = ["--robust", str(vary)]
    rc = main(["plan", "--to", "0.3", "0.1", "--out", str(tmp_path / "plan.csv"), "--no-plots", "--quiet", *extra])
    assert rc == ExitCode.BAD_INPUT and "recorded" in capsys.readouterr().err
    assert len(seen) == 1 + robust
    assert all(isinstance(o, FastStart) for o in seen), seen
