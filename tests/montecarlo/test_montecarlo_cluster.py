"""Monte-Carlo beyond one process: workers sharing a folder through claim files, their gather,
JAX's multi-process runtime (two processes on this machine, CPU collectives), and the SLURM
scripts of examples/cluster/ run here with SLURM's variables set by hand."""

import json
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

import jsphere
from jsphere._runtime.errors import InputError
from jsphere.montecarlo import claims
from jsphere.montecarlo.workers import gather, work

ROOT = Path(__file__).resolve().parents[2]
CLUSTER = ROOT / "examples" / "cluster"
VARY = {"r_m[2]": ("normal", -0.0270146, 1e-4)}
GAITS = [jsphere.acceleration(), jsphere.braking()]
#: the study of `study`, as a study file
STUDY_TOML = (
    'trials = 256\nseed = 7\nbatch_size = 128\ngaits = [{kind = "acceleration"}, {kind = "braking"}]\n'
    '[vary]\n"r_m[2]" = ["normal", -0.0270146, 1e-4]\n'
)


@pytest.fixture(scope="module")
def study(paper):
    return jsphere.monte_carlo(
        paper, GAITS, vary=VARY, n=256, options=jsphere.StudyOptions(seed=7, batch_size=128), progress=False
    )


def _stats_file(out: Path) -> dict:
    """`stats.json` without what the command line adds to `MonteCarloResult.stats()`."""
    st = json.loads((out / "stats.json").read_text())
    st.pop("planned_stop_m")
    return st


# ---------------------------------------------------------------- claims and workers, in this process


def test_a_claim_is_exclusive_and_a_stale_one_is_taken_over(tmp_path):
    assert claims.try_claim(tmp_path, 3, timeout=60)
    mine = claims.read_claim(claims.claim_path(tmp_path, 3))
    assert (mine.host, mine.pid) == (socket.gethostname(), os.getpid()) and abs(mine.time - time.time()) < 5
    assert not claims.try_claim(tmp_path, 3, timeout=60)  # held, and fresh
    claims.release(tmp_path, 3)
    assert not claims.claim_path(tmp_path, 3).exists()
    # another worker's claim: kept while fresh, taken over once older than the timeout, never released by us
    other = claims.claim_path(tmp_path, 4)
    other.write_text(json.dumps({"host": "node7", "pid": 4242, "time": time.time() - 30}))
    assert not claims.try_claim(tmp_path, 4, timeout=60)
    claims.release(tmp_path, 4)
    assert claims.read_claim(other).host == "node7"
    assert claims.try_claim(tmp_path, 4, timeout=10)
    assert claims.read_claim(other).pid == os.getpid() and not list(tmp_path.glob(".*"))
    # a claim whose worker died before writing it dates from the file's time
    empty = claims.claim_path(tmp_path, 5)
    empty.write_text("")
    os.utime(empty, (time.time() - 100, time.time() - 100))
    assert claims.read_claim(empty).host == "?"
    assert not claims.try_claim(tmp_path, 5, timeout=1000) and claims.try_claim(tmp_path, 5, timeout=50)


