"""Progress of long work on stderr, the same for `fit`, `plan` and `monte_carlo`.

A `progress` argument of the library takes one of:

- `None` (the default): tqdm bars with an ETA when stderr is a terminal, nothing otherwise;
- `True`: bars when stderr is a terminal, plain lines on stderr otherwise;
- `False`: no bars and no lines;
- a callable: it gets every line (no bars).

Lines that are not given to a callable (stages at `INFO`; steps at `INFO`, or `DEBUG` while a
bar shows them) go to the `jsphere` logger, where a program that configured logging sees them;
the command line puts a handler there (`-q`: warnings only, `-v`: debug). Where that logger has
no handler of its own, `True` and the bars print the `INFO` lines on stderr themselves.

A long compilation is a phase of its own: `Progress.compiling` says "compiling (first call,
~N s)" before a program that is not compiled yet, and keeps that time out of the rates of the
bars. Whether it is compiled, and N, come from a record in the persistent compilation cache's
directory (`first_calls.json`: the keys of the programs compiled there, and the last first-call
time of each kind of program), else from `FIRST_CALL_S`. tqdm is imported only when a bar is
drawn.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import logging
import os
import sys
import threading
import time
from pathlib import Path
from typing import Any, Callable, Iterator

logger = logging.getLogger("jsphere")

#: Seconds of a first call (tracing and compiling, no cache) of each kind of program, on
#: 2 CPU cores: the estimate until the cache's record holds a time of this machine.
FIRST_CALL_S = {
    "fit": 10.0,  # the residuals and their Jacobian, single or multiple shooting
    "plan": 20.0,  # the planner's vmapped search
    "montecarlo": 45.0,  # one batch of trials
    "reproduce": 17.0,  # every solve of Section 5
    "design": 40.0,  # the design criterion's gradient (reverse over forward mode)
}
#: the record beside the compilation cache
RECORD = "first_calls.json"
#: a recorded first call shorter than this [s] was not compiled: it is not used as an estimate
MIN_RECORDED_S = 1.0
#: the programs compiled in this process (`(kind, key)`)
_COMPILED: set[tuple[str, str]] = set()
_LOCK = threading.Lock()


def _handled() -> bool:
    """Whether someone (the command line) put a handler on the `jsphere` logger."""
    return any(not isinstance(h, logging.NullHandler) for h in logger.handlers)


class Progress:
    """What a `progress` argument asks for (see the module), and the bars and lines of one call.

    `say(line)`: a stage (INFO); `step(line)`: a step that a bar also shows (DEBUG while a bar
    is drawn, else INFO); `bar(...)`, `phase(...)`, `compiling(...)`: below."""

    def __init__(self, progress: bool | None | Callable[[str], Any] = None):
        if not (progress is None or isinstance(progress, bool) or callable(progress)):
            raise TypeError(f"progress must be None, True, False or a callable; got {type(progress).__name__}.")
        self.callback = progress if callable(progress) and not isinstance(progress, bool) else None
        try:
            terminal = bool(sys.stderr.isatty())
        except (AttributeError, ValueError):  # no stderr, or a closed one
            terminal = False
        self.bars = progress is not False and self.callback is None and terminal
        self.lines = progress is True or self.bars
        self._open: list = []

    def _write(self, level: int, line: str) -> None:
        if self.callback is not None:
            self.callback(line)
        elif self.lines and not _handled():
            if level >= logging.INFO:
                write(line)
        else:
            logger.log(level, line)

    def say(self, line: str) -> None:
        self._write(logging.INFO, line)

    def step(self, line: str) -> None:
        self._write(logging.DEBUG if any(b.bar is not None for b in self._open) else logging.INFO, line)

    def bar(self, total: int | None, desc: str, unit: str = "it", initial: int = 0, **tqdm_kwargs) -> "_Bar":
        """A bar of `total` steps (`initial` done already), closed at the end of a `with`."""
        return _Bar(self, total, desc, unit, initial, tqdm_kwargs)

    @contextlib.contextmanager
    def phase(self, desc: str) -> Iterator[None]:
        """A bar showing the time spent in one long call (`desc: 12 s`), refreshed every second."""
        if not self.bars:
            yield
            return
        with self.bar(None, desc, bar_format="{desc}: {elapsed}{postfix}") as b:
            done = threading.Event()

            def tick():
                while not done.wait(1.0):
                    b.bar.refresh()

            t = threading.Thread(target=tick, name="jsphere-progress", daemon=True)
            t.start()
            try:
                yield
            finally:
                done.set()
                t.join()

    @contextlib.contextmanager
    def compiling(self, kind: str, key: str, what: str) -> Iterator[None]:
        """The first call of a program of `kind` (`FIRST_CALL_S`) identified by `key` (its
        shapes and settings): says "`what`: compiling (first call, ~N s)" unless this process or
        the compilation cache has it already, keeps the time out of the open bars' rates, and
        records the time in the cache's directory."""
        full = _full_key(kind, key)
        estimate = expected_compile_s(kind, full)
        if estimate is not None:
            self.say(f"{what}: compiling (first call, ~{estimate:.0f} s) ...")
        t0 = time.perf_counter()
        yield
        with _LOCK:
            _COMPILED.add((kind, full))
        if estimate is not None:
            _record(kind, full, time.perf_counter() - t0)
            for b in self._open:
                b.restart_clock()


