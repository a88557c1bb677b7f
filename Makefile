# viewloc: `make run` serves, `make test` checks, `make bench` measures.
SHELL := /bin/bash
PY := .venv/bin/python
PORT ?= 8000
export PYOPENGL_PLATFORM ?= egl
export VIEWLOC_DATA_DIR ?= ./var

.PHONY: setup run test lint pytest bench worker clean

setup:
	@bash scripts/setup.sh

run: setup
	$(PY) -m viewloc_cli serve --host 0.0.0.0 --port $(PORT)

lint: setup
	$(PY) -m ruff check .
	$(PY) -m mypy viewloc_core model_store app viewloc_bench viewloc_cli viewloc_client

pytest: setup
	$(PY) -m pytest -q $(PYTEST_ARGS)

test: lint pytest

# make bench                      all sets, on the core directly
# make bench URL=http://host:8000 the same through the HTTP API
# make bench BENCH_ARGS="--sets paper --quick"
bench: setup
	$(PY) -m viewloc_bench $(if $(URL),--url $(URL),) $(BENCH_ARGS)

worker: setup
	$(PY) -m viewloc_cli worker

clean:
	rm -rf bench_out .mypy_cache .ruff_cache .pytest_cache
