"""A study's folder: its manifest, its batch files (written atomically, byte for byte the same
whatever the run that wrote them), its statistics, and what a killed run leaves there.

    out/manifest.json          the study's fingerprint, n, seed, batch size and vary
    out/batch_000000.npz ...   the outcomes of each finished batch (`BATCH_KEYS`)
    out/time_000000.json ...   how long each batch took to compute, where and when (`TIME_KEYS`)
    out/stats.json             `MonteCarloResult.stats()` of the whole study
    out/claim_000042.json      a worker's claim of a batch it computes (`claims`)
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import socket
import warnings
import zipfile
from pathlib import Path

import jax
import numpy as np

from .._runtime.errors import InputError
from .._runtime.files import atomic_write, atomic_write_json, temporary_pattern
from .batch import CHUNK
from .claims import create_exclusively
from .result import ComputeTime, MonteCarloResult
from .sampling import MAX_REDRAWS, REASONS

#: the arrays of a batch file
BATCH_KEYS = ("vals", "x", "y", "speed", "status", "gamma3_sd", "reject")
#: the fields of a batch's time record: its trials, the seconds its computation took (a process's
#: first batch includes the compilation), its start and end (Unix time [s]), and its process
TIME_KEYS = ("batch", "trials", "compute_s", "start_unix_s", "end_unix_s", "host", "pid")
#: the hidden temporary files of `jsphere._runtime.files.atomic_write` in a study folder, by the file they become
_TEMPORARY = temporary_pattern(r"((?:batch|time)_(\d{6})|manifest|stats|stop_points)", r"\.(npz|tmp|png)")


class MonteCarloWarning(UserWarning):
    """Something `monte_carlo` repaired on its own (a corrupt batch file it recomputes)."""


def fingerprint(params, gaits, spec, seed, batch_size, options, rtol, atol) -> str:
    """A hash of everything that changes a study's results (also the rules a draw must meet, the
    redraw limit of "truncate" and the chunk width); `options`: the other settings."""
    leaves = [np.asarray(x).tolist() for x in jax.tree_util.tree_leaves((params, gaits)) if hasattr(x, "shape")]
    study = [leaves, str(params.R0.dtype), str(jax.tree_util.tree_structure(gaits)), spec, seed, batch_size]
    text = json.dumps([*study, repr(options), rtol, atol, REASONS, MAX_REDRAWS, CHUNK])
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def _manifest(folder) -> dict:
    """The manifest of the study folder `folder`; `OSError` if it cannot be read, `ValueError` if it
    is not a JSON object."""
    record = json.loads((Path(folder) / "manifest.json").read_text())
    if not isinstance(record, dict):
        raise ValueError("not a JSON object")
    return record


@dataclasses.dataclass(frozen=True)
class StudyFolder:
    """The folder `path` of a study with batches of `batch_size` trials and `n_vary` varied names."""

    path: Path
    batch_size: int
    n_vary: int

    def batch_path(self, k: int) -> Path:
        return self.path / f"batch_{k:06d}.npz"

    def open(self, fp: str, n: int, seed: int, vary) -> None:
        """Create the folder with its manifest (exclusively: of two processes, the second checks
        it), or check that it holds the study `fp` with at most `n` trials, extending one of fewer
        (its batches are the first ones of the larger study)."""
        folder = self.path
        if folder.exists() and not folder.is_dir():
            raise InputError(
                f"monte_carlo: out = {folder} is a file; give a folder for the study (it is created if missing)."
            )
        folder.mkdir(parents=True, exist_ok=True)
        manifest = folder / "manifest.json"
        vary = {k: list(v) for k, v in vary.items()}
        record = {"fingerprint": fp, "n": n, "seed": seed, "batch_size": self.batch_size, "vary": vary}
        if not manifest.exists():
            if any(folder.glob("batch_*.npz")):
                raise InputError(
                    f"monte_carlo: {folder} holds batch files but no manifest.json, so it cannot tell which study they "
                    "belong to; delete them (or choose another `out` folder)."
                )
            if create_exclusively(manifest, record):
                return
        old_n = self.check_manifest(fp, n)
        if old_n < n:
            atomic_write_json(manifest, record)

    @staticmethod
    def manifest_batch_size(path) -> int | None:
        """The batch size recorded in the manifest of the folder `path`, if it has a readable one."""
        try:
            size = _manifest(path).get("batch_size")
        except (OSError, ValueError):
            return None
        return size if isinstance(size, int) and not isinstance(size, bool) and size > 0 else None

    def check_manifest(self, fp: str, n: int) -> int:
        """The number of trials of the study in the folder's manifest, which must be `fp` with at
        most `n`."""
        try:
            old = _manifest(self.path)
        except ValueError as e:
            raise InputError(
                f"monte_carlo: {self.path / 'manifest.json'} is not a valid study manifest ({e}), so the batches in {self.path} cannot be "
                "trusted; delete the folder (or choose another `out`) to run the study again."
            ) from None
        old_n = old.get("n")
        if old.get("fingerprint") != fp or not isinstance(old_n, int):
            raise InputError(
                f"monte_carlo: {self.path} holds a different study (other parameters, gaits, vary, seed, mode, "
                "tolerances or batch size); choose another `out` folder or delete it."
            )
        if old_n > n:
            raise InputError(
                f"monte_carlo: {self.path} holds this study with {old_n} trials; a study is extended to more trials "
                f"but not cut to fewer: give n (--trials) >= {old_n}, or another `out` folder."
            )
        return old_n

    def remove_temporary_files(self, batches, others: bool) -> None:
        """Remove the hidden temporary files a killed run left in the folder: those of the batch
        files `batches` (which no other process is writing), and with `others` (no other
        process may be writing them) those of the manifest, the statistics and the figure."""
        batches = set(batches)
        for f in self.path.iterdir():
            m = _TEMPORARY.fullmatch(f.name)
            if m and (int(m.group(2)) in batches if m.group(2) else others):
                f.unlink(missing_ok=True)

    def has_batch(self, k: int) -> bool:
        return self.batch_path(k).exists()

    def load_batches(self, batches, *, stacklevel: int = 2) -> list[dict | None]:
        """The arrays of `batches` (`read_batch`), None for each that is missing or cannot be
        read; a `MonteCarloWarning` names each file that cannot be read (it is recomputed) and
        points `stacklevel` frames above this method."""
        out = []
        for k in batches:
            try:
                out.append(self.read_batch(k) if self.has_batch(k) else None)
            except ValueError as e:
                message = f"monte_carlo: {e}; recomputing that batch."
                warnings.warn(message, MonteCarloWarning, stacklevel=stacklevel + 1)
                out.append(None)
        return out

    def read_batch(self, k: int) -> dict:
        """The arrays of batch `k`; `ValueError` saying why if the file cannot be read or does not
        hold a batch of this study (a truncated copy, a full disk, random bytes)."""
        B = self.batch_size
        try:
            with open(self.batch_path(k), "rb") as fh:
                if not zipfile.is_zipfile(fh):
                    raise ValueError("not an .npz archive: empty, cut short or overwritten")
                fh.seek(0)
                with np.load(fh, allow_pickle=False) as z:
                    part = {key: z[key] for key in z.files}
            if set(part) != set(BATCH_KEYS):
                raise ValueError(f"arrays {sorted(part)}, expected {sorted(BATCH_KEYS)}")
            shapes = {key: part[key].shape for key in BATCH_KEYS}
            if shapes["vals"] != (B, self.n_vary) or any(shapes[k] != (B,) for k in BATCH_KEYS if k != "vals"):
                raise ValueError(f"shapes {shapes} do not match a batch of {B} trials")
        except Exception as e:  # noqa: BLE001 - any unreadable file is recomputed
            reason = str(e) if isinstance(e, ValueError) else f"{type(e).__name__}: {e}"
            raise ValueError(f"{self.batch_path(k)} is corrupt or incomplete ({reason})") from None
        return part

    def save_batch(self, k: int, part: dict) -> None:
        """Write batch `k` atomically as an `.npz` file whose bytes depend on its arrays only
        (fixed member order and time stamps), so a resumed study's files equal an uninterrupted
        one's."""

        def write(tmp):
            with zipfile.ZipFile(tmp, "w", compression=zipfile.ZIP_STORED) as zf:
                for key in BATCH_KEYS:
                    info = zipfile.ZipInfo(f"{key}.npy", date_time=(1980, 1, 1, 0, 0, 0))
                    with zf.open(info, "w", force_zip64=True) as f:
                        np.lib.format.write_array(f, np.ascontiguousarray(part[key]), allow_pickle=False)

        atomic_write(self.batch_path(k), write)

    def time_path(self, k: int) -> Path:
        return self.path / f"time_{k:06d}.json"

    def save_time(self, k: int, trials: int, start: float, seconds: float) -> None:
        """Write the time record of batch `k` (`TIME_KEYS`: its `trials`, computed by this process
        in `seconds` from the Unix time `start`) atomically beside its batch file. A record of its
        own, so that the batch files stay the same bytes whatever run wrote them."""
        record = (k, trials, seconds, start, start + seconds, socket.gethostname(), os.getpid())
        atomic_write_json(self.time_path(k), dict(zip(TIME_KEYS, record)))

    def load_times(self, batches) -> list[dict | None]:
        """The time records of `batches` (`save_time`), None for each that is missing or cannot
        be read (a record is a report, not part of the study: nothing is recomputed)."""
        out = []
        for k in batches:
            try:
                record = json.loads(self.time_path(k).read_text())
                ok = isinstance(record, dict) and set(TIME_KEYS) <= set(record)
                ok = ok and all(isinstance(record[key], (int, float)) for key in TIME_KEYS[:5])
            except (OSError, ValueError):
                ok = False
            out.append(record if ok else None)
        return out

    def write_stats(self, stats: dict) -> None:
        atomic_write_json(self.path / "stats.json", stats)


