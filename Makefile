# Quick start: `make run` (set up, run matrix.yaml, write its report) and `make test`.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin

.PHONY: setup setup-gpu run report test bench clean

$(BIN)/bench-matrix: requirements.lock pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -r requirements.lock
	$(BIN)/python -m pip install --quiet --no-deps -e .
	touch $@

setup: $(BIN)/bench-matrix

# On an NVIDIA GPU machine: ONNX Runtime's CUDA and TensorRT providers (docs/gpu.md).
setup-gpu: setup
	$(BIN)/python -m pip uninstall --quiet --yes onnxruntime
	$(BIN)/python -m pip install --quiet -r requirements-gpu.txt

run: setup
	$(BIN)/bench-matrix run matrix.yaml
	$(BIN)/bench-matrix report

report: setup
	$(BIN)/bench-matrix report

test: setup
	$(BIN)/python -m pytest -q -n 2 --dist loadfile --no-loadscope-reorder --durations=40

bench: setup
	$(BIN)/python benchmarks/harness_overhead.py

clean:
	rm -rf $(VENV) .bench-matrix
