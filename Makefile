# Quick start: `make run` (= bgrl up: the whole platform) and `make test` (lint + tests).
PYTHON ?= $(shell command -v python3.11 || command -v python3)
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed

.PHONY: install run test lint format bench reproduce clean

$(STAMP): pyproject.toml requirements.lock
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -c requirements.lock -e '.[dev]'
	touch $(STAMP)

install: $(STAMP)

run: install
	$(VENV)/bin/bgrl up

lint: install
	$(VENV)/bin/ruff check services benchmarks tests
	$(VENV)/bin/ruff format --check services benchmarks tests
	$(VENV)/bin/lint-imports

format: install
	$(VENV)/bin/ruff check --fix services benchmarks tests
	$(VENV)/bin/ruff format services benchmarks tests

# Two test processes (pytest-xdist; a module's tests share one, so do tests/deploy's, see
# tests/conftest.py): less wall time on 2 cores. `make test TEST_PROCESSES=0`: one process.
TEST_PROCESSES ?= 2

test: lint
	$(PY) -m pytest -n $(TEST_PROCESSES)

bench: install
	$(VENV)/bin/bgrl bench all --out benchmarks/results

reproduce: install
	$(VENV)/bin/bgrl reproduce --out results/reproduce

clean:
	rm -rf $(VENV) .pytest_cache .ruff_cache
