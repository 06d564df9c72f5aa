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
	$(BIN)/pressurepose pose --out out/demo/pose
	$(BIN)/pressurepose sample --out out/demo/sample --n 96 --partition general
	$(BIN)/pressurepose simulate --out out/demo/simulate --partition supine --gender male --index 3
	$(BIN)/pressurepose generate --out out/demo/data --preset tiny
	$(BIN)/pressurepose info out/demo/data
	$(BIN)/pressurepose train --data out/demo/data --out out/demo/run --preset smoke --epochs 2
	$(BIN)/pressurepose evaluate --model out/demo/run --data out/demo/data --out out/demo/report

test: $(STAMP)
	$(BIN)/python -m pytest -q

bench: $(STAMP)
	$(BIN)/python benchmarks/body.py
	$(BIN)/python benchmarks/sampling.py
	$(BIN)/python benchmarks/sim.py

clean-venv:
	rm -rf $(VENV)
