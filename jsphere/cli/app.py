"""The `jsphere` command line: its parser, the dispatch to one module per command (each adds its
sub-parser with its `EXAMPLES`, and runs it), the options every command has, and the mapping of
every error to one line on stderr and its exit code (`ExitCode`). A command module imports
nothing heavy at its top, so that `--help`, `--version` and argument errors stay quick."""

from __future__ import annotations

import argparse
import contextlib
import logging
import os
import sys
import textwrap

from .._runtime.errors import EXIT_CODES_HELP, ExitCode, SolverFailure
from . import animate, compare, convert, design, fit, montecarlo, plan, reproduce, synth, track
from .compilation import compile_for_one_run, fast_start

#: the commands, in the order `jsphere --help` lists them
COMMANDS = (reproduce, montecarlo, convert, synth, fit, compare, plan, track, design, animate)


def version() -> str:
    """The installed package's version (its metadata), else the source tree's `__version__`."""
    from importlib import metadata

    try:
        return metadata.version("jsphere")
    except metadata.PackageNotFoundError:  # a source tree on the path: its package, imported already
        return sys.modules["jsphere"].__version__


def parser() -> argparse.ArgumentParser:
    """The parser of `jsphere` and its commands."""
    top = argparse.ArgumentParser(
        prog="jsphere",
        description=textwrap.fill(
            "Spherical robot with an internal omniwheel platform (JAX): the paper's numbers, Monte-Carlo "
            "studies, motion capture, system identification and motion planning.",
            88,
        ),
        epilog="examples:\n  jsphere reproduce --out jsphere-reproduce\n  jsphere fit --help\n\n"
        + EXIT_CODES_HELP.replace(_RESUME, "; fit and montecarlo keep what was finished: rerun to resume"),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    top.add_argument("--version", action="version", version=f"%(prog)s {version()}")
    sub = top.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for command in COMMANDS:
        command.add_parser(sub)
        p = sub.choices[command.NAME]
        p.formatter_class = argparse.RawDescriptionHelpFormatter
        p.description = textwrap.fill(p.description, 88)
        p.epilog = "examples:\n" + command.EXAMPLES.strip("\n") + "\n\n" + _exit_codes(EXIT_CODES_HELP, command.NAME)
        cache = "do not use the persistent compilation cache" if command is not convert else argparse.SUPPRESS
        p.add_argument("--no-cache", action="store_true", help=cache)
        out = p.add_argument_group("messages on stderr")
        loud = out.add_mutually_exclusive_group()
        loud.add_argument("-q", "--quiet", action="store_true", help="warnings and errors only: no progress")
        loud.add_argument("-v", "--verbose", action="store_true", help="also every step (debug messages)")
    return top


def _exit_codes(text: str, command: str) -> str:
    """The exit codes of `command`: those of `text` that are not another command's own."""
    names = {c.NAME for c in COMMANDS} - {command}
    keep, mine = [], True
    for line in text.splitlines():
        if line.startswith("  ") and line[2:3].strip():  # a code's first line: "  6    fit, compare: ..."
            who = {w.strip() for w in line.split("    ", 1)[-1].split(":", 1)[0].split(",")}
            mine = command in who or not who & names
        if mine or not line.startswith("  "):
            keep.append(line)
    if command not in _RESUMES:  # only fit and montecarlo resume; the others write their files at the end
        keep = [line.replace(_RESUME, ", nothing written (files are written at the end)") for line in keep]
    return "\n".join(keep)


#: how the exit code 130 of `EXIT_CODES_HELP` ends for a command that resumes
_RESUME = " after saving what was finished; rerun to resume"


#: the commands whose solves run their programs exported, kept for the next run (`fast_start`)
_EXPORTING = (fit.NAME, plan.NAME, reproduce.NAME, montecarlo.NAME)


def main(argv=None) -> int:
    """Run `jsphere` with the arguments `argv` (default: the process's); return its exit code."""
    args = parser().parse_args(argv)
    if args.command == reproduce.NAME and not args.optimize:
        compile_for_one_run()
    with _messages(args):
        _jax_setup()
        with fast_start(cache=not args.no_cache, export=args.command in _EXPORTING):
            return _run(args)


def _jax_setup() -> None:
    """Before any JAX array is made: float64, and one CPU device per core (`use_cpu_cores`) for
    `montecarlo`'s batches, unless the environment sets a count or JAX runs already."""
    from .._runtime.cores import use_cpu_cores
    from .._runtime.precision import enable_x64

    enable_x64()
    if "JAX_NUM_CPU_DEVICES" in os.environ or "device_count" in os.environ.get("XLA_FLAGS", ""):
        return
    try:
        use_cpu_cores()
    except RuntimeError:  # JAX runs already, with its own count
        pass


class _StderrHandler(logging.Handler):
    """The `jsphere` logger's lines on the stderr of the moment, leaving progress bars intact."""

    def emit(self, record: logging.LogRecord) -> None:
        from .._runtime.progress import write

        try:
            write(self.format(record))
        except Exception:  # noqa: BLE001 - logging must not end the command
            self.handleError(record)


@contextlib.contextmanager
def _messages(args):
    """The `jsphere` logger on stderr while a command runs: INFO (progress and stages), WARNING
    with `--quiet`, DEBUG with `--verbose`."""
    log = logging.getLogger("jsphere")
    handler = _StderrHandler()
    handler.setFormatter(logging.Formatter("%(message)s"))
    level = logging.WARNING if args.quiet else logging.DEBUG if args.verbose else logging.INFO
    old_level, old_propagate = log.level, log.propagate
    log.addHandler(handler)
    log.setLevel(level)
    log.propagate = False
    try:
        yield
    finally:
        log.removeHandler(handler)
        log.setLevel(old_level)
        log.propagate = old_propagate


#: what a command interrupted by Ctrl-C or SIGTERM has kept (the others write their files at the end)
_RESUMES = {command.NAME: command.RESUMES for command in COMMANDS if hasattr(command, "RESUMES")}

#: Errors that mean bad input: a file, option or value (the message names it), exit code 2.
_INPUT_ERRORS = (ValueError, FileNotFoundError, IsADirectoryError, NotADirectoryError, PermissionError, FileExistsError)


def _run(args) -> int:
    """Run the command; every error becomes one line on stderr and its exit code (`ExitCode`),
    except an internal error (a bug), which keeps its traceback."""
    import traceback

    commands = {command.NAME: command.run for command in COMMANDS}
    name = f"jsphere {args.command}"
    try:
        return int(commands[args.command](args))
    except KeyboardInterrupt:
        resume = _RESUMES.get(args.command)
        print(f"\n{name}: interrupted" + (f"; {resume}" if resume else "; nothing was written") + ".", file=sys.stderr)
        return ExitCode.INTERRUPTED
    except (SolverFailure, ImportError) as e:  # ImportError: an optional dependency (ezc3d for C3D files)
        print(f"{name}: error: {e}", file=sys.stderr)
        return ExitCode.SOLVER_FAILURE if isinstance(e, SolverFailure) else ExitCode.BAD_INPUT
    except UnicodeDecodeError as e:  # a reader that did not name its file
        print(
            f"{name}: error: a file is not UTF-8 text ({e.reason} at byte {e.start}); save it as UTF-8 (CSV or TOML).",
            file=sys.stderr,
        )
        return ExitCode.BAD_INPUT
    except _INPUT_ERRORS as e:
        print(f"{name}: error: {_one_line(e, args.command)}", file=sys.stderr)
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
    """Make SIGTERM end a command as Ctrl-C does (exit code 130), and deliver again an interruption
    that Python dropped because it arrived inside a callback (JAX's garbage-collection one)."""
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
            return line[len("jsphere: ") :]
    return None


def console() -> int:
    """The `jsphere` program: `main`, and after an interruption an immediate exit (130): with XLA
    work in flight the interpreter's shutdown can crash, and there is nothing left to save."""
    _interrupts_end_the_command()
    code = main()
    if code == 130:
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(code)
    return code


if __name__ == "__main__":
    sys.exit(console())
