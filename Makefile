# The README quick start calls exactly two targets: `make demo` and `make test`. Both install into a
# project virtual environment (.venv) made with the `python3` found on PATH, so that a distribution's
# system Python (which refuses `pip install` under PEP 668) is left alone.
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
PIP := $(PY) -m pip
OUT ?= demo_out
SEED ?= 0

.PHONY: install demo test test-slow lint bench

$(PY):
	$(PYTHON) -m venv $(VENV)

install: $(PY)
	# torch first, pinned, so that no dependency pulls a CUDA build
	$(PIP) install -q torch==2.13.0
	$(PIP) install -q -c constraints.txt -e ".[dev]"
	# the CPU kernels into numba's cache, so that the first run after an install does not compile
	$(PY) -m fluoronav.cli.compile_kernels

demo: install
	$(VENV)/bin/fluoronav demo --out $(OUT) --seed $(SEED)

test: install
	$(VENV)/bin/lint-imports
	$(PY) -m pytest -q -m "not slow" -p no:cacheprovider

test-slow: install
	$(PY) -m pytest -q -m slow -p no:cacheprovider

lint: install
	$(VENV)/bin/ruff check src tests
	$(VENV)/bin/ruff format --check src tests
	$(VENV)/bin/mypy
	$(VENV)/bin/lint-imports

bench: install
	$(VENV)/bin/fluoronav bench
