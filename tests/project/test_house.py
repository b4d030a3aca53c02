"""The rules of the house (docs/architecture.md), checked per package: no public callable over 12
parameters, no function body over 80 lines, drawing on top (nothing below `plots/` imports it)
and the start-up machinery named only in `cli/` and `_runtime/`.

A package known to break a rule is marked `xfail(strict=True)` below: the mark makes its case
fail as soon as the package keeps the rule, so that the mark goes."""

from __future__ import annotations

import ast
import dataclasses
import inspect
from pathlib import Path

import pytest

import jsphere

PACKAGE = Path(jsphere.__file__).resolve().parent
#: the top-level subpackages and modules of jsphere (`__init__`: the package's own module)
PACKAGES = sorted(
    {p.relative_to(PACKAGE).parts[0].removesuffix(".py") for p in PACKAGE.glob("*") if p.name != "__pycache__"}
)
#: the most parameters of a public callable (`**kwargs`, kept for compatibility, counts as none)
MAX_PARAMETERS = 12
#: the most lines of a function's body (its docstring included)
MAX_BODY_LINES = 80
#: the packages under `plots/` in the house, and those allowed to name the start-up machinery
BELOW_PLOTS = set(PACKAGES) - {"plots", "cli", "__init__"}
START_UP_HOMES = {"cli", "_runtime"}


def _cases(rule: str, failing: dict[str, str], packages=PACKAGES) -> list:
    """`packages` as parameters, those in `failing` marked as known to break `rule`."""
    return [
        pytest.param(p, marks=pytest.mark.xfail(strict=True, reason=f"{p}: {failing[p]} ({rule})"))
        if p in failing
        else p
        for p in sorted(packages)
    ]


def _files(package: str) -> list[Path]:
    if package == "__init__":
        return [PACKAGE / "__init__.py"]
    path = PACKAGE / package
    return sorted(path.rglob("*.py")) if path.is_dir() else [PACKAGE / f"{package}.py"]


def _package_of(module: str) -> str:
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else "__init__"


# ------------------------------------------------------------------------- (a) parameters


def _parameters(fn) -> int | None:
    """The parameters of `fn` a caller may pass (not `self`/`cls`, not `**kwargs`)."""
    try:
        sig = inspect.signature(fn)
    except (TypeError, ValueError):
        return None
    return sum(1 for p in sig.parameters.values() if p.kind is not p.VAR_KEYWORD and p.name not in ("self", "cls"))


def _is_data(cls) -> bool:
    """A data class or options object (a dataclass, an `eqx.Module`, a named tuple): its
    constructor lists its fields and is exempt."""
    return dataclasses.is_dataclass(cls) or (issubclass(cls, tuple) and hasattr(cls, "_fields"))


def public_callables() -> list[tuple[str, str, object]]:
    """`(package, name, callable)` of every public callable: the names `jsphere` exports and the
    public methods of the classes among them (their constructors, but a data class's)."""
    out = []
    for name in jsphere.__all__:
        obj = getattr(jsphere, name)
        if not callable(obj) or not getattr(obj, "__module__", "").startswith("jsphere"):
            continue
        package = _package_of(obj.__module__)
        if not inspect.isclass(obj):
            out.append((package, name, obj))
            continue
        if not _is_data(obj) and "__init__" in vars(obj):
            out.append((package, f"{name}()", obj))
        for attr in dir(obj):
            raw = inspect.getattr_static(obj, attr)
            fn = raw.__func__ if isinstance(raw, (staticmethod, classmethod)) else raw
            if attr.startswith("_") or not inspect.isfunction(fn) or not fn.__module__.startswith("jsphere"):
                continue
            out.append((package, f"{name}.{attr}", fn))
    return out


@pytest.mark.parametrize(
    "package",
    _cases(
        "public callables over 12 parameters",
        {},
    ),
)
def test_no_public_callable_over_12_parameters(package):
    long = {
        name: n
        for p, name, fn in public_callables()
        if p == package and (n := _parameters(fn)) is not None and n > MAX_PARAMETERS
    }
    assert not long, (
        f"{package}: public callables over {MAX_PARAMETERS} parameters (group options in an options object): {long}"
    )


def test_the_parameter_count_sees_one():
    """The count skips `self` and `**kwargs`, and a data class's constructor is exempt."""

    def f(self, a, b, *args, c=1, **kwargs):
        pass

    assert _parameters(f) == 4
    assert _is_data(jsphere.SolverOptions) and not _is_data(jsphere.InputError)


