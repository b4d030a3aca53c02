"""A slalom through three waypoints, stopping at each, planned by gradients through the gait
dynamics, and compared with the paper's hand-made gaits.

    python examples/plan_slalom.py [OUT_DIR]

The hand-made version uses the paper's acceleration (5.1) and braking (5.3) for each leg, in
the leg's direction, with `theta_max` scaled from the paper's straight line (0.1 rad over
2 s + 2 s moves 259.2 mm): it misses the waypoints because of the sideways drift the wheels'
inertia causes and because the errors add up leg after leg. The planner hits every
waypoint at rest. Writes `slalom.csv` (the wheel commands), `slalom.png` and prints a table.
"""

import math
import sys
from pathlib import Path

import numpy as np

import jsphere
from jsphere.plots import plan_figure

jsphere.enable_x64()  # float64, which jsphere's accuracy needs (JAX's default is float32)

WAYPOINTS = [(0.45, 0.3), (0.9, -0.3), (1.35, 0.3)]


def hand_made(p):
    """Acceleration + braking per leg, `theta_max = 0.1 d / 0.2592`, `phi` towards the waypoint
    as seen from the intended (not the reached) previous waypoint."""
    gaits, prev = [], (0.0, 0.0)
    for w in WAYPOINTS:
        dx, dy = w[0] - prev[0], w[1] - prev[1]
        th, ph = 0.1 * math.hypot(dx, dy) / 0.2592, math.atan2(dy, dx)
        gaits += [jsphere.acceleration(th, ph), jsphere.braking(th, ph)]
        prev = w
    tr = jsphere.simulate_gaits(p, gaits)
    stops = [(float(tr.x[k]), float(tr.y[k])) for k in np.nonzero(np.diff(np.asarray(tr.segment)))[0][1::2]]
    stops.append((float(tr.x[-1]), float(tr.y[-1])))
    return tr, stops


def main(out="plan-slalom"):
    out = Path(out)
    p = jsphere.RobotParams.paper()
    # at most 4.5 s per leg, to compare with the hand-made gaits' 4 s per leg
    request = jsphere.PlanOptions(restarts=4, rate=1000.0)
    pl = jsphere.plan_route(p, WAYPOINTS, limits=jsphere.Limits(max_time=4.5), plan_options=request, progress=True)
    print(pl.summary())
    pl.to_csv(out / "slalom.csv")
    tr_h, stops_h = hand_made(p)
    cols = pl.table()
    ends = np.nonzero(np.diff(np.asarray(pl.trajectory.segment)))[0].tolist() + [len(cols["t"]) - 1]
    print(f"\n{'waypoint':<16}{'planned stop':<26}{'error [mm]':<12}{'hand-made stop':<26}{'error [mm]':<12}")
    for w, k, sh in zip(WAYPOINTS, ends, stops_h):
        sp = (cols["x"][k], cols["y"][k])
        ep, eh = (1e3 * math.hypot(s[0] - w[0], s[1] - w[1]) for s in (sp, sh))
        print(f"{w!s:<16}({sp[0]:.5f}, {sp[1]:.5f}){'':<6}{ep:<12.4f}({sh[0]:.5f}, {sh[1]:.5f}){'':<6}{eh:<12.2f}")
    print(
        f"duration: planned {pl.duration:.2f} s, hand-made {float(tr_h.ts[-1]):.2f} s; "
        f"max |K|: planned {1e3 * np.max(np.abs(pl.trajectory.K)):.2f} mN m, hand-made {1e3 * np.max(np.abs(tr_h.K)):.2f} mN m"
    )
    rep = jsphere.replay_errors(pl, mode="torques")
    print(
        f"replaying the CSV torques through jsphere.simulate: end {1e3 * rep['target_error_m']:.4f} mm from the last waypoint"
    )
    plan_figure(pl, out / "slalom.png", compare=[("paper's gaits (hand-made)", tr_h)], title="slalom with stops")
    print(f"wrote {out / 'slalom.csv'}, {out / 'slalom.png'}")


if __name__ == "__main__":
    main(*sys.argv[1:])
