"""What the benchmarks of this folder share (benchmarks/README.md). Importing it imports no JAX:
`startup.py`'s parent process keeps JAX out of its own.
"""

from __future__ import annotations

import argparse
import datetime
import hashlib
import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
if str(ROOT) not in sys.path[:1]:
    sys.path.insert(0, str(ROOT))  # the jsphere of this checkout


def log(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


# ------------------------------------------------------------------------ timing


def time_call(fn, *args, repeats: int, min_total_s: float = 1.0, max_repeats: int = 25) -> dict:
    """First call (trace + compile + run), then `repeats` steady-state calls (more, up to
    `max_repeats`, while their total is under `min_total_s`). Returns the timings and the
    output of the last call (`_out`; `public` drops it)."""
    import jax

    t = time.perf_counter()
    out = jax.block_until_ready(fn(*args))
    first = time.perf_counter() - t
    times = []
    while len(times) < repeats or (sum(times) < min_total_s and len(times) < max_repeats):
        t = time.perf_counter()
        out = jax.block_until_ready(fn(*args))
        times.append(time.perf_counter() - t)
    med = statistics.median(times)
    return {
        "first_call_s": first,
        "median_s": med,
        "compile_s": max(first - med, 0.0),
        "compile_s_raw": first - med,
        "repeats": len(times),
        "times_s": times,
        "_out": out,
    }


def public(d: dict) -> dict:
    return {k: v for k, v in d.items() if not k.startswith("_")}


def timed(fn, *args, **kwargs):
    """`(fn(*args, **kwargs), its wall time in seconds)`."""
    t = time.perf_counter()
    out = fn(*args, **kwargs)
    return out, time.perf_counter() - t


def default_device():
    """The JAX device the benchmark runs on (`--device`, else JAX's default)."""
    import jax

    return jax.config.jax_default_device or jax.devices()[0]


# ------------------------------------------------------------------------ the record's head


def source_digest() -> str:
    """sha256 over jsphere/**/*.py of this checkout (to tell whether the package changed mid-run)."""
    h = hashlib.sha256()
    package = ROOT / "jsphere"
    for f in sorted(package.rglob("*.py")):
        h.update(f.relative_to(package).as_posix().encode() + b"\0" + f.read_bytes())
    return h.hexdigest()[:16]


def _git(*args):
    try:
        return subprocess.run(["git", *args], cwd=ROOT, capture_output=True, text=True, timeout=10).stdout.strip()
    except Exception:  # noqa: BLE001
        return None


def _checkout_version():
    try:
        import tomllib

        return tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["version"]
    except Exception:  # noqa: BLE001
        return None


def loadavg():
    return list(os.getloadavg()) if hasattr(os, "getloadavg") else None


def environment(source_at_start: str | None = None) -> dict:
    """Date, machine (load averages included), JAX's device, library versions and the source
    measured: the head of every result file."""
    import jax
    import numpy as np

    import jsphere

    def ver(name):
        try:
            return version(name)
        except PackageNotFoundError:
            return None

    dev = default_device()
    return {
        "date_utc": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        "machine": {
            "platform": platform.platform(),
            "processor": platform.processor() or platform.machine(),
            "python": platform.python_version(),
            "cpu_count": os.cpu_count(),
            "loadavg_start": loadavg(),
        },
        "jax": {
            "backend": jax.default_backend(),
            "device_kind": dev.device_kind,
            "device": str(dev),
            "device_count": jax.device_count(),
            "platform": dev.platform,
            "x64": bool(jax.config.jax_enable_x64),
        },
        "versions": {"jax": jax.__version__}
        | {name: ver(name) for name in ("jaxlib", "diffrax", "equinox")}
        | {"numpy": np.__version__, "scipy": ver("scipy")}
        | {"jsphere": _checkout_version() or getattr(jsphere, "__version__", None)},
        "jsphere_path": str(Path(jsphere.__file__).resolve().parent),
        "jsphere_git": {
            "commit": _git("rev-parse", "HEAD"),
            "uncommitted_changes_in_jsphere": _git("status", "--porcelain", "--", "jsphere"),
            "source_sha256_start": source_at_start or source_digest(),
        },
    }


def environment_in_child() -> dict:
    """`environment()` computed in a new process, so that this one imports no JAX."""
    code = "import json, sys; sys.path.insert(0, sys.argv[1]); import common; print(json.dumps(common.environment()))"
    out = subprocess.run([sys.executable, "-c", code, str(HERE)], env=cli_env(), capture_output=True, text=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def finish(env: dict) -> dict:
    """`env` with the load averages and the source digest at the end of the run."""
    end = source_digest()
    env["machine"]["loadavg_end"] = loadavg()
    env["jsphere_git"]["source_sha256_end"] = end
    env["jsphere_git"]["changed_during_run"] = end != env["jsphere_git"]["source_sha256_start"]
    if env["jsphere_git"]["changed_during_run"]:
        log("WARNING: jsphere/*.py changed on disk during the run; the numbers are for the code imported at the start.")
    return env


# ------------------------------------------------------------------------ output


def write_json(path, obj, say: bool = True) -> None:
    """`obj` as JSON in `path`, atomically (a temporary file in the same folder, then `os.replace`)."""
    path = Path(path)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "w") as f:
            f.write(json.dumps(obj, indent=2) + "\n")
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    if say:
        print(f"wrote {path}")


def print_pairs(rows) -> None:
    """A two-column table of `(label, value)` rows."""
    w = max(len(a) for a, _ in rows)
    for a, b in rows:
        print(f"{a.ljust(w)}  {b}")


def table(columns, rows) -> list[str]:
    """The lines of a table of `rows` (dicts): `columns` are `(heading, key, format)`, `key` a
    key of the row or a function of it, `format` a format spec (`".2f"`); a missing value is
    blank. The first column is left-aligned, the others right-aligned, each as wide as its
    heading or widest cell."""
    cells = [
        ["" if (v := k(r) if callable(k) else r.get(k)) is None else format(v, f) for _, k, f in columns] for r in rows
    ]
    widths = [max([len(h)] + [len(c[i]) for c in cells]) for i, (h, _, _) in enumerate(columns)]

    def line(texts):
        return "  ".join(t.ljust(w) if i == 0 else t.rjust(w) for i, (t, w) in enumerate(zip(texts, widths)))

    head = line([h for h, _, _ in columns])
    return [head, "-" * len(head), *map(line, cells)]


def print_table(columns, rows) -> None:
    print("\n".join(table(columns, rows)))


def result_path(args, name: str) -> Path:
    """`--out` where given, else `benchmarks/<name>`."""
    return Path(args.out) if getattr(args, "out", None) else HERE / name


def parser(prog: str, out: str | None = None, **kwargs) -> argparse.ArgumentParser:
    """A command's argument parser; with `out`, an `--out` option whose default is `benchmarks/<out>`."""
    ap = argparse.ArgumentParser(prog=prog, **kwargs)
    if out:
        ap.add_argument("--out", type=Path, default=HERE / out, help="the JSON record")
    return ap


# ------------------------------------------------------------------------ new processes


def cli_env(**extra) -> dict:
    """The environment of a new process that imports this checkout's `jsphere`, with no
    compiler flags or caches of the caller's."""
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    for k in ("XLA_FLAGS", "JAX_COMPILATION_CACHE_DIR", "JSPHERE_CACHE_DIR", "EQX_ON_ERROR"):
        env.pop(k, None)
    return env | extra


def timed_run(cmd: list[str], env: dict | None = None, quiet: bool = False) -> tuple[str, float]:
    """Run `cmd` in a new process (this checkout's `jsphere`, `cli_env`, unless `env`) from the
    checkout's root, timed from the outside: its standard output (none if `quiet`) and seconds.
    A failure raises `RuntimeError` with the end of its standard error."""
    pipe = subprocess.DEVNULL if quiet else subprocess.PIPE
    t = time.perf_counter()
    out = subprocess.run(cmd, env=env or cli_env(), stdout=pipe, stderr=pipe, text=True, cwd=ROOT)
    wall = time.perf_counter() - t
    if out.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed ({out.returncode}):\n{(out.stderr or '')[-3000:]}")
    return out.stdout or "", wall


def run_cli(argv: list[str], cache_dir: str | None = None) -> float:
    """Seconds of one `jsphere` process (`python -m jsphere.cli.app *argv`) with its cache in
    `cache_dir`, timed from the outside."""
    env = cli_env(**({"JSPHERE_CACHE_DIR": cache_dir} if cache_dir else {}))
    return timed_run([sys.executable, "-m", "jsphere.cli.app", *argv], env, quiet=True)[1]


def run_child(script: str, argv: list[str], env: dict | None = None) -> dict:
    """`python benchmarks/<script> *argv` in a new process; the JSON of its last line of output,
    with the process's seconds (`wall_s`) and the load average before it (`loadavg_1min_before`)."""
    load = os.getloadavg()[0]
    out, wall = timed_run([sys.executable, str(HERE / script), *argv], env)
    return json.loads(out.strip().splitlines()[-1]) | {"wall_s": wall, "loadavg_1min_before": load}


def dispatch(commands: dict, argv, doc: str) -> int:
    """`python SCRIPT COMMAND [options]`: the function of `commands` named by the first argument."""
    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv or argv[0] not in commands:
        print(doc.strip() + "\n\ncommands: " + ", ".join(commands), file=sys.stderr)
        return 0 if argv[:1] in (["-h"], ["--help"]) else 2
    return commands[argv[0]](argv[1:]) or 0
