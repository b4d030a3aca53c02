"""Start-up cost of the CLI: `jsphere reproduce` in fresh processes, first with an empty
persistent compilation cache, then three times with the cache the first run filled (the
median is reported: single runs vary by ~1 s on a 2-core machine).

    python benchmarks/startup.py [--out benchmarks/results-startup.json]

Each run is a new Python process (`python -m jsphere.cli.app reproduce ...`), timed from the
outside (interpreter start, imports, tracing, compilation or cache loads, the solves, the
figures). Measured in the same run, each with its own empty cache:
- `default`: the README's command (figures included);
- `optimize`: the same with `--optimize` (XLA's backend optimisation left on: the baseline
  for the quick compilation `reproduce` uses by default);
- `no-plots`: without the figures;
and a last run with `--no-cache` (what the cache saves). The numbers and the bounds they are
held to are in docs/performance.md.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Callable

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
CONFIGS = {"default": [], "optimize": ["--optimize"], "no-plots": ["--no-plots"]}


def run_once(cache_dir: str, argv: list[str]) -> float:
    """Seconds of one `jsphere` process (`python -m jsphere.cli.app *argv`) with the cache in
    `cache_dir`, timed from the outside."""
    env = dict(
        os.environ, JSPHERE_CACHE_DIR=cache_dir, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", "")
    )
    env.pop("XLA_FLAGS", None)
    cmd = [sys.executable, "-m", "jsphere.cli.app", *argv]
    t = time.perf_counter()
    subprocess.run(cmd, env=env, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    return time.perf_counter() - t


def reproduce_argv(tmp: str, name: str, extra: list[str]) -> list[str]:
    """`jsphere reproduce` of configuration `name` (its options `extra`), writing into `tmp`."""
    return ["reproduce", "--out", os.path.join(tmp, f"out-{name}"), *extra]


def measure(tmp: str, name: str, extra: list[str], cached_runs: int = 3, command: Callable = reproduce_argv) -> dict:
    """A first process of `command(tmp, name, extra)` (its arguments) with an empty cache in
    `tmp`, then `cached_runs` processes reusing it (their median is `second_process_s`)."""
    cache, argv = os.path.join(tmp, f"cache-{name}"), command(tmp, name, extra)
    first = run_once(cache, argv)
    seconds = [run_once(cache, argv) for _ in range(cached_runs)]
    size = sum(f.stat().st_size for f in Path(cache).rglob("*") if f.is_file())
    return {
        "args": extra,
        "first_process_s": first,
        "second_process_s": sorted(seconds)[len(seconds) // 2],
        "second_process_runs_s": seconds,
        "cache_bytes": size,
    }


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, default=HERE / "results-startup.json")
    args = ap.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        runs = {}
        for name, extra in CONFIGS.items():
            runs[name] = measure(tmp, name, extra)
            r = runs[name]
            print(f"  {name:<9} first {r['first_process_s']:5.1f} s, second {r['second_process_s']:4.1f} s", flush=True)
        no_cache = run_once(os.path.join(tmp, "unused"), reproduce_argv(tmp, "no-cache", ["--no-cache"]))
    d, b = runs["default"], runs["optimize"]
    res = {
        "command": "python -m jsphere.cli.app reproduce",
        "runs": runs,
        "no_cache_process_s": no_cache,
        "first_default_over_optimize": d["first_process_s"] / b["first_process_s"],
        "second_default_over_optimize": d["second_process_s"] / b["second_process_s"],
        "cpu_count": os.cpu_count(),
        "machine": platform.machine(),
        "python": platform.python_version(),
        "loadavg": list(os.getloadavg()) if hasattr(os, "getloadavg") else None,
        "targets": {"first_s": 20.0, "second_s": 5.0},
    }
    print(
        f"jsphere reproduce: first process {d['first_process_s']:.1f} s (empty cache), second {d['second_process_s']:.1f} s; "
        f"with --optimize {b['first_process_s']:.1f} / {b['second_process_s']:.1f} s "
        f"(ratios {res['first_default_over_optimize']:.2f} / {res['second_default_over_optimize']:.2f}); "
        f"without cache {no_cache:.1f} s"
    )
    tmpf = args.out.with_suffix(".tmp")
    tmpf.write_text(json.dumps(res, indent=2) + "\n")
    tmpf.replace(args.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
