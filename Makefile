# Two entry points for a new user:  `make demo`  and  `make test`.
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin

.PHONY: install demo test lint bench clean

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

bench: install
	$(BIN)/liecontrol bench lie --json out/bench_lie.json

clean:
	rm -rf $(VENV) out .pytest_cache .ruff_cache build *.egg-info
