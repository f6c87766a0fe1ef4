# Two commands are the contract (see README): `make run` and `make test`.
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: run test test-slow test-browser screenshots browser bench venv clean mutation mutation-sample figures figures-check lint docs

$(STAMP): pyproject.toml
	$(PY) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q -e ".[test,mdf,docs]"
	touch $(STAMP)

venv: $(STAMP)

## main job: the whole chain on the bundled logs, report into reports/
run: $(STAMP)
	MPLBACKEND=Agg $(BIN)/iptm run

## the test suite that CI runs; it lists its 15 slowest tests (full-size checks belong in test-slow)
test: $(STAMP)
	MPLBACKEND=Agg $(BIN)/python -m pytest -q -m "not slow and not browser" --durations=15

## static checks (ruff, configured in pyproject.toml); CI runs them before the tests
lint: $(STAMP)
	$(BIN)/ruff check .

## the full-size checks left out of `make test` (tens of minutes to hours on 2 cores)
test-slow: $(STAMP)
	MPLBACKEND=Agg $(BIN)/python -m pytest -q -m "slow and not browser"

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

## mutation testing of the core modules (long: hours on 2 cores); score and survivors -> reports/mutation.json
mutation: $(STAMP)
	$(BIN)/python scripts/mutation.py --jobs 2 --out reports/mutation.json

## a small seeded sample (a few mutants per module, minutes) for CI
mutation-sample: $(STAMP)
	$(BIN)/python scripts/mutation.py --module calib/ingest/resample.py --module calib/units.py --sample 4 --seed 0 --out reports/mutation-sample.json

## re-run the benchmarks behind the README's figures and rewrite them; figures-check compares without re-running
figures: $(STAMP)
	MPLBACKEND=Agg $(BIN)/python scripts/figures.py run

figures-check: $(STAMP)
	$(BIN)/python scripts/figures.py check

## the documentation site (Sphinx, from docs/ and the docstrings) into docs/_build/html; warnings are errors
docs: $(STAMP)
	test -x $(BIN)/sphinx-build || $(BIN)/python -m pip install -q -e ".[docs]"
	$(BIN)/sphinx-build -W --keep-going -b html docs docs/_build/html

clean:
	rm -rf $(VENV) .pytest_cache
