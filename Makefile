# Two commands on a fresh machine (only Python ≥ 3.11 needed):
#   make demo   — create .venv, install everything, run the main job end to end on the twin
#   make test   — create .venv if needed, run the whole test suite (CI runs exactly this)
#   make check  — lint and the fast tier (every test not marked slow): what to run while working
PYTHON ?= python3
VENV   ?= .venv
BIN     = $(VENV)/bin
LAB    ?= lab

.PHONY: demo test check test-under-load lint format bench loop docs clean

$(BIN)/.installed: pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[dev]'
	touch $@

# The project's own modules byte-compiled (only those changed since): pip compiles what it installs, but an
# editable install leaves the project's sources to the interpreter, and where PYTHONDONTWRITEBYTECODE is set
# (as on this project's machines) every process compiled every module it imported again: ~0.15 s of each
# command, daemon and rig the suite starts (`vslab --help` 0.6 → 0.44 s). A stale file is still recompiled.
COMPILE = $(BIN)/python -m compileall -q -j 0 acquisition analysis models pipeline twin vslab > /dev/null

demo: $(BIN)/.installed
	$(COMPILE)
	$(BIN)/vslab --lab $(LAB) demo

# The suite runs in a worker process per core (pytest-xdist), each computing on one thread (tests/conftest.py):
# on 2 cores the fast tier 145 → 92 s. `--dist loadgroup`: the tests that read the tutorials' quick main job
# share one worker, so it runs once (tests/conftest.py groups them). The tests that judge a real-time recording (marked real_time) then run
# alone: beside another worker, one lost 64 of 3,801 servo samples (a 160 ms stall) where a busy loop on
# every core (test-under-load) costs none — found, not yet explained.
PYTEST = $(BIN)/python -m pytest
# The real-time run collects only the files that name real_time (a test asking for the fixture, or marked; a collection of
# the whole suite is ~4 s of imports for 17 tests); tests/test_suite_workers.py checks that no shared fixture
# asks for it on a test's behalf, which would hide a real-time test from this list.
REAL_TIME_FILES = $(shell grep -lw real_time tests/test_*.py)

test: $(BIN)/.installed
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .
	$(COMPILE)
	$(PYTEST) -n auto --dist loadgroup -m "not real_time"
	$(PYTEST) -m real_time $(REAL_TIME_FILES)

check: $(BIN)/.installed
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .
	$(COMPILE)
	$(PYTEST) -n auto --dist loadgroup -m "not slow and not real_time"
	$(PYTEST) -m "real_time and not slow" $(REAL_TIME_FILES)

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

# the lab's loop against its goals: main job, campaign, cold build, ingest, the suite (takes ~40 min)
loop: $(BIN)/.installed
	$(BIN)/python bench/loop.py

# the documentation site (docs/, mkdocs.yml) into site/: --strict, so a broken link or reference fails
docs: $(BIN)/.installed
	$(BIN)/mkdocs build --strict --site-dir site

lint format: $(BIN)/.installed
	$(BIN)/ruff check --fix .
	$(BIN)/ruff format .

clean:
	rm -rf $(VENV) $(LAB) site .pytest_cache .ruff_cache
