"""A user's mistakes through the command line: each line of `tests/cli/bad_inputs/cases.txt` is one
class of mistake with its exit code and a fragment of its one-line message; no traceback."""

from __future__ import annotations

import shlex
from pathlib import Path

import pytest

from jsphere import cli

HERE = Path(__file__).resolve().parent / "bad_inputs"
DATA = HERE.parents[2] / "examples" / "data"


def _cases():
    for n, line in enumerate((HERE / "cases.txt").read_text().splitlines(), 1):
        if not line.strip() or line.lstrip().startswith("#"):
            continue
        code, fragment, command = (part.strip() for part in line.split("|", 2))
        yield pytest.param(int(code), fragment, command, id=f"{n}:{command.split()[0]}:{fragment[:40]}")


def run_cli(command: str, tmp_path, monkeypatch, capsys) -> tuple[int, str, str]:
    """`jsphere COMMAND` in-process from `tests/cli/bad_inputs/`: (exit code, stdout, stderr)."""
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


def test_interrupt_exits_130(tmp_path):
    """Ctrl-C (SIGINT) during a command: one line, exit 130, no traceback, no file."""
    import os
    import signal
    import subprocess
    import sys
    import time

    env = {**os.environ, "PYTHONPATH": str(HERE.parents[2])}
    # Python's own SIGINT handler, also where the tests run as a background job (which ignores SIGINT)
    script = (
        "import signal, sys; signal.signal(signal.SIGINT, signal.default_int_handler); "
        "from jsphere.cli.app import console; print('started', flush=True); sys.exit(console())"
    )
    proc = subprocess.Popen(
        [sys.executable, "-c", script, "reproduce", "--no-cache", "--no-plots", "--out", str(tmp_path / "out")],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        env=env,
        text=True,
    )
    assert proc.stdout.readline().strip() == "started"
    # jsphere imported, the solves about to compile: its first line on stderr
    assert any("Section 5" in proc.stderr.readline() for _ in range(20))
    for _ in range(10):  # as a user would, again if Python dropped the first one (in a gc callback)
        time.sleep(0.5)
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(timeout=2.0)
            break
        except subprocess.TimeoutExpired:
            pass
    out, err = proc.communicate(timeout=120)
    assert proc.returncode == 130, err
    assert "interrupted" in err and "Traceback" not in err, err
    assert not (tmp_path / "out").exists()


def test_help_and_argument_errors_import_no_jax():
    """The command modules import what they run only when they run: `--help` and an argument
    error build the parser alone (checked without the package's `__init__`, which imports jax)."""
    import os
    import subprocess
    import sys

    script = (
        "import sys, types\n"
        "pkg = types.ModuleType('jsphere'); pkg.__path__ = [sys.argv[1]]; sys.modules['jsphere'] = pkg\n"
        "from jsphere.cli.app import main\n"
        "for argv in (['--help'], *([c, '--help'] for c in ('reproduce', 'montecarlo', 'convert', 'synth', 'fit', 'plan')),\n"
        "             ['plan'], ['synth', '--trials']):\n"
        "    try:\n"
        "        main(argv)\n"
        "    except SystemExit:\n"
        "        pass\n"
        "print(sorted(m for m in ('jax', 'numpy', 'equinox') if m in sys.modules))\n"
    )
    env = {**os.environ, "PYTHONPATH": str(HERE.parents[2])}
    done = subprocess.run(
        [sys.executable, "-c", script, str(HERE.parents[2] / "jsphere")],
        capture_output=True,
        text=True,
        env=env,
        timeout=60,
    )
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip().splitlines()[-1] == "[]", done.stdout[-500:]
