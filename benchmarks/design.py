"""Excitation design benchmark: `jsphere design --free 'r_m[2],j,I[2,2]' --duration 8 --kind K
--trials 2` end to end (a process of its own, cold compilation cache), then the design and its
baseline (random multisines of the same RMS amplitude) simulated on a robot 6-8 % away from the
design's, with capture noise, and fitted with `jsphere.fit`.

    python benchmarks/design.py                       # restarts 4, steps 60
    python benchmarks/design.py --steps 100 --out /tmp/design.json

Reports per free name the factor baseline SE / design SE, predicted (design.json) and fitted,
and writes `benchmarks/results-design.json` with machine information.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import jax
import jax.numpy as jnp

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
import jsphere
from jsphere.controls import Sampled, Torques

ROOT = Path(__file__).resolve().parents[1]
jsphere.enable_x64()  # float64, which jsphere's accuracy needs (JAX's default is float32)

FREE = "r_m[2],j,I[2,2]"
#: the "true" robot of the synthetic trials: the design's values times these factors
TRUTH = {"r_m[2]": 1.06, "j": 0.93, "I[2,2]": 1.08}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--duration", type=float, default=8.0)
    ap.add_argument("--trials", type=int, default=2)
    ap.add_argument("--restarts", type=int, default=4)
    ap.add_argument("--steps", type=int, default=60)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default=str(Path(__file__).with_name("results-design.json")))
    args = ap.parse_args(argv)
    work = Path(tempfile.mkdtemp(prefix="jsphere-design-"))
    out = work / "design.csv"
    cmd = [sys.executable, "-m", "jsphere.cli", "design", "--free", FREE, "--duration", str(args.duration)]
    cmd += ["--kind", "K", "--trials", str(args.trials), "--restarts", str(args.restarts), "--steps", str(args.steps)]
    cmd += [
        "--seed",
        str(args.seed),
        "--out",
        str(out),
        "--baseline-out",
        str(work / "baseline.csv"),
        "--no-cache",
        "-q",
    ]
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    t0 = time.perf_counter()
    subprocess.run(cmd, check=True, env=env)
    t_design = time.perf_counter() - t0
    doc = json.loads(out.with_suffix(".json").read_text())

    # the design's and the baseline's tables as written
    p = jsphere.RobotParams.paper()
    names = lambda stem: (
        [work / f"{stem}.csv"] if args.trials == 1 else [work / f"{stem}_{k + 1}.csv" for k in range(args.trials)]
    )
    design_tables = [jsphere.read_inputs_csv(q)[:2] for q in names("design")]
    baseline_tables = [jsphere.read_inputs_csv(q)[:2] for q in names("baseline")]
    truth = p
    for name, f in TRUTH.items():
        truth = jsphere.set_value(truth, name, jsphere.get_value(p, name) * f)
    fitted, t_fit = {}, {}
    for which, tables in (("design", design_tables), ("baseline", baseline_tables)):
        trials = [
            jsphere.synthetic_trial(
                truth,
                Torques(Sampled(jnp.asarray(t), jnp.asarray(u), "cubic")),
                args.duration,
                rate=100.0,
                pos_sd=1e-3,
                rot_sd_deg=0.5,
                seed=100 + k,
                name=f"{which}_{k + 1}",
            )
            for k, (t, u) in enumerate(tables)
        ]
        t0 = time.perf_counter()
        fr = jsphere.fit(trials, p, FREE, progress=False)
        t_fit[which] = time.perf_counter() - t0
        fitted[which] = {
            n: {"value": fr.values[n], "truth": float(jsphere.get_value(truth, n)), "stderr": fr.stderr[n]}
            for n in doc["free"]
        }
        fitted[which]["status"] = fr.status

    rows = [
        ("command", " ".join(["jsphere", *cmd[3:-6]])),
        ("design, end to end (cold) [s]", f"{t_design:.1f}"),
        ("fit of the design's trials [s]", f"{t_fit['design']:.1f}"),
        ("criterion design / baseline", f"{doc['criterion']['design']:.3f} / {doc['criterion']['baseline']:.3f}"),
    ]
    factors = {}
    for n in doc["free"]:
        pred = doc["stderr_predicted_baseline"][n] / doc["stderr_predicted"][n]
        fit = fitted["baseline"][n]["stderr"] / fitted["design"][n]["stderr"]
        factors[n] = {
            "predicted": pred,
            "fitted": fit,
            "se_design_predicted": doc["stderr_predicted"][n],
            "se_design_fitted": fitted["design"][n]["stderr"],
            "se_baseline_predicted": doc["stderr_predicted_baseline"][n],
            "se_baseline_fitted": fitted["baseline"][n]["stderr"],
        }
        rows.append(
            (
                f"{n}: SE design pred/fit, baseline pred/fit",
                f"{pred:.2f}x predicted, {fit:.2f}x fitted  ({doc['stderr_predicted'][n]:.3g} / "
                f"{fitted['design'][n]['stderr']:.3g}, {doc['stderr_predicted_baseline'][n]:.3g} / "
                f"{fitted['baseline'][n]['stderr']:.3g})",
            )
        )
    w = max(len(a) for a, _ in rows)
    for a, b in rows:
        print(f"{a.ljust(w)}  {b}")
    info = {
        "machine": {
            "platform": platform.platform(),
            "processor": platform.processor(),
            "cpu_count": os.cpu_count(),
            "jax": jax.__version__,
            "devices": [str(d) for d in jax.devices()],
            "python": platform.python_version(),
        },
        "command": cmd[3:],
        "design_end_to_end_s": t_design,
        "fit_s": t_fit,
        "criterion": doc["criterion"],
        "criterion_model": doc["criterion_model"],
        "rms": doc["rms"],
        "baseline_equal_rms": doc["baseline_equal_rms"],
        "limits": doc["limits"],
        "limits_baseline": doc["limits_baseline"],
        "truth_factors": TRUTH,
        "factor_baseline_over_design": factors,
        "fitted": fitted,
        "geometric_mean_factor": {
            k: math.exp(sum(math.log(v[k]) for v in factors.values()) / len(factors)) for k in ("predicted", "fitted")
        },
    }
    from jsphere._runtime.files import atomic_write_json

    atomic_write_json(args.out, info)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
