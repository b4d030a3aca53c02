"""The robust fit on a glitchy capture against the same fit on the clean capture, in the same run.

    python benchmarks/robust_fit.py                        # cauchy (default), huber and l2 on the glitchy capture
    python benchmarks/robust_fit.py --losses cauchy        # the time ratio alone
    python benchmarks/robust_fit.py --long                 # a long capture: Cauchy from Huber's point or in every stage

Five 6 s torque trials at 100 Hz (1 mm and 0.5 deg noise) of a robot 5-20 % away from the
paper's (`fit_length.truth`), fitted from the paper's values with seven free parameters
(`r_m[2], j, I[0,0], I[1,1], I[2,2], m0, I0`) and `fit`'s defaults (two starts, multiple
shooting then single). The glitchy capture is the same with `add_glitches` (about 1 % ghost
frames 1-5 cm off, two marker-swap bursts of 5-15 frames per trial, 30-90 deg off). The first
fit (clean, default loss) compiles; the clean fit is then timed again, compiled, and the
glitchy fits after it, so that the ratio glitchy / clean compares optimisations, not
compilations. Per fit: wall time, iterations, the largest error in standard errors, the noise
levels, the share of injected bad frames set aside and the clean frames set aside; last the
clean capture with `l2`, against which the robust fit of the clean capture is compared (values
in standard errors, standard errors as ratios). Writes JSON (`--out`).

`--long`: three 15 s trials and one 30 s trial of the same robot (clean), fitted with the
default loss as the fit runs it (Huber's loss in the warm-up stages, multiple shooting and the
Adam steps, Cauchy's in the Levenberg-Marquardt stages: `jsphere.identify.robust.WARM_LOSS`) and with Cauchy's in every stage, in the same process
(`results-robust-fit-long.json`).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # this checkout's jsphere first

import jsphere
from jsphere._runtime.files import atomic_write_text
from jsphere.capture.synthetic import add_glitches

jsphere.enable_x64()

sys.path.insert(0, str(Path(__file__).resolve().parent))
from fit import metadata  # noqa: E402
from fit_length import FREE, trials, truth  # noqa: E402


def glitchy(clean, seed: int):
    out, bad = [], {}
    for i, t in enumerate(clean):
        g, rows = add_glitches(t, seed=seed * 100 + i)
        out.append(g)
        bad[g.name] = set(rows.tolist())
    return out, bad


def one(robot, tr, bad, loss):
    t = time.perf_counter()
    res = jsphere.fit(tr, jsphere.RobotParams.paper(), FREE, loss=loss, progress=False)
    wall = time.perf_counter() - t
    z = [abs((res.values[k] - float(jsphere.get_value(robot, k))) / res.stderr[k]) for k in res.free]
    named = {k: set(v["frames"]) for k, v in res.outliers.items()}
    injected = sum(len(b) for b in bad.values())
    return {
        "loss": loss,
        "wall_s": wall,
        "iterations": res.iterations,
        "max_error_se": float(max(z)),
        "status": res.status,
        "sigma_pos_mm": res.sigma_pos * 1e3,
        "sigma_rot_deg": math.degrees(res.sigma_rot),
        "injected": injected,
        "named_share": sum(len(bad.get(k, set()) & v) for k, v in named.items()) / injected if injected else None,
        "clean_frames_set_aside": sum(len(v - bad.get(k, set())) for k, v in named.items()),
        "values": {k: res.values[k] for k in res.free},
        "stderr": {k: res.stderr[k] for k in res.free},
    }


def long_capture(out: str) -> None:
    """`--long` (module docstring)."""
    from jsphere.identify import fit as fit_module

    robot = truth()
    tr = []
    for i, length in enumerate((15.0, 15.0, 15.0, 30.0)):
        u = jsphere.random_inputs(robot, length, kind="torques", f_min=0.3, f_max=0.7, seed=i)
        tr.append(jsphere.synthetic_trial(robot, u, length, rate=100.0, seed=i, name=f"t{i}"))
    rows = []
    for how, redescending in (("huber, then cauchy", fit_module.REDESCENDING), ("cauchy in every stage", ())):
        print(f"long capture, {how} ...", file=sys.stderr, flush=True)
        fit_module.REDESCENDING = redescending  # () : no warm stage, the fit's loss in every stage
        try:
            rows.append({"stages": how} | one(robot, tr, {}, "cauchy"))
        finally:
            fit_module.REDESCENDING = ("cauchy",)
    head = f"{'stages':<22} {'wall s':>7} {'iters':>6} {'max|z|':>7} {'sigma mm':>8} {'set aside':>9}  status"
    print(head)
    print("-" * len(head))
    for r in rows:
        print(
            f"{r['stages']:<22} {r['wall_s']:>7.1f} {r['iterations']:>6d} {r['max_error_se']:>7.2f} "
            f"{r['sigma_pos_mm']:>8.3f} {r['clean_frames_set_aside']:>9d}  {r['status']}"
        )
    doc = {**metadata(), "config": {"free": FREE, "lengths_s": [15, 15, 15, 30], "rate_hz": 100.0}, "rows": rows}
    atomic_write_text(out, json.dumps(doc, indent=2) + "\n")
    print(f"wrote {out}")


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument(
        "--losses", nargs="+", default=["cauchy", "huber", "l2"], help="losses fitted to the glitchy capture"
    )
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--long", action="store_true", help="the long capture: Cauchy from Huber's point or in every stage")
    ap.add_argument(
        "--out", help="result JSON (default results-robust-fit.json, with --long results-robust-fit-long.json)"
    )
    args = ap.parse_args()
    here = os.path.dirname(__file__)
    if args.long:
        long_capture(args.out or os.path.join(here, "results-robust-fit-long.json"))
        return
    args.out = args.out or os.path.join(here, "results-robust-fit.json")
    robot = truth()
    clean = trials(robot, 5, 6.0, args.seed)
    dirty, bad = glitchy(clean, args.seed)
    print("clean capture, cauchy (compiles) ...", file=sys.stderr, flush=True)
    first = one(robot, clean, {}, "cauchy")
    rows = []
    print("clean capture, cauchy, compiled ...", file=sys.stderr, flush=True)
    rows.append({"capture": "clean"} | one(robot, clean, {}, "cauchy"))
    for loss in args.losses:
        print(f"glitchy capture, {loss} ...", file=sys.stderr, flush=True)
        rows.append({"capture": "glitchy"} | one(robot, dirty, bad, loss))
    print("clean capture, l2 ...", file=sys.stderr, flush=True)
    l2 = one(robot, clean, {}, "l2")
    rows.append({"capture": "clean"} | l2)
    rob = rows[0]
    # no cost on clean data: the robust fit against least squares, in the latter's standard errors
    clean_vs_l2 = {
        "max_value_difference_se": max(abs(rob["values"][k] - l2["values"][k]) / l2["stderr"][k] for k in l2["values"]),
        "stderr_ratio_range": [
            min(rob["stderr"][k] / l2["stderr"][k] for k in l2["values"]),
            max(rob["stderr"][k] / l2["stderr"][k] for k in l2["values"]),
        ],
    }
    base = rows[0]["wall_s"]
    head = f"{'capture':<8} {'loss':<8} {'wall s':>7} {'x clean':>8} {'iters':>6} {'max|z|':>7} {'sigma mm':>8} {'sigma deg':>9} {'named':>6} {'clean out':>9}  status"
    print(head)
    print("-" * len(head))
    for r in rows:
        named = "" if r["named_share"] is None else f"{r['named_share']:.0%}"
        print(
            f"{r['capture']:<8} {r['loss']:<8} {r['wall_s']:>7.1f} {r['wall_s'] / base:>8.2f} {r['iterations']:>6d} "
            f"{r['max_error_se']:>7.2f} {r['sigma_pos_mm']:>8.3f} {r['sigma_rot_deg']:>9.3f} {named:>6} "
            f"{r['clean_frames_set_aside']:>9d}  {r['status']}"
        )
    print(
        f"clean capture, cauchy against l2: values within {clean_vs_l2['max_value_difference_se']:.3f} SE, standard errors "
        f"x{clean_vs_l2['stderr_ratio_range'][0]:.3f} to x{clean_vs_l2['stderr_ratio_range'][1]:.3f}"
    )
    doc = {
        **metadata(),
        "config": {"free": FREE, "trials": 5, "length_s": 6.0, "rate_hz": 100.0, "seed": args.seed},
        "first_fit_with_compilation": first,
        "rows": rows,
        "ratio_glitchy_to_clean": {r["loss"]: r["wall_s"] / base for r in rows[1:] if r["capture"] == "glitchy"},
        "clean_cauchy_against_l2": clean_vs_l2,
    }
    atomic_write_text(args.out, json.dumps(doc, indent=2) + "\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
