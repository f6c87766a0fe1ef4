#!/usr/bin/env bash
# Installs what the real-browser dashboard test (tests/test_browser.py, `make test-browser`) needs:
# Chromium from the system packages (Debian: chromium, chromium-driver) and the playwright Python package
# into .venv. Playwright's own browser download is not used: the test launches /usr/bin/chromium.
set -euo pipefail
cd "$(dirname "$0")/.."
SUDO=""
if [ "$(id -u)" != 0 ]; then SUDO="sudo"; fi
if ! command -v chromium >/dev/null 2>&1; then
    $SUDO apt-get update -qq
    $SUDO apt-get install -y -qq chromium chromium-driver
fi
PY="${VENV_PY:-.venv/bin/python}"
"$PY" -m pip install -q "playwright>=1.40"
chromium --version
"$PY" -c "import playwright.sync_api; print('playwright ok')"
