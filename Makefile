# Two entry points for a new user:  `make demo`  and  `make test`.
# Each installs only what it uses: the demo the package itself, the tests the `dev` extra (pytest, ruff,
# the numerical oracles and the two light anchors pypose and roma). The heavy anchors of the benchmarks
# (`bench` extra: crocoddyl/pinocchio, EnvPool, CasADi, about 1.9 GB) come with `make bench-env`.
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin

.PHONY: install demo test lint bench bench-env clean

# The CPU build of torch first: a bare `torch` requirement would pull a multi-GB CUDA build.
$(BIN)/python:
	$(PY) -m venv $(VENV)
	$(BIN)/pip install -q --upgrade pip
	$(BIN)/pip install -q torch==2.13.0

# One stamp per set of extras, redone when pyproject.toml changes.
$(VENV)/.installed-base: pyproject.toml | $(BIN)/python
	$(BIN)/pip install -q -e .
	touch $@

$(VENV)/.installed-dev: pyproject.toml | $(BIN)/python
	$(BIN)/pip install -q -e '.[dev]'
	touch $@

$(VENV)/.installed-bench: pyproject.toml | $(BIN)/python
	$(BIN)/pip install -q -e '.[dev,bench]'
	touch $@

install: $(VENV)/.installed-dev

demo: $(VENV)/.installed-base
	$(BIN)/liecontrol demo

test: $(VENV)/.installed-dev
	$(BIN)/ruff check .
	$(BIN)/python -m pytest -q -n 2 tests

lint: $(VENV)/.installed-dev
	$(BIN)/ruff check .

bench: bench-env
	$(BIN)/liecontrol bench lie --json out/bench_lie.json
	$(BIN)/liecontrol bench lqr --json out/bench_lqr.json
	$(BIN)/liecontrol bench ilqr --json out/bench_ilqr.json
	$(BIN)/liecontrol bench solver --json out/bench_solver.json

# The anchors: the `bench` extra in .venv, and mpc.pytorch, which pins numpy<2, in an environment of its
# own (.venv-mpc), called by the benchmarks in a subprocess. With them `make test` also runs the anchor tests.
bench-env: $(VENV)/.installed-bench .venv-mpc/bin/python

.venv-mpc/bin/python:
	$(PY) -m venv .venv-mpc
	.venv-mpc/bin/pip install -q torch==2.13.0
	.venv-mpc/bin/pip install -q 'numpy<2' mpc pypose

clean:
	rm -rf $(VENV) .venv-mpc out .pytest_cache .ruff_cache build *.egg-info
