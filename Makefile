# rl2s_jax: every target that runs code sets the environment up first (`setup`).
PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed

.PHONY: setup test hopper walker2d halfcheetah ant bench lint clean

setup: $(STAMP)

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q -e '.[dev]'
	touch $(STAMP)

test: setup
	$(PY) -m pytest -q tests

# The whole pipeline for one task with the shipped zoo; results land in results/<task>/.
hopper walker2d halfcheetah ant: setup
	$(VENV)/bin/rl2s pipeline --task $@

bench: setup
	$(PY) experiments/bench.py
	$(PY) experiments/bench_train.py

lint: setup
	$(VENV)/bin/ruff check rl2s_jax tests experiments examples

clean:
	rm -rf $(VENV) results .pytest_cache
