"""The errors jsphere raises for a user's mistake or a failed computation, and the exit codes
of the `jsphere` command line.

A user's mistake is an `InputError` (a `ValueError`): its message is one line that names the
file, field or value and says what to do. The command line turns each kind of error into its
own exit code (`ExitCode`) and prints one line; anything else is a bug, reported with its
traceback and exit code 1.
"""

from __future__ import annotations

import enum


class ExitCode(enum.IntEnum):
    """Exit codes of the `jsphere` command line; what each means: `EXIT_CODES_HELP`."""

    OK = 0
    INTERNAL = 1
    BAD_INPUT = 2
    INFEASIBLE = 3
    SOLVER_FAILURE = 4
    NOT_CONVERGED = 5
    MISFIT = 6
    INTERRUPTED = 130


#: what each `ExitCode` means, as `jsphere --help` shows it
EXIT_CODES_HELP = """exit codes:
  0    success
  1    internal error (a bug in jsphere: the traceback is printed; please report it)
  2    bad input: a file, option or value that cannot be used (the message names it)
  3    plan: the request cannot be met within the limits (the best plan is still written)
  4    solver failure: an ODE solve or a fit failed (the message says where and what to try)
  5    fit: the optimiser did not converge (fit.json is written; its status says why)
  6    fit, compare: the model does not explain the trials: a misfit or a model error (fit.json is written),
       or a compare verdict other than consistent (compare.json is written)
  130  interrupted (Ctrl-C or SIGTERM) after saving what was finished; rerun to resume"""


class InputError(ValueError):
    """Bad input: a file, field, option or value that cannot be used. The message names it and
    says what to do."""


class SolverFailure(RuntimeError):
    """A computation that failed on valid input (an ODE solve that cannot reach its end, a fit
    none of whose starts gives a finite cost). The message says where and what to try."""
