"""Regenerate the small synthetic capture dataset in `examples/data/` (deterministic).

    python examples/make_capture_data.py [--out examples/data]

(About 250 kB in all; identical bytes on every run with the same jax/numpy versions.)

Writes, from a *perturbed* version of the paper's robot (its true parameters in `truth.toml`):
- `ws_01.csv .. ws_03.csv`: wheel-speed trials, 5 s at 100 Hz, 1 mm / 0.5 deg noise, 2% gaps;
- `tq_01.csv, tq_02.csv`: torque trials, 3 s;
- `raw/motive.csv` + `raw/vicon.csv` (1.5 s, four markers on the platform, 0.2 mm noise, 2% of
  markers missing; Motive-style in mm and Y-up, Vicon-style in mm and Z-up) and their inputs
  table `raw/inputs.csv`; `raw/body_markers.csv` gives the markers' platform coordinates.
  `jsphere convert examples/data/raw/vicon.csv --format vicon --inputs examples/data/raw/inputs.csv
  --out trial.csv` turns either into a trial (see docs/capture.md).

The trial CSVs sit alone in `examples/data/`, so `jsphere.read_trials(["examples/data"])` reads
exactly them.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

import jsphere
from jsphere._runtime.files import atomic_write_text
from jsphere.capture.synthetic import default_marker_set

jsphere.enable_x64()  # float64, which jsphere's accuracy needs (JAX's default is float32)

HERE = Path(__file__).resolve().parent


def perturbed_params() -> jsphere.RobotParams:
    """The paper's robot with a heavier, lower platform, more wheel inertia and some rolling
    resistance: what a fit should recover."""
    p = jsphere.RobotParams.paper()
    return p.replace(
        R_m=0.030,
        j=3.2e-4,
        m=2.6,
        I=np.diag([0.0172, 0.0168, 0.0241]),
        c_roll=2e-3,
    )


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default=str(HERE / "data"))
    args = ap.parse_args(argv)
    out = Path(args.out)
    p = perturbed_params()
    p.save(out / "truth.toml")
    written = [out / "truth.toml"]
    for i, seed in enumerate((11, 12, 13)):
        c = jsphere.random_inputs(p, 5.0, kind="wheel_speeds", seed=seed)
        tr = jsphere.synthetic_trial(p, c, 5.0, dropout=0.02, seed=seed, name=f"ws_{i + 1:02d}")
        jsphere.write_trial(out / f"{tr.name}.csv", tr)
        written.append(out / f"{tr.name}.csv")
    for i, seed in enumerate((21, 22)):
        c = jsphere.random_inputs(p, 3.0, kind="torques", seed=seed)
        tr = jsphere.synthetic_trial(p, c, 3.0, dropout=0.02, seed=seed, name=f"tq_{i + 1:02d}")
        jsphere.write_trial(out / f"{tr.name}.csv", tr)
        written.append(out / f"{tr.name}.csv")
    # raw marker exports of one short wheel-speed trial
    c = jsphere.random_inputs(p, 1.5, kind="wheel_speeds", seed=31)
    truth = jsphere.synthetic_trial(p, c, 1.5, pos_sd=0.0, rot_sd_deg=0.0, seed=31, name="raw")
    body = default_marker_set(float(p.R0))
    names = ["m1", "m2", "m3", "m4"]
    m = jsphere.synthetic_markers(truth, body, z=float(p.R0), marker_sd=2e-4, dropout=0.02, seed=31)
    raw = out / "raw"
    jsphere.write_motive_csv(raw / "motive.csv", truth.t, m, names, units="mm", up_axis="y")
    jsphere.write_vicon_csv(raw / "vicon.csv", truth.t, m, names, units="mm")
    jsphere.write_inputs_csv(raw / "inputs.csv", truth.t, truth.inputs, truth.kind)
    atomic_write_text(
        raw / "body_markers.csv",
        "# marker coordinates in the platform frame, relative to the shell centre [m]\nname,x,y,z\n"
        + "".join(f"{n},{b[0]:.6f},{b[1]:.6f},{b[2]:.6f}\n" for n, b in zip(names, body)),
    )
    written += [raw / f for f in ("motive.csv", "vicon.csv", "inputs.csv", "body_markers.csv")]
    total = sum(f.stat().st_size for f in written)
    for f in written:
        print(f"{f}  {f.stat().st_size / 1024:.1f} kB")
    print(f"total {total / 1024:.1f} kB")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
