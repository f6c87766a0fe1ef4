"""The package structure: layers import in one direction, no import cycles, a documented public API.

The test cars (``testcars``: foreign and perturbed plants, fabricated logs) sit beside the physics: they
import ``calib``, and neither ``calib`` nor ``optimize`` may import them."""
from __future__ import annotations

import ast
import importlib
import inspect
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("calib", "optimize", "iptm", "testcars")
#: what each layer may import of the project (besides itself)
ALLOWED = {"calib": set(), "optimize": {"calib"}, "testcars": {"calib"}, "iptm": {"calib", "optimize", "testcars"}}
API_MODULES = ("calib", "calib.model", "calib.fit", "calib.ingest", "optimize", "optimize.dp",
               "optimize.formulations")


def _modules():
    for pkg in PACKAGES:
        for f in sorted((ROOT / pkg).rglob("*.py")):
            parts = f.relative_to(ROOT).with_suffix("").parts
            name = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
            yield name, f, parts[-1] == "__init__"


MODULES = {name: (f, is_pkg) for name, f, is_pkg in _modules()}


def _imports(name: str, f: Path, is_pkg: bool):
    """Every project module ``name`` imports (at module level or inside functions), as (line, target)."""
    pkg = name if is_pkg else name.rpartition(".")[0]
    for node in ast.walk(ast.parse(f.read_text(), str(f))):
        if isinstance(node, ast.Import):
            for a in node.names:
                yield node.lineno, a.name
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = pkg.split(".")
                base = base[: len(base) - (node.level - 1)]
                mod = ".".join(base + ([node.module] if node.module else []))
            else:
                mod = node.module or ""
            for a in node.names:
                sub = f"{mod}.{a.name}"
                yield node.lineno, sub if sub in MODULES else mod


def _project(target: str) -> str | None:
    top = target.split(".")[0]
    return top if top in PACKAGES else None


def test_layers_import_one_way():
    bad = []
    for name, (f, is_pkg) in MODULES.items():
        layer = name.split(".")[0]
        for line, tgt in _imports(name, f, is_pkg):
            other = _project(tgt)
            if other and other != layer and other not in ALLOWED[layer]:
                bad.append(f"{f.relative_to(ROOT)}:{line} imports {tgt}")
    assert not bad, "layer rule (calib <- optimize <- iptm, calib <- testcars <- iptm) broken:\n" + "\n".join(bad)


def test_no_import_cycles():
    graph = {n: set() for n in MODULES}
    for name, (f, is_pkg) in MODULES.items():
        for _, tgt in _imports(name, f, is_pkg):
            while tgt and tgt not in MODULES:  # `from pkg.mod import name` -> pkg.mod
                tgt = tgt.rpartition(".")[0]
            # a package's __init__ re-exporting its own submodules is the front door, not a cycle
            if tgt and tgt != name and not (is_pkg and tgt.startswith(name + ".")):
                graph[name].add(tgt)
    cycles, state = [], {}

    def visit(n, stack):
        state[n] = 1
        stack.append(n)
        for m in sorted(graph[n]):
            if state.get(m) == 1:
                cycles.append(stack[stack.index(m):] + [m])
            elif m not in state:
                visit(m, stack)
        stack.pop()
        state[n] = 2

    for n in sorted(graph):
        if n not in state:
            visit(n, [])
    assert not cycles, "import cycles:\n" + "\n".join(" -> ".join(c) for c in cycles)


def test_the_checks_see_a_violation(tmp_path):
    """The walkers above find imports inside functions and relative imports (so they can fail)."""
    f = tmp_path / "m.py"
    f.write_text("def g():\n    from ..optimize import dp\n    import iptm.cli\n")
    found = {t for _, t in _imports("calib.x.m", f, False)}
    assert "calib.optimize" in found or "calib.optimize.dp" in found
    assert "iptm.cli" in found


def _public_api():
    for modname in API_MODULES:
        mod = importlib.import_module(modname)
        assert hasattr(mod, "__all__"), f"{modname} has no __all__"
        for name in mod.__all__:
            assert hasattr(mod, name), f"{modname}.__all__ names {name}, which it does not define"
            obj = getattr(mod, name)
            if inspect.isfunction(obj) or inspect.isclass(obj) or hasattr(obj, "py_func"):
                yield f"{modname}.{name}", obj


@pytest.mark.parametrize("qualname,obj", list(_public_api()), ids=lambda v: v if isinstance(v, str) else "")
def test_public_api_is_documented(qualname, obj):
    doc = inspect.getdoc(getattr(obj, "py_func", obj))
    assert doc and len(doc.strip()) >= 10, f"{qualname} has no docstring"
    if inspect.isclass(obj):
        missing = [m for m, v in vars(obj).items()
                   if not m.startswith("_") and (inspect.isfunction(v) or isinstance(v, property))
                   and not inspect.getdoc(v.fget if isinstance(v, property) else v)]
        assert not missing, f"{qualname}: public methods without a docstring: {missing}"
