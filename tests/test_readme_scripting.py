"""The README's scripting example runs as written, through the public API only."""
from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_readme_scripting_example_runs(monkeypatch, capsys):
    text = (ROOT / "README.md").read_text()
    section = text.split("## Scripting", 1)[1].split("\n## ", 1)[0]
    code = re.search(r"```python\n(.*?)```", section, re.S).group(1)
    assert "import calib" in code and "import optimize" in code
    assert not re.search(r"from (calib|optimize)\.", code), "the example must use the front door only"
    monkeypatch.chdir(ROOT)
    exec(compile(code, "README.md#scripting", "exec"), {"__name__": "readme"})
    out = capsys.readouterr().out
    assert "Thermal-DP" in out and " g over " in out
