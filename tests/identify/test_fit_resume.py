"""A fit stopped anywhere resumes to the same `fit.json`, bit for bit; a fit whose every start
fails stops with `SolverFailure`; a damaged checkpoint is ignored with a warning; `jsphere fit`
checks its output path before any work.

The fits share one tiny problem (one trial of 1 s at 25 Hz, free `R_m, j`, 2 starts), so the
fit's functions are compiled once for the module (~30 s on 2 cores); each fit then takes ~2 s.
The kills come from `jsphere.identify.checkpoint._checkpoint_hook`, called inside every checkpoint write
(after the temporary file is written, and after its rename); the slow test kills a `jsphere
fit` process with SIGKILL.
"""

from __future__ import annotations

import contextlib
import io
import json
import os
import signal
import subprocess
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest

import jsphere
from jsphere._runtime.errors import SolverFailure
from jsphere._runtime.files import dumps_json
from jsphere.cli.app import main
from jsphere.identify import checkpoint as _checkpoint
from jsphere.identify import fit as _fit

#: a real fit to every checkpoint and back (~40 s): run with `-m slow`
pytestmark = pytest.mark.slow


FREE = "R_m,j"
OPTS = {"n_starts": 2, "adam_steps": 2, "max_iter": 15}
ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def tiny_trials():
    truth = jsphere.RobotParams.paper().replace(R_m=0.029, j=3.2e-4)
    u = jsphere.random_inputs(truth, 1.0, kind="wheel_speeds", seed=0)
    return [jsphere.synthetic_trial(truth, u, 1.0, rate=25.0, seed=0, name="t0", dropout=0.05)]


def run_fit(trials, ckpt, progress=None, max_steps=None, **kw):
    solver = None if max_steps is None else jsphere.SolverOptions(max_steps=max_steps)
    options = jsphere.FitOptions(**{**OPTS, **kw}, solver=solver)
    return jsphere.fit(
        trials, jsphere.RobotParams.paper(), FREE, fix={"m": 2.5}, checkpoint=ckpt, options=options, progress=progress
    )


def document(res) -> str:
    """`fit.json` as it is written, less its one wall time (`elapsed_s`)."""
    doc = res.to_json()
    doc.pop("elapsed_s")
    return dumps_json(doc)


@contextlib.contextmanager
def checkpoint_hook(hook):
    old, _checkpoint._checkpoint_hook = _checkpoint._checkpoint_hook, hook
    try:
        yield
    finally:
        _checkpoint._checkpoint_hook = old


def kill_at(event: str, n: int):
    """A hook that raises KeyboardInterrupt at the `n`-th `event` ("written": the temporary file
    is complete but not renamed; "saved": the checkpoint is in place)."""
    seen = {"written": 0, "saved": 0}

    def hook(ev, path):
        seen[ev] += 1
        if ev == event and seen[ev] == n:
            raise KeyboardInterrupt

    return hook


def arrays(npz: bytes) -> dict[str, bytes]:
    """The arrays of a checkpoint, as bytes (the zip file's own time stamps left out)."""
    with np.load(io.BytesIO(npz)) as z:
        return {k: z[k].tobytes() for k in z.files}


def stage_of(ckpt: Path) -> tuple[int, int]:
    with np.load(ckpt) as z:
        return int(z["stage"]), int(z["adam_k"] if int(z["stage"]) == 0 else z["it"])


@pytest.fixture(scope="module")
def reference(tiny_trials, tmp_path_factory):
    """The uninterrupted fit: its document and the number of checkpoints it writes."""
    events = []
    with checkpoint_hook(lambda ev, path: events.append(ev)):
        res = run_fit(tiny_trials, tmp_path_factory.mktemp("ref") / "fit.json.ckpt.npz")
    return document(res), events.count("saved"), res


# ------------------------------------------------------------------ kill and resume


