"""The lab's loop, end to end, with a synthetic robot standing in for the lab (docs/lab.md).

    python examples/lab_loop.py [--out lab-loop]

1. Plan a manoeuvre with the model we have (the paper's values) and write its axle torques
   for the robot: `jsphere plan --commands commands_1.csv --command-kind K`.
2. The "lab" runs the commands: a robot whose true R_m and j differ from the model's, motor
   drivers that follow the commands with a lag. Driven by torques, where it stops depends on
   R_m and j.
3. Identification trials: exciting wheel-speed programs, run the same way (servos with a lag,
   encoders logged on the robot's clock, a motion capture with marker noise and dropped frames
   whose clock runs 0.15 s behind the robot's), then `jsphere convert --time-offset auto`,
   `jsphere fit --fit-time-offset` on three of them and `jsphere compare` on the two held
   out, for the fitted and for the starting model.
4. Plan again with the fitted robot (`--params fit.json`) and run it: it lands closer.

Writes everything under OUT, and OUT/loop.json: where each plan stopped and the fitted values.
"""

import argparse
import json
from pathlib import Path

import numpy as np

import jsphere
from jsphere.capture.synthetic import default_marker_set, eval_controls
from jsphere.cli.app import main

jsphere.enable_x64()  # float64, which jsphere's accuracy needs (JAX's default is float32)

MODEL = jsphere.RobotParams.paper()  # what we believe before the loop
TRUTH = MODEL.replace(R_m=0.0290, j=3.2e-4)  # the robot in the lab
CLOCK = 0.15  # the capture's clock runs this much behind the robot's [s]
LAG = 0.02  # the wheel servos and motor drivers follow their commands with this time constant [s]
START = 0.5  # the robot starts its commands this long after its log starts [s]
RATE = 100.0  # command, encoder and capture rate [Hz]
TARGET = (0.4, 0.1)
NAMES = ["m1", "m2", "m3", "m4"]


def cli(*args, expect: int = 0) -> None:
    """A `jsphere` command, as typed in a shell, and the exit code it must give."""
    print("$ jsphere", " ".join(map(str, args)))
    rc = main([str(a) for a in args])
    assert rc == expect, f"jsphere {args[0]} exited with {rc}"


def servo(t_cmd, u_cmd, tau):
    """What the servos (wheel speeds) or drivers (torques) reach at the robot's times `tau`: a
    first-order lag of time constant `LAG` behind the commands, which start at `START` and hold
    their last row."""
    dt = 1e-3
    fine = np.arange(0.0, tau[-1] + dt / 2, dt)
    u = np.stack([np.interp(fine - START, t_cmd, u_cmd[:, i], left=0.0) for i in range(u_cmd.shape[1])], 1)
    a = np.exp(-dt / LAG)
    out = np.zeros_like(u)
    for k in range(1, len(fine)):
        out[k] = a * out[k - 1] + (1.0 - a) * u[k]
    return np.stack([np.interp(tau, fine, out[:, i]) for i in range(u.shape[1])], 1)


def run_on_robot(commands: Path, folder: Path, name: str, seed: int, capture: bool = True):
    """The lab runs the commands table: returns the robot's true final position [m] and, with
    `capture`, writes its encoder log (`<name>_encoders.csv`, robot clock) and the capture
    (`<name>_capture.csv`, Motive CSV in mm, Y up, capture clock)."""
    t_cmd, u_cmd, kind, _ = jsphere.read_inputs_csv(commands)
    tau = np.arange(int((START + t_cmd[-1] + 1.0) * RATE) + 1) / RATE
    wheels = servo(t_cmd, u_cmd, tau)
    drive = jsphere.WheelSpeeds if kind == "wheel_speeds" else jsphere.Torques
    controls = drive.from_samples(tau, wheels)
    state0 = jsphere.State.at_rest(TRUTH)
    end = jsphere.simulate(TRUTH, state0, controls, float(tau[-1]), rtol=1e-9, atol=1e-11)
    final = np.array([float(end.x[-1]), float(end.y[-1])])
    if capture:
        jsphere.write_inputs_csv(folder / f"{name}_encoders.csv", tau, wheels, kind)
        stamps = np.arange(int(0.3 * RATE), int((tau[-1] - CLOCK - 0.3) * RATE)) / RATE  # capture clock
        seen = jsphere.simulate(TRUTH, state0, controls, float(tau[-1]), ts=stamps + CLOCK, rtol=1e-9, atol=1e-11)
        poses = jsphere.Trial(
            stamps, np.asarray(seen.x), np.asarray(seen.y), np.asarray(seen.q), wheels[:1].repeat(len(stamps), 0), kind
        )
        rng = np.random.default_rng(seed)
        gaps = np.zeros(len(stamps), bool)
        for s in rng.choice(len(stamps) - 10, 4, replace=False) + 5:  # occluded frames
            gaps[s : s + rng.integers(2, 8)] = True
        nan = lambda a: np.where(gaps.reshape((-1,) + (1,) * (a.ndim - 1)), np.nan, a)
        poses = poses.replace(x=nan(poses.x), y=nan(poses.y), q=nan(poses.q))
        markers = jsphere.synthetic_markers(
            poses, default_marker_set(float(TRUTH.R0)), z=float(TRUTH.R0), marker_sd=3e-4, dropout=0.01, seed=seed
        )
        jsphere.write_motive_csv(folder / f"{name}_capture.csv", stamps, markers, NAMES, units="mm", up_axis="y")
    return final


