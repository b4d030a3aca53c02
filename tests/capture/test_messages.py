"""The messages of `jsphere convert` and its readers speak in the command's options and plain
words: every `--option` they advise exists (in `jsphere convert --help`, or in the help of the
command they name), no message names a Python parameter (`name=` or a snake_case parameter of the
readers), and the advice fits the format (a ROS bag's messages never advise `--up-axis`,
`--body-markers` or an alignment; a take with no labelled markers is refused saying so)."""

from __future__ import annotations

import argparse
import ast
import re
from pathlib import Path

import numpy as np
import pytest

import jsphere
from jsphere.cli.app import main, parser

ROOT = Path(jsphere.__file__).parent
FILES = sorted((ROOT / "capture").glob("*.py")) + [ROOT / "cli" / "convert.py"]
#: snake_case words that messages use as words of the file formats, not as Python parameters
FILE_WORDS = {"chi_dot"}


def _options() -> dict[str, set[str]]:
    """`{command: its option strings}` of the jsphere CLI, from its argparse parser."""
    sub = next(a for a in parser()._actions if isinstance(a, argparse._SubParsersAction))
    return {name: {o for action in p._actions for o in action.option_strings} for name, p in sub.choices.items()}


def _docstrings(tree: ast.AST) -> set[int]:
    ids = set()
    for node in ast.walk(tree):
        if isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)) and node.body:
            first = node.body[0]
            if isinstance(first, ast.Expr) and isinstance(first.value, ast.Constant):
                ids.add(id(first.value))
    return ids


def _messages(path: Path) -> list[tuple[int, str]]:
    """The text of the string literals of `path` (f-strings with `{}` for their fields) that are
    not docstrings, nor an option's own name in `add_argument`, with their lines."""
    tree = ast.parse(path.read_text())
    skip = _docstrings(tree)
    for node in ast.walk(tree):  # add_argument("--name", ...): the name itself
        if isinstance(node, ast.Call) and getattr(node.func, "attr", "") == "add_argument":
            skip.update(id(a) for a in node.args)
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.JoinedStr):
            text = "".join(v.value if isinstance(v, ast.Constant) else "{}" for v in node.values)
            out.append((node.lineno, text))
            skip.update(id(v) for v in node.values)
    for node in ast.walk(tree):
        if isinstance(node, ast.Constant) and isinstance(node.value, str) and id(node) not in skip:
            out.append((node.lineno, node.value))
    return out


def _parameters(paths) -> set[str]:
    """The snake_case parameter names of the functions of `paths`."""
    names = set()
    for path in paths:
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                a = node.args
                names.update(x.arg for x in a.posonlyargs + a.args + a.kwonlyargs if "_" in x.arg.strip("_"))
    return names - FILE_WORDS


OPTION = re.compile(r"(?<![\w-])--([a-z][a-z0-9-]*)")
COMMAND = re.compile(r"jsphere ([a-z][a-z-]*)")


@pytest.mark.parametrize("path", FILES, ids=lambda p: p.name)
def test_advised_options_exist(path):
    """Each `--option` in a message is an option of `jsphere convert`, or of the `jsphere
    <command>` the message names before it."""
    options = _options()
    bad = []
    for line, text in _messages(path):
        for m in OPTION.finditer(text):
            named = [c.group(1) for c in COMMAND.finditer(text[: m.start()]) if c.group(1) in options]
            command = named[-1] if named else "convert"
            if f"--{m.group(1)}" not in options[command]:
                bad.append(f"{path.name}:{line}: --{m.group(1)} is not an option of jsphere {command}: {text!r}")
    assert not bad, "\n".join(bad)


#: files whose messages still name Python parameters to the command's user (kept apart so that
#: the others stay checked): the text and line of each is in the failure this mark expects
OUTSTANDING: dict[str, str] = {}
PARAMS = [
    pytest.param(p, marks=pytest.mark.xfail(reason=OUTSTANDING[p.name])) if p.name in OUTSTANDING else p for p in FILES
]
#: a message to a Python caller names the function first (`rigid_body_pose: markers must be ...`),
#: and a repr its class (`Trial(name=...)`): they may name its parameters
TO_PYTHON = re.compile(r"^(\{\}: )?[a-z_]+[a-z0-9_]*: |^[A-Z][A-Za-z]*\(")