def test_workers_skip_fresh_claims_take_over_stale_ones_and_gather_names_what_is_missing(paper, study, tmp_path):
    """Batch 0 is claimed by a dead worker (stale), batch 1 by a live one: a worker computes
    batch 0 and leaves batch 1; the gather names batch 1 and its claim; a later worker (a claim
    timeout of 0) takes batch 1 over; the gather's statistics are bitwise the one-process study's."""
    out = tmp_path / "study"
    kw = dict(vary=VARY, n=256, options=jsphere.StudyOptions(seed=7, batch_size=128), out=out, progress=False)
    out.mkdir()
    claims.claim_path(out, 0).write_text(json.dumps({"host": "dead", "pid": 1, "time": time.time() - 7200}))
    claims.claim_path(out, 1).write_text(json.dumps({"host": "busy", "pid": 2, "time": time.time()}))
    report = work(paper, GAITS, claim_timeout=3600, **kw)
    assert report.computed == (0,) and list(report.claimed) == [1] and (report.done, report.n_batches) == (1, 2)
    assert "claimed by other workers" in report.summary()
    with pytest.raises(
        InputError, match=r"1 of 2 batches missing: 1 \(1 claimed by busy:2, 0 s ago\); run more workers"
    ):
        gather(paper, GAITS, **{k: v for k, v in kw.items() if k != "progress"})
    again = work(paper, GAITS, claim_timeout=3600, **kw)
    assert again.computed == () and again.done == 1  # nothing it may take: it returns at once
    last = work(paper, GAITS, claim_timeout=0, **kw)
    assert last.computed == (1,) and last.done == 2 and "--gather" in last.summary()
    res = gather(paper, GAITS, **{k: v for k, v in kw.items() if k != "progress"})
    assert res.stats() == study.stats() and np.array_equal(res.x_final, study.x_final)
    assert json.loads((out / "stats.json").read_text()) == json.loads(json.dumps(study.stats()))
    assert sorted(f.name for f in out.iterdir()) == [
        "batch_000000.npz",
        "batch_000001.npz",
        "manifest.json",
        "stats.json",
        "time_000000.json",
        "time_000001.json",
    ]
    assert res.compute_time.recorded == 2 and res.compute_time.processes == 1 and res.compute_time.sum_s > 0
    with pytest.raises(InputError, match="no manifest.json"):
        gather(paper, GAITS, vary=VARY, n=256, seed=7, out=tmp_path / "empty")


def test_gather_reports_the_workers_recorded_compute_time_and_its_own_apart(tmp_path, capsys):
    """`--worker` records each batch's compute time beside it (time_*.json); `--gather` reports
    their sum as the study's time (here records as two workers on other hosts would leave them:
    300 s and 150 s, over 400 s of wall clock) and its own time on a line of its own. Without
    records it says so."""
    from jsphere.cli.app import main

    cfg = tmp_path / "study.toml"
    cfg.write_text(STUDY_TOML)
    out = tmp_path / "study"
    assert main(["montecarlo", str(cfg), "--out", str(out), "--worker", "-q"]) == 0
    capsys.readouterr()
    records = [json.loads((out / f"time_{k:06d}.json").read_text()) for k in range(2)]
    for k, r in enumerate(records):
        assert (r["batch"], r["trials"], r["pid"], r["host"]) == (k, 128, os.getpid(), socket.gethostname())
        assert 0 < r["compute_s"] == pytest.approx(r["end_unix_s"] - r["start_unix_s"], abs=1e-5)
        assert abs(r["end_unix_s"] - time.time()) < 600
    t0 = 1.7e9
    for k, (host, start, seconds) in enumerate([("node1", t0, 300.0), ("node2", t0 + 250.0, 150.0)]):
        rec = dict(records[k], host=host, pid=100 + k, start_unix_s=start, end_unix_s=start + seconds)
        (out / f"time_{k:06d}.json").write_text(json.dumps(rec | {"compute_s": seconds}))
    begin = time.perf_counter()
    assert main(["montecarlo", str(cfg), "--out", str(out), "--gather", "--no-plots", "-q"]) == 0
    took = time.perf_counter() - begin
    lines = capsys.readouterr().out.splitlines()
    assert lines[0] == "jsphere montecarlo: 256 trials in 450.0 s of the workers' compute: 256 ok, 0 rejected, 0 failed"
    assert lines[1] == "  2 batch(es) by 2 process(es), 400.0 s from the first batch's start to the last one's end"
    assert lines[2].startswith("  gathered in ") and float(lines[2].split()[2]) <= took
    (out / "time_000001.json").unlink()
    (out / "time_000000.json").write_text("{")  # unreadable: not counted
    assert main(["montecarlo", str(cfg), "--out", str(out), "--gather", "--no-plots", "-q"]) == 0
    first = capsys.readouterr().out.splitlines()[0]
    assert first == (
        "jsphere montecarlo: 256 trials (the batches' compute time is not recorded in the folder): "
        "256 ok, 0 rejected, 0 failed"
    )


