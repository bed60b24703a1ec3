# Two entry points (see README): `make demo` and `make test`. Both create .venv on first use.
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
export PYOPENGL_PLATFORM ?= egl

$(BIN)/torchevtrack: pyproject.toml
	$(PY) -m venv $(VENV)
	$(BIN)/pip install -q --upgrade pip
	$(BIN)/pip install -q -e ".[dev,ycb,viz,io]"
	touch $@

.PHONY: install demo test bench
install: $(BIN)/torchevtrack

demo: install
	$(BIN)/torchevtrack demo --out demo_out

test: install
	$(BIN)/python -m pytest

bench: install
	$(BIN)/python tools/benchmark_report.py
