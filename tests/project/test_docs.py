"""The documentation: the API reference names every public name, and the README's and the docs'
self-contained Python blocks and the example scripts run as written, each in a fresh process
(where JAX's float64 starts off, as for a user)."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]


def _public_names() -> set[str]:
    import jsphere

    return set(jsphere.__all__)


def test_api_reference_lists_every_public_name():
    documented = re.findall(r"^::: jsphere\.(\w+)$", (ROOT / "docs" / "api.md").read_text(), flags=re.M)
    assert len(documented) == len(set(documented)), "a name is documented twice"
    assert set(documented) == _public_names()


def _python_blocks(path: Path) -> list[str]:
    return re.findall(r"^```python\n(.*?)^```", path.read_text(), flags=re.M | re.S)


#: the code blocks that run by themselves (the others continue one of these, or need a
#: cluster, capture files of the user's or 10^5 trials)
BLOCKS = [("README.md", 0), ("docs/index.md", 0), ("docs/capture.md", 0), ("docs/planning.md", 0)]

#: every example script, with arguments that keep it short
EXAMPLES = {
    "quickstart.py": [],
    "kinematic_vs_gaits.py": [],
    "fit_paper_Rm_j.py": [],
    "make_capture_data.py": ["--out", "{tmp}/data"],
    "plan_slalom.py": ["{tmp}/slalom"],
    "montecarlo_stop_points.py": ["--trials", "64", "--out", "{tmp}/study"],
    "montecarlo_fig2.py": ["--trials", "64", "--out", "{tmp}/fig2"],
    "fit_synthetic_capture.py": ["--out", "{tmp}/fit"],
    "lab_loop.py": ["--out", "{tmp}/lab"],
}


def _run(args: list[str], cwd: Path) -> subprocess.CompletedProcess:
    env = {k: v for k, v in os.environ.items() if k != "JAX_ENABLE_X64"}
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT), env.get("PYTHONPATH", "")])
    env["MPLBACKEND"] = "Agg"
    out = subprocess.run([sys.executable, *args], cwd=cwd, env=env, capture_output=True, text=True, timeout=1800)
    assert out.returncode == 0, out.stdout[-2000:] + out.stderr[-4000:]
    assert "PrecisionWarning" not in out.stderr, out.stderr[-2000:]
    return out


def test_every_example_is_listed():
    assert set(EXAMPLES) == {f.name for f in (ROOT / "examples").glob("*.py")}


@pytest.mark.slow
@pytest.mark.parametrize("where,index", BLOCKS, ids=[f"{w}[{i}]" for w, i in BLOCKS])
def test_code_block_runs_as_written(where, index, tmp_path):
    (tmp_path / "examples").symlink_to(ROOT / "examples")  # the blocks read examples/data
    out = _run(["-c", _python_blocks(ROOT / where)[index]], tmp_path)
    if where in ("README.md", "docs/index.md"):  # the stop point the block's comment gives
        assert re.match(r"0\.25919\d* 0\.00359\d*", out.stdout), out.stdout


@pytest.mark.slow
@pytest.mark.parametrize("name", sorted(EXAMPLES))
def test_example_runs_as_written(name, tmp_path):
    _run([str(ROOT / "examples" / name), *(a.format(tmp=tmp_path) for a in EXAMPLES[name])], tmp_path)
