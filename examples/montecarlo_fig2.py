"""The paper's Fig. 2 as a Monte-Carlo study: kinematic control (2.9) against gait control.

Both controls are planned for the nominal robot and replayed as wheel-speed commands on robots
whose centre of mass, wheel inertia and rolling resistance are uncertain, through motors with
a 2 % gain error. After the commands end (t = 4 s) we record the spread of gamma_3, the
quantity the paper measured (0.018 for kinematic control, 0.001 for gaits), and the stop point
(the paper: 369.2 +- 37.7 mm from five runs).

    python examples/montecarlo_fig2.py --trials 100000 --out study-fig2

Replaying wheel-speed commands is the slow mode (the rocking after the kinematic stop needs
many solver steps): budget tens of minutes for 10^5 trials on a 2-core laptop; the study
resumes where it stopped if interrupted.
"""

import argparse
import dataclasses

import numpy as np

import jsphere
from jsphere.plots import figure2_study

jsphere.enable_x64()  # float64, which jsphere's accuracy needs (JAX's default is float32)

ap = argparse.ArgumentParser()
ap.add_argument("--trials", type=int, default=100_000)
ap.add_argument("--out", default="study-fig2")
args = ap.parse_args()

p = jsphere.RobotParams.paper()
gaits = [jsphere.acceleration(), jsphere.braking()]
vary = {
    "r_m[2]": ("normal", float(p.r_m[2]), 0.5e-3),
    "j": ("uniform", 2.0e-4, 3.5e-4),
    "c_roll": ("uniform", 0.0, 0.02),  # unmodelled rolling resistance [N m s]
}
motors = jsphere.Actuators(gain_sd=0.02)
u = np.asarray(jsphere.kinematic_wheel_speeds(p, np.array([float(p.R0) * 0.864, 0.0])))  # (5.5), 4 s
kinematic = (np.array([0.0, 4.0]), np.stack([u, u]))
options = jsphere.StudyOptions(seed=0, batch_size=4096, mode="wheel_speeds", actuators=motors, settle=4.0)
replayed = dataclasses.replace(options, commands=kinematic)
kin = jsphere.monte_carlo(p, gaits, vary=vary, n=args.trials, options=replayed, out=f"{args.out}/kinematic")
gait = jsphere.monte_carlo(p, gaits, vary=vary, n=args.trials, options=options, out=f"{args.out}/gaits")
for name, res in (("kinematic", kin), ("gaits", gait)):
    st = res.stats()
    print(
        f"{name:9s}: sd(gamma_3, t > 4 s) median {st['gamma3_sd_after']['quantiles'][1]:.4f} "
        f"[{st['gamma3_sd_after']['quantiles'][0]:.4f}, {st['gamma3_sd_after']['quantiles'][2]:.4f}] (95 %); "
        f"stop mean ({1e3 * st['mean_xy_m'][0]:.1f}, {1e3 * st['mean_xy_m'][1]:.1f}) mm, sd "
        f"({1e3 * st['sd_xy_m'][0]:.1f}, {1e3 * st['sd_xy_m'][1]:.1f}) mm"
    )
print("paper (measured): sd(gamma_3) 0.018 kinematic, 0.001 gaits; stop (fig. frame) (-1.4 +- 28.9, 369.2 +- 37.7) mm")
figure2_study(kin, gait, f"{args.out}/fig2_study.png")
