"""Studies: `jsphere.monte_carlo` throughput against a loop of `simulate_gaits` calls; with
`--workers K`, `jsphere montecarlo` in K `--worker` processes and `--gather`, alternating with one
process (one process, workers, one process). benchmarks/README.md says what each records.

    python benchmarks/studies.py [--trials 100000] [--cores N]
    python benchmarks/studies.py --workers 2 [--trials 1000000]
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import jax
import numpy as np
from common import cli_env, environment, parser, result_path, timed, write_json

import jsphere

jsphere.enable_x64()  # float64, which jsphere's accuracy needs (JAX's default is float32)


#: the study of the comparison of workers with one process, as a study file
STUDY = """trials = 1000
seed = 0
batch_size = {batch}
gaits = [{{kind = "acceleration"}}, {{kind = "braking"}}]
[vary]
"r_m[2]" = ["normal", -0.0270146, 1e-4]
"""


def _jsphere(*argv: str, env: dict) -> subprocess.Popen:
    cmd = [sys.executable, "-m", "jsphere.cli.app", "montecarlo", *argv, "--no-plots", "-q"]
    return subprocess.Popen(cmd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)


def _wait(*procs: subprocess.Popen) -> None:
    for p in procs:
        _, err = p.communicate()
        if p.returncode:
            raise SystemExit(f"jsphere montecarlo failed ({p.returncode}): {err}")


def workers_against_one_process(n: int, k: int, batch: int, out: str) -> None:
    """One process against `k` workers and a gather, on the same study of `n` trials."""
    tmp = Path(tempfile.mkdtemp(prefix="jsphere-mc-workers-"))
    env = cli_env(JSPHERE_CACHE_DIR=str(tmp / "cache"))
    study = tmp / "study.toml"
    study.write_text(STUDY.format(batch=batch))
    _wait(_jsphere(str(study), "--trials", str(batch), "--out", str(tmp / "warm"), env=env))  # fills the cache

    def one(name):
        return n / timed(lambda: _wait(_jsphere(str(study), "--trials", str(n), "--out", str(tmp / name), env=env)))[1]

    one_a = one("one-a")
    t = time.perf_counter()
    workers_argv = [str(study), "--trials", str(n), "--out", str(tmp / "workers")]
    _wait(*[_jsphere(*workers_argv, "--worker", env=env) for _ in range(k)])
    _wait(_jsphere(*workers_argv, "--gather", env=env))
    workers = n / (time.perf_counter() - t)
    one_b = one("one-b")
    same = (tmp / "workers" / "stats.json").read_bytes() == (tmp / "one-a" / "stats.json").read_bytes()
    shutil.rmtree(tmp)
    row = {
        **environment(),
        "trials": n,
        "batch_size": batch,
        "workers": k,
        "one_process_trials_per_s": [one_a, one_b],
        "workers_trials_per_s": workers,
        "ratio_workers_vs_one_process": workers / ((one_a + one_b) / 2),
        "stats_identical": same,
    }
    print(f"{'':34s}{'trials/s':>12s}")
    print(f"{'one process (before, after)':34s}{one_a:>12,.0f}{one_b:>12,.0f}")
    print(f"{f'{k} workers + gather':34s}{workers:>12,.0f}")
    print(f"ratio {row['ratio_workers_vs_one_process']:.2f}x; statistics identical: {same}; load {os.getloadavg()}")
    write_json(out, row)


def monte_carlo_against_a_loop(args) -> None:
    """`monte_carlo` of `args.trials` trials against a loop of `simulate_gaits` calls."""
    p = jsphere.RobotParams.paper()
    gaits = [jsphere.acceleration(), jsphere.braking()]
    vary = {"r_m[2]": ("normal", float(p.r_m[2]), 1e-4)}

    def study(n: int, seed: int):
        options = jsphere.StudyOptions(seed=seed, batch_size=args.batch_size)
        return jsphere.monte_carlo(p, gaits, vary=vary, n=n, options=options, progress=False)

    _, compile_and_one_batch = timed(study, args.batch_size, 1)
    res, mc_s = timed(study, args.trials, 0)

    ts = jax.numpy.array([4.0])
    zs = np.random.default_rng(0).normal(size=args.baseline_trials)
    jsphere.simulate_gaits(p.replace(R_m=0.027), gaits, ts=ts)  # compile
    t = time.perf_counter()
    for z in zs:
        jsphere.simulate_gaits(p.replace(R_m=0.0270146 + 1e-4 * z), gaits, ts=ts).x.block_until_ready()
    loop_rate = args.baseline_trials / (time.perf_counter() - t)

    rate = args.trials / mc_s
    row = {
        **environment(),
        "trials": args.trials,
        "batch_size": args.batch_size,
        "monte_carlo_s": mc_s,
        "monte_carlo_trials_per_s": rate,
        "first_call_incl_compile_s": compile_and_one_batch,
        "baseline_loop_trials_per_s": loop_rate,
        "ratio_vs_loop": rate / loop_rate,
        "stop_distance_sd_mm": 1e3 * res.stats()["distance_m"]["sd"],
    }
    print(f"{'':28s}{'trials':>10s}{'seconds':>10s}{'trials/s':>12s}")
    print(f"{'monte_carlo (gait mode)':28s}{args.trials:>10d}{mc_s:>10.1f}{rate:>12,.0f}")
    n = args.baseline_trials
    print(f"{'loop of simulate_gaits':28s}{n:>10d}{n / loop_rate:>10.1f}{loop_rate:>12,.0f}")
    print(
        f"ratio {rate / loop_rate:.1f}x; first call incl. compile {compile_and_one_batch:.1f} s; device {row['jax']['device_kind']} x {row['jax']['device_count']}"
    )
    write_json(args.out, row)


def main(argv=None) -> int:
    ap = parser("studies.py")
    ap.add_argument("--trials", type=int, default=100_000)
    ap.add_argument("--baseline-trials", type=int, default=200)
    ap.add_argument("--batch-size", type=int, default=8192)
    ap.add_argument("--workers", type=int, default=0, help="compare K --worker processes with one process")
    ap.add_argument("--out", default=None, help="JSON file (default: benchmarks/results-montecarlo[-workers].json)")
    ap.add_argument("--cores", type=int, help="CPU devices, one per core (default: every core; 1: JAX's single device)")
    args = ap.parse_args(argv)
    jsphere.use_cpu_cores(args.cores)  # before JAX's first operation: monte_carlo splits its batches over them
    if args.workers:
        args.out = result_path(args, "results-montecarlo-workers.json")
        workers_against_one_process(args.trials, args.workers, args.batch_size, args.out)
    else:
        args.out = result_path(args, "results-montecarlo.json")
        monte_carlo_against_a_loop(args)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
