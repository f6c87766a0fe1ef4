"""The application layer and the studies use ``calib`` and ``optimize`` only through their front doors.

What is enforced, on every ``.py`` file under ``iptm/``, ``pages/`` and ``studies/`` and on ``app.py``:

* A **front door** is the package ``calib``, the package ``optimize``, or one of their sub-packages (a folder
  with an ``__init__.py``, no path segment starting with ``_``) whose ``__init__`` defines ``__all__``
  (today ``calib.model``, ``calib.fit``, ``calib.ingest``, ``optimize.dp``, ``optimize.formulations``,
  ``optimize.causal``). Its public names are exactly its ``__all__``.
* ``import D`` (or ``import D as x``) is allowed only when ``D`` is a front door.
* ``from D import n`` is allowed only when ``D`` is a front door and ``n`` is in ``D.__all__`` or ``D.n``
  is itself a front door. So ``from calib.model.params import ParameterSet`` (a module, not a door) and
  ``from calib.fit import _private`` (not in ``__all__``) are refused.
* An attribute chain on a name bound by such an import (``calib.model.simulate``) may only step from a door
  to a sub-door or to a name in the door's ``__all__``; past that name the attributes are the object's own.

Not covered: imports by string (``importlib.import_module``) and files loaded by path
(``studies/kernel_ab`` loads an earlier revision's kernel file from git, on purpose).
"""
from __future__ import annotations

import ast
import importlib
from functools import cache
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
CHECKED = sorted(p for d in ("iptm", "pages", "studies") for p in (ROOT / d).rglob("*.py")) + [ROOT / "app.py"]
TOPS = ("calib", "optimize")


def _doors() -> set[str]:
    out = set()
    for top in TOPS:
        for init in (ROOT / top).rglob("__init__.py"):
            parts = init.parent.relative_to(ROOT).parts
            if any(p.startswith("_") for p in parts):
                continue
            name = ".".join(parts)
            if hasattr(importlib.import_module(name), "__all__"):
                out.add(name)
    return out


DOORS = _doors()


@cache
def _public(door: str) -> frozenset:
    return frozenset(importlib.import_module(door).__all__)


def _chain(node: ast.Attribute) -> list[str] | None:
    """``a.b.c`` as ["a", "b", "c"], or None when the chain does not start at a plain name."""
    out = []
    while isinstance(node, ast.Attribute):
        out.append(node.attr)
        node = node.value
    if not isinstance(node, ast.Name):
        return None
    return [node.id] + out[::-1]


def violations(path: Path) -> list[str]:
    """Every use of ``calib`` or ``optimize`` in ``path`` that goes past a front door, as "line: what"."""
    tree = ast.parse(path.read_text(), str(path))
    _mark_parents(tree)  # an inner link of a chain is checked as part of its whole chain
    bad, bound = [], {}  # bound: local name -> the door it names
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for a in node.names:
                if a.name.split(".")[0] not in TOPS:
                    continue
                if a.name not in DOORS:
                    bad.append(f"{node.lineno}: import {a.name} (not a front door)")
                    continue
                # `import calib.model` binds `calib`; `import calib.model as m` binds `m` to calib.model
                bound[a.asname] = a.name if a.asname else None
                if not a.asname:
                    bound[a.name.split(".")[0]] = a.name.split(".")[0]
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module \
                and node.module.split(".")[0] in TOPS:
            if node.module not in DOORS:
                bad.append(f"{node.lineno}: from {node.module} import ... (not a front door)")
                continue
            for a in node.names:
                sub = f"{node.module}.{a.name}"
                if sub in DOORS:
                    bound[a.asname or a.name] = sub
                elif a.name not in _public(node.module):
                    bad.append(f"{node.lineno}: from {node.module} import {a.name} (not in its __all__)")
    bound.pop(None, None)
    for node in ast.walk(tree):
        if not isinstance(node, ast.Attribute) or isinstance(getattr(node, "_parent", None), ast.Attribute):
            continue
        chain = _chain(node)
        if not chain or chain[0] not in bound:
            continue
        door = bound[chain[0]]
        for attr in chain[1:]:
            if f"{door}.{attr}" in DOORS:
                door = f"{door}.{attr}"
            elif attr in _public(door):
                break
            else:
                bad.append(f"{node.lineno}: {'.'.join(chain)} ({door}.{attr} is not in {door}.__all__)")
                break
    return bad


def _mark_parents(tree):
    for n in ast.walk(tree):
        for c in ast.iter_child_nodes(n):
            c._parent = n


def test_the_front_doors_are_the_documented_packages():
    assert {"calib", "optimize", "calib.model", "calib.fit", "calib.ingest", "optimize.formulations"} <= DOORS
    assert not any(d.split(".")[-1].startswith("_") for d in DOORS)


def test_the_check_sees_each_kind_of_violation(tmp_path):
    f = tmp_path / "m.py"
    f.write_text("import calib\nimport calib.model.params\nfrom calib.model.params import ParameterSet\n"
                 "from calib.fit import _fill\nfrom optimize import formulations as F\n"
                 "x = calib.model.simulate\ny = calib.store.Store\nz = F.solve.build_problem\n")
    found = violations(f)
    assert [v.split(":")[0] for v in found] == ["2", "3", "4", "7", "8"], found
    f.write_text("import calib\nimport optimize.formulations as F\nfrom calib.model import ParameterSet, ftp\n"
                 "from optimize import formulations\nx = calib.model.simulate\ny = F.DPScenario().cycle\n"
                 "z = formulations.build_problem\nw = calib.read_log('x').data.index\n")
    assert violations(f) == []


def test_app_layer_and_studies_use_only_the_front_doors():
    bad = []
    for f in CHECKED:
        bad += [f"{f.relative_to(ROOT)}:{v}" for v in violations(f)]
    assert not bad, "past a front door (export the name from a door's __all__, or use one that is):\n" + "\n".join(bad)
