# Two commands from a fresh clone: `make demo` and `make test`.
# Each creates .venv when missing and installs what is needed.
# Bring your own torch: `make test TORCH_SPEC="torch==2.5.1"` or install it in .venv first
# (an installed torch is never replaced).
PYTHON ?= python3
VENV ?= .venv
TORCH_SPEC ?= torch==2.13.0
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: demo test bench clean-venv

$(BIN)/python:
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip

$(STAMP): pyproject.toml | $(BIN)/python
	$(BIN)/python -c "import torch" 2>/dev/null || $(BIN)/pip install "$(TORCH_SPEC)"
	$(BIN)/pip install --quiet -e ".[test]"
	touch $(STAMP)

demo: $(STAMP)
	$(BIN)/pressurepose demo --out out/demo

# ruff (lint + format check), then the suite; tests/test_architecture.py runs import-linter's
# layers contract (docs/architecture.md).
test: $(STAMP)
	$(BIN)/ruff check src tests benchmarks
	$(BIN)/ruff format --check src tests benchmarks
	$(BIN)/python -m pytest -q

bench: $(STAMP)
	$(BIN)/python benchmarks/body.py
	$(BIN)/python benchmarks/sampling.py
	$(BIN)/python benchmarks/sim.py
	$(BIN)/python benchmarks/sim1_floor.py

clean-venv:
	rm -rf $(VENV)
