"""The package's layering: imports flow from higher layers to lower ones, never back, and no two
modules import each other, directly or through others (lazy imports inside functions included)."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[2] / "jsphere"

#: Each subpackage (or top-level module) and its layer: a module may import from its own
#: subpackage and from lower layers only.
LAYERS = {
    "_runtime": 0,
    "numerics": 0.5,  # least squares, sine and cosine: know nothing of the robot; import only `_runtime`
    "model": 2,
    "controls": 3,
    "solve.batched": 4,
    "solve": 5,
    "gaits": 6,
    "capture": 7,
    "identify": 8,
    "planning": 8,
    "montecarlo": 8.5,  # studies replay the feedback tables of `planning.tracking` (a study's `track` key)
    "paper": 9,
    "design": 9,  # excitation design: identify, planning, capture, solve, model
    "plots": 9.5,  # draws the result objects of the layers below (animations replay fits and studies)
    "cli": 10,  # one module per command; reads files into results and hands them to plots
    "__init__": 11,
}


def _modules() -> dict[str, Path]:
    out = {}
    for f in sorted(PACKAGE.rglob("*.py")):
        parts = f.relative_to(PACKAGE).with_suffix("").parts
        if parts[-1] == "__init__":
            parts = parts[:-1]
        out[".".join(("jsphere", *parts))] = f
    return out


def _imports(name: str, path: Path, known: set[str]) -> set[str]:
    """The jsphere modules that `name` imports anywhere in its source."""
    is_package = path.name == "__init__.py"
    package = name if is_package else name.rpartition(".")[0]
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            found |= {a.name for a in node.names if a.name == "jsphere" or a.name.startswith("jsphere.")}
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[: len(base) - (node.level - 1)]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            if not target.startswith("jsphere"):
                continue
            for alias in node.names:  # `from pkg import module` imports the module
                sub = f"{target}.{alias.name}"
                found.add(sub if sub in known else target)
    found.discard(name)
    return found


def _layer(module: str) -> tuple[str, int]:
    if module == "jsphere":
        return "__init__", LAYERS["__init__"]
    rest = module.split(".")[1:]
    for n in (2, 1):
        key = ".".join(rest[:n])
        if len(rest) >= n and key in LAYERS:
            return key, LAYERS[key]
    raise KeyError(module)


GRAPH = {name: _imports(name, path, set(_modules())) for name, path in _modules().items()}


def test_every_module_has_a_layer():
    unplaced = []
    for name in GRAPH:
        try:
            _layer(name)
        except KeyError:
            unplaced.append(name)
    assert not unplaced, f"modules outside every layer (add them to LAYERS): {unplaced}"


@pytest.mark.parametrize("name", sorted(GRAPH))
def test_imports_flow_down(name):
    group, rank = _layer(name)
    upward = []
    for target in GRAPH[name]:
        tgroup, trank = _layer(target)
        if tgroup != group and not trank < rank:
            upward.append(f"{target} ({tgroup}, layer {trank})")
    assert not upward, f"{name} ({group}, layer {rank}) imports from a layer at or above its own: {upward}"


def test_no_import_cycles():
    state: dict[str, int] = {}
    stack: list[str] = []

    def visit(m):
        state[m] = 1
        stack.append(m)
        for t in sorted(GRAPH.get(m, ())):
            if state.get(t) == 1:
                cycle = stack[stack.index(t) :] + [t]
                pytest.fail("import cycle: " + " -> ".join(cycle))
            if t in GRAPH and not state.get(t):
                visit(t)
        stack.pop()
        state[m] = 2

    for m in sorted(GRAPH):
        if not state.get(m):
            visit(m)


def _package(module: str) -> str:
    """The top-level subpackage (or top-level module) that `module` belongs to."""
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else "__init__"


def _private_imports(name: str, path: Path, known: set[str]) -> list[str]:
    """`_`-prefixed names that `name` imports from another subpackage (a module's own name,
    such as `_runtime`, is not a private name)."""
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    out = []
    for node in ast.walk(ast.parse(path.read_text())):
        if not isinstance(node, ast.ImportFrom):
            continue
        if node.level:
            base = package.split(".")
            base = base[: len(base) - (node.level - 1)]
            target = ".".join(base + ([node.module] if node.module else []))
        else:
            target = node.module or ""
        if not target.startswith("jsphere") or _package(target) == _package(name):
            continue
        out += [
            f"{target}.{a.name} (line {node.lineno})"
            for a in node.names
            if a.name.startswith("_") and f"{target}.{a.name}" not in known
        ]
    return out


def test_no_private_names_across_packages():
    """What a package shares with others is public inside it (`jsphere.<package>.internal`):
    no module imports another package's `_`-prefixed names."""
    modules = _modules()
    found = {name: _private_imports(name, path, set(modules)) for name, path in modules.items()}
    found = {k: v for k, v in found.items() if v}
    assert not found, f"private names imported across packages: {found}"


def test_private_import_check_sees_one(tmp_path):
    """The check above flags a planted import of another package's private name."""
    f = tmp_path / "probe.py"
    f.write_text("from ..model.params import _FIELDS, RobotParams\nfrom .problem import _duration\n")
    found = _private_imports("jsphere.planning.probe", f, set(_modules()))
    assert found == ["jsphere.model.params._FIELDS (line 1)"]


#: the machinery of a quick start (exported programs, equinox's error mode, the persistent
#: cache, first-call records): the command line's, or a caller's explicit choice. (The compiler
#: options of eager programs, `jsphere._runtime.quick_compile`, are a property of the programs.)
START_UP = {
    "jsphere._runtime.fast_start",
    "jsphere._runtime.compilation_cache",
    "jsphere._runtime.progress",
}
#: the numerical core: pure functions of their arguments
PURE = ("model", "controls", "solve", "solve.batched", "gaits")


def _reachable(name: str) -> set[str]:
    seen, todo = set(), [name]
    while todo:
        for target in GRAPH.get(todo.pop(), ()):
            if target not in seen:
                seen.add(target)
                todo.append(target)
    return seen


@pytest.mark.parametrize("name", sorted(n for n in GRAPH if _layer(n)[0] in PURE))
def test_the_core_imports_no_start_up_machinery(name):
    """`simulate`, `simulate_gaits` and the batch engine read and switch no process-global
    state: what makes a first call quick is the application's (`jsphere.cli.compilation`)."""
    assert not (_reachable(name) & START_UP), f"{name} reaches {sorted(_reachable(name) & START_UP)}"
    private = PACKAGE / "_runtime" / "private.py"
    for node in ast.walk(ast.parse(Path(GRAPH and _modules()[name]).read_text())):
        if isinstance(node, ast.ImportFrom) and (node.module or "").endswith("private"):
            names = {a.name for a in node.names}
            assert names <= {"rk_tableau"}, f"{name} imports {names} from {private.name}"