def test_distributed_settings_are_checked(paper, tmp_path, capsys):
    """A distributed run's settings without `distributed`, and `distributed=True` in a process
    that has made JAX arrays before starting JAX's distributed runtime, are refused with what to
    do; so are the command line's conflicting or stray options."""
    from jsphere.cli.app import main

    with pytest.raises(InputError, match="coordinator, num_processes set up a distributed run; pass distributed=True"):
        jsphere.monte_carlo(paper, GAITS, vary=VARY, n=64, coordinator="127.0.0.1:1234", num_processes=2)
    with pytest.raises(
        InputError, match=r"starts only before JAX makes any array; call jax.distributed.initialize\(\)"
    ):
        jsphere.monte_carlo(paper, GAITS, vary=VARY, n=64, distributed=True)
    from jsphere.montecarlo import Distributed

    with pytest.raises(InputError, match=r"coordinator must be HOST:PORT \(of process 0\); got 'node7'"):
        jsphere.monte_carlo(paper, GAITS, vary=VARY, n=64, distributed=Distributed(coordinator="node7"))
    with pytest.raises(InputError, match=r"process_id must be below num_processes; got 2 of 2"):
        jsphere.monte_carlo(paper, GAITS, vary=VARY, n=64, distributed=Distributed(None, 2, 2))
    cfg = tmp_path / "study.toml"
    cfg.write_text(STUDY_TOML)
    assert main(["montecarlo", str(cfg), "--out", str(tmp_path / "o"), "--process-id", "1"]) == 2
    assert "--process-id set up a distributed run; add --distributed" in capsys.readouterr().err
    assert main(["montecarlo", str(cfg), "--out", str(tmp_path / "o"), "--worker", "--claim-timeout", "-1"]) == 2
    assert "--claim-timeout must be a finite number >= 0" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["montecarlo", str(cfg), "--worker", "--gather"])
    assert "not allowed with argument" in capsys.readouterr().err


# ---------------------------------------------------------------- the SLURM scripts


def test_cluster_scripts_are_valid_bash_and_run_the_documented_commands():
    scripts = sorted(p.name for p in CLUSTER.iterdir())
    assert scripts == ["distributed.sbatch", "gather.sbatch", "submit_array.sh", "worker_array.sbatch"]
    for name in scripts:
        subprocess.run(["bash", "-n", str(CLUSTER / name)], check=True)
        assert os.access(CLUSTER / name, os.X_OK), name
    text = {name: (CLUSTER / name).read_text() for name in scripts}
    assert "#SBATCH --array=0-99%10" in text["worker_array.sbatch"]
    assert 'jsphere montecarlo "$STUDY" --trials "$TRIALS" --out "$OUT" --worker' in text["worker_array.sbatch"]
    assert 'jsphere montecarlo "$STUDY" --trials "$TRIALS" --out "$OUT" --gather' in text["gather.sbatch"]
    assert (
        'srun jsphere montecarlo "$STUDY" --trials "$TRIALS" --out "$OUT" --distributed' in text["distributed.sbatch"]
    )


def _bin(tmp_path: Path) -> Path:
    """A folder of stand-ins for the cluster's commands: `jsphere` (this source tree), `srun`
    (runs its command as one task: the test starts the tasks) and `sbatch` (records its
    arguments, prints a job id)."""
    b = tmp_path / "bin"
    b.mkdir(exist_ok=True)
    tools = {
        "jsphere": f'#!/bin/sh\nexec "{sys.executable}" -m jsphere.cli.app "$@"\n',
        "srun": '#!/bin/sh\nexec "$@"\n',
        "sbatch": f'#!/bin/sh\necho "$@" >> "{tmp_path}/sbatch.log"\necho "$((4000 + $(wc -l < "{tmp_path}/sbatch.log")));cluster0"\n',
    }
    for name, text in tools.items():
        (b / name).write_text(text)
        (b / name).chmod(0o755)
    return b


def test_submit_array_submits_the_gather_after_the_workers(tmp_path):
    env = dict(os.environ, PATH=f"{_bin(tmp_path)}:{os.environ['PATH']}")
    done = subprocess.run(
        ["bash", str(CLUSTER / "submit_array.sh")], env=env, capture_output=True, text=True, check=True
    )
    calls = (tmp_path / "sbatch.log").read_text().splitlines()
    assert calls == [
        f"--parsable {CLUSTER}/worker_array.sbatch",
        f"--parsable --dependency=afterany:4001 {CLUSTER}/gather.sbatch",
    ]
    assert "workers: job 4001; gather: job 4002" in done.stdout


def _env(tmp_path: Path, **extra) -> dict:
    return dict(
        os.environ,
        PATH=f"{_bin(tmp_path)}:{os.environ['PATH']}",
        PYTHONPATH=str(ROOT),
        JAX_PLATFORMS="cpu",
        JSPHERE_CACHE_DIR=str(tmp_path / "cache"),
        **extra,
    )


