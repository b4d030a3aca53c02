"""The `jsphere` command line: its parser, the dispatch to one module per command (`reproduce`,
`montecarlo`, `convert`, `synth`, `fit`, `plan`: each adds its sub-parser and runs it), and the
mapping of every error to one line on stderr and its exit code (`ExitCode`).

A command module imports nothing heavy at its top: `--help` and argument errors stay quick, and
each command imports what it runs when it runs.
"""

from __future__ import annotations

import argparse
import os
import sys

from . import convert, fit, montecarlo, plan, reproduce, synth
from .compilation import compile_for_one_run, enable_compilation_cache

#: the commands, in the order `jsphere --help` lists them
COMMANDS = (reproduce, montecarlo, convert, synth, fit, plan)


def main(argv=None) -> int:
    """Run `jsphere` with the arguments `argv` (default: the process's); return its exit code."""
    from .._runtime.errors import EXIT_CODES_HELP

    parser = argparse.ArgumentParser(
        prog="jsphere",
        description="Spherical robot with an internal omniwheel platform (JAX).",
        epilog=EXIT_CODES_HELP,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    sub = parser.add_subparsers(dest="command", required=True)
    for command in COMMANDS:
        command.add_parser(sub)
    for command in sub.choices.values():  # every command's --help lists the exit codes
        command.epilog = EXIT_CODES_HELP
        command.formatter_class = argparse.RawDescriptionHelpFormatter
    args = parser.parse_args(argv)
    from .._runtime.precision import enable_x64

    enable_x64()  # the commands compute in float64: before any JAX array is made
    if args.command == reproduce.NAME and not args.optimize:
        compile_for_one_run()
    if not args.no_cache:
        enable_compilation_cache()
    return _run(args)


#: What a command interrupted by Ctrl-C or SIGTERM has kept (the others write their files only
#: at the end, each atomically: an interrupted run leaves the previous files as they were).
_RESUMES = {command.NAME: command.RESUMES for command in COMMANDS if hasattr(command, "RESUMES")}

#: Errors that mean bad input: a file, option or value (the message names it), exit code 2.
_INPUT_ERRORS = (ValueError, FileNotFoundError, IsADirectoryError, NotADirectoryError, PermissionError, FileExistsError)


def _run(args) -> int:
    """Run the command; every error becomes one line on stderr and its exit code (`ExitCode`),
    except an internal error (a bug), which keeps its traceback."""
    import traceback

    from .._runtime.errors import ExitCode, SolverFailure

    commands = {command.NAME: command.run for command in COMMANDS}
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
        print(
            f"{name}: error: a file is not UTF-8 text ({e.reason} at byte {e.start}); save it as UTF-8 (CSV or TOML).",
            file=sys.stderr,
        )
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
            return line[len("jsphere: ") :]
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
