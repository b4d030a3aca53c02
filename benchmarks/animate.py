"""What an animation costs: a 10 s clip at 30 frames per second (the paper's straight line,
acceleration (5.1) and braking (5.3), 4 s of run played at speed 0.4: 300 frames, 640 x 480)
as MP4 and GIF, and the HTML viewer of the same run at 30 and 15 (its default) frames per second
(its size). The MP4 is also written the way
matplotlib's animations write (every frame drawn in full, then grabbed by the writer), the
same-run baseline of the blitted frames (docs/decisions/viewer.md, docs/performance.md).

    python benchmarks/animate.py                       # the table, and results-animate.json
    python benchmarks/animate.py --out some/where.json

Wall time and CPU time (this process and its ffmpeg child) of each output; the scene's
geometry (one `simulate_gaits`) is computed before the clocks start."""

from __future__ import annotations

import argparse
import os
import platform
import resource
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def _cpu() -> float:
    me, kids = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return me.ru_utime + me.ru_stime + kids.ru_utime + kids.ru_stime


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default=str(ROOT / "benchmarks" / "results-animate.json"))
    args = ap.parse_args()

    import jsphere
    from jsphere._runtime.files import atomic_write_json

    jsphere.enable_x64()
    from jsphere.plots.animation.scene import Scene, body_from_trajectory
    from jsphere.plots.animation.video import render
    from jsphere.plots.animation.viewer import write_html

    params = jsphere.RobotParams.paper()
    traj = jsphere.simulate_gaits(params, [jsphere.acceleration(), jsphere.braking()])
    run_s = float(traj.ts[-1])
    speed, fps, size = run_s / 10.0, 30.0, (640, 480)
    scene = Scene([body_from_trajectory(traj, label="gaits")], params, title="the paper's straight line")

    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        render([scene], Path(tmp) / "warm.gif", fps=2, speed=1.0, size=(160, 120), progress=False)  # imports
        cases = [
            ("mp4", "blitted (jsphere)", lambda p: render([scene], p, fps=fps, speed=speed, size=size, progress=False)),
            (
                "mp4",
                "full redraw (matplotlib's way)",
                lambda p: render([scene], p, fps=fps, speed=speed, size=size, progress=False, blit=False),
            ),
            ("gif", "blitted (jsphere)", lambda p: render([scene], p, fps=fps, speed=speed, size=size, progress=False)),
            ("html", "plotly, bundle embedded, 30 fps", lambda p: write_html([scene], p, fps=fps, speed=speed)),
            ("html", "plotly, bundle embedded, 15 fps", lambda p: write_html([scene], p, fps=15.0, speed=speed)),
        ]
        for k, (suffix, how, make) in enumerate(cases):
            path = Path(tmp) / f"clip{k}.{suffix}"
            c0, w0 = _cpu(), time.perf_counter()
            make(path)
            wall, cpu = time.perf_counter() - w0, _cpu() - c0
            rows.append({"output": suffix, "how": how, "wall_s": wall, "cpu_s": cpu, "bytes": path.stat().st_size})
            print(f"  {suffix} {how}: {wall:.1f} s", file=sys.stderr)

    base = next(r for r in rows if r["how"].startswith("full"))
    blit = rows[0]
    ratio = base["wall_s"] / blit["wall_s"]
    print(
        f"10 s clip at {fps:.0f} fps ({int(round(10 * fps))} frames, {size[0]} x {size[1]}), load {os.getloadavg()[0]:.2f}"
    )
    print(f"{'output':<6} {'how':<34} {'wall [s]':>9} {'CPU [s]':>8} {'size [MB]':>10}")
    for r in rows:
        print(f"{r['output']:<6} {r['how']:<34} {r['wall_s']:>9.1f} {r['cpu_s']:>8.1f} {r['bytes'] / 1e6:>10.2f}")
    print(f"blitted frames against full redraws (MP4, same run): {ratio:.1f}x faster")
    atomic_write_json(
        args.out,
        {
            "clip": {"seconds": 10.0, "fps": fps, "frames": int(round(10 * fps)), "size": list(size), "run_s": run_s},
            "rows": rows,
            "blit_speedup_mp4": ratio,
            "machine": {"platform": platform.platform(), "cpus": os.cpu_count(), "python": platform.python_version()},
            "load_average_end": os.getloadavg()[0],
        },
    )
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
