# Two entry points (see README): `make demo` and `make test`. Both create .venv on first use and install
# the tested versions (constraints.txt) of the package's dependencies, with the OpenGL extra the simulator needs.
# On a machine without a local CPU wheel of torch, take it from PyTorch's CPU index:
#   make test TORCH_INDEX=https://download.pytorch.org/whl/cpu
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
TORCH_INDEX ?=
export PYOPENGL_PLATFORM ?= egl

$(BIN)/torchevtrack: pyproject.toml constraints.txt
	$(PY) -m venv $(VENV)
	$(BIN)/pip install -q --upgrade pip
	$(if $(TORCH_INDEX),$(BIN)/pip install -q -c constraints.txt torch --index-url $(TORCH_INDEX))
	$(BIN)/pip install -q -c constraints.txt -e ".[dev,gl,ycb,viz,io,ray,rerun,live]"
	touch $@

.PHONY: install demo test bench
install: $(BIN)/torchevtrack

demo: install
	$(BIN)/torchevtrack demo --out demo_out

# the suite in one process per core (pytest-xdist), each test file whole in one of them (its module fixtures once)
TEST_JOBS ?= auto
test: install
	$(BIN)/python -m pytest -n $(TEST_JOBS) --dist loadfile

# The README's speed figures: the standard benchmark data (made once), then the bench command it quotes.
data/bench/mustard_fast/events.h5: | install
	$(BIN)/torchevtrack synth-benchmark --out data/bench

bench: install data/bench/mustard_fast/events.h5
	$(BIN)/torchevtrack bench data/bench/mustard_fast --duration 0.5 --batch 8 --repeat 10 --threads 1
