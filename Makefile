# Two entry points for a new user:  `make demo`  and  `make test`.
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin

.PHONY: install demo test lint bench bench-env clean

$(BIN)/liecontrol: pyproject.toml
	$(PY) -m venv $(VENV)
	$(BIN)/pip install -q --upgrade pip
	# The CPU build of torch first: a bare `torch` requirement would pull a multi-GB CUDA build.
	$(BIN)/pip install -q torch==2.13.0
	$(BIN)/pip install -q -e '.[dev,bench]'
	touch $@

install: $(BIN)/liecontrol

demo: install
	$(BIN)/liecontrol demo --out out

test: install
	$(BIN)/ruff check .
	$(BIN)/python -m pytest -q -n 2 tests

lint: install
	$(BIN)/ruff check .

bench: install bench-env
	$(BIN)/liecontrol bench lie --json out/bench_lie.json
	$(BIN)/liecontrol bench lqr --json out/bench_lqr.json
	$(BIN)/liecontrol bench ilqr --json out/bench_ilqr.json

# mpc.pytorch pins numpy<2: it gets an environment of its own, called by the benchmarks in a subprocess.
bench-env: .venv-mpc/bin/python

.venv-mpc/bin/python:
	$(PY) -m venv .venv-mpc
	.venv-mpc/bin/pip install -q torch==2.13.0
	.venv-mpc/bin/pip install -q 'numpy<2' mpc pypose

clean:
	rm -rf $(VENV) .venv-mpc out .pytest_cache .ruff_cache build *.egg-info
