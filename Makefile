# physicsrl: `make help` lists the targets.
PYTHON ?= python3.12
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed

.PHONY: help setup train test test-resolved test-slurm bench lint clean

help:  ## list the targets
	@grep -E '^[a-z-]+:.*## ' $(MAKEFILE_LIST) | awk -F':.*## ' '{printf "  make %-14s %s\n", $$1, $$2}'

$(BIN)/python:
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip

$(STAMP): pyproject.toml | $(BIN)/python
	$(BIN)/python -m pip install -q -e '.[dev]'
	touch $(STAMP)

setup: $(STAMP)  ## create .venv (Python 3.12) and install physicsrl editable with dev extras

train: setup  ## train DQN on the heat task on 2 MPI ranks and print the summary
	$(BIN)/physicsrl-train mpi.ranks=2

# make test's workers (pytest-xdist), each taking whole test files; 2 fill a 2-core machine
TEST_WORKERS ?= 2
test: setup  ## run the test suite (unit and MPI tests; the slowest results rows: test-resolved)
	$(BIN)/python -m pytest -n $(TEST_WORKERS) --dist loadfile

test-resolved: setup  ## the results rows that take minutes on 2 ranks (1000 x 1000, the timing agent's 20 draws) or repeat a kind make test checks (~16 min)
	$(BIN)/python -m pytest -m 'resolved or slow'

SLURM := tests/slurm/local_slurm.sh
test-slurm: setup  ## the Slurm launcher on a local single-node Slurm (installed where possible, else skipped)
	@if $(SLURM) install && $(SLURM) start; then \
	  SLURM_CONF=/tmp/physicsrl-slurm/slurm.conf $(BIN)/python -m pytest -m slurm tests/test_slurm.py; \
	  status=$$?; $(SLURM) stop; exit $$status; \
	else echo "test-slurm: skipped, no local Slurm here (the line above says why)"; fi

bench: setup  ## run the benchmarks, beside their baselines, into benchmarks/results/
	$(BIN)/python benchmarks/ping_scaling.py
	$(BIN)/python benchmarks/ms_scaling.py
	$(BIN)/physicsrl-bench env hydra.run.dir=benchmarks/results/env

lint: setup  ## ruff
	$(BIN)/ruff check physicsrl tests benchmarks examples

clean:  ## remove the virtual environment and build outputs
	rm -rf $(VENV) build dist *.egg-info
