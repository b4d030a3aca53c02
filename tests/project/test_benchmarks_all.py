"""`benchmarks/all.py`: its steps are the commands behind every result file that
docs/performance.md cites, and a run that stops goes on where it stopped."""

import importlib.util
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def _load():
    spec = importlib.util.spec_from_file_location("benchmarks_all", ROOT / "benchmarks" / "all.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_every_result_file_the_performance_page_cites_has_a_step():
    bench = _load()
    cited = set(re.findall(r"results[-a-z0-9]*\.json", (ROOT / "docs" / "performance.md").read_text()))
    made = {result for _, _, result in bench.STEPS}
    assert cited <= made, sorted(cited - made)
    for _, argv, _ in bench.STEPS:
        assert (ROOT / "benchmarks" / argv[0]).is_file(), argv[0]


def test_a_stopped_run_goes_on_where_it_stopped(tmp_path):
    """Steps done for this source are skipped; a failed step runs again; `fresh` runs all."""
    bench = _load()
    for name, code in (("ok.py", 0), ("bad.py", 1)):
        (tmp_path / name).write_text(
            "import pathlib, sys\n"
            f"p = pathlib.Path({str(tmp_path)!r}) / '{name}.runs'\n"
            "p.write_text(str(int(p.read_text()) + 1) if p.exists() else '1')\n"
            f"sys.exit({code})\n"
        )
    steps = [("ok", ["ok.py"], "results-ok.json"), ("bad", ["bad.py"], "results-bad.json")]
    state, out, said = tmp_path / "state.json", tmp_path / "all.json", []

    def runs(name):
        return int((tmp_path / f"{name}.runs").read_text())

    assert bench.run_steps(steps, state, out, folder=tmp_path, log=said.append) == 1
    assert (runs("ok.py"), runs("bad.py")) == (1, 1)
    assert bench.run_steps(steps, state, out, folder=tmp_path, log=said.append) == 1
    assert (runs("ok.py"), runs("bad.py")) == (1, 2) and any("ok: done for this source" in s for s in said)
    bench.run_steps(steps, state, out, fresh=True, folder=tmp_path, log=said.append)
    assert (runs("ok.py"), runs("bad.py")) == (2, 3)
    summary = bench.json.loads(out.read_text())
    assert [s["name"] for s in summary["steps"]] == ["ok", "bad"] and summary["steps"][1]["returncode"] == 1


def test_an_unknown_step_is_refused_with_exit_2(capsys):
    assert _load().main(["--only", "nonesuch", "--list"]) == 2
    assert "unknown step 'nonesuch'" in capsys.readouterr().err
