"""The documentation: the API reference names every public name; every `jsphere CMD --flag` the
README, the docs and the examples show exists; every relative link and repository path resolves;
every page is reachable; CITATION.cff is valid CFF 1.2; and the README's and the docs'
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
#: pages whose Python blocks continue one another: run together, in order
PAGES = ["docs/jax.md"]

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
    "lab_loop.py": None,  # run, and its results checked, by tests/planning/test_lab.py
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
@pytest.mark.parametrize("name", sorted(k for k, v in EXAMPLES.items() if v is not None))
def test_example_runs_as_written(name, tmp_path):
    _run([str(ROOT / "examples" / name), *(a.format(tmp=tmp_path) for a in EXAMPLES[name])], tmp_path)


@pytest.mark.slow
@pytest.mark.parametrize("where", PAGES)
def test_page_runs_as_written(where, tmp_path):
    _run(["-c", "\n".join(_python_blocks(ROOT / where))], tmp_path)


def test_the_conventions_block_runs_and_prints_a_plan_command(tmp_path):
    """docs/robot.md's lab target in the plan's start frame (NumPy only: fast)."""
    out = _run(["-c", _python_blocks(ROOT / "docs" / "robot.md")[0]], tmp_path)
    x, y, heading = (float(v) for v in re.findall(r"--to (\S+) (\S+) --heading (\S+)", out.stdout)[0])
    # (0.6, 0.5) m in the lab, turned by -30 degrees into the start frame; heading 90 - 30 degrees
    assert (x, y) == pytest.approx((0.6 * 3**0.5 / 2 + 0.25, 0.5 * 3**0.5 / 2 - 0.3), abs=1e-4)
    assert heading == pytest.approx(3.141592653589793 / 3, abs=1e-4)


# --- what the documentation names exists ---

#: the documents a user reads: their commands, links and paths are checked
DOCUMENTS = sorted(
    [ROOT / "README.md", ROOT / "CONTRIBUTING.md", ROOT / "examples" / "README.md", ROOT / "benchmarks" / "README.md"]
    + list((ROOT / "docs").rglob("*.md"))
)
#: the example scripts, study files and cluster scripts: their `jsphere CMD --flag` lines are checked
SCRIPTS = sorted(
    [*(ROOT / "examples").glob("*.py"), *(ROOT / "examples").glob("*.toml"), *(ROOT / "examples" / "cluster").iterdir()]
)


def _segments(path: Path) -> list[str]:
    """The code a document shows: its code blocks' lines (continuation lines joined, comments
    dropped) and its inline code spans; a script's lines."""
    text = re.sub(r"\\\n\s*", " ", path.read_text())
    if path.suffix != ".md":
        return text.splitlines()
    out, in_block = [], False
    for line in text.splitlines():
        if line.lstrip().startswith("```"):
            in_block = not in_block
            continue
        out += [line.split(" # ")[0]] if in_block else re.findall(r"`([^`]+)`", line)
    return out


def _options() -> dict[str, set[str]]:
    """Every command of `jsphere` and the options its --help lists."""
    from jsphere.cli.app import parser

    sub = next(a for a in parser()._actions if a.__class__.__name__ == "_SubParsersAction")
    return {name: {o for a in p._actions for o in a.option_strings} for name, p in sub.choices.items()}


def _flags_used(segment: str, commands) -> list[tuple[str, str]]:
    """`(command, flag)` for every `--flag` that follows `jsphere CMD` in a segment (up to the
    next `jsphere`)."""
    found = []
    matches = list(re.finditer(r"(?:^|[\s/(`'\"])jsphere\s+([a-z]+)\b", segment))
    for k, m in enumerate(matches):
        if m.group(1) not in commands:
            continue
        end = matches[k + 1].start() if k + 1 < len(matches) else len(segment)
        found += [(m.group(1), f) for f in re.findall(r"(?<![\w-])(--[a-z][a-z0-9-]*)", segment[m.end() : end])]
    return found


