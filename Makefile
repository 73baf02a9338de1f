# The README quick start calls exactly two targets: `make demo` and `make test`.
PY ?= python3
PIP := $(PY) -m pip
OUT ?= demo_out
SEED ?= 0

.PHONY: install demo test test-slow lint bench

install:
	# torch first, pinned, so that no dependency pulls a CUDA build
	$(PIP) install -q torch==2.13.0
	$(PIP) install -q -c constraints.txt -e ".[dev]"

demo: install
	fluoronav demo --out $(OUT) --seed $(SEED)

test: install
	$(PY) -m pytest -q -m "not slow" -p no:cacheprovider

test-slow: install
	$(PY) -m pytest -q -m slow -p no:cacheprovider

lint:
	ruff check src tests
	ruff format --check src tests
	mypy

bench:
	fluoronav bench
