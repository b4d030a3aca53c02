"""Section 5.2 as a Monte-Carlo study: where do 10^5 robots stop after the straight-line gaits?

Each trial draws the centre-of-mass offset, the wheels' inertia and the shell's mass, then
either executes the gaits exactly (the paper's model, `--mode gait`) or replays the torques
planned for the nominal robot through imperfect motors (`--mode torques`: 2 % gain error,
white torque noise). Prints the stop-point statistics next to the paper's 95 % interval from
five runs, and writes `stop_points.png` and the study folder (resumable: run it again after an
interruption).

    python examples/montecarlo_stop_points.py --trials 100000 --out study-gait
"""

import argparse
import json

import jsphere
from jsphere.plots import montecarlo_figure

jsphere.enable_x64()  # float64, which jsphere's accuracy needs (JAX's default is float32)

ap = argparse.ArgumentParser()
ap.add_argument("--trials", type=int, default=100_000)
ap.add_argument("--mode", choices=["gait", "torques", "wheel_speeds"], default="gait")
ap.add_argument("--out", default="study-stop-points")
args = ap.parse_args()

p = jsphere.RobotParams.paper()
gaits = [jsphere.acceleration(), jsphere.braking()]
vary = {
    "r_m[2]": ("normal", float(p.r_m[2]), 0.5e-3),  # centre of mass known to 0.5 mm
    "j": ("uniform", 2.0e-4, 3.5e-4),
    "m0": ("normal", 0.8, 0.02),
}
actuators = jsphere.Actuators(gain_sd=0.02, white_sd=1e-4) if args.mode != "gait" else None
options = jsphere.StudyOptions(seed=0, batch_size=8192, mode=args.mode, actuators=actuators)
res = jsphere.monte_carlo(p, gaits, vary=vary, n=args.trials, options=options, out=args.out)
st = res.stats()
plan = jsphere.simulate_gaits(p, gaits)
print(json.dumps(st, indent=2))
fx, fy = jsphere.to_figure_frame(st["mean_xy_m"][0], st["mean_xy_m"][1])
print(f"\n{args.trials} trials in {res.elapsed_s:.1f} s")
print(
    f"stop (paper's frame): mean ({1e3 * fx:.1f}, {1e3 * fy:.1f}) mm, sd ({1e3 * st['sd_xy_m'][1]:.1f}, "
    f"{1e3 * st['sd_xy_m'][0]:.1f}) mm; planned (-3.6, 259.2) mm"
)
print("paper: simulation (-0.07, 344.6) mm; experiment (-1.4 +- 28.9, 369.2 +- 37.7) mm (95 %, 5 runs)")
montecarlo_figure(res, f"{args.out}/stop_points.png", planned=(float(plan.x[-1]), float(plan.y[-1])), frame="paper")
