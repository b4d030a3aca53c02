"""Command line: `jsphere reproduce` (Section 5 of the paper)."""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path


def enable_compilation_cache() -> None:
    """Persist XLA executables between processes (`$JSPHERE_CACHE_DIR`, default
    `~/.cache/jsphere/jax`), so a second run skips compilation.

    JAX does not persist executables that contain host callbacks, and equinox's run-time
    checks inside diffrax are host callbacks. For the CLI (whose inputs are validated before
    any solve, and whose solver failures jsphere reports itself, outside the compiled code)
    those checks are switched to equinox's `nan` mode unless `EQX_ON_ERROR` is set.
    """
    import jax

    if "EQX_ON_ERROR" not in os.environ:
        try:
            import equinox._errors as eqx_errors

            if getattr(eqx_errors, "EQX_ON_ERROR", None) == "raise":
                eqx_errors.EQX_ON_ERROR = "nan"
        except ImportError:  # pragma: no cover - a future equinox without this module
            pass

    path = os.environ.get("JSPHERE_CACHE_DIR", str(Path.home() / ".cache" / "jsphere" / "jax"))
    try:
        Path(path).mkdir(parents=True, exist_ok=True)
        jax.config.update("jax_compilation_cache_dir", path)
        jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.5)
        jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    except Exception as e:  # a read-only home must not stop the run
        print(f"jsphere: compilation cache disabled ({e})", file=sys.stderr)


def _cmd_reproduce(args) -> int:
    import jsphere

    from ._io import atomic_write_text

    params = jsphere.RobotParams.load(args.params) if args.params else jsphere.RobotParams.paper()
    t0 = time.perf_counter()
    print("jsphere: reproducing Section 5 of Karavaev & Kilin (2016) ...", flush=True)
    rep = jsphere.reproduce(params, full_stop=not args.no_full_stop)
    print(rep.table())
    out = Path(args.out)
    atomic_write_text(out / "reproduce.json", json.dumps({"rows": [r.__dict__ for r in rep.rows], "values": rep.values}, indent=2) + "\n")
    written = [out / "reproduce.json"]
    if not args.no_plots:
        from .plots import write_reproduction_figures

        written += write_reproduction_figures(rep, out)
    print(f"\nwrote {', '.join(str(p) for p in written)}  ({time.perf_counter() - t0:.1f} s)")
    return 0


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="jsphere", description="Spherical robot with an internal omniwheel platform (JAX).")
    sub = parser.add_subparsers(dest="command", required=True)
    rp = sub.add_parser("reproduce", help="recompute every number of Section 5 of the paper, with figures")
    rp.add_argument("--out", default="jsphere-reproduce", help="output folder (default: ./jsphere-reproduce)")
    rp.add_argument("--params", help="a parameter file (.toml or .json) instead of the paper's robot")
    rp.add_argument("--no-plots", action="store_true", help="skip the figures")
    rp.add_argument("--no-full-stop", action="store_true", help="skip the search for the braking gait that stops")
    rp.add_argument("--no-cache", action="store_true", help="do not use the persistent compilation cache")
    args = parser.parse_args(argv)
    if not args.no_cache:
        enable_compilation_cache()
    if args.command == "reproduce":
        return _cmd_reproduce(args)
    parser.error(f"unknown command {args.command}")
    return 2


if __name__ == "__main__":
    sys.exit(main())
