# Two commands: `make demo` and `make test`. Both set everything up on a fresh machine first
# (the `viz` extra too: the demo records a Rerun live view and tests/test_live.py reads it back).
SHELL := /bin/bash
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.lampsam-installed
SUDO := $(shell [ "$$(id -u)" = "0" ] || echo sudo)
OUT ?= out/demo
PYTEST_WORKERS ?= 2
# One BLAS/OpenMP thread per process: tests and comparisons parallelise over processes,
# and threaded BLAS on small matrices was measured ~7x slower on 2 cores.
export OPENBLAS_NUM_THREADS ?= 1
export OMP_NUM_THREADS ?= 1
export MKL_NUM_THREADS ?= 1

.PHONY: demo test setup syslibs lint bench clean

# Open3D 0.20 needs libusb-1.0 to import; install it only when the loader cannot find it.
syslibs:
	@if ! ldconfig -p 2>/dev/null | grep -q 'libusb-1.0.so.0'; then \
		echo "installing libusb-1.0-0 (needed by open3d)"; \
		$(SUDO) apt-get update -qq && DEBIAN_FRONTEND=noninteractive $(SUDO) apt-get install -y -qq libusb-1.0-0 >/dev/null; \
	fi

$(STAMP): pyproject.toml
	@test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --disable-pip-version-check --upgrade pip
	$(PY) -m pip install -q --disable-pip-version-check -e ".[test,viz]"
	@touch $(STAMP)

setup: syslibs $(STAMP)

demo: setup
	$(PY) -m lampsam demo --out $(OUT)

test: setup
	$(PY) -m pytest -q -n $(PYTEST_WORKERS) --durations=15

lint: setup
	$(VENV)/bin/ruff check .
	@# mypy names modules after folders: check the package as `lampsam` through a link, whatever
	@# this clone's folder is called (a clone named otherwise made mypy see every module twice).
	@d=$$(mktemp -d) && ln -s "$(CURDIR)" "$$d/lampsam" && cd "$$d" && \
		"$(CURDIR)/$(VENV)/bin/mypy" -p lampsam --config-file "$(CURDIR)/pyproject.toml" \
		--cache-dir "$(CURDIR)/.mypy_cache"; rc=$$?; rm -rf "$$d"; exit $$rc

bench: setup
	for b in scripts/bench/bench_*.py; do echo "== $$b"; $(PY) $$b || exit 1; done

clean:
	rm -rf out .pytest_cache
