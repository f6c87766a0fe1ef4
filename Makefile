# Two commands are the contract (see README): `make run` and `make test`.
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: run test test-slow test-browser screenshots browser bench venv clean

$(STAMP): pyproject.toml
	$(PY) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q -e ".[test,mdf]"
	touch $(STAMP)

venv: $(STAMP)

## main job: the whole chain on the bundled logs, report into reports/
run: $(STAMP)
	MPLBACKEND=Agg $(BIN)/iptm run

## the test suite that CI runs
test: $(STAMP)
	MPLBACKEND=Agg $(BIN)/python -m pytest -q -m "not slow and not browser"

test-slow: $(STAMP)
	MPLBACKEND=Agg $(BIN)/python -m pytest -q -m slow

## real-browser dashboard test (needs Chromium + playwright: scripts/install_browser.sh)
browser: $(STAMP)
	VENV_PY=$(BIN)/python bash scripts/install_browser.sh

test-browser: $(STAMP)
	IPTM_REQUIRE_BROWSER=1 MPLBACKEND=Agg $(BIN)/python -m pytest -q -m browser -rs tests/test_browser.py

## the README's dashboard screenshots (bundled logs, whole cycle, paper grids) into reports/figures/
screenshots: $(STAMP)
	IPTM_README_SHOTS=1 IPTM_REQUIRE_BROWSER=1 MPLBACKEND=Agg $(BIN)/python -m pytest -q -m browser -rs tests/test_browser.py

bench: $(STAMP)
	MPLBACKEND=Agg $(BIN)/iptm bench

clean:
	rm -rf $(VENV) .pytest_cache