class _Bar:
    """One tqdm bar (nothing without bars); a context manager that closes it."""

    def __init__(self, owner: Progress, total, desc: str, unit: str, initial: int, tqdm_kwargs: dict):
        self.owner, self.bar = owner, None
        if owner.bars:
            from tqdm import tqdm

            kw = dict(total=total, desc=desc, unit=unit, initial=initial, file=sys.stderr, dynamic_ncols=True)
            self.bar = tqdm(**{**kw, **tqdm_kwargs})

    def __enter__(self) -> "_Bar":
        self.owner._open.append(self)
        return self

    def __exit__(self, *exc) -> None:
        self.owner._open.remove(self)
        if self.bar is not None:
            self.bar.close()

    def update(self, n: int = 1, status: str | None = None) -> None:
        """`n` more steps done; `status` shown beside the bar."""
        if self.bar is not None:
            if status is not None:
                self.bar.set_postfix_str(status, refresh=False)
            self.bar.update(n)

    def done(self) -> None:
        """The work ended before `total` (converged): the bar ends where it stands."""
        if self.bar is not None and self.bar.total != self.bar.n:
            self.bar.total = self.bar.n
            self.bar.refresh()

    def restart_clock(self) -> None:
        """Leave the time since the bar's last refresh out of its rate and ETA (a compilation)."""
        if self.bar is not None:
            self.bar.unpause()


def write(line: str) -> None:
    """A line on stderr that leaves the bars drawn there intact."""
    if "tqdm" in sys.modules:
        from tqdm import tqdm

        tqdm.write(line, file=sys.stderr)
    else:
        print(line, file=sys.stderr, flush=True)


# ----------------------------------------------------------------------------- first calls


def _cache_dir() -> Path | None:
    """The persistent compilation cache's directory, if one is switched on."""
    if "jax" not in sys.modules:
        return None
    import jax

    d = jax.config.jax_compilation_cache_dir
    return Path(d) if d else None


def _full_key(kind: str, key: str) -> str:
    """`key` with what every program depends on: jsphere's sources, the libraries' versions,
    the backend, float precision and `XLA_FLAGS`."""
    import jax

    from .fast_start import environment

    h = hashlib.sha256()
    for part in (kind, key, environment(), str(jax.config.jax_enable_x64), os.environ.get("XLA_FLAGS", "")):
        h.update(part.encode() + b"\0")
    return h.hexdigest()[:32]


def _read_record(folder: Path | None) -> dict:
    try:
        data = json.loads((folder / RECORD).read_text())
        return data if isinstance(data, dict) else {}
    except (OSError, TypeError, ValueError):  # no folder, no record, or a damaged one
        return {}


def expected_compile_s(kind: str, full_key: str) -> float | None:
    """The seconds the first call of this program will take (`None`: it is compiled already,
    in this process or in the compilation cache)."""
    with _LOCK:
        if (kind, full_key) in _COMPILED:
            return None
    entry = _read_record(_cache_dir()).get(kind, {})
    if full_key in entry.get("keys", ()):
        return None
    last = entry.get("last_s")
    fresh = isinstance(last, (int, float)) and last >= MIN_RECORDED_S
    return float(last) if fresh else FIRST_CALL_S.get(kind, 30.0)


def _record(kind: str, full_key: str, seconds: float, keep: int = 64) -> None:
    """Note in the cache's directory that `full_key` is compiled there, and its time."""
    folder = _cache_dir()
    if folder is None:
        return
    from .files import atomic_write_text

    data = _read_record(folder)
    entry = data.get(kind) if isinstance(data.get(kind), dict) else {}
    keys = [k for k in entry.get("keys", []) if k != full_key][-(keep - 1) :] + [full_key]
    # a first call quicker than MIN_RECORDED_S was served by JAX's cache (the same programs under
    # another key), not compiled: it keeps the estimate it had
    last = round(seconds, 1) if seconds >= MIN_RECORDED_S else entry.get("last_s")
    data[kind] = {"keys": keys, "last_s": last}
    try:
        atomic_write_text(folder / RECORD, json.dumps(data, indent=1))
    except OSError:  # a read-only cache: the estimate stays the table's
        pass
