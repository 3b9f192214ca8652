# Quickstart: `make demo` then `make test`. Both bootstrap .venv from nothing.
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed

.PHONY: demo test lint bench bench-deps clean

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q -e '.[test]'
	touch $(STAMP)

demo: $(STAMP)
	JAX_PLATFORMS=cpu $(VENV)/bin/cpgjax demo

# The test files spread over one pytest-xdist worker per CPU (-n auto, at most 4), each file's tests in one worker,
# so that a module's compiled fixtures are built once.
test: $(STAMP)
	JAX_PLATFORMS=cpu $(PY) -m pytest -q -n auto --maxprocesses 4 --dist loadfile

# Ruff's formatter (a file it would change fails), then its rules (pyproject.toml's [tool.ruff]), then the dead-code
# check ([tool.vulture]: what nothing in the package, tests, benchmarks or studies uses).
lint: $(STAMP)
	$(VENV)/bin/ruff format --check .
	$(VENV)/bin/ruff check .
	$(VENV)/bin/vulture

bench: $(STAMP)
	JAX_PLATFORMS=cpu $(PY) benchmarks/rollout.py --quick

# What the benchmarks import beyond the package (benchmarks/bo.py: torch, BoTorch).
bench-deps: $(STAMP)
	$(PY) -m pip install -q -e '.[bench]'

clean:
	rm -rf $(VENV) .pytest_cache .ruff_cache
