# Two commands on a fresh machine (only Python ≥ 3.11 needed):
#   make demo   — create .venv, install everything, run the main job end to end on the twin
#   make test   — create .venv if needed, run the whole test suite (CI runs exactly this)
PYTHON ?= python3
VENV   ?= .venv
BIN     = $(VENV)/bin
LAB    ?= lab

.PHONY: demo test test-under-load lint format bench clean

$(BIN)/.installed: pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[dev]'
	touch $@

demo: $(BIN)/.installed
	$(BIN)/vslab --lab $(LAB) demo

test: $(BIN)/.installed
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .
	$(BIN)/python -m pytest

# the whole suite with every core busy (a CPU-bound process per core): real-time tests must hold there too
test-under-load: $(BIN)/.installed
	$(BIN)/python bench/load.py -- $(BIN)/python -m pytest

bench: $(BIN)/.installed
	$(BIN)/python bench/twin_kernel.py
	$(BIN)/python bench/devices.py
	$(BIN)/python bench/record.py
	$(BIN)/python bench/rig.py
	$(BIN)/python bench/acquire.py --seconds 60
	$(BIN)/python bench/simulate.py
	$(BIN)/python bench/ingest.py
	$(BIN)/python bench/can_bus.py
	$(BIN)/python bench/bus.py

lint format: $(BIN)/.installed
	$(BIN)/ruff check --fix .
	$(BIN)/ruff format .

clean:
	rm -rf $(VENV) $(LAB) .pytest_cache .ruff_cache
