"""File I/O at the edge of the package: atomic writes, TOML/JSON tables, inputs never overwritten."""

from __future__ import annotations

import json
import math
import os
import re
import tempfile
import tomllib
from pathlib import Path
from typing import Any

_UMASK = os.umask(0o022)  # the process's file-creation mask, read at import before any thread starts
os.umask(_UMASK)
_NEW_FILE_MODE = 0o666 & ~_UMASK


def atomic_write(path, write, *, suffix: str | None = None) -> None:
    """Call `write(tmp_path)` on a temporary file beside `path`, then rename it to `path`, so that
    a killed process leaves either the old file or the new one (never a partial file). The new
    file gets the usual permissions (those of the file it replaces, else `0o666` less the
    umask). The temporary file is hidden (`.name.XXXX`) and ends in `suffix` (default: the
    suffix of `path`, for writers that infer the format from it)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(
        dir=path.parent, prefix=f".{path.stem}.", suffix=path.suffix if suffix is None else suffix
    )
    os.close(fd)
    try:
        write(tmp)
        try:  # the mode a plain `open(path, "w")` gives (`mkstemp` creates `0o600`)
            mode = path.stat().st_mode & 0o7777
        except FileNotFoundError:
            mode = _NEW_FILE_MODE
        os.chmod(tmp, mode)
        fd = os.open(tmp, os.O_RDWR)  # flushed to disk before the rename (fsync needs write access)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def temporary_pattern(stem: str, suffix: str) -> re.Pattern:
    """The names `atomic_write` gives its hidden temporary files, `.<stem>.<random><suffix>`,
    for `stem` and `suffix` given as regular expressions (their groups are kept)."""
    return re.compile(rf"\.{stem}\.[A-Za-z0-9_]+{suffix}")


def remove_stale_temporaries(path, suffix: str | None = None) -> list[Path]:
    """Remove the temporary files that a process killed while writing `path` atomically left
    beside it (`suffix` by default that of `path`, as `atomic_write` names them). Returns the
    files removed."""
    path = Path(path)
    pattern = temporary_pattern(re.escape(path.stem), re.escape(path.suffix if suffix is None else suffix))
    removed = []
    if path.parent.is_dir():
        for f in path.parent.iterdir():
            if pattern.fullmatch(f.name) and f.is_file():
                f.unlink(missing_ok=True)
                removed.append(f)
    return removed


def atomic_write_text(path, text: str) -> None:
    """Write `text` to `path` atomically (`atomic_write`; the temporary file ends in `.tmp`, so
    a reader globbing `*.csv` never sees one a killed process left)."""

    atomic_write(path, lambda tmp: Path(tmp).write_text(text), suffix=".tmp")


def atomic_savefig(fig, path, **kwargs) -> None:
    """`fig.savefig` through a temporary file and an atomic rename."""
    atomic_write(path, lambda tmp: fig.savefig(tmp, **kwargs))


def _strict(v: Any) -> Any:
    """`v` with every non-finite float replaced by `None` (JSON's `null`), recursively."""
    if isinstance(v, float):
        return v if math.isfinite(v) else None
    if isinstance(v, dict):
        return {k: _strict(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_strict(x) for x in v]
    if hasattr(v, "tolist") and hasattr(v, "dtype"):  # NumPy and JAX arrays and scalars
        return _strict(v.tolist())
    return v


def dumps_json(obj: Any, **kwargs) -> str:
    """Strict JSON (RFC 8259) of `obj`, indented by 2 and ending in a newline: a NaN or an
    infinity is written as `null` (Python's `json` would write the bare `NaN` that strict
    parsers reject); arrays are written as lists."""
    kwargs.setdefault("indent", 2)
    return json.dumps(_strict(obj), allow_nan=False, **kwargs) + "\n"


def atomic_write_json(path, obj: Any) -> None:
    """`atomic_write_text(path, dumps_json(obj))`."""
    atomic_write_text(path, dumps_json(obj))


def _toml_plain(v: Any) -> Any:
    """`v` as the TOML values of a parameter file: every number a float (`1` is written `1.0`),
    lists (nested), booleans and strings; anything else is a `TypeError`."""
    if isinstance(v, (list, tuple)):
        return [_toml_plain(x) for x in v]
    if isinstance(v, (bool, str)):
        return v
    if isinstance(v, (int, float)):
        return float(v)
    raise TypeError(f"cannot write {type(v).__name__} to TOML")


def dumps_toml(d: dict[str, Any], header: str = "") -> str:
    """TOML (`tomli_w`) of a flat table of numbers, strings and (nested) lists of numbers, after
    `header` as comment lines."""
    import tomli_w

    comments = "".join(f"# {line}\n" for line in header.splitlines())
    return comments + tomli_w.dumps({k: _toml_plain(v) for k, v in d.items()})


def write_mapping(path, d: dict[str, Any], *, header: str = "") -> None:
    """Write a flat table as TOML or JSON, chosen by the file suffix, atomically."""
    path = Path(path)
    if path.suffix.lower() == ".toml":
        text = dumps_toml(d, header=header)
    elif path.suffix.lower() == ".json":
        text = dumps_json(d)
    else:
        raise ValueError(f"{path}: parameter files must end in .toml or .json.")
    atomic_write_text(path, text)


def read_mapping(path) -> dict[str, Any]:
    """A TOML or JSON file as a dict; errors name the file."""
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"parameter file {path} does not exist.")
    suffix = path.suffix.lower()
    try:
        if suffix == ".toml":
            return tomllib.loads(path.read_text())
        if suffix == ".json":
            return json.loads(path.read_text())
        raise ValueError("parameter files must end in .toml or .json.")
    except (tomllib.TOMLDecodeError, json.JSONDecodeError) as e:
        raise ValueError(f"{path}: not valid {suffix[1:].upper()}: {e}") from None
    except ValueError as e:
        raise ValueError(f"{path}: {e}") from None


# --------------------------------------------------------------------------- inputs vs outputs


def _same_file(a: Path, b: Path) -> bool:
    """Whether `a` and `b` name one file: equal after resolving `~`, `.`/`..`, relative paths
    and symbolic links, or (both existing) one file through a hard link or a case-insensitive
    file system (`os.path.samefile`)."""
    if a.expanduser().resolve() == b.expanduser().resolve():
        return True
    try:
        return os.path.samefile(a.expanduser(), b.expanduser())
    except OSError:  # one of them does not exist (yet)
        return False


def refuse_overwrite(outputs, inputs, *, option: str = "--out") -> None:
    """Raise `InputError` if a file that a command would write is one of the files it reads
    (writing the result over an input destroys the user's data without a word): call it before
    any work. `outputs`: a path or an iterable of paths (`None` entries skipped); `inputs`: a
    mapping `{description: path or list of paths}` (the description names the input in the
    message, e.g. `"the raw export"`) or an iterable of paths; `option`: what names the outputs.
    Paths are compared after resolving `~`, `.`/`..` and links, and existing ones with
    `os.path.samefile` (a hard link counts); the message names both and says what to do."""
    from .errors import InputError

    outs = [outputs] if isinstance(outputs, (str, os.PathLike)) else list(outputs or ())
    if isinstance(inputs, dict):  # a description may name several paths
        ins = [(k, p) for k, v in inputs.items() for p in (v if isinstance(v, (list, tuple)) else [v])]
    else:
        ins = [(None, p) for p in ([inputs] if isinstance(inputs, (str, os.PathLike)) else list(inputs or ()))]
    for out in outs:
        if out is None:
            continue
        for what, inp in ins:
            if inp is None:
                continue
            if _same_file(Path(out), Path(inp)):
                desc = f"{what} {inp}" if what else f"the input file {inp}"
                how = "" if Path(out) == Path(inp) else " (the same file by another path or a link)"
                raise InputError(
                    f"{option} {out} would write over {desc}{how}: a command never replaces its own input; "
                    f"give {option} another path."
                )


def check_output(
    out, *, folder: bool = False, writes=(), inputs=None, option: str = "--out", example: str | None = None
) -> None:
    """Refuse, before any work, an output that cannot be written: raise `InputError` naming it.

    - `out`: the file (or, with `folder`, the folder) a command writes.
    - A file `out` must not be a folder; a folder `out` must not be a file. The nearest folder
      on its way that exists must be a folder in which a file can be created (tried, so that
      read-only file systems count, whoever runs the command).
    - `writes`: the other files the command writes (beside `out` or in it); these and a file
      `out` must not be one of the `inputs` (`refuse_overwrite`).
    - `example`: a path to suggest when `out` is of the wrong kind.
    """
    from .errors import InputError

    out = Path(out)
    if not folder and out.is_dir():
        raise InputError(
            f"{option} {out} is a folder; give the file to write" + (f" (e.g. {example})." if example else ".")
        )
    if folder and out.exists() and not out.is_dir():
        raise InputError(f"{option} {out} is a file; give the folder to write the results in.")
    nearest = out if folder else out.parent
    while not nearest.exists() and nearest != nearest.parent:
        nearest = nearest.parent
    if not nearest.is_dir():
        raise InputError(f"{option} {out}: {nearest} is a file, not a folder; choose another {option}.")
    try:
        with tempfile.TemporaryFile(dir=nearest):
            pass
    except OSError as e:
        raise InputError(
            f"{option} {out}: cannot write in the folder {nearest} ({(e.strerror or str(e)).lower()}); choose another {option}."
        ) from None
    refuse_overwrite(list(writes) if folder else [out, *writes], inputs, option=option)