@pytest.mark.parametrize("path", PARAMS, ids=lambda p: p.name)
def test_no_python_parameter_names(path):
    """No message to the command's user names a Python parameter: no `name=` and no snake_case
    parameter of the capture modules (`allow_truncated`, `max_gap_fraction`, `up_axis`, ...)."""
    params = _parameters(FILES)
    functions = {n.name for f in FILES for n in ast.walk(ast.parse(f.read_text())) if isinstance(n, ast.FunctionDef)}
    word = re.compile(r"\b(" + "|".join(sorted(params, key=len, reverse=True)) + r")\b")
    bad = []
    for line, text in _messages(path):
        if " " not in text.strip():  # a key, a column name or a format, not a sentence
            continue
        head = TO_PYTHON.match(text)
        if head and (head.group(0).endswith("(") or head.group(0).removeprefix("{}: ")[:-2] in functions):
            continue
        if m := re.search(r"\b[a-z_][a-z0-9_]*=(?!=)", text):
            bad.append(f"{path.name}:{line}: {m.group(0)!r} in {text!r}")
        elif m := word.search(text):
            bad.append(f"{path.name}:{line}: parameter {m.group(0)!r} in {text!r}")
    assert not bad, "\n".join(bad)


def test_scanner_finds_what_it_looks_for(tmp_path):
    """The scan sees an f-string's words, skips docstrings, and knows the options."""
    src = tmp_path / "m.py"
    src.write_text(
        '"""Doc --nothing."""\n\ndef f(up_axis):\n    raise ValueError(f"{up_axis}: pass --no-such (x=1)")\n'
    )
    texts = [t for _, t in _messages(src)]
    assert texts == ["{}: pass --no-such (x=1)"]
    assert "--up-axis" in _options()["convert"] and "--no-such" not in _options()["convert"]
    assert "up_axis" in _parameters([src])


# --------------------------------------------------------------------------- format-specific cases


def _inputs(path: Path, t_end: float) -> Path:
    t = np.arange(0.0, t_end + 0.01, 0.01)
    path.write_text("t,chi_dot_1,chi_dot_2,chi_dot_3\n" + "".join(f"{v:.2f},0,0,0\n" for v in t))
    return path


def _convert(capsys, *args) -> tuple[int, str]:
    code = main(["convert", *map(str, args)])
    return code, capsys.readouterr().err


def _bag(path: Path, lying: bool = False) -> Path:
    """A ROS bag of a rolling ball's poses on `/mocap/robot/pose` and its wheels on
    `/joint_states` (`test_rosbag.write_bag`); `lying`: the platform turned on its side."""
    pytest.importorskip("rosbags")
    from test_rosbag import N, write_bag  # noqa: PLC0415

    t = np.arange(N) * 0.01
    p = np.stack([0.2 * np.sin(t), 0.1 * t**2, np.full(N, 0.15)], axis=1)
    yaw = 0.4 * t
    q = np.stack([np.cos(yaw / 2), 0 * t, 0 * t, np.sin(yaw / 2)], axis=1)
    if lying:  # a quarter turn about X after the heading
        c = np.sqrt(0.5)
        w, x, y, z = q.T
        q = np.stack([c * w, c * x + c * w, c * y + c * z, c * z - c * y], axis=1)
    chi = np.stack([np.sin(t + k) for k in range(3)], axis=1)
    return write_bag(path, (t, q, p, chi, 0.01 * chi), ros1=True)


BAG_ARGS = ["--format", "rosbag", "--pose-topic", "/mocap/robot/pose", "--inputs-topic", "/joint_states"]


def test_rosbag_options_that_do_not_apply(tmp_path, capsys):
    """A ROS bag's poses are in metres, Z up, of the pose topic's own frame: `--up-axis`,
    `--body-markers` and `--rigid-body` are refused, and the refusal advises none of them."""
    bag = _bag(tmp_path / "run.bag")
    body = tmp_path / "body.csv"
    body.write_text("name,x,y,z\na,0.1,0,0\nb,0,0.1,0\nc,0,0,0.1\n")
    for extra, says in (
        (["--up-axis", "y"], "drop --units and --up-axis"),
        (["--body-markers", body], "drop --body-markers"),
        (["--rigid-body", "robot"], "drop it"),
    ):
        code, err = _convert(capsys, bag, *BAG_ARGS, *extra, "--out", tmp_path / "t.csv")
        assert code == 2 and says in err and err.count("\n") == 1, err
        assert "alignment" not in err and "--body-markers FILE" not in err and "--up-axis y" not in err, err


