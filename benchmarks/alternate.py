"""One benchmark script of this checkout and of a reference checkout, run alternately in one
session on one machine, with the ratio of their times (the machine's load shared by both).

    python benchmarks/alternate.py --reference /tmp/ref --repeat 3 --keys compile_s,search_s \\
        plan.py -- --restarts 4 --targets 4
    python benchmarks/alternate.py --reference /tmp/ref --repeat 2 --keys fit_s_including_compile \\
        --compare iterations,sigma_pos_mm fit.py -- --trials 3 --duration 4 --n-starts 1

`--reference`: a checkout of the code to compare with (e.g. `git archive main | tar -x -C /tmp/ref`);
each script puts its own checkout's `jsphere` first on the path. The script must accept `--out` and
write JSON. Prints per key the median of each side and the ratio (this / reference), and the
values of the `--compare` keys of both sides' last runs; writes the whole record as JSON.
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

HERE = Path(__file__).resolve().parents[1]


def _run(root: Path, script: str, extra: list[str], out: Path) -> dict:
    subprocess.run([sys.executable, str(root / "benchmarks" / script), *extra, "--out", str(out)], check=True)
    return json.loads(out.read_text())


def main(argv=None) -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--reference", required=True, help="a checkout of the code to compare with")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--keys", required=True, help="timings in the script's JSON (comma-separated)")
    ap.add_argument("--compare", default="", help="results in the JSON shown side by side (comma-separated)")
    ap.add_argument("--out", default=None, help="JSON record (default: benchmarks/results-alternate-<script>.json)")
    ap.add_argument("script", help="a script in benchmarks/ of both checkouts")
    ap.add_argument("args", nargs=argparse.REMAINDER, help="after --: the script's arguments")
    a = ap.parse_args(argv)
    extra = a.args[1:] if a.args[:1] == ["--"] else a.args
    keys = [k for k in a.keys.split(",") if k]
    sides = {"this": HERE, "reference": Path(a.reference).resolve()}
    runs: dict[str, list[dict]] = {s: [] for s in sides}
    with tempfile.TemporaryDirectory() as tmp:
        for i in range(a.repeat):
            for side, root in sides.items():
                runs[side].append(_run(root, a.script, extra, Path(tmp) / f"{side}-{i}.json"))
    rows = []
    for k in keys:
        med = {s: statistics.median(float(r[k]) for r in runs[s]) for s in sides}
        rows.append({"key": k, **med, "ratio": med["this"] / med["reference"]})
    print(f"\n{a.script} {' '.join(extra)}: {a.repeat} runs each, alternating (medians)")
    print(f"{'key':<28} {'this':>12} {'reference':>12} {'ratio':>7}")
    for r in rows:
        print(f"{r['key']:<28} {r['this']:>12.4g} {r['reference']:>12.4g} {r['ratio']:>7.3f}")
    shown = {k: {s: runs[s][-1].get(k) for s in sides} for k in a.compare.split(",") if k}
    for k, v in shown.items():
        print(f"{k}: this {v['this']}  reference {v['reference']}")
    out = Path(a.out or HERE / "benchmarks" / f"results-alternate-{Path(a.script).stem}.json")
    out.write_text(json.dumps({"script": a.script, "args": extra, "timings": rows, "results": shown}, indent=2) + "\n")
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