@pytest.mark.slow
def test_array_job_workers_interleave_survive_a_kill_and_gather_bitwise(study, tmp_path):
    """examples/cluster/worker_array.sbatch run here as array tasks 0, 1, 2 at once (the
    batches interleave between them), task 1 killed with SIGKILL while it holds a claim, then
    task 3 (a claim timeout of 0 s: it takes the dead task's batch over), then gather.sbatch:
    the statistics are bitwise those of a single run. ~1-2 min on 2 cores."""
    (tmp_path / "study.toml").write_text(STUDY_TOML.replace("batch_size = 128", "batch_size = 64"))
    base = _env(tmp_path, STUDY=str(tmp_path / "study.toml"), OUT=str(tmp_path / "out"), TRIALS="256")
    base.update(SLURM_ARRAY_JOB_ID="4001", SLURM_JOB_ID="4001")

    def task(i: int, **extra) -> subprocess.Popen:
        env = dict(base, SLURM_ARRAY_TASK_ID=str(i), **extra)
        cmd = ["bash", str(CLUSTER / "worker_array.sbatch")]
        return subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, start_new_session=True)

    tasks = [task(i) for i in range(3)]
    out = tmp_path / "out"
    deadline = time.monotonic() + 600

    def held_by(proc) -> list[int]:
        pids = {
            int(p)
            for p in subprocess.run(["pgrep", "-g", str(proc.pid)], capture_output=True, text=True).stdout.split()
        }
        return [
            int(c.stem[6:])
            for c in out.glob("claim_*.json")
            if (cl := claims.read_claim(c)) is not None and cl.pid in pids
        ]

    while not held_by(tasks[1]) and tasks[1].poll() is None and time.monotonic() < deadline:
        time.sleep(0.01)
    lost = held_by(tasks[1])
    os.killpg(tasks[1].pid, signal.SIGKILL)
    tasks[1].wait()
    assert len(lost) == 1, "task 1 was killed while computing a batch"
    logs = [tasks[i].communicate(timeout=600)[0].decode() for i in (0, 2)]
    assert all(t.returncode == 0 for t in (tasks[0], tasks[2])), logs
    written = [{int(w) for w in _written(log)} for log in logs]
    assert written[0] and written[1], f"the batches interleave between the workers: {logs}"
    assert not (out / f"batch_{lost[0]:06d}.npz").exists() and claims.claim_path(out, lost[0]).exists()
    gathered = subprocess.run(["bash", str(CLUSTER / "gather.sbatch")], env=base, capture_output=True, text=True)
    assert gathered.returncode == 2 and f"1 of 4 batches missing: {lost[0]}" in gathered.stderr
    fourth = subprocess.run(
        ["bash", str(CLUSTER / "worker_array.sbatch")],
        env=dict(base, SLURM_ARRAY_TASK_ID="3", CLAIM_TIMEOUT="0"),
        capture_output=True,
        text=True,
    )
    assert fourth.returncode == 0 and _written(fourth.stderr) == [f"{lost[0]:06d}"], fourth.stderr
    assert "4 of 4 done" in fourth.stdout
    gathered = subprocess.run(["bash", str(CLUSTER / "gather.sbatch")], env=base, capture_output=True, text=True)
    assert gathered.returncode == 0, gathered.stderr
    assert _stats_file(out) == json.loads(json.dumps(study.stats()))
    assert (out / "stop_points.png").exists() and not list(out.glob("claim_*")) and not list(out.glob(".*"))


def _written(log: str) -> list[str]:
    """The batches a worker's messages say it wrote."""
    return [line.split("batch_")[1][:6] for line in log.splitlines() if " written (" in line]


def _free_port(low: int = 0) -> int:
    """A port that is free now: any, or the first from `low` on."""
    for port in [0] if low == 0 else range(low, 65536):
        with socket.socket() as s:
            try:
                s.bind(("127.0.0.1", port))
            except OSError:
                continue
            return s.getsockname()[1]
    raise RuntimeError(f"no free port above {low}")


