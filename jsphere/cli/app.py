"""Command line: `jsphere reproduce` (Section 5 of the paper)."""

from __future__ import annotations

import argparse
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

    Every executable is kept, however quick its compilation: `jsphere reproduce` compiles ~100
    small programs (eager operations between the solves) besides its solves, and with JAX's
    default threshold (1 s; 0.5 s here before) recompiling them took ~6 s of a second run's
    ~16 s (benchmarks/NOTES.md, session 4).
    """
    import jax

    from .._runtime import export_cache as _aot

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
        jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
        jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
        _aot.enable(path)  # exported solves: a second run skips their tracing too
    except Exception as e:  # a read-only home must not stop the run
        print(f"jsphere: compilation cache disabled ({e})", file=sys.stderr)


_ONE_RUN_XLA_FLAG = "--xla_backend_optimization_level=0"


def compile_for_one_run() -> bool:
    """Have XLA compile this process's programs quickly rather than make them fast
    (`--xla_backend_optimization_level=0`, LLVM without its optimisation passes), unless
    `XLA_FLAGS` already sets the level. Returns whether the flag is in force.

    For `jsphere reproduce`, whose first run is almost all compilation: each of its ~30 solves
    is a single trajectory of a few milliseconds, so programs ~2x slower cost ~0.3 s in all,
    against ~3 s less compilation (benchmarks/NOTES.md, session 11). The flag is part of the
    persistent cache's key (JAX hashes `XLA_FLAGS`), so these executables never serve other
    commands. It must be set before JAX creates its CPU client; later it changes nothing.
    """
    flags = os.environ.get("XLA_FLAGS", "")
    if "xla_backend_optimization_level" in flags:
        return _ONE_RUN_XLA_FLAG in flags.split()
    if "jax" in sys.modules:
        from jax._src import xla_bridge

        if xla_bridge.backends_are_initialized():
            return False
    os.environ["XLA_FLAGS"] = f"{flags} {_ONE_RUN_XLA_FLAG}".strip()
    return True


def _preload_matplotlib():
    """Import matplotlib (~0.5 s) in a thread while the solves compile (XLA releases the GIL)."""
    import threading

    def load():
        try:
            from ..plots.base import pyplot as _plt

            _plt()
        except Exception:  # noqa: BLE001 - the figures will report it themselves
            pass

    t = threading.Thread(target=load, name="jsphere-matplotlib", daemon=True)
    t.start()
    return t


def _cmd_reproduce(args) -> int:
    import jsphere

    from .._runtime.files import atomic_write_json, check_output
    from ..plots import REPRODUCTION_FIGURES as figures

    out = Path(args.out)
    writes = [out / "reproduce.json", *([] if args.no_plots else [out / f for f in figures])]
    check_output(out, folder=True, writes=writes, inputs={"the parameter file (--params)": args.params})
    params = jsphere.RobotParams.load(args.params) if args.params else jsphere.RobotParams.paper()
    t0 = time.perf_counter()
    print("jsphere: reproducing Section 5 of Karavaev & Kilin (2016) ...", flush=True)
    loader = None if args.no_plots else _preload_matplotlib()
    rep = jsphere.reproduce(params, full_stop=not args.no_full_stop)
    print(rep.table())
    atomic_write_json(out / "reproduce.json", {"rows": [r.__dict__ for r in rep.rows], "values": rep.values})
    written = [out / "reproduce.json"]
    if not args.no_plots:
        loader.join()
        from ..plots import write_reproduction_figures

        written += write_reproduction_figures(rep, out)
    print(f"\nwrote {', '.join(str(p) for p in written)}  ({time.perf_counter() - t0:.1f} s)")
    return 0


GAIT_KINDS = ("acceleration", "braking", "turn")


def load_study(path) -> dict:
    """Read a Monte-Carlo study description (TOML). Schema (every key optional but `vary`):

        trials = 10000            # overridden by --trials (a whole number >= 1)
        seed = 0                  # a whole number in [0, 2**32)
        batch_size = 4096
        mode = "gait"             # "gait" | "torques" | "wheel_speeds"
        params = "robot.toml"     # default: the paper's robot (path relative to this file)
        Omega0_sd = 0.0           # [1/s], >= 0
        settle = 1.0              # [s] (replay modes), >= 0
        reset = false
        gaits = [{kind = "acceleration", theta_max = 0.1, phi = 0.0, T = 2.0}, {kind = "braking"}]
        [vary]                    # names as in `jsphere fit --free`
        "r_m[2]" = ["normal", -0.0270146, 1e-4]
        j = ["uniform", 2.0e-4, 3.5e-4]
        m0 = ["normal", 0.8, 0.3, "truncate"]   # truncated to valid robots (m0 > 0)
        [actuators]               # replay modes only; see jsphere.Actuators
        gain_sd = 0.02
        delay_s = 0.01

    A distribution is `["normal", mean, sd]` or `["uniform", low, high]` with finite numbers
    (`sd >= 0`, `low <= high`). Draws that break a rule of `RobotParams` (a negative mass, an
    inertia tensor no body has, the centre of mass outside the shell, ...) are not simulated
    and are counted apart; with a last entry `"truncate"` such draws are redrawn instead (the
    distribution truncated to valid robots; docs/montecarlo.md).

    Every value is checked here, before any work: a bad one raises `InputError` naming the file
    and the key.
    """
    import dataclasses

    import jsphere

    from .._runtime.errors import InputError
    from .._runtime.files import tomllib
    from .._runtime.checks import real
    from ..montecarlo.run import _check_vary, check_settings

    path = Path(path)
    try:
        cfg = tomllib.loads(path.read_text())
    except FileNotFoundError:
        raise InputError(f"{path}: no such study file.") from None
    except tomllib.TOMLDecodeError as e:
        raise InputError(f"{path}: not valid TOML: {e}") from None
    known = {"trials", "seed", "batch_size", "mode", "params", "Omega0_sd", "settle", "reset", "gaits", "vary", "actuators"}
    unknown = sorted(set(cfg) - known)
    if unknown:
        raise InputError(f"{path}: unknown key(s) {unknown}; expected {sorted(known)}.")
    if "vary" not in cfg:
        raise InputError(f"{path}: a study needs a [vary] table, e.g. \"r_m[2]\" = [\"normal\", -0.027, 1e-4].")
    if not isinstance(cfg["vary"], dict):
        raise InputError(f"{path}: vary must be a table of distributions, e.g. [vary] \"r_m[2]\" = [\"normal\", -0.027, 1e-4]; "
                         f"got {cfg['vary']!r}.")  # fmt: skip
    keys = {"trials": "n", "seed": "seed", "batch_size": "batch_size", "settle": "settle", "Omega0_sd": "Omega0_sd"}
    given = {keys[k]: cfg[k] for k in keys if k in cfg}
    settings = check_settings(str(path), given, names={v: k for k, v in keys.items()})
    mode = cfg.get("mode", "gait")
    if mode not in ("gait", "torques", "wheel_speeds"):
        raise InputError(f"{path}: mode must be \"gait\", \"torques\" or \"wheel_speeds\"; got {mode!r}.")
    reset = cfg.get("reset", False)
    if not isinstance(reset, (bool, list)):
        raise InputError(f"{path}: reset must be true, false or a list (one entry per gait boundary); got {reset!r}.")
    params = jsphere.RobotParams.paper()
    if "params" in cfg:
        if not isinstance(cfg["params"], str):
            raise InputError(f"{path}: params must be the path of a parameter file (.toml or .json); got {cfg['params']!r}.")
        params = jsphere.RobotParams.load((path.parent / cfg["params"]).resolve())
    gait_list = cfg.get("gaits", [{"kind": "acceleration"}, {"kind": "braking"}])
    if not isinstance(gait_list, list) or not gait_list:
        raise InputError(f"{path}: gaits must be a non-empty list of tables, e.g. gaits = [{{kind = \"acceleration\"}}, "
                         f"{{kind = \"braking\"}}]; got {gait_list!r}.")  # fmt: skip
    gaits = []
    for k, g in enumerate(gait_list):
        if not isinstance(g, dict):
            raise InputError(f"{path}: gaits[{k}] must be a table such as {{kind = \"acceleration\", theta_max = 0.1}}; got {g!r}.")
        g = dict(g)
        kind = g.pop("kind", None)
        if kind not in GAIT_KINDS:
            raise InputError(f"{path}: gaits[{k}].kind must be one of {GAIT_KINDS}; got {kind!r}.")
        try:
            gaits.append(getattr(jsphere, kind)(**g))
        except (TypeError, ValueError) as e:
            raise InputError(f"{path}: gaits[{k}]: {e}") from None
    kwargs = dict(vary=dict(cfg["vary"]), mode=mode,
                  reset=reset, **{k: v for k, v in settings.items() if k != "n"})  # fmt: skip
    kwargs.setdefault("batch_size", 4096)
    if "actuators" in cfg:
        act = cfg["actuators"]
        if not isinstance(act, dict):
            raise InputError(f"{path}: actuators must be a table (e.g. [actuators] gain_sd = 0.02); got {act!r}.")
        fields = [f.name for f in dataclasses.fields(jsphere.Actuators)]
        unknown = sorted(set(act) - set(fields))
        if unknown:
            raise InputError(f"{path}: [actuators]: unknown key(s) {unknown}; expected {fields}.")
        kwargs["actuators"] = jsphere.Actuators(**{k: real(f"{path}: [actuators]", k, v) for k, v in act.items()})
    try:  # the checks monte_carlo makes before any work, with this file's name
        _check_vary(params, kwargs["vary"])
    except ValueError as e:
        raise InputError(f"{path}: {e}") from None
    return {"params": params, "gaits": gaits, "n": settings.get("n", 1000), "kwargs": kwargs}


def _cmd_montecarlo(args) -> int:
    import warnings

    import jsphere

    from .._runtime.checks import whole
    from .._runtime.errors import InputError, SolverFailure
    from .._runtime.files import atomic_write_json, check_output, dumps_json

    def one_line(message, category, filename, lineno, file=None, line=None):
        print(f"jsphere montecarlo: warning: {message}", file=sys.stderr, flush=True)

    out = Path(args.out)
    writes = [out / name for name in ("stats.json", "manifest.json", *(() if args.no_plots else ("stop_points.png",)))]
    check_output(out, folder=True, writes=writes, inputs={"the study file": args.config})
    study = load_study(args.config)
    n = whole("jsphere montecarlo", "--trials", args.trials, 1) if args.trials is not None else study["n"]
    with warnings.catch_warnings():
        warnings.showwarning = one_line
        res = jsphere.monte_carlo(study["params"], study["gaits"], n=n, out=out, progress=True, **study["kwargs"])
    st = res.stats()
    planned = jsphere.simulate_gaits(study["params"], study["gaits"], reset=study["kwargs"]["reset"])
    st["planned_stop_m"] = [float(planned.x[-1]), float(planned.y[-1])]
    atomic_write_json(out / "stats.json", st)
    print(dumps_json(st), end="")
    why = "; ".join(f"{reason}: {k}" for reason, k in st["rejected"].items())
    if st["n_rejected"]:
        print(f"jsphere montecarlo: warning: {st['n_rejected']} of {n} draws rejected, not simulated (their parameters "
              f"break a rule of RobotParams): {why}. Narrow the distributions or truncate them (a last entry "
              f"\"truncate\", docs/montecarlo.md).", file=sys.stderr)  # fmt: skip
    if st["n_failed"]:
        kinds = {"1": "reached max_steps", "2": "gave NaN or inf"}
        how = ", ".join(f"{k} {kinds.get(c, f'ended with status {c}')}" for c, k in st["failed_status"].items())
        print(f"jsphere montecarlo: warning: {st['n_failed']} of {n} trials failed in the solver ({how}); they are left "
              "out of the statistics.", file=sys.stderr)  # fmt: skip
    if st["n_ok"] and not args.no_plots:
        from ..plots import montecarlo_figure

        montecarlo_figure(res, out / "stop_points.png", planned=st["planned_stop_m"])
    print(f"{n} trials ({st['n_ok']} ok, {st['n_failed']} failed, {st['n_rejected']} rejected) in {res.elapsed_s:.1f} s; "
          f"results in {out}/")  # fmt: skip
    if not st["n_ok"]:
        if st["n_rejected"] == n:
            raise InputError(f"every draw was rejected ({why}); no statistics. Check the [vary] distributions.")
        raise SolverFailure(f"no trial succeeded ({st['n_failed']} solver failures, {st['n_rejected']} rejected draws); no statistics.")
    return 0

# --- capture data: `jsphere convert`, `jsphere synth` ---


def _cmd_convert(args) -> int:
    import math
    import warnings

    import jsphere

    from ..capture.trial import CaptureWarning
    from .._runtime.errors import InputError
    from .._runtime.files import check_output

    if not all(math.isfinite(v) for v in args.body_offset):
        raise InputError(f"--body-offset X Y Z must be finite numbers [m]; got {' '.join(f'{v:g}' for v in args.body_offset)}.")
    if not math.isfinite(args.time_offset):
        raise InputError(f"--time-offset must be a finite number of seconds; got {args.time_offset:g}.")
    out = Path(args.out)
    inputs = {"the raw export": args.raw, "the inputs table": args.inputs, "the body markers": args.body_markers}
    check_output(out, inputs=inputs, example=str(out / "trial.csv"))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", CaptureWarning)
        try:
            body = jsphere.read_body_markers(args.body_markers) if args.body_markers else None
            trial = jsphere.convert_raw(
                args.raw, args.inputs, format=args.format, units=args.units, up_axis=args.up_axis, rigid_body=args.rigid_body,
                body_markers=body, body_offset=tuple(args.body_offset), time_offset=args.time_offset,
                allow_truncated=args.allow_truncated,
            )  # fmt: skip
        finally:  # the warnings of a conversion that then fails say what went before
            for w in caught:
                if issubclass(w.category, CaptureWarning):
                    print(f"jsphere convert: warning: {w.message}", file=sys.stderr)
                else:
                    warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)
    jsphere.write_trial(out, trial)
    print(f"{trial!r} -> {out}")
    return 0


def _cmd_synth(args) -> int:
    import math

    import jsphere

    from .._runtime.errors import InputError
    from .._runtime.files import check_output

    checks = (
        ("--trials", args.trials, args.trials >= 1, "at least 1"),
        ("--duration", args.duration, math.isfinite(args.duration) and args.duration > 0, "a positive number of seconds"),
        ("--pos-sd", args.pos_sd, math.isfinite(args.pos_sd) and args.pos_sd >= 0, "a finite number >= 0 (metres)"),
        ("--rot-sd-deg", args.rot_sd_deg, math.isfinite(args.rot_sd_deg) and args.rot_sd_deg >= 0, "a finite number >= 0 (degrees)"),
        ("--dropout", args.dropout, 0.0 <= args.dropout < 1.0, "a fraction in [0, 1)"),
        ("--seed", args.seed, args.seed >= 0, "an integer >= 0"),
    )  # fmt: skip
    for option, value, ok, what in checks:
        if not ok:
            raise InputError(f"{option} must be {what}; got {value:g}.")
    out = Path(args.out)
    names = [f"{args.kind}_{i:02d}" for i in range(args.trials)]
    check_output(out, folder=True, writes=[out / f"{n}.csv" for n in names], inputs={"the parameter file": args.params})
    params = jsphere.RobotParams.load(args.params) if args.params else jsphere.RobotParams.paper()
    for i, name in enumerate(names):
        seed = args.seed + i
        controls = jsphere.random_inputs(params, args.duration, kind=args.kind, seed=seed)
        trial = jsphere.synthetic_trial(
            params, controls, args.duration, pos_sd=args.pos_sd, rot_sd_deg=args.rot_sd_deg, dropout=args.dropout,
            seed=seed, name=name,
        )  # fmt: skip
        jsphere.write_trial(out / f"{trial.name}.csv", trial)
        print(f"{trial!r} -> {out / (trial.name + '.csv')}")
    return 0


def _add_capture_parsers(sub) -> None:
    cv = sub.add_parser("convert", help="raw motion-capture export + inputs table -> trial CSV (docs/capture.md)")
    cv.add_argument("raw", help="the raw export (Motive CSV, Vicon Nexus CSV, or C3D)")
    cv.add_argument("--format", required=True, choices=("motive", "vicon", "c3d"))
    cv.add_argument("--inputs", required=True, help="inputs table: t, chi_dot_1..N or t, K_1..N")
    cv.add_argument("--out", required=True, help="the trial CSV to write (never one of the input files)")
    cv.add_argument("--units", default="auto", choices=("auto", "m", "mm"), help="length units of the export (default: auto)")
    cv.add_argument("--up-axis", choices=("y", "z"), help="the export's up axis (default: y for Motive, z otherwise)")
    cv.add_argument("--rigid-body", help="Motive rigid body / Vicon subject whose markers to use")
    cv.add_argument("--body-markers", help="CSV name,x,y,z: the markers in the platform frame [m] (default: from the first full frame)")
    cv.add_argument("--body-offset", type=float, nargs=3, default=(0.0, 0.0, 0.0), metavar=("X", "Y", "Z"),
                    help="shell centre relative to the marker centroid, platform frame [m]")  # fmt: skip
    cv.add_argument("--time-offset", type=float, default=0.0, help="added to the capture times to match the inputs' clock [s]")
    cv.add_argument("--allow-truncated", action="store_true",
                    help="convert an export cut short (fewer frames than its header declares, a last row cut off) "
                    "with a warning instead of an error")  # fmt: skip
    cv.add_argument("--no-cache", action="store_true", help=argparse.SUPPRESS)
    sy = sub.add_parser("synth", help="synthetic capture-like trial CSVs from random input programs")
    sy.add_argument("--out", required=True, help="output folder")
    sy.add_argument("--trials", type=int, default=3, help="number of trials (default 3)")
    sy.add_argument("--kind", default="wheel_speeds", choices=("wheel_speeds", "torques"))
    sy.add_argument("--params", help="a parameter file (.toml or .json); default: the paper's robot")
    sy.add_argument("--duration", type=float, default=6.0, help="trial length [s] (default 6)")
    sy.add_argument("--seed", type=int, default=0, help="trial i uses seed + i")
    sy.add_argument("--pos-sd", type=float, default=1e-3, help="position noise [m] (default 1e-3)")
    sy.add_argument("--rot-sd-deg", type=float, default=0.5, help="orientation noise per axis [deg] (default 0.5)")
    sy.add_argument("--dropout", type=float, default=0.02, help="fraction of frames lost (default 0.02)")
    sy.add_argument("--no-cache", action="store_true", help="do not use the persistent compilation cache")


_CAPTURE_COMMANDS = {"convert": _cmd_convert, "synth": _cmd_synth}
# --- end capture data ---

# --- system identification: `jsphere fit` ---


def _parse_assignments(items, option: str) -> dict:
    from .._runtime.errors import InputError

    out = {}
    for item in items or []:
        name, eq, value = item.partition("=")
        if not eq or not name.strip() or not value.strip():
            raise InputError(f"{option} expects NAME=VALUE (e.g. {option} m=2.5); got {item!r}.")
        if name.strip() in out:
            raise InputError(f"{option}: {name.strip()!r} is given twice.")
        out[name.strip()] = value.strip()
    return out


def _parse_bounds(items) -> dict:
    import math

    from .._runtime.errors import InputError

    out = {}
    for name, value in _parse_assignments(items, "--bound").items():
        lo, colon, hi = value.partition(":")
        if not colon:
            raise InputError(f"--bound {name}={value}: expected LO:HI with either side empty for an open end (e.g. j=0:1e-3).")
        try:
            out[name] = (float(lo) if lo.strip() else None, float(hi) if hi.strip() else None)
        except ValueError:
            raise InputError(f"--bound {name}={value}: LO and HI must be numbers.") from None
        if any(v is not None and math.isnan(v) for v in out[name]):
            raise InputError(f"--bound {name}={value}: LO and HI must be numbers, not NaN (leave a side empty for an open end).")
    return out


def _cmd_fit(args) -> int:
    """`jsphere fit`. What a user can get wrong is checked before anything is compiled: the
    output path first, then the options, the parameter file and the trials.

    A finished fit writes its files whatever its verdict; the last line on stdout is the
    verdict, and the exit code says it: 0 converged, 5 not converged (`ExitCode.NOT_CONVERGED`),
    6 a misfit (`ExitCode.MISFIT`: residuals far above the capture's noise floor)."""
    import warnings

    import jsphere

    from .._runtime.errors import ExitCode, InputError
    from .._runtime.files import check_output, remove_stale_temporaries
    from ..identify.verdict import headline

    out = Path(args.out)
    ckpt = out.with_name(out.name + ".ckpt.npz")
    figures = [out.with_name(f"{out.stem}_{k}.png") for k in ("overlay", "residuals")]
    if not out.is_dir() and out.suffix.lower() != ".json":
        raise InputError(f"--out {out}: the result is JSON; give a path ending in .json.")
    inputs = {"the trial file": [t for t in args.trials if not Path(t).is_dir()], "the parameter file (--params)": args.params}
    check_output(out, writes=[ckpt, *([] if args.no_plots else figures)], inputs=inputs, example=str(out / "fit.json"))
    for t in map(Path, args.trials):
        if t.is_dir() and not any(f for f in t.glob("*.csv") if not f.name.startswith(".")):
            raise InputError(f"{t} holds no trial CSV files (*.csv); give the folder of the trials or the files themselves.")
    fix = _parse_assignments(args.fix, "--fix")
    bounds = _parse_bounds(args.bound)
    params = jsphere.RobotParams.load(args.params) if args.params else jsphere.RobotParams.paper()
    trials = jsphere.read_trials(args.trials)
    for f in [(out, ".tmp"), *((g, None) for g in figures)]:  # what a killed writer left
        remove_stale_temporaries(*f)
    sigma_rot = None if args.sigma_rot_deg is None else args.sigma_rot_deg * 3.141592653589793 / 180.0
    with warnings.catch_warnings():  # one line per warning (a checkpoint that cannot be used)
        warnings.showwarning = lambda message, *a, **k: print(f"jsphere fit: warning: {message}", file=sys.stderr)
        res = jsphere.fit(
            trials, params, args.free, fix=fix, bounds=bounds, n_starts=args.n_starts, seed=args.seed, max_iter=args.max_iter,
            shooting=args.shooting, segment=args.segment,
            sigma_pos=args.sigma_pos, sigma_rot=sigma_rot, checkpoint=ckpt, restart=args.restart, progress=not args.quiet,
        )  # fmt: skip
    written = res.save(out, plots=not args.no_plots)
    ckpt.unlink(missing_ok=True)
    print(res.table())
    for w in res.identifiability["warnings"]:
        print(f"jsphere fit: warning: {w}", file=sys.stderr)
    print(f"wrote {', '.join(str(p) for p in written)}  ({res.elapsed_s:.1f} s)")
    print(f"jsphere fit: {headline(res.status, res.status_reason, res.verdict)}")  # the last line: the verdict
    return {"converged": ExitCode.OK, "not_converged": ExitCode.NOT_CONVERGED, "misfit": ExitCode.MISFIT}[res.status]


def _add_fit_parser(sub) -> None:
    ft = sub.add_parser("fit", help="fit robot parameters to captured trials (docs/identification.md)")
    ft.add_argument("trials", nargs="+", help="trial CSV files (docs/capture.md)")
    ft.add_argument("--free", required=True, help="comma-separated names to fit: fields (j, m0, I0, I, r_m) or components (I[0,0], r_m[2]), or R_m")
    ft.add_argument("--fix", nargs="+", action="extend", metavar="NAME=VALUE", help="set and hold a parameter (e.g. m=2.5; a JSON list for a whole field)")
    ft.add_argument("--bound", nargs="+", action="extend", metavar="NAME=LO:HI", help="bounds of a free name (e.g. j=0:1e-3; an empty side is open)")
    ft.add_argument("--params", help="start values (.toml or .json; default: the paper's robot)")
    ft.add_argument("--out", default="fit.json", help="result JSON (default fit.json); plots and the checkpoint go beside it")
    ft.add_argument("--n-starts", type=int, default=2, help="starts vmapped together (default 2)")
    ft.add_argument("--seed", type=int, default=0, help="seed of the start design (a Latin hypercube over the bounds)")
    ft.add_argument(
        "--shooting", choices=("auto", "single", "multiple"), default="auto",
        help="multiple: segments with their own initial states, joined by raising the weight of their defects, then single "
        "shooting; auto (default): multiple when a trial is longer than two segments",
    )  # fmt: skip
    ft.add_argument("--segment", type=float, default=2.0, metavar="SECONDS", help="segment length of multiple shooting [s] (default 2)")
    ft.add_argument("--max-iter", type=int, default=40, help="Levenberg-Marquardt iterations per stage (default 40)")
    ft.add_argument("--sigma-pos", type=float, help="position noise [m] (default: estimated)")
    ft.add_argument("--sigma-rot-deg", type=float, help="orientation noise [deg] (default: estimated)")
    ft.add_argument("--restart", action="store_true", help="ignore the checkpoint a killed fit left (by default the fit resumes from it)")
    ft.add_argument("--no-plots", action="store_true", help="skip the figures")
    ft.add_argument("--quiet", action="store_true", help="no progress lines")
    ft.add_argument("--no-cache", action="store_true", help="do not use the persistent compilation cache")


# --- end system identification ---


# ---- plan: gait optimisation and motion planning -------------------------------------
def _cmd_plan(args) -> int:
    import math

    import jsphere

    from .._runtime.errors import InputError
    from .._runtime.files import atomic_write_json, check_output

    out = Path(args.out)
    writes = [out.with_suffix(".json"), *([] if args.no_plots else [out.with_suffix(".png")])]
    check_output(out, writes=writes, inputs={"the parameter file (--params)": args.params}, example=str(Path(args.out) / "plan.csv"))
    none = {"none", "off", "inf"}
    lim_kw = {}
    for name in ("max_torque", "max_wheel_speed", "max_tilt", "max_torque_rate"):
        v = getattr(args, name)
        if v is not None:
            try:
                lim_kw[name] = None if str(v).lower() in none else float(v)
            except ValueError:
                raise InputError(f"--{name.replace('_', '-')} {v}: expected a number or 'none' (no limit).") from None
    if args.max_time is not None:
        lim_kw["max_time"] = float(args.max_time)
    limits = jsphere.Limits(**lim_kw)
    params = jsphere.RobotParams.load(args.params) if args.params else jsphere.RobotParams.paper()
    obj = jsphere.Objective(energy=args.energy_weight, time=args.time_weight)
    pl = jsphere.plan(params, tuple(args.to), heading=args.heading, limits=limits, objective=obj,
                      restarts=args.restarts, rate=args.rate, seed=args.seed, allow_infeasible=True, progress=True)  # fmt: skip
    print(pl.summary())
    pl.to_csv(out)
    info = {"feasible": pl.feasible, "shortfall": pl.shortfall, "target": [None if math.isnan(v) else v for v in pl.target.tolist()],
            "duration_s": pl.duration, "errors": pl.errors, "limits": pl.limits_report, "iterations": pl.iterations,
            "elapsed_s": pl.elapsed_s, "restarts": pl.restarts, "rate_hz": pl.rate}  # fmt: skip
    atomic_write_json(out.with_suffix(".json"), info)
    written = [out, out.with_suffix(".json")]
    if not args.no_plots:
        from ..plots import plan_figure

        plan_figure(pl, out.with_suffix(".png"))
        written.append(out.with_suffix(".png"))
    print(f"wrote {', '.join(str(p) for p in written)}")
    if not pl.feasible:
        print("jsphere plan: WARNING: the request cannot be met within the limits; the files hold the best plan "
              "found: " + "; ".join(pl.shortfall), file=sys.stderr)  # fmt: skip
        return 3
    return 0


def _add_plan_parser(sub) -> None:
    pp = sub.add_parser("plan", help="plan a rest-to-rest manoeuvre to (X, Y) within motor limits; CSV of wheel commands")
    pp.add_argument("--to", nargs=2, type=float, required=True, metavar=("X", "Y"), help="target position [m] (robot starts at rest at the origin)")
    pp.add_argument("--heading", type=float, help="final platform heading [rad] (default: free)")
    pp.add_argument("--max-torque", help="wheel torque limit [N m] (default 0.1; 'none' for no limit)")
    pp.add_argument("--max-wheel-speed", help="wheel speed limit [rad/s] (default 20)")
    pp.add_argument("--max-tilt", help="platform tilt limit [rad] (default 0.35)")
    pp.add_argument("--max-torque-rate", help="torque rate limit [N m/s] (default 1)")
    pp.add_argument("--max-time", type=float, help="longest manoeuvre [s] (default 12)")
    pp.add_argument("--energy-weight", type=float, default=0.0, help="cost per joule of motor energy (default 0)")
    pp.add_argument("--time-weight", type=float, default=1e-3, help="cost per second of duration (default 1e-3)")
    pp.add_argument("--rate", type=float, default=1000.0, help="rows per second of the CSV (default 1000)")
    pp.add_argument("--restarts", type=int, default=8, help="random restarts (default 8)")
    pp.add_argument("--seed", type=int, default=0)
    pp.add_argument("--params", help="a parameter file (.toml or .json) instead of the paper's robot")
    pp.add_argument("--out", default="plan.csv", help="CSV of t, K_i, chi_dot_i, x, y, gamma_1..3, heading, tilt (default plan.csv); .json and .png beside it")
    pp.add_argument("--no-plots", action="store_true", help="skip the figure")
    pp.add_argument("--no-cache", action="store_true", help="do not use the persistent compilation cache")
# ---- end plan ---------------------------------------------------------------------------------


def main(argv=None) -> int:
    from .._runtime.errors import EXIT_CODES_HELP

    parser = argparse.ArgumentParser(
        prog="jsphere", description="Spherical robot with an internal omniwheel platform (JAX).", epilog=EXIT_CODES_HELP,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )  # fmt: skip
    sub = parser.add_subparsers(dest="command", required=True)
    rp = sub.add_parser("reproduce", help="recompute every number of Section 5 of the paper, with figures")
    rp.add_argument("--out", default="jsphere-reproduce", help="output folder (default: ./jsphere-reproduce)")
    rp.add_argument("--params", help="a parameter file (.toml or .json) instead of the paper's robot")
    rp.add_argument("--no-plots", action="store_true", help="skip the figures")
    rp.add_argument("--no-full-stop", action="store_true", help="skip the search for the braking gait that stops")
    rp.add_argument("--no-cache", action="store_true", help="do not use the persistent compilation cache")
    rp.add_argument(
        "--optimize", action="store_true",
        help="let XLA optimise the compiled solves (by default this one-off job compiles them quickly instead)",
    )  # fmt: skip
    mc = sub.add_parser("montecarlo", help="a Monte-Carlo study of the gaits (TOML description; see load_study)")
    mc.add_argument("config", help="study description (.toml)")
    mc.add_argument("--trials", type=int, help="number of trials (overrides the file)")
    mc.add_argument("--out", default="study", help="output folder; a killed study resumes there (default: ./study)")
    mc.add_argument("--no-plots", action="store_true", help="skip the figure")
    mc.add_argument("--no-cache", action="store_true", help="do not use the persistent compilation cache")
    _add_capture_parsers(sub)
    _add_fit_parser(sub)
    _add_plan_parser(sub)
    for command in sub.choices.values():  # every command's --help lists the exit codes
        command.epilog = EXIT_CODES_HELP
        command.formatter_class = argparse.RawDescriptionHelpFormatter
    args = parser.parse_args(argv)
    if args.command == "reproduce" and not args.optimize:
        compile_for_one_run()
    if not args.no_cache:
        enable_compilation_cache()
    return _run(args)


#: What a command interrupted by Ctrl-C or SIGTERM has kept (the others write their files only
#: at the end, each atomically: an interrupted run leaves the previous files as they were).
_RESUMES = {
    "montecarlo": "the finished batches are kept in the --out folder: rerun the same command to resume",
    "fit": "the finished stages are kept in the checkpoint beside --out: rerun the same command to resume",
}

#: Errors that mean bad input: a file, option or value (the message names it), exit code 2.
_INPUT_ERRORS = (ValueError, FileNotFoundError, IsADirectoryError, NotADirectoryError, PermissionError, FileExistsError)


def _run(args) -> int:
    """Run the command; every error becomes one line on stderr and its exit code (`ExitCode`),
    except an internal error (a bug), which keeps its traceback."""
    import traceback

    from .._runtime.errors import ExitCode, SolverFailure

    commands = {"reproduce": _cmd_reproduce, "montecarlo": _cmd_montecarlo, "fit": _cmd_fit, "plan": _cmd_plan, **_CAPTURE_COMMANDS}
    name = f"jsphere {args.command}"
    try:
        return int(commands[args.command](args))
    except KeyboardInterrupt:
        resume = _RESUMES.get(args.command)
        print(f"\n{name}: interrupted" + (f"; {resume}" if resume else "; nothing was written") + ".", file=sys.stderr)
        return ExitCode.INTERRUPTED
    except SolverFailure as e:
        print(f"{name}: error: {e}", file=sys.stderr)
        return ExitCode.SOLVER_FAILURE
    except UnicodeDecodeError as e:  # a reader that did not name its file
        print(f"{name}: error: a file is not UTF-8 text ({e.reason} at byte {e.start}); save it as UTF-8 (CSV or TOML).", file=sys.stderr)
        return ExitCode.BAD_INPUT
    except _INPUT_ERRORS as e:
        print(f"{name}: error: {_one_line(e, args.command)}", file=sys.stderr)
        return ExitCode.BAD_INPUT
    except ImportError as e:  # an optional dependency (ezc3d for C3D files)
        print(f"{name}: error: {e}", file=sys.stderr)
        return ExitCode.BAD_INPUT
    except Exception as e:  # noqa: BLE001
        solver = _solver_message(e)
        if solver is not None:
            print(f"{name}: error: {solver}", file=sys.stderr)
            return ExitCode.SOLVER_FAILURE
        traceback.print_exc()
        print(f"{name}: internal error (a bug in jsphere; please report it with the traceback above).", file=sys.stderr)
        return ExitCode.INTERNAL


def _interrupts_end_the_command() -> None:
    """Make SIGTERM (a scheduler's or `kill`'s stop) end a command as Ctrl-C does (the finished
    work is kept, exit code 130), and deliver again an interruption that Python dropped because
    it arrived inside a callback (JAX's garbage-collection callback: Python then prints
    "Exception ignored" and carries on)."""
    import signal
    import threading

    if threading.current_thread() is not threading.main_thread():
        return

    def interrupt(signum, frame):
        raise KeyboardInterrupt

    signal.signal(signal.SIGTERM, interrupt)
    default = sys.unraisablehook

    def dropped(unraisable):
        if isinstance(unraisable.exc_value, KeyboardInterrupt):
            threading.Timer(0.05, os.kill, (os.getpid(), signal.SIGINT)).start()
            return
        default(unraisable)

    sys.unraisablehook = dropped


def _one_line(e: BaseException, command: str = "") -> str:
    """The message of `e` without the name of the function that raised it when that is the
    command's own (`plan: ...` from `jsphere plan`); an `OSError` as `PATH: reason`."""
    if isinstance(e, OSError) and e.filename is not None and e.strerror:
        return f"{e.filename}: {e.strerror.lower()}."
    text = str(e)
    head, sep, rest = text.partition(": ")
    if sep and command and head.replace("_", "") == command:
        return rest
    return text


def _solver_message(e: BaseException) -> str | None:
    """The "jsphere: ..." line of a run-time error raised from inside a compiled solve (equinox
    puts it first, followed by the trace), or None for any other error."""
    for line in str(e).splitlines():
        if line.startswith("jsphere: "):
            return line[len("jsphere: "):]
    return None


def console() -> int:
    """The `jsphere` program: `main`, and after an interruption an immediate exit (130), which
    skips the interpreter's shutdown: with XLA work still in flight that shutdown can crash,
    and there is nothing left to save (files are written atomically, and the command has
    already kept what it finished)."""
    _interrupts_end_the_command()
    code = main()
    if code == 130:
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(code)
    return code


if __name__ == "__main__":
    sys.exit(console())
