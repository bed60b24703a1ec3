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

# The README's speed figures: the standard benchmark data (made once), then the bench command it quotes.
data/bench/mustard_fast/events.h5: | install
	$(BIN)/torchevtrack synth-benchmark --out data/bench

bench: install data/bench/mustard_fast/events.h5
	$(BIN)/torchevtrack bench data/bench/mustard_fast --duration 0.5 --batch 8 --repeat 10 --threads 1
