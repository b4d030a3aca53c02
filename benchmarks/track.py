"""Tracking benchmark: the gains along a plan and the plan replayed open and closed loop on
drawn robots (`jsphere.track`), against the open-loop wheel-speed replay of the robust planner
(`miss_distribution`) on the same draws.

    python benchmarks/track.py                    # plan to (0.4, 0.2) m, 1000 draws
    python benchmarks/track.py --samples 4000 --out /tmp/results-track.json

Prints a table and writes `benchmarks/results-track.json` with machine information: the miss
(mean, p95) of both loops and their ratio, the largest torque, and the time of each stage,
first call (with compilation) and second call.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path

import jax
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
import jsphere
from jsphere.planning.tracking.track import default_uncertainty, evaluate, gains

jsphere.enable_x64()


def main(argv=None) -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--to", nargs=2, type=float, default=(0.4, 0.2))
    ap.add_argument("--samples", type=int, default=1000)
    ap.add_argument("--rate", type=float, default=100.0)
    ap.add_argument("--restarts", type=int, default=16, help="as `jsphere plan`")
    ap.add_argument("--out", default=str(Path(__file__).with_name("results-track.json")))
    args = ap.parse_args(argv)
    p = jsphere.RobotParams.paper()
    t0 = time.perf_counter()
    pl = jsphere.plan(p, tuple(args.to), restarts=args.restarts)
    t_plan = time.perf_counter() - t0
    tr = pl.trajectory
    ts, K = np.asarray(tr.ts), np.asarray(tr.K)
    keep = np.concatenate([np.diff(ts) > 0, [True]])
    times = {}
    for run in ("first", "second"):
        t0 = time.perf_counter()
        fields = gains(ts[keep], K[keep], p, rate=args.rate, weights=jsphere.TrackWeights(), target=pl.target[:2])
        times[f"gains_{run}_s"] = time.perf_counter() - t0
    tracker = jsphere.Tracker(**fields)
    unc = default_uncertainty(p)
    _, drawn = unc.draw(p, args.samples, 0)
    for run, seed in (("first", 0), ("second", 1)):
        t0 = time.perf_counter()
        mc = evaluate(tracker, drawn, seed=seed, source=unc.source)
        times[f"evaluation_{run}_s"] = time.perf_counter() - t0
        if run == "first":
            miss_mc = mc
    for run in ("first", "second"):
        t0 = time.perf_counter()
        ws = jsphere.miss_distribution(pl, drawn)
        times[f"wheel_speed_replay_{run}_s"] = time.perf_counter() - t0
    o, c = miss_mc["open_loop"], miss_mc["closed_loop"]
    rows = [
        ("open loop (torques)", o["mean"], o["p95"], o["speed_p95"], o["max_torque_N_m"]),
        ("closed loop", c["mean"], c["p95"], c["speed_p95"], c["max_torque_N_m"]),
        (
            "open loop (wheel speeds, exact)",
            float(np.mean(ws["miss_m"])),
            float(np.percentile(ws["miss_m"], 95)),
            float(np.percentile(ws["speed_m_s"], 95)),
            float("nan"),
        ),
    ]
    print(
        f"plan to {tuple(args.to)} m: T = {pl.duration:.3f} s, planned in {t_plan:.1f} s; {args.samples} draws "
        f"({unc.source}); rate {args.rate:g} Hz"
    )
    print(f"{'loop':<34}{'miss mean [mm]':>16}{'p95 [mm]':>10}{'speed p95 [mm/s]':>18}{'max |K| [N m]':>15}")
    for name, m, p95, v, u in rows:
        print(f"{name:<34}{1e3 * m:>16.3f}{1e3 * p95:>10.3f}{1e3 * v:>18.3f}{u:>15.4f}")
    ratio = {"mean": o["mean"] / c["mean"], "p95": o["p95"] / c["p95"]}
    print(f"open / closed loop miss: mean {ratio['mean']:.1f}x, p95 {ratio['p95']:.1f}x")
    for k, v in times.items():
        print(f"  {k:<30}{v:>8.2f} s")
    per_draw = times["evaluation_second_s"] / (2 * args.samples)
    print(f"  one draw, one loop ({len(tracker.ts)} rows + settling): {1e3 * per_draw:.3f} ms")
    out = {
        "to": list(args.to),
        "samples": args.samples,
        "rate_hz": args.rate,
        "duration_s": pl.duration,
        "plan_s": t_plan,
        "miss_mc": miss_mc,
        "wheel_speed_open_loop": {"mean": rows[2][1], "p95": rows[2][2], "speed_p95": rows[2][3]},
        "ratio_open_over_closed": ratio,
        "times_s": times,
        "machine": {
            "platform": platform.platform(),
            "cpus": os.cpu_count(),
            "jax": jax.__version__,
            "devices": [str(d) for d in jax.devices()],
        },
    }
    Path(args.out).write_text(json.dumps(out, indent=2) + "\n")
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
