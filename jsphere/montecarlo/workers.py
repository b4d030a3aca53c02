"""A study shared by independent jobs through its folder (`jsphere montecarlo --worker` and
`--gather`): each worker claims (`claims`) and computes the batches no other worker holds and
exits, never waiting, so any number of workers started in any order finish the study between
them (a SLURM array whose concurrency limit is below its task count included); the gather joins
the batches once they are all there.
"""

from __future__ import annotations

import contextlib
import dataclasses
import itertools
import time
from typing import Sequence

from .._runtime.checks import real
from .._runtime.errors import InputError
from .._runtime.progress import Progress
from ..solve.options import SolverOptions
from . import claims
from .options import StudyOptions, study_arguments
from .result import MonteCarloResult
from .run import _PROGRESS, _result, _Run, prepare

#: `work`'s default: seconds after which another worker takes over a claimed batch that is
#: still missing (longer than a batch takes)
CLAIM_TIMEOUT = 3600.0


@dataclasses.dataclass(frozen=True)
class WorkReport:
    """What a worker did: the batches it `computed`, those it left to other workers' fresh
    claims (`claimed`: batch -> claim), and how many of the study's `n_batches` are `done`."""

    computed: tuple[int, ...]
    claimed: dict[int, claims.Claim]
    done: int
    n_batches: int

    def summary(self) -> str:
        line = f"{_PROGRESS} this worker computed {len(self.computed)} batch(es); {self.done} of {self.n_batches} done"
        if self.done == self.n_batches:
            return line + "; every batch is there: run with --gather for the statistics"
        rest = f"; {self.n_batches - self.done} left, {len(self.claimed)} of them claimed by other workers"
        return line + rest + " (start another worker when they end; a claim older than --claim-timeout is taken over)"


def work(
    params,
    gaits,
    *,
    vary,
    n: int,
    out,
    options: StudyOptions | None = None,
    solver: SolverOptions | None = None,
    claim_timeout: float = CLAIM_TIMEOUT,
    progress: bool | None = None,
    **deprecated,
) -> WorkReport:
    """Compute the batches of the study in `out` that are missing and not claimed by another
    worker (claims older than `claim_timeout` seconds are taken over), then return. `vary`, `n`,
    `options`, `solver` (and the keywords that moved into them): the study, as `monte_carlo`
    takes it. The first worker creates the folder; the others check that it holds the study."""
    claim_timeout = real("monte_carlo", "claim_timeout", claim_timeout, unit="s")
    run = _prepare("work", params, gaits, vary, n, out, options, solver, deprecated)
    run.folder.open(run.fingerprint, run.n, run.seed, run.vary)
    progress = Progress(progress)
    computed, claimed = [], {}
    path = run.folder.path
    finished = lambda k: run.folder.load_batches([k], stacklevel=4)[0] is not None  # a corrupt one is computed again
    for k in range(run.n_batches):
        if finished(k):
            continue
        if not claims.try_claim(path, k, claim_timeout):
            claim = claims.read_claim(claims.claim_path(path, k))
            if claim is not None and not run.folder.has_batch(k):
                claimed[k] = claim
            continue
        try:
            if finished(k):  # written since the first look
                continue
            run.folder.remove_temporary_files([k], others=False)
            t = time.perf_counter()
            first = progress.compiling("montecarlo", run.program, f"{_PROGRESS} batch {k} (compiles)")
            with contextlib.nullcontext() if computed else first:
                run.compute(k)
            rate = f", {run.trials_of(k) / (time.perf_counter() - t):,.0f} trials/s" if computed else ""
            computed.append(k)
            progress.step(f"{_PROGRESS} {run.folder.batch_path(k).name} written ({len(computed)} by this worker{rate})")
        finally:
            claims.release(path, k)
    done = sum(run.folder.has_batch(k) for k in range(run.n_batches))
    return WorkReport(tuple(computed), claimed, done, run.n_batches)


def _prepare(where: str, params, gaits, vary, n: int, out, options, solver, deprecated: dict) -> _Run:
    """The study of a worker or a gather (`run.prepare`), which share it through its folder `out`."""
    options, solver, _ = study_arguments(where, options, solver, False, deprecated)
    if out is None:
        raise InputError("monte_carlo: workers and their gather share a study through its folder; pass `out`.")
    return prepare(params, gaits, vary=vary, n=n, options=options, solver=solver, out=out)


def gather(
    params,
    gaits,
    *,
    vary,
    n: int,
    out,
    options: StudyOptions | None = None,
    solver: SolverOptions | None = None,
    **deprecated,
) -> MonteCarloResult:
    """The study in `out` joined from its batch files (the arguments as `work`'s), its statistics
    written to `out/stats.json`, and what workers leave behind (temporary files, claims)
    removed; `InputError` naming the missing batches (and who claims them) if any are."""
    t0 = time.perf_counter()
    run = _prepare("gather", params, gaits, vary, n, out, options, solver, deprecated)
    path = run.folder.path
    if not (path / "manifest.json").exists():
        raise InputError(f"monte_carlo: {path} holds no study (no manifest.json); run the workers first.")
    recorded = run.folder.check_manifest(run.fingerprint, run.n)
    if recorded < run.n:
        raise InputError(
            f"monte_carlo: {path} holds this study with {recorded} trials; run workers with n = {run.n} (--trials) "
            f"first, or gather {recorded}."
        )
    parts = run.folder.load_batches(range(run.n_batches), stacklevel=3)
    missing = [k for k, p in enumerate(parts) if p is None]
    if missing:
        raise InputError(f"monte_carlo: {path}: {_describe_missing(path, missing, run.n_batches)}")
    run.folder.remove_temporary_files(range(run.n_batches), others=True)
    for k in range(run.n_batches):
        claims.claim_path(path, k).unlink(missing_ok=True)
    res = _result(run, parts, time.perf_counter() - t0)
    run.folder.write_stats(res.stats())
    return res


def _describe_missing(path, missing: Sequence[int], n_batches: int) -> str:
    """`"3 of 10 batches missing: 2, 5-6 (5 claimed by host:pid, 3 min ago); ..."`."""
    now = time.time()
    held = {k: c for k in missing if (c := claims.read_claim(claims.claim_path(path, k))) is not None}
    text = f"{len(missing)} of {n_batches} batches missing: {_ranges(missing)}"
    if held:
        shown = list(held.items())[:5]
        text += " (" + "; ".join(f"{k} claimed by {c.describe(now)}" for k, c in shown)
        text += f"; {len(held) - 5} more claimed)" if len(held) > 5 else ")"
    return text + "; run more workers (--worker), then --gather again."


def _ranges(ks: Sequence[int]) -> str:
    """`[2, 5, 6, 7]` -> `"2, 5-7"`."""
    runs = [[k for _, k in g] for _, g in itertools.groupby(enumerate(ks), lambda ik: ik[1] - ik[0])]
    return ", ".join(f"{r[0]}" if len(r) == 1 else f"{r[0]}-{r[-1]}" for r in runs)
