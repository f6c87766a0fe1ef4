#!/usr/bin/env bash
# A normal (non-editable) install in a fresh virtual environment, used from a folder that holds no source:
# `iptm run` on the bundled logs, and the dashboard (app.py and pages/ only) loading the bundled logs.
# Usage: bash scripts/check_install.sh [WORKDIR]   (default: a new temporary folder)
set -euo pipefail
src="$(cd "$(dirname "$0")/.." && pwd)"
work="${1:-$(mktemp -d -t iptm-install-XXXX)}"
mkdir -p "$work"
python3 -m venv "$work/venv"
"$work/venv/bin/python" -m pip install -q --upgrade pip
"$work/venv/bin/python" -m pip install -q "$src"
mkdir -p "$work/app" "$work/run"
cp -r "$src/app.py" "$src/pages" "$src/.streamlit" "$work/app/"
cd "$work/run"
MPLBACKEND=Agg "$work/venv/bin/iptm" run --quiet | tail -12
cd "$work/app"
"$work/venv/bin/python" - <<'PY'
import iptm
from streamlit.testing.v1 import AppTest

at = AppTest.from_file("app.py", default_timeout=240)
at.run()
assert not at.exception, [e.value for e in at.exception]
at.button(key="load_bundled").click()
at.run()
assert not at.exception and not at.error, ([e.value for e in at.exception], [e.value for e in at.error])
names = list(at.session_state["iptm_logs"])
assert len(names) == 3, names
print(f"dashboard from the installed package ({iptm.__file__}) loaded the bundled logs: {names}")
PY
echo "non-editable install OK in $work"