def convert(folder: Path, name: str) -> Path:
    out = folder / f"{name}.csv"
    cli(
        "convert",
        folder / f"{name}_capture.csv",
        "--format",
        "motive",
        "--inputs",
        folder / f"{name}_encoders.csv",
        "--body-markers",
        folder / "body_markers.csv",
        "--time-offset",
        "auto",
        "--out",
        out,
    )
    return out


def main_loop(out: Path) -> dict:
    lab = out / "lab"
    lab.mkdir(parents=True, exist_ok=True)
    body = default_marker_set(float(TRUTH.R0))
    (lab / "body_markers.csv").write_text(
        "name,x,y,z\n" + "".join(f"{n},{b[0]:.6f},{b[1]:.6f},{b[2]:.6f}\n" for n, b in zip(NAMES, body))
    )
    plan_args = ["--to", *TARGET, "--rate", RATE, "--restarts", 4, "--max-time", 6, "--no-plots"]
    # 1. the first plan, with the model we have
    cli(
        "plan",
        *plan_args,
        "--commands",
        out / "commands_1.csv",
        "--command-kind",
        "K",
        "--out",
        out / "plan_1.csv",
    )
    first = run_on_robot(out / "commands_1.csv", lab, "plan_1", seed=1, capture=False)
    # 2. identification trials: exciting wheel-speed programs, run and captured like any commands
    trials = []
    for i in range(5):
        c = jsphere.random_inputs(MODEL, 4.0, seed=40 + i)
        t = np.arange(int(4.0 * RATE) + 1) / RATE
        u = np.asarray(eval_controls(c, t))
        jsphere.write_inputs_csv(lab / f"excite_{i}_commands.csv", t, u, "wheel_speeds")
        run_on_robot(lab / f"excite_{i}_commands.csv", lab, f"excite_{i}", seed=10 + i)
        trials.append(convert(lab, f"excite_{i}"))
    fit_trials, held_out = trials[:3], trials[3:]
    cli("fit", *fit_trials, "--free", "R_m,j", "--fit-time-offset", "--no-plots", "--out", out / "fit.json")
    cli("compare", *held_out, "--params", out / "fit.json", "--out", out / "compare_fitted.json")
    MODEL.save(out / "model.toml")
    # the paper's values: compare's verdict is a model error (exit 6), which the fit then corrects
    cli(
        "compare",
        *held_out,
        "--params",
        out / "model.toml",
        "--no-plots",
        "--out",
        out / "compare_model.json",
        expect=6,
    )
    # 3. the second plan, with the fitted robot
    cli(
        "plan",
        *plan_args,
        "--params",
        out / "fit.json",
        "--commands",
        out / "commands_2.csv",
        "--command-kind",
        "K",
        "--out",
        out / "plan_2.csv",
    )
    second = run_on_robot(out / "commands_2.csv", lab, "plan_2", seed=2, capture=False)
    fit = json.loads((out / "fit.json").read_text())
    fitted = json.loads((out / "compare_fitted.json").read_text())["overall"]["fit_percent"]
    model = json.loads((out / "compare_model.json").read_text())["overall"]["fit_percent"]
    summary = {
        "target": list(TARGET),
        "first_plan_stop": first.tolist(),
        "second_plan_stop": second.tolist(),
        "first_plan_miss_m": float(np.hypot(*(first - TARGET))),
        "second_plan_miss_m": float(np.hypot(*(second - TARGET))),
        "truth": {"R_m": float(TRUTH.R_m), "j": float(TRUTH.j), "clock_offset_s": CLOCK},
        "fitted": {k: [fit["values"][k], fit["stderr"][k]] for k in ("R_m", "j")},
        # the clock offsets: convert's estimate (the trials' times are the capture's plus it; the
        # capture's first stamp is 0.3 s) and what the fit found left over
        "convert_time_offset": [float(jsphere.read_trial(p).t[0]) - 0.3 for p in fit_trials],
        "fit_time_offset": fit["time_offset"],
        "held_out_fit_percent": {"fitted": fitted, "model": model},
    }
    (out / "loop.json").write_text(json.dumps(summary, indent=2))
    return summary


if __name__ == "__main__":
    ap = argparse.ArgumentParser()
    ap.add_argument("--out", default="lab-loop")
    s = main_loop(Path(ap.parse_args().out))
    print(f"\nfirst plan (model):   stopped {1e3 * s['first_plan_miss_m']:.1f} mm from the target")
    print(f"second plan (fitted): stopped {1e3 * s['second_plan_miss_m']:.1f} mm from the target")
    for k, (v, se) in s["fitted"].items():
        print(f"{k}: fitted {v:.6g} +- {se:.2g}, true {s['truth'][k]:.6g}")
    total = [a + b for a, b in zip(s["convert_time_offset"], s["fit_time_offset"])]
    print(f"clock offsets: {', '.join(f'{1e3 * v:.1f} ms' for v in total)} (truth {1e3 * CLOCK:.0f} ms)")
    print(f"held-out fit [%]: fitted {s['held_out_fit_percent']['fitted']}, model {s['held_out_fit_percent']['model']}")
