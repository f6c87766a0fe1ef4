"""The front-door examples in the package docstrings run as written (from the repository root, where the
bundled logs are)."""
from __future__ import annotations

import doctest
import importlib
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.parametrize("name", ["calib", "optimize", "iptm"])
def test_front_door_examples_run(name, monkeypatch):
    monkeypatch.chdir(ROOT)
    mod = importlib.import_module(name)
    res = doctest.testmod(mod, optionflags=doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE, report=True)
    assert res.failed == 0, f"{name}: {res.failed} of {res.attempted} docstring example(s) failed (printed above)"
    if name == "calib":
        assert res.attempted >= 4  # the example is a doctest, not a literal block that nothing runs
