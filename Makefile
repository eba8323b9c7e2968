# rl2s_jax: every target that runs code sets the environment up first (`setup`).
PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed

.PHONY: setup test test-all hopper walker2d halfcheetah ant paper bench lint clean

setup: $(STAMP)

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q -e '.[dev]'
	touch $(STAMP)

# Two pytest-xdist workers (one per core: most of the suite's time is single-threaded XLA
# compilation), files kept whole on a worker so module fixtures are built once; each worker
# also compiles only about half of the suite, which keeps it clear of the kernel's memory-map
# limit that a single process compiling everything hit (XLA crashed late in such a run).
# tests/conftest.py makes loadfile's units of work its UNITS (a file, or the files sharing
# Hopper data) and hands them out costliest first.
test: setup
	$(PY) -m pytest -q -n 2 --dist loadfile -m "not heavy" --durations=25 tests

# Everything, including the heavy smoke runs (make paper's driver on tiny sizes, ~5 min more).
test-all: setup
	$(PY) -m pytest -q tests

# The whole pipeline for one task with the shipped zoo; results land in results/<task>/.
hopper walker2d halfcheetah ant: setup
	$(VENV)/bin/rl2s pipeline --task $@

# The paper's protocol on the four tasks (sizes by JAX backend, see experiments/paper.py)
# into results/paper/<task>.json, then the tables; with 2+ GPUs the units (a whole task per GPU
# when tasks <= GPUs < 2 x tasks, else (task, family) pairs) share the GPUs costliest first,
# one process per GPU at a time, a task's data collected once, and the wall time per unit is
# printed (experiments/paper_all.sh, docs/SCALING.md).
paper: setup
	PY=$(PY) bash experiments/paper_all.sh results/paper

bench: setup
	$(PY) experiments/bench.py
	$(PY) experiments/bench_train.py

lint: setup
	$(VENV)/bin/ruff check rl2s_jax tests experiments examples

clean:
	rm -rf $(VENV) results .pytest_cache
