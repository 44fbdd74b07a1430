# Two commands for a newcomer: `make demo` and `make test`. Both create .venv on first use.
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed

export NUMBA_CACHE_DIR ?= $(CURDIR)/.cache/numba
export OMP_NUM_THREADS ?= 2
export OMP_WAIT_POLICY ?= PASSIVE

.PHONY: install test demo bench clean

install: $(STAMP)

# torch==2.13.0 first: it is the CPU build available locally; an open range would pull a multi-GB CUDA build.
$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q torch==2.13.0
	$(PY) -m pip install -q -e '.[dev]'
	touch $(STAMP)

test: install
	$(PY) -m mypy
	$(PY) -m pytest -q

demo: install
	$(VENV)/bin/stgc demo --out demo_out

# The speed benchmarks of benchmarks/RESULTS.md (training runs are listed there with their own commands).
bench: install
	$(PY) benchmarks/rasterizer.py
	$(PY) benchmarks/knn.py
	$(PY) benchmarks/codec.py

clean:
	rm -rf $(VENV) .cache demo_out