def test_a_fit_killed_at_every_checkpoint_resumes_bit_for_bit(tiny_trials, reference, tmp_path):
    """Killed after each of its checkpoint writes in turn (every Adam step, the start of each
    Levenberg-Marquardt stage, each LM iteration, the noise estimate, the finished optimisation)
    and, every third write, also inside the write, the fit ends with the uninterrupted `fit.json`."""
    ref_doc, n_saves, ref = reference
    assert n_saves == OPTS["adam_steps"] + ref.iterations + 3  # Adam steps, LM start, LM steps, noise estimate, end
    ckpt = tmp_path / "fit.json.ckpt.npz"
    visited, lines = [], []
    for k in range(1, n_saves + 1):
        if k % 3 == 1:  # inside the write: the previous checkpoint stays, no temporary file is left
            before = ckpt.read_bytes() if ckpt.exists() else None
            with checkpoint_hook(kill_at("written", 1)), pytest.raises(KeyboardInterrupt):
                run_fit(tiny_trials, ckpt)
            assert (ckpt.read_bytes() if ckpt.exists() else None) == before
            assert sorted(p.name for p in tmp_path.iterdir()) == ([ckpt.name] if before is not None else [])
        with checkpoint_hook(kill_at("saved", 1)), pytest.raises(KeyboardInterrupt):
            run_fit(tiny_trials, ckpt, progress=lines.append)
        visited.append(stage_of(ckpt))
    assert visited == sorted(visited, key=lambda v: v[0]) and {s for s, _ in visited} == {0, 1, 2, 3}
    assert visited[: OPTS["adam_steps"] + 1] == [(0, 1), (0, 2), (1, 0)] and visited[-1] == (3, visited[-2][1])
    res = run_fit(tiny_trials, ckpt, progress=lines.append)  # resumes from the finished optimisation
    assert any("resuming" in s and "stage 3" in s for s in lines)
    assert document(res) == ref_doc
    assert sorted(p.name for p in tmp_path.iterdir()) == [ckpt.name]


def test_cli_ctrl_c_returns_130_keeps_the_checkpoint_and_resumes_bit_for_bit(tiny_trials, tmp_path, capsys):
    jsphere.write_trial(tmp_path / "t0.csv", tiny_trials[0])
    argv = [
        "fit",
        str(tmp_path / "t0.csv"),
        "--free",
        FREE,
        "--fix",
        "m=2.5",
        "--n-starts",
        "2",
        "--no-plots",
        "--quiet",
        "--no-cache",
    ]
    assert main([*argv, "--out", str(tmp_path / "a" / "fit.json")]) == 0
    whole = json.loads((tmp_path / "a" / "fit.json").read_text())
    out = tmp_path / "b" / "fit.json"
    ckpt = out.with_name("fit.json.ckpt.npz")
    capsys.readouterr()
    with checkpoint_hook(kill_at("saved", 6)):  # 3 Adam steps, the LM start, 2 LM steps
        assert main([*argv, "--out", str(out)]) == 130
    assert "interrupted" in capsys.readouterr().err
    assert stage_of(ckpt) == (1, 2) and not out.exists()
    assert main([*argv, "--out", str(out)]) == 0
    resumed = json.loads(out.read_text(), parse_constant=lambda c: pytest.fail(f"fit.json holds {c}"))
    assert {k: v for k, v in resumed.items() if k != "elapsed_s"} == {
        k: v for k, v in whole.items() if k != "elapsed_s"
    }
    assert sorted(p.name for p in out.parent.iterdir()) == ["fit.json"]


# ------------------------------------------------------------------ damaged checkpoints