# --------------------------------------------------------------------------- (b) body length


def long_bodies(source: str, where: str) -> list[str]:
    """`where:line name (N lines)` of each function in `source` whose body is over
    `MAX_BODY_LINES` lines."""
    out = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            lines = node.end_lineno - node.body[0].lineno + 1
            if lines > MAX_BODY_LINES:
                out.append(f"{where}:{node.lineno} {node.name} ({lines} lines)")
    return out


@pytest.mark.parametrize(
    "package",
    _cases(
        "function bodies over 80 lines",
        {},
    ),
)
def test_no_function_body_over_80_lines(package):
    long = [f for p in _files(package) for f in long_bodies(p.read_text(), str(p.relative_to(PACKAGE)))]
    assert not long, f"{package}: function bodies over {MAX_BODY_LINES} lines: {long}"


def test_the_body_count_sees_one():
    source = "def f():\n" + "    x = 1\n" * 81 + "\n\ndef g():\n" + '    """doc"""\n' + "    x = 1\n" * 79
    assert long_bodies(source, "probe.py") == ["probe.py:1 f (81 lines)"]


# ------------------------------------------------------------------------- (c) drawing on top


def plots_imports(path: Path) -> list[str]:
    """The imports of `jsphere.plots` (lazy ones included) in `path`, as `line: module`."""
    module = ".".join(("jsphere", *path.relative_to(PACKAGE).with_suffix("").parts))
    package = module if path.name == "__init__.py" else module.rpartition(".")[0]
    out = []
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            targets = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = package.split(".")[: len(package.split(".")) - (node.level - 1)] if node.level else []
            targets = [".".join([*base, node.module] if node.module else base) if node.level else node.module or ""]
            targets += [f"{targets[0]}.{a.name}" for a in node.names]
        else:
            continue
        out += [f"{node.lineno}: {t}" for t in targets if t == "jsphere.plots" or t.startswith("jsphere.plots.")][:1]
    return out


@pytest.mark.parametrize(
    "package",
    _cases(
        "modules below plots/ that import it",
        {},
        BELOW_PLOTS,
    ),
)
def test_nothing_below_plots_imports_it(package):
    found = {str(p.relative_to(PACKAGE)): i for p in _files(package) if (i := plots_imports(p))}
    assert not found, f"{package} sits below plots/ but imports it (results are data; plots/ draws them): {found}"


# -------------------------------------------------------------------------- (d) start-up


def _start_up_name(node) -> str | None:
    """The start-up machinery `node` names: `FastStart`, a `programs` argument, field or
    keyword (`SolverOptions(programs=...)`), or JAX's exported programs (`jax.export`)."""
    if isinstance(node, ast.Name) and node.id in ("FastStart", "programs"):
        return node.id
    if isinstance(node, ast.Attribute) and node.attr in ("FastStart", "programs"):
        return f".{node.attr}"
    if isinstance(node, ast.Attribute) and node.attr == "export" and getattr(node.value, "id", "") == "jax":
        return "jax.export"
    if isinstance(node, ast.alias) and node.name.split(".")[-1] in ("FastStart", "export", "fast_start"):
        return f"import {node.name}"
    if isinstance(node, ast.ImportFrom) and (node.module or "").split(".")[-1] in ("export", "fast_start"):
        return f"from {node.module}"
    if isinstance(node, ast.keyword) and node.arg == "programs":
        return "programs="
    if isinstance(node, ast.arg) and node.arg == "programs":
        return "programs (argument)"
    if isinstance(node, ast.Constant) and isinstance(node.value, str) and "FastStart" in node.value:
        return "FastStart (in text)"
    return None


def start_up_names(path: Path) -> list[str]:
    tree = ast.parse(path.read_text())
    return sorted({f"{n.lineno}: {w}" for n in ast.walk(tree) if (w := _start_up_name(n)) and hasattr(n, "lineno")})


@pytest.mark.parametrize(
    "package",
    _cases(
        "start-up machinery named outside cli/ and _runtime/",
        {},
        set(PACKAGES) - START_UP_HOMES,
    ),
)
def test_no_start_up_machinery_outside_cli_and_runtime(package):
    found = {str(p.relative_to(PACKAGE)): n for p in _files(package) if (n := start_up_names(p))}
    assert not found, f"{package} names start-up machinery (it belongs to cli/ and _runtime/): {found}"