def _two_processes(cmds: list[list[str]], envs: list[dict], timeout: float = 600) -> list[subprocess.CompletedProcess]:
    procs = [
        subprocess.Popen(c, env=e, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        for c, e in zip(cmds, envs)
    ]
    try:
        outs = [p.communicate(timeout=timeout) for p in procs]
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
                p.wait()
    return [subprocess.CompletedProcess(p.args, p.returncode, o, e) for p, (o, e) in zip(procs, outs)]


@pytest.mark.slow
def test_distributed_two_processes_with_cpu_collectives_match_one_process(study, tmp_path):
    """`jsphere montecarlo --distributed --coordinator 127.0.0.1:PORT --num-processes 2
    --process-id I`: two processes of 2 host devices each (a global mesh of 4 devices, CPU
    collectives through gloo); process 0 writes the batches and statistics, bitwise those of
    one process; a second run resumes from the batches (one deleted: only it is computed). A
    batch of 192 trials is computed as 256 (whole chunks of 64 on the 4 devices: the next
    trials' draws fill them and are dropped). ~1-2 min on 2 cores."""
    cfg = tmp_path / "study.toml"
    cfg.write_text(STUDY_TOML.replace("batch_size = 128", "batch_size = 192"))
    out = tmp_path / "out"
    env = _env(
        tmp_path,
        XLA_FLAGS="--xla_force_host_platform_device_count=2",
        JAX_CPU_COLLECTIVES_IMPLEMENTATION="gloo",
    )

    def run():
        port = _free_port()
        cmd = [sys.executable, "-m", "jsphere.cli.app", "montecarlo", str(cfg), "--out", str(out), "--no-plots"]
        cmd += ["--distributed", "--coordinator", f"127.0.0.1:{port}", "--num-processes", "2", "--process-id"]
        done = _two_processes([cmd + ["0"], cmd + ["1"]], [env, env])
        assert [d.returncode for d in done] == [0, 0], [d.stderr[-3000:] for d in done]
        return done

    done = run()
    assert "256 trials in" in done[0].stdout and "trials in" not in done[1].stdout  # process 0 reports
    assert _stats_file(out) == json.loads(json.dumps(study.stats()))
    files = [
        "batch_000000.npz",
        "batch_000001.npz",
        "manifest.json",
        "stats.json",
        "time_000000.json",
        "time_000001.json",
    ]
    assert sorted(f.name for f in out.iterdir()) == files
    assert json.loads((out / "manifest.json").read_text())["batch_size"] == 192
    first = (out / "batch_000000.npz").read_bytes()
    (out / "batch_000000.npz").write_bytes(b"")  # cut short: recomputed, with a warning on process 0
    done = run()
    assert "corrupt or incomplete" in done[0].stderr
    assert (out / "batch_000000.npz").read_bytes() == first
    assert _stats_file(out) == json.loads(json.dumps(study.stats()))


@pytest.mark.slow
def test_distributed_sbatch_script_runs_here_with_slurm_variables(study, tmp_path):
    """examples/cluster/distributed.sbatch as two SLURM tasks on this machine (SLURM's variables
    set by hand, `srun` a stand-in that runs one task): JAX finds the coordinator and the
    processes from them. ~1-2 min on 2 cores."""
    (tmp_path / "study.toml").write_text(STUDY_TOML.replace("batch_size = 128", "batch_size = 256"))
    job = str(_free_port(61440 + os.getpid() % 2048) - 61440)  # JAX's port under SLURM: 61440 + job id % 4096
    base = _env(
        tmp_path,
        STUDY=str(tmp_path / "study.toml"),
        OUT=str(tmp_path / "out"),
        TRIALS="256",
        XLA_FLAGS="--xla_force_host_platform_device_count=2",
        SLURM_JOB_ID=job,
        SLURM_STEP_NODELIST="127.0.0.1",
        SLURM_NTASKS="2",
        SLURM_JOB_NUM_NODES="1",
    )
    envs = [dict(base, SLURM_PROCID=str(i), SLURM_LOCALID=str(i)) for i in range(2)]
    done = _two_processes([["bash", str(CLUSTER / "distributed.sbatch")]] * 2, envs)
    assert [d.returncode for d in done] == [0, 0], [d.stderr[-3000:] for d in done]
    assert "2 processes" in done[0].stdout and "256 trials" in done[0].stdout
    assert _stats_file(tmp_path / "out") == json.loads(json.dumps(study.stats()))
