"""A user's mistakes through the command line: each line of `tests/bad_inputs/cases.txt` is one
class of mistake with its exit code and a fragment of its one-line message; no traceback."""

from __future__ import annotations

import shlex
from pathlib import Path

import pytest

from jsphere import cli

HERE = Path(__file__).resolve().parent / "bad_inputs"
DATA = HERE.parents[1] / "examples" / "data"


def _cases():
    for n, line in enumerate((HERE / "cases.txt").read_text().splitlines(), 1):
        if not line.strip() or line.lstrip().startswith("#"):
            continue
        code, fragment, command = (part.strip() for part in line.split("|", 2))
        yield pytest.param(int(code), fragment, command, id=f"{n}:{command.split()[0]}:{fragment[:40]}")


def run_cli(command: str, tmp_path, monkeypatch, capsys) -> tuple[int, str, str]:
    """`jsphere COMMAND` in-process from `tests/bad_inputs/`: (exit code, stdout, stderr)."""
    monkeypatch.chdir(HERE)
    argv = shlex.split(command.replace("{tmp}", str(tmp_path)).replace("{data}", str(DATA)))
    if "--no-cache" not in argv:
        argv.append("--no-cache")
    try:
        code = cli.main(argv)
    except SystemExit as e:  # argparse's own errors
        code = e.code
    out, err = capsys.readouterr()
    return code, out, err


@pytest.mark.parametrize("code, fragment, command", list(_cases()))
def test_bad_input(code, fragment, command, tmp_path, monkeypatch, capsys):
    got, out, err = run_cli(command, tmp_path, monkeypatch, capsys)
    assert "Traceback" not in err, err
    assert got == code, f"exit {got}, expected {code}; stderr:\n{err}"
    assert fragment.lower() in err.lower(), f"{fragment!r} not in stderr:\n{err}"
