"""Start-up cost of the CLI: `jsphere reproduce --no-plots` in a fresh process: once with an
empty persistent compilation cache, then three times with the cache the first run filled
(the median is reported: single runs vary by ~1 s on a 2-core machine).

    python benchmarks/startup.py [--out benchmarks/results-startup.json]

Each run is a new Python process (`python -m jsphere.cli reproduce --no-plots`), timed from the
outside (interpreter start, imports, tracing, compilation or cache loads, the solves). A last
run with `--no-cache` shows what the cache saves. Issue 6 targets: first run < 20 s, second < 5 s.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent


def run_once(cache_dir: str, out_dir: str, *extra: str) -> float:
    env = dict(os.environ, JSPHERE_CACHE_DIR=cache_dir, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    cmd = [sys.executable, "-m", "jsphere.cli", "reproduce", "--no-plots", "--out", out_dir, *extra]
    t = time.perf_counter()
    subprocess.run(cmd, env=env, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    return time.perf_counter() - t


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, default=HERE / "results-startup.json")
    args = ap.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        cache, out = os.path.join(tmp, "cache"), os.path.join(tmp, "out")
        first = run_once(cache, out)
        seconds = [run_once(cache, out) for _ in range(3)]
        second = sorted(seconds)[1]
        no_cache = run_once(cache, out, "--no-cache")
        size = sum(f.stat().st_size for f in Path(cache).rglob("*") if f.is_file())
    res = {
        "command": "python -m jsphere.cli reproduce --no-plots",
        "first_process_s": first,
        "second_process_s": second,
        "second_process_runs_s": seconds,
        "no_cache_process_s": no_cache,
        "cache_bytes": size,
        "cpu_count": os.cpu_count(),
        "loadavg": list(os.getloadavg()) if hasattr(os, "getloadavg") else None,
        "targets": {"first_s": 20.0, "second_s": 5.0},
    }
    print(f"jsphere reproduce: first process {first:.1f} s (empty cache), second {second:.1f} s (cache, {size / 1e6:.1f} MB), "
          f"without cache {no_cache:.1f} s; targets 20 s / 5 s")  # fmt: skip
    tmpf = args.out.with_suffix(".tmp")
    tmpf.write_text(json.dumps(res, indent=2) + "\n")
    tmpf.replace(args.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
