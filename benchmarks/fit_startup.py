"""Start-up cost of a fit on the command line: `jsphere fit` of five 6 s torque trials (seven
free parameters, 2 starts) in fresh processes, as a user runs it again and again while tuning
an experiment.

    python benchmarks/fit_startup.py [--out benchmarks/results-fit-startup.json]

The trials are `jsphere synth`'s (100 Hz, 1 mm and 0.5 deg of noise, 2 % lost frames) of
`benchmarks/fit.py`'s truth. Each run is a new process timed from the outside
(`benchmarks/startup.py`): first with an empty cache, then twice with the cache the first run
filled (JAX's executables and the fit's programs exported by `jsphere.FastStart`; the median is
reported), and once with `--no-cache` (every process compiles everything: the same-run
baseline). Every run's fitted values must be the same to the last digit. The numbers and the
target they are held to are in docs/performance.md.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # this checkout's jsphere first

from fit import TRUTH, metadata  # noqa: E402
from startup import ROOT, measure, run_once  # noqa: E402

HERE = Path(__file__).resolve().parent
FREE = "R_m,j,I[0,0],I[1,1],I[2,2],m0,I0"
TARGET_SECOND_S = 15.0


def fit_argv(tmp: str, name: str, extra: list[str]) -> list[str]:
    """`jsphere fit` of the trials in `tmp/trials`, its result in `tmp/fit-<name>.json`."""
    out = os.path.join(tmp, f"fit-{name}.json")
    return ["fit", os.path.join(tmp, "trials"), "--free", FREE, "--out", out, "--no-plots", "--quiet", *extra]


def make_trials(tmp: str) -> None:
    """Five synthetic 6 s torque trials of the truth in `tmp/trials` (`jsphere synth`)."""
    import jsphere

    jsphere.RobotParams.paper().replace(**TRUTH).save(os.path.join(tmp, "truth.toml"))
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    synth = ["synth", "--out", os.path.join(tmp, "trials"), "--trials", "5", "--kind", "torques"]
    synth += ["--duration", "6", "--params", os.path.join(tmp, "truth.toml"), "--no-cache", "--quiet"]
    subprocess.run([sys.executable, "-m", "jsphere.cli.app", *synth], env=env, check=True, stdout=subprocess.DEVNULL)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, default=HERE / "results-fit-startup.json")
    ap.add_argument("--cached-runs", type=int, default=2, help="processes reusing the cache")
    args = ap.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        make_trials(tmp)
        cached = measure(tmp, "cached", [], cached_runs=args.cached_runs, command=fit_argv)
        values = {"cached": json.loads(Path(tmp, "fit-cached.json").read_text())["values"]}
        no_cache = run_once(os.path.join(tmp, "unused"), fit_argv(tmp, "no-cache", ["--no-cache"]))
        values["no_cache"] = json.loads(Path(tmp, "fit-no-cache.json").read_text())["values"]
    same = values["cached"] == values["no_cache"]
    res = {
        **metadata(),
        "command": "python -m jsphere.cli.app " + " ".join(fit_argv("TMP", "cached", [])),
        "cached": cached,
        "first_process_s": cached["first_process_s"],
        "second_process_s": cached["second_process_s"],
        "no_cache_process_s": no_cache,
        "second_over_no_cache": cached["second_process_s"] / no_cache,
        "values": values["cached"],
        "same_values": same,
        "python": platform.python_version(),
        "targets": {"second_process_s": TARGET_SECOND_S},
    }
    print(f"{'jsphere fit, 5 x 6 s torque trials':<36} {'seconds':>8}")
    print(f"{'first process, empty cache':<36} {cached['first_process_s']:8.1f}")
    print(f"{'next processes, cache filled':<36} {cached['second_process_s']:8.1f}")
    print(f"{'a process without cache':<36} {no_cache:8.1f}")
    print(f"next / without cache: {res['second_over_no_cache']:.2f}; the same values in every run: {same}")
    tmpf = args.out.with_suffix(".tmp")
    tmpf.write_text(json.dumps(res, indent=2) + "\n")
    tmpf.replace(args.out)
    return 0 if same else 1


if __name__ == "__main__":
    raise SystemExit(main())
