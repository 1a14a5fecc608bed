# Two commands do everything on a fresh machine: `make test` and `make demo`.
# Both create .venv, install system and Python packages, then run.
SHELL := /bin/bash
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.wreckmap-installed
# The suite on three workers (pytest-xdist) for two cores: whole files at a time, the
# longest first (the order tests/conftest.py gives them). A third worker fills the time
# the others wait on subprocesses, pseudo-terminals and real-time recordings (the tests
# used 1200 s of CPU in 1950 s of test time). PYTEST_WORKERS=0 runs it in one process.
PYTEST_WORKERS ?= 3
PYTEST_PARALLEL := -n $(PYTEST_WORKERS) --dist loadfile --no-loadscope-reorder

.PHONY: setup test test-fast lint demo bench clean

setup: $(STAMP)

$(STAMP): pyproject.toml package.json package-lock.json deploy/setup.sh deploy/system-packages.txt
	PYTHON=$(PYTHON) VENV=$(VENV) bash deploy/setup.sh
	touch $(STAMP)

lint: setup
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .
	$(BIN)/mypy

test: lint
	$(BIN)/pytest $(PYTEST_PARALLEL)

# Skips tests marked slow: for a quick loop while editing.
test-fast: setup
	$(BIN)/pytest $(PYTEST_PARALLEL) -m "not slow and not hardware and not gpu"

demo: setup
	$(BIN)/python bench/demo.py --out demo-output

# Every benchmark in turn; each prints its figures (some run for minutes).
bench: setup
	set -e; for script in bench/bench_*.py; do echo "== $$script"; $(BIN)/python $$script; done

clean:
	rm -rf $(VENV) .pytest_cache .mypy_cache .ruff_cache demo-output bench-output
