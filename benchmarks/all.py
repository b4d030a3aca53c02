"""Every benchmark behind `docs/performance.md`, one after another, each in a new process.

    python benchmarks/all.py [--list] [--only run,work_precision] [--fresh]

Each step (`STEPS`) resumes from the state file for the same source of `jsphere/`; exit status
0 if every step selected exited 0, 1 if one failed, 2 for an unknown step name. benchmarks/README.md
has the details.
"""

from __future__ import annotations

import json
import subprocess
import sys
from datetime import datetime, timezone
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from common import HERE, ROOT, parser, source_digest, timed, write_json  # noqa: E402  (the digest the result files record)

#: (name, script and arguments, result file): the commands `docs/performance.md` gives
STEPS = (
    ("run", ["run.py"], "results.json"),
    ("work_precision", ["work_precision.py"], "results-work-precision.json"),
    ("startup", ["startup.py", "reproduce"], "results-startup.json"),
    ("first_result", ["startup.py", "first-result"], "results-first-result.json"),
    ("fit_startup", ["startup.py", "fit"], "results-fit-startup.json"),
    ("fit_long", ["tasks.py", "fit-long"], "results-fit-long.json"),
    ("robust_fit", ["tasks.py", "robust-fit"], "results-robust-fit.json"),
    ("robust_fit_long", ["tasks.py", "robust-fit", "--long"], "results-robust-fit-long.json"),
    ("onboard_fit", ["tasks.py", "onboard-fit"], "results-onboard-fit.json"),
    ("montecarlo", ["studies.py"], "results-montecarlo.json"),
    ("montecarlo_workers", ["studies.py", "--workers", "2", "--trials", "1000000"], "results-montecarlo-workers.json"),
    ("plan", ["tasks.py", "plan", "--restarts", "8"], "results-plan.json"),
    ("track", ["tasks.py", "track"], "results-track.json"),
    ("animate", ["tasks.py", "animate"], "results-animate.json"),
)


def read_state(path: Path, digest: str) -> dict:
    """The steps done for `digest` (`{name: record}`); none for another source or no file."""
    try:
        state = json.loads(path.read_text())
    except (OSError, ValueError):
        return {}
    return state.get("done", {}) if state.get("source_sha256") == digest else {}


def run_steps(steps, state_path: Path, out: Path, *, fresh: bool = False, folder: Path = HERE, log=print) -> int:
    """Run `steps` (`(name, argv, result file)`, `argv` a script of `folder` and its arguments)
    in turn, skipping those the state file records as done for this source unless `fresh`;
    1 if one failed, else 0."""
    digest = source_digest()
    done = {} if fresh else read_state(state_path, digest)
    failed = False
    for i, (name, argv, result) in enumerate(steps, 1):
        if name in done and done[name]["returncode"] == 0:
            log(f"[{i}/{len(steps)}] {name}: done for this source ({done[name]['finished_utc']}), skipped")
            continue
        command = ["python", f"benchmarks/{argv[0]}", *argv[1:]]
        log(f"[{i}/{len(steps)}] {name}: {' '.join(command)} ...")
        proc, wall = timed(subprocess.run, [sys.executable, str(folder / argv[0]), *argv[1:]], cwd=ROOT)
        rc = proc.returncode
        log(f"[{i}/{len(steps)}] {name}: exit {rc}, {wall:.0f} s, {result}")
        failed |= rc != 0
        done[name] = {
            "command": command,
            "result_file": f"benchmarks/{result}",
            "returncode": rc,
            "wall_s": wall,
            "finished_utc": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        }
        write_json(state_path, {"source_sha256": digest, "done": done}, say=False)
    write_json(
        out, {"source_sha256": digest, "steps": [done[n] | {"name": n} for n, _, _ in steps if n in done]}, say=False
    )
    return 1 if failed else 0


def main(argv=None) -> int:
    ap = parser("all.py", "results-all.json", description=__doc__.split("\n\n")[0])
    ap.add_argument("--list", action="store_true", help="print the steps and exit")
    ap.add_argument("--only", default="", help="comma-separated step names (default: all)")
    ap.add_argument("--fresh", action="store_true", help="run every selected step again")
    ap.add_argument("--state", type=Path, default=HERE / ".all-state.json")
    args = ap.parse_args(argv)
    names = [n for n in args.only.split(",") if n]
    if unknown := [n for n in names if n not in {s[0] for s in STEPS}]:
        print(f"all.py: unknown step {unknown[0]!r}; the steps are {', '.join(s[0] for s in STEPS)}", file=sys.stderr)
        return 2
    steps = [s for s in STEPS if not names or s[0] in names]
    if args.list:
        for name, a, result in steps:
            print(f"{name:<20} python benchmarks/{' '.join(a):<58} -> benchmarks/{result}")
        return 0
    return run_steps(steps, args.state, args.out, fresh=args.fresh, log=lambda s: print(s, file=sys.stderr, flush=True))


if __name__ == "__main__":
    sys.exit(main())