def read_result(folder) -> MonteCarloResult:
    """The trials that the batch files of a study folder (`monte_carlo(out=...)`) hold, as a
    `MonteCarloResult`: the study's result, bitwise, once every batch is there, else the batches
    written so far (their indices in `trials`). `InputError` naming the file when the folder has
    no manifest, no batch file, or a batch file that cannot be read."""
    path = Path(folder)
    try:
        manifest = _manifest(path)
        n, seed, B, names = int(manifest["n"]), int(manifest["seed"]), int(manifest["batch_size"]), manifest["vary"]
    except FileNotFoundError:
        raise InputError(
            f"{path}: not a Monte-Carlo study (no manifest.json); give a folder that jsphere montecarlo wrote."
        ) from None
    except (ValueError, KeyError, TypeError) as e:
        raise InputError(f"{path / 'manifest.json'}: not a valid study manifest ({e}).") from None
    study = StudyFolder(path, B, len(names))
    ks = [k for k in range(-(-n // B)) if study.has_batch(k)]
    if not ks:
        raise InputError(f"{path}: no batch files (batch_*.npz); run the study there first (jsphere montecarlo).")
    try:
        parts = [{key: a[: min(B, n - k * B)] for key, a in study.read_batch(k).items()} for k in ks]
    except ValueError as e:
        raise InputError(f"monte_carlo: {e}; run the study again.") from None
    trials = np.concatenate([k * B + np.arange(len(p["x"])) for k, p in zip(ks, parts)])
    more = {"compute_time": ComputeTime.of(study.load_times(ks)), "trials": None if len(trials) == n else trials}
    return MonteCarloResult.of_batches(parts, names, len(trials), seed, **more)