def _damage(kind: str, ckpt: Path, good: bytes) -> None:
    if kind == "empty":
        ckpt.write_bytes(b"")
    elif kind == "truncated":
        ckpt.write_bytes(good[: len(good) // 2])
    elif kind == "random bytes":
        ckpt.write_bytes(np.random.default_rng(0).bytes(2000))
    elif kind == "other keys":
        np.savez(ckpt, a=np.zeros(3))
    elif kind == "a key missing":
        with np.load(ckpt) as z:
            arrays = {k: z[k] for k in z.files if k != "adam_k"}
        np.savez(ckpt, **arrays)
    elif kind == "a wrong shape":
        with np.load(ckpt) as z:
            arrays = {k: z[k] for k in z.files}
        arrays["theta"] = arrays["theta"][:1]
        np.savez(ckpt, **arrays)


@pytest.fixture(scope="module")
def first_checkpoint(tiny_trials, tmp_path_factory):
    """The bytes of the checkpoint after the first Adam step."""
    ckpt = tmp_path_factory.mktemp("first") / "c.npz"
    with checkpoint_hook(kill_at("saved", 1)), pytest.raises(KeyboardInterrupt):
        run_fit(tiny_trials, ckpt)
    return ckpt.read_bytes()


@pytest.mark.parametrize(
    "kind, says",
    [
        ("empty", "cannot be read"),
        ("truncated", "cannot be read"),
        ("random bytes", "cannot be read"),
        ("other keys", "not a checkpoint of jsphere fit"),
        ("a key missing", "it has no 'adam_k'"),
        ("a wrong shape", "'theta' is float64 of shape (1, 2)"),
    ],
)
def test_a_damaged_checkpoint_is_ignored_with_a_warning(tiny_trials, first_checkpoint, tmp_path, kind, says):
    ckpt = tmp_path / "c.npz"
    ckpt.write_bytes(first_checkpoint)
    _damage(kind, ckpt, first_checkpoint)
    lines = []
    with (
        checkpoint_hook(kill_at("saved", 1)),
        pytest.raises(KeyboardInterrupt),
        warnings.catch_warnings(record=True) as caught,
    ):
        warnings.simplefilter("always")
        run_fit(tiny_trials, ckpt, progress=lines.append)
    [w] = caught
    assert says in str(w.message) and "starts afresh" in str(w.message) and "\n" not in str(w.message)
    assert not any("resuming" in s for s in lines)
    assert arrays(ckpt.read_bytes()) == arrays(first_checkpoint)  # started afresh: the same first step


def test_cli_says_in_one_line_that_a_damaged_checkpoint_is_ignored(tiny_trials, tmp_path, capsys):
    jsphere.write_trial(tmp_path / "t0.csv", tiny_trials[0])
    out = tmp_path / "fit.json"
    out.with_name("fit.json.ckpt.npz").write_bytes(b"PK\x03\x04 broken off")
    with checkpoint_hook(kill_at("saved", 1)):
        rc = main(
            [
                "fit",
                str(tmp_path / "t0.csv"),
                "--free",
                FREE,
                "--fix",
                "m=2.5",
                "--n-starts",
                "2",
                "--out",
                str(out),
                "--quiet",
                "--no-cache",
            ]
        )
    assert rc == 130
    err = capsys.readouterr().err
    assert f"jsphere fit: warning: fit: the checkpoint {out}.ckpt.npz cannot be read (BadZipFile: " in err
    assert "Traceback" not in err


def test_a_checkpoint_of_another_fit_is_not_resumed(tiny_trials, first_checkpoint, tmp_path):
    ckpt = tmp_path / "c.npz"
    ckpt.write_bytes(first_checkpoint)
    with (
        checkpoint_hook(kill_at("saved", 1)),
        pytest.raises(KeyboardInterrupt),
        pytest.warns(UserWarning, match="from another fit"),
    ):
        run_fit(tiny_trials, ckpt, max_iter=16)  # another option: another fit


# ------------------------------------------------------------------ every start fails


class _Failing:
    """The compiled functions of a fit whose simulations give NaN from sample `k0` of the first
    trial on, after `finite_calls` evaluations that succeed."""

    def __init__(self, fns, k0: int, finite_calls: int):
        self.fns, self.k0, self.left = fns, k0, finite_calls
        self.step = fns.step

    def run(self, name: str, *args):
        """As `_Functions.run`, without exported programs."""
        return getattr(self, name)(*args)

    def jacobian(self, base, th, nu, d, sig):
        res, ok, J, (x, y, q) = self.fns.jacobian(base, th, nu, d, sig)
        if self.left > 0:
            self.left -= 1
            return res, ok, J, (x, y, q)
        x = np.asarray(x).copy()
        x[:, 0, self.k0 :] = np.nan
        return np.zeros_like(res), np.zeros(np.shape(ok), bool), J, (x, y, q)


@pytest.fixture
def failing(monkeypatch):
    real = _fit._functions

    def install(k0: int, finite_calls: int):
        monkeypatch.setattr(_fit, "_functions", lambda *a, **kw: _Failing(real(*a, **kw), k0, finite_calls))

    return install


@pytest.mark.parametrize("finite_calls, where", [(0, "the Adam warm start"), (2, "Levenberg-Marquardt stage 1")])
def test_a_fit_whose_every_start_fails_stops_says_where_and_removes_its_checkpoint(
    tiny_trials, failing, tmp_path, finite_calls, where
):
    failing(k0=7, finite_calls=finite_calls)
    ckpt = tmp_path / "c.npz"
    lines = []
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no divide warnings on the way
        with pytest.raises(SolverFailure) as e:
            run_fit(tiny_trials, ckpt, progress=lines.append)
    msg = str(e.value)
    t7 = tiny_trials[0].t[7]
    assert f"every start failed in {where}" in msg
    assert f"trial 't0' at t = {t7:.6g} s (sample 7), channel x" in msg and "Try:" in msg and "\n" not in msg
    assert not ckpt.exists() and not list(tmp_path.iterdir())
    assert not any("noise estimated" in s or "LM stage" in s for s in lines)


def test_cli_exits_4_when_every_start_fails(tiny_trials, failing, tmp_path, capsys):
    failing(k0=0, finite_calls=0)
    jsphere.write_trial(tmp_path / "t0.csv", tiny_trials[0])
    out = tmp_path / "out" / "fit.json"
    rc = main(
        [
            "fit",
            str(tmp_path / "t0.csv"),
            "--free",
            FREE,
            "--fix",
            "m=2.5",
            "--n-starts",
            "2",
            "--out",
            str(out),
            "--quiet",
            "--no-cache",
        ]
    )
    err = capsys.readouterr().err
    assert rc == 4, err
    assert "jsphere fit: error: fit: every start failed in the Adam warm start" in err and "channel x" in err
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1
    assert not out.parent.exists() or not list(out.parent.iterdir())


# ------------------------------------------------------------------ slow: a real SIGKILL, a real failure


def _cli(args, env, **kw):
    return subprocess.run(
        [sys.executable, "-m", "jsphere.cli.app", *args], env=env, capture_output=True, text=True, **kw
    )


_KILLER = """
import os, signal, sys
from jsphere import cli
from jsphere.identify import checkpoint as _checkpoint
n = {"saved": 0}
def hook(event, path):
    n[event] = n.get(event, 0) + 1
    if event == "written" and n.get("saved", 0) == int(os.environ["KILL_AFTER"]):
        os.kill(os.getpid(), signal.SIGKILL)  # inside a write: its temporary file is left behind
_checkpoint._checkpoint_hook = hook
sys.exit(cli.main(sys.argv[1:]))
"""


@pytest.mark.slow
def test_a_fit_killed_with_sigkill_resumes_to_the_same_file(tiny_trials, tmp_path):
    """`jsphere fit` killed by SIGKILL inside a checkpoint write (its temporary file left
    behind), then run again: the same `fit.json` as an uninterrupted run, no temporary file."""
    jsphere.write_trial(tmp_path / "t0.csv", tiny_trials[0])
    env = {**os.environ, "PYTHONPATH": str(ROOT), "JSPHERE_CACHE_DIR": str(tmp_path / "cache")}
    args = [str(tmp_path / "t0.csv"), "--free", FREE, "--fix", "m=2.5", "--n-starts", "2", "--no-plots", "--quiet"]
    whole = _cli(["fit", *args, "--out", str(tmp_path / "a" / "fit.json")], env, cwd=ROOT)
    assert whole.returncode == 0, whole.stderr
    out = tmp_path / "b" / "fit.json"
    for kill_after in (5, 1):  # inside the 6th write (an LM step), then, resumed, inside the 2nd after it
        killed = subprocess.run(
            [sys.executable, "-c", _KILLER, "fit", *args, "--out", str(out)],
            env={**env, "KILL_AFTER": str(kill_after)},
            capture_output=True,
            text=True,
            cwd=ROOT,
        )
        assert killed.returncode == -signal.SIGKILL, killed.stderr
        assert any(
            p.name.startswith(".fit.json.ckpt.") for p in out.parent.iterdir()
        )  # the killed write's temporary file
    resumed = _cli(["fit", *args, "--out", str(out)], env, cwd=ROOT)
    assert resumed.returncode == 0, resumed.stderr
    a, b = (json.loads(p.read_text()) for p in (tmp_path / "a" / "fit.json", out))
    assert {k: v for k, v in a.items() if k != "elapsed_s"} == {k: v for k, v in b.items() if k != "elapsed_s"}
    assert sorted(p.name for p in out.parent.iterdir()) == ["fit.json"]


@pytest.mark.slow
def test_a_fit_the_solver_cannot_follow_fails_with_the_place(tiny_trials, tmp_path):
    """Inputs the ODE solver cannot follow within `max_steps`: a `SolverFailure` naming the
    first sample the simulation did not reach, and no checkpoint left."""
    t = tiny_trials[0]
    wild = jsphere.Trial(t.t, t.x, t.y, t.q, np.asarray(t.inputs) * 1e4, t.kind, name="wild")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(SolverFailure, match=r"every start failed in the Adam warm start .* trial 'wild' at t = "):
            run_fit([wild], tmp_path / "c.npz", max_steps=64)
    assert not list(tmp_path.iterdir())


# ------------------------------------------------------------------ the output path, checked first


def _fit_cli(trial: str, out, *extra) -> list[str]:
    return ["fit", trial, "--free", FREE, "--out", str(out), "--no-plots", "--quiet", "--no-cache", *extra]


def test_out_is_checked_before_the_trials_are_read(tmp_path, capsys):
    assert main(_fit_cli(str(tmp_path / "missing.csv"), tmp_path)) == 2  # a folder
    assert "is a folder" in capsys.readouterr().err
    (tmp_path / "file").write_text("")
    assert main(_fit_cli(str(tmp_path / "missing.csv"), tmp_path / "file" / "deeper" / "fit.json")) == 2
    assert "is a file, not a folder" in capsys.readouterr().err


@pytest.mark.skipif(os.geteuid() == 0, reason="permission bits do not stop root (the /proc case covers it)")
def test_out_in_a_read_only_folder_is_refused(tmp_path, capsys):
    ro = tmp_path / "ro"
    ro.mkdir(mode=0o500)
    try:
        assert main(_fit_cli(str(tmp_path / "missing.csv"), ro / "fit.json")) == 2
        assert "cannot write in the folder" in capsys.readouterr().err
    finally:
        ro.chmod(0o700)


def test_out_that_is_an_input_through_a_link_is_refused(tmp_path, capsys):
    jsphere.RobotParams.paper().save(tmp_path / "robot.json")
    (tmp_path / "link.json").symlink_to(tmp_path / "robot.json")
    before = (tmp_path / "robot.json").read_bytes()
    assert (
        main(_fit_cli(str(tmp_path / "missing.csv"), tmp_path / "link.json", "--params", str(tmp_path / "robot.json")))
        == 2
    )
    assert "would write over" in capsys.readouterr().err and (tmp_path / "robot.json").read_bytes() == before


def test_more_unknowns_than_measured_values_is_refused(tiny_trials):
    t = tiny_trials[0]
    short = jsphere.Trial(t.t[:4], t.x[:4], t.y[:4], t.q[:4], np.asarray(t.inputs)[:4], t.kind, name="short")
    with pytest.raises(ValueError, match="the trials hold 20 measured values but the fit has 20 unknowns"):
        jsphere.fit([short], jsphere.RobotParams.paper(), "I,r_m,j,m0,I0")


def test_fit_json_is_strict_json_with_null_for_what_is_missing(reference):
    import dataclasses

    _, _, res = reference
    res = dataclasses.replace(res, starts=[res.cost, float("inf")], stderr={**res.stderr, "j": float("inf")})
    doc = json.loads(dumps_json(res.to_json()), parse_constant=lambda c: pytest.fail(f"fit.json holds {c}"))
    assert doc["starts_cost"][1] is None and doc["stderr"]["j"] is None


@pytest.mark.slow
def test_multiple_shooting_killed_at_every_checkpoint_resumes_bit_for_bit(tiny_trials, tmp_path):
    """The same with multiple shooting (two segments of 0.5 s): killed after each checkpoint of
    its continuation levels and of the single-shooting stages, it ends with the same `fit.json`."""
    kw = {"shooting": "multiple", "segment": 0.5}
    events = []
    with checkpoint_hook(lambda ev, path: events.append(ev)):
        ref = run_fit(tiny_trials, tmp_path / "ref.npz", **kw)
    assert ref.shooting["method"] == "multiple" and ref.shooting["segments"] == 2
    ckpt = tmp_path / "fit.json.ckpt.npz"
    visited = []
    for _ in range(events.count("saved")):
        with checkpoint_hook(kill_at("saved", 1)), pytest.raises(KeyboardInterrupt):
            run_fit(tiny_trials, ckpt, **kw)
        with np.load(ckpt) as z:
            visited.append(int(z["stage"]))
    assert visited[0] == 4 and visited[-1] == 3 and {1, 2} <= set(visited)
    assert document(run_fit(tiny_trials, ckpt, **kw)) == document(ref)
