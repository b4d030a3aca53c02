"""`jsphere reproduce`: every number of Section 5 of the paper, with figures."""

from __future__ import annotations

import time
from pathlib import Path

from .options import progress, robot

NAME = "reproduce"
EXAMPLES = """
  jsphere reproduce --out jsphere-reproduce
  jsphere reproduce --params robot.toml --no-plots --out reproduce-robot
"""


def add_parser(sub) -> None:
    rp = sub.add_parser(
        NAME,
        help="recompute every number of Section 5 of the paper, with figures",
        description="Recompute every number of Section 5 of Karavaev & Kilin (2016): prints the table (the "
        "paper's value, jsphere's, and jsphere's in the paper's figure frame), writes reproduce.json and the "
        "figures, drawn in the paper's figure frame as the paper draws them. Compiled programs are kept in "
        "the persistent cache: a second run is quicker.",
    )
    rp.add_argument("--out", default="jsphere-reproduce", help="output folder (default: ./jsphere-reproduce)")
    rp.add_argument("--params", help="a parameter file (.toml or .json) instead of the paper's robot")
    rp.add_argument("--no-plots", action="store_true", help="skip the figures")
    rp.add_argument("--no-full-stop", action="store_true", help="skip the search for the braking gait that stops")
    rp.add_argument(
        "--optimize",
        action="store_true",
        help="let XLA optimise the compiled solves (by default this one-off job compiles them quickly instead)",
    )


def _preload_matplotlib():
    """Import matplotlib in a thread while the solves compile (XLA releases the GIL)."""
    import contextlib
    import threading

    def load():
        with contextlib.suppress(Exception):  # the figures will report it themselves
            from ..plots.base import pyplot

            pyplot()

    t = threading.Thread(target=load, name="jsphere-matplotlib", daemon=True)
    t.start()
    return t


def run(args) -> int:
    from .._runtime.files import atomic_write_json, check_output
    from .._runtime.progress import Progress, logger
    from ..paper.reproduce import reproduce
    from ..plots import REPRODUCTION_FIGURES as figures

    out = Path(args.out)
    writes = [out / "reproduce.json", *([] if args.no_plots else [out / f for f in figures])]
    check_output(out, folder=True, writes=writes, inputs={"the parameter file (--params)": args.params})
    params = robot(args)
    t0 = time.perf_counter()
    logger.info("jsphere reproduce: Section 5 of Karavaev & Kilin (2016)")
    loader = None if args.no_plots else _preload_matplotlib()
    program = repr((sorted(params.to_dict().items()), not args.no_full_stop))
    with Progress(progress(args)).compiling("reproduce", program, "jsphere reproduce"):
        rep = reproduce(params, full_stop=not args.no_full_stop)
    print(rep.table())
    atomic_write_json(out / "reproduce.json", {"rows": [r.__dict__ for r in rep.rows], "values": rep.values})
    written = [out / "reproduce.json"]
    if not args.no_plots:
        loader.join()
        from ..plots import write_reproduction_figures

        written += write_reproduction_figures(rep, out)
    print(f"\nwrote {', '.join(str(p) for p in written)}  ({time.perf_counter() - t0:.1f} s)")
    return 0
