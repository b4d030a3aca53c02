"""Claim files: how workers that share a study folder split its batches without waiting for
each other (`jsphere montecarlo --worker`).

A worker claims batch `k` by creating `claim_000042.json` exclusively (`create_exclusively`)
with its host, pid and the time, and removes it once the batch file is written. A claim older
than the claim timeout whose batch is still missing is taken over: the stale claim is renamed
away first, which only one worker can do (one that renamed a fresher claim puts it back). Two
workers that compute the same batch write the same bytes, so nothing is lost but time.
"""

from __future__ import annotations

import dataclasses
import json
import os
import socket
import tempfile
import time
from pathlib import Path


@dataclasses.dataclass(frozen=True)
class Claim:
    """Who claimed a batch and when (`time`: seconds since the epoch on the claiming host)."""

    host: str
    pid: int
    time: float

    def describe(self, now: float | None = None) -> str:
        """`"host:pid, 12 min ago"`."""
        age = (time.time() if now is None else now) - self.time
        ago = f"{age:.0f} s" if age < 120 else f"{age / 60:.0f} min" if age < 7200 else f"{age / 3600:.1f} h"
        return f"{self.host}:{self.pid}, {ago} ago"


def claim_path(folder: Path, k: int) -> Path:
    return Path(folder) / f"claim_{k:06d}.json"


def read_claim(path: Path) -> Claim | None:
    """The claim in `path`, or None if there is none. A claim that cannot be read (its worker
    was killed between creating and writing it) dates from the file's modification time."""
    try:
        text = path.read_text()
        mtime = path.stat().st_mtime
    except FileNotFoundError:
        return None
    try:
        d = json.loads(text)
        return Claim(str(d["host"]), int(d["pid"]), float(d["time"]))
    except (ValueError, KeyError, TypeError):
        return Claim("?", 0, mtime)


def create_exclusively(path: Path, record: dict) -> bool:
    """Write the JSON `record` to `path` unless it exists (complete or not at all: a hidden
    temporary file linked into place, atomic on local file systems and NFS); False if it exists."""
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.stem}.", suffix=".tmp")
    with os.fdopen(fd, "w") as f:
        json.dump(record, f)
    try:
        os.link(tmp, path)
    except FileExistsError:
        return False
    finally:
        os.unlink(tmp)
    return True


def _create(path: Path) -> bool:
    """Create the claim `path` exclusively with this process's host, pid and time; False if it
    exists."""
    return create_exclusively(path, {"host": socket.gethostname(), "pid": os.getpid(), "time": time.time()})


def try_claim(folder: Path, k: int, timeout: float) -> bool:
    """Claim batch `k` of the study in `folder`: True if this process now holds the claim,
    False if another worker does (a claim younger than `timeout` seconds)."""
    path = claim_path(folder, k)
    if _create(path):
        return True
    old = read_claim(path)
    if old is None:  # released between the two looks
        return _create(path)
    if time.time() - old.time <= timeout:
        return False
    aside = path.with_name(f".{path.stem}.{socket.gethostname()}.{os.getpid()}.stale")
    try:
        os.rename(path, aside)
    except FileNotFoundError:  # another worker took it over first
        return False
    if read_claim(aside) != old:  # a fresh claim, made after the look: put it back
        try:
            os.link(aside, path)
        except FileExistsError:
            pass
        aside.unlink(missing_ok=True)
        return False
    aside.unlink(missing_ok=True)
    return _create(path)


def release(folder: Path, k: int) -> None:
    """Remove this process's claim of batch `k` (once its batch file is written)."""
    path = claim_path(folder, k)
    c = read_claim(path)
    if c is not None and c.host == socket.gethostname() and c.pid == os.getpid():
        path.unlink(missing_ok=True)