def test_rosbag_warnings_advise_no_marker_options(tmp_path, capsys):
    """The plausibility warnings on a ROS bag's poses (a platform lying on its side) advise
    neither `--up-axis` nor `--body-markers` nor an alignment: the bag's frames are its own."""
    bag = _bag(tmp_path / "run.bag", lying=True)
    code, err = _convert(capsys, bag, *BAG_ARGS, "--out", tmp_path / "t.csv")
    assert code == 0 and "tilts" in err, err
    for word in ("--up-axis", "up_axis", "--body-markers", "alignment"):
        assert word not in err, err


def _qtm_3d(path: Path, names: list[str], n: int = 50) -> Path:
    rng = np.random.default_rng(0)
    head = [
        "NO_OF_FRAMES\t" + str(n), "NO_OF_CAMERAS\t8", f"NO_OF_MARKERS\t{len(names)}", "FREQUENCY\t100",
        "DATA_INCLUDED\t3D", "MARKER_NAMES\t" + "\t".join(names),
        "\t".join(["Frame", "Time", *(f"{m} {a}" for m in names for a in "XYZ")]),
    ]  # fmt: skip
    rows = [
        "\t".join([str(i + 1), f"{i / 100:.5f}", *(f"{v:.3f}" for v in 100 + rng.normal(0, 50, 3 * len(names)))])
        for i in range(n)
    ]
    path.write_text("\n".join(head + rows) + "\n")
    return path


def test_qtm_take_without_labelled_markers(tmp_path, capsys):
    """A QTM 3D take with no labelled markers, and a 6DOF take with no body, are refused
    saying so; the take with 3 labelled markers converts."""
    inputs = _inputs(tmp_path / "u.csv", 0.5)
    none = _qtm_3d(tmp_path / "none.tsv", [])
    code, err = _convert(capsys, none, "--format", "qualisys", "--inputs", inputs, "--out", tmp_path / "t.csv")
    assert code == 2 and "holds no labelled markers" in err and err.count("\n") == 1, err
    six = tmp_path / "none_6d.tsv"
    six.write_text("NO_OF_FRAMES\t2\nNO_OF_BODIES\t0\nFREQUENCY\t100\nDATA_INCLUDED\t6D\nBODY_NAMES\n1\t0.0\n2\t0.01\n")
    code, err = _convert(capsys, six, "--format", "qualisys", "--inputs", inputs, "--out", tmp_path / "t.csv")
    assert code == 2 and "holds no rigid body" in err, err


def test_vicon_take_with_only_unlabelled_markers(tmp_path, capsys):
    """A Nexus export whose trajectories are all unlabelled (`*N`) is refused saying it holds
    no labelled markers, and how many unlabelled ones."""
    names = ",".join(f",,*{i}" for i in range(18))[1:]
    rows = ["Trajectories", "100", "," + names.replace(",,", ",,", 1),
            "Frame,Sub Frame," + ",".join("X,Y,Z" for _ in range(18)),
            ",," + ",".join("mm,mm,mm" for _ in range(18))]  # fmt: skip
    rows += [f"{i + 1},0," + ",".join(f"{v:.2f}" for v in np.arange(54) + i) for i in range(30)]
    raw = tmp_path / "take.csv"
    raw.write_text("\n".join(rows) + "\n")
    code, err = _convert(
        capsys, raw, "--format", "vicon", "--inputs", _inputs(tmp_path / "u.csv", 0.3), "--out", tmp_path / "t.csv"
    )
    assert code == 2 and "no labelled markers (only 18 unlabelled ones" in err, err


def test_height_in_metres_not_exponents():
    """A height that varies by metres is said in metres, not as `8.8e+03 cm`."""
    from jsphere.capture.validation import _length  # noqa: PLC0415

    assert _length(88.0) == "88.00 m" and _length(0.031) == "3.1 cm"
