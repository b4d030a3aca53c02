"""Monte-Carlo throughput: 10^5 trials of the paper's 4 s straight-line manoeuvre.

    python benchmarks/montecarlo.py [--trials 100000] [--out benchmarks/results-montecarlo.json]

Measures, in one run, the same study through `jsphere.monte_carlo` (gait mode, trials in
vmapped chunks, sharded over local devices) and, as the baseline, a plain loop of
`jsphere.simulate_gaits` calls on the same robot (one trial at a time, compiled once), and
reports the ratio. Writes JSON with the machine, device and versions.
"""

import argparse
import json
import os
import platform
import time

import jax
import numpy as np

import jsphere
from jsphere._runtime.files import atomic_write_text

jsphere.enable_x64()  # float64, which jsphere's accuracy needs (JAX's default is float32)

ap = argparse.ArgumentParser()
ap.add_argument("--trials", type=int, default=100_000)
ap.add_argument("--baseline-trials", type=int, default=200)
ap.add_argument("--batch-size", type=int, default=8192)
ap.add_argument("--out", default=os.path.join(os.path.dirname(__file__), "results-montecarlo.json"))
args = ap.parse_args()

p = jsphere.RobotParams.paper()
gaits = [jsphere.acceleration(), jsphere.braking()]
vary = {"r_m[2]": ("normal", float(p.r_m[2]), 1e-4)}

t = time.perf_counter()
jsphere.monte_carlo(p, gaits, vary=vary, n=args.batch_size, seed=1, batch_size=args.batch_size, progress=False)
compile_and_one_batch = time.perf_counter() - t
t = time.perf_counter()
res = jsphere.monte_carlo(p, gaits, vary=vary, n=args.trials, seed=0, batch_size=args.batch_size, progress=False)
mc_s = time.perf_counter() - t

ts = jax.numpy.array([4.0])
zs = np.random.default_rng(0).normal(size=args.baseline_trials)
jsphere.simulate_gaits(p.replace(R_m=0.027), gaits, ts=ts)  # compile
t = time.perf_counter()
for z in zs:
    jsphere.simulate_gaits(p.replace(R_m=0.0270146 + 1e-4 * z), gaits, ts=ts).x.block_until_ready()
loop_rate = args.baseline_trials / (time.perf_counter() - t)

rate = args.trials / mc_s
row = {
    "date_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
    "machine": {"platform": platform.platform(), "cpu_count": os.cpu_count(), "loadavg": os.getloadavg()},
    "device": {"backend": jax.default_backend(), "kind": jax.devices()[0].device_kind, "count": jax.device_count()},
    "versions": {"jax": jax.__version__, "jsphere": jsphere.__version__, "numpy": np.__version__},
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
print(
    f"{'loop of simulate_gaits':28s}{args.baseline_trials:>10d}{args.baseline_trials / loop_rate:>10.1f}{loop_rate:>12,.0f}"
)
print(f"ratio {rate / loop_rate:.1f}x; first call incl. compile {compile_and_one_batch:.1f} s; device {row['device']}")
atomic_write_text(args.out, json.dumps(row, indent=2) + "\n")