def test_every_command_line_flag_shown_exists():
    commands = _options()
    used, unknown = 0, []
    for path in DOCUMENTS + SCRIPTS:
        for segment in _segments(path):
            for command, flag in _flags_used(segment, commands):
                used += 1
                if flag not in commands[command]:
                    unknown.append(f"{path.relative_to(ROOT)}: jsphere {command} {flag}")
    assert not unknown, "options that the command's --help does not list:\n" + "\n".join(unknown)
    assert used > 150  # the check reads the documents (every page shows commands)


def test_flags_are_found_where_they_are_shown():
    commands = {"plan": {"--to"}, "fit": {"--free"}}
    assert _flags_used("jsphere plan --to 1 0 --rigid-body x; jsphere fit --free j", commands) == [
        ("plan", "--to"),
        ("plan", "--rigid-body"),
        ("fit", "--free"),
    ]


#: repository paths in inline code, e.g. `examples/robot.toml` or `jsphere/identify/`
_REPO_PATH = re.compile(r"^(?:docs|examples|benchmarks|tests|jsphere|\.ci)/[\w./-]*$")
#: paths that the documents name as outputs, not as files of the repository
_OUTPUTS = {"benchmarks/results-quick.json"}


def test_every_relative_link_and_repository_path_resolves():
    missing = []
    for path in DOCUMENTS:
        text = path.read_text()
        for target in re.findall(r"\]\(([^)\s]+)\)", text):
            if re.match(r"[a-z]+:", target) or target.startswith("#"):
                continue
            if not (path.parent / target.split("#")[0]).exists():
                missing.append(f"{path.relative_to(ROOT)}: link {target}")
        for span in re.findall(r"`([^`\s]+)`", text):
            if _REPO_PATH.match(span) and span not in _OUTPUTS and "*" not in span and not (ROOT / span).exists():
                missing.append(f"{path.relative_to(ROOT)}: path {span}")
    assert not missing, "\n".join(missing)


def test_the_documents_name_no_private_module():
    private = [f"{p.relative_to(ROOT)}: {m}" for p in DOCUMENTS for m in re.findall(r"jsphere\._\w+", p.read_text())]
    assert not private, "\n".join(private)


def test_every_page_is_in_the_site_and_linked_from_the_index():
    nav = set(re.findall(r"^\s*-\s+(?:[^:\n]+:\s+)?([\w/.-]+\.md)\s*$", (ROOT / "mkdocs.yml").read_text(), flags=re.M))
    pages = {str(p.relative_to(ROOT / "docs")) for p in (ROOT / "docs").rglob("*.md")}
    assert pages == nav
    index = (ROOT / "docs" / "index.md").read_text()
    linked = set(re.findall(r"\]\(([\w/.-]+\.md)(?:#[\w-]*)?\)", index))
    assert {p for p in pages if "/" not in p} - {"index.md"} <= linked
    assert "decisions/index.md" in linked


def test_citation_file_is_valid_cff_1_2():
    import yaml

    cff = yaml.safe_load((ROOT / "CITATION.cff").read_text())
    assert cff["cff-version"] == "1.2.0"
    for key in ("message", "title", "version", "license"):
        assert isinstance(cff[key], str) and cff[key], key
    assert cff["type"] in ("software", "dataset")
    assert cff["license"] == re.search(r'^license = "(.+)"', (ROOT / "pyproject.toml").read_text(), re.M).group(1)
    assert cff["version"] == re.search(r'^version = "(.+)"', (ROOT / "pyproject.toml").read_text(), re.M).group(1)

    def _person_or_entity(a):
        return isinstance(a, dict) and (isinstance(a.get("name"), str) or isinstance(a.get("family-names"), str))

    assert cff["authors"] and all(_person_or_entity(a) for a in cff["authors"])
    paper = cff["preferred-citation"]
    assert paper["type"] == "article" and isinstance(paper["title"], str)
    assert paper["authors"] and all(_person_or_entity(a) for a in paper["authors"])
    assert isinstance(paper["year"], int) and isinstance(paper["volume"], int)
    assert "Karavaev" in {a.get("family-names") for a in paper["authors"]}
    assert (ROOT / "LICENSE").read_text().startswith("MIT License")
