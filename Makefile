PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: test demo reproduce install lint bench docs clean

$(STAMP): pyproject.toml
	test -x $(BIN)/python || $(PY) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q -e ".[dev]"
	touch $(STAMP)

install: $(STAMP)

test: $(STAMP)
	OPENBLAS_NUM_THREADS=1 $(BIN)/python -m pytest -q -m "not slow" tests

demo: $(STAMP)
	OPENBLAS_NUM_THREADS=1 $(BIN)/python -m dissil_jax.experiments nonlinear --data initial \
		--segments 25 --inits 10 --methods pgd gd ico ico_nc mlp --out runs/demo

# The paper's full protocol (all sizes, both regimes, both examples); see README for its time.
# Two worker processes share the configurations of each example (one solver thread each).
reproduce: $(STAMP)
	OPENBLAS_NUM_THREADS=1 $(BIN)/python -m dissil_jax.experiments nonlinear \
		--data initial sliding --inits 100 --jobs 2 --out runs/reproduce
	OPENBLAS_NUM_THREADS=1 $(BIN)/python -m dissil_jax.experiments linear \
		--data initial sliding --inits 10 --jobs 2 --out runs/reproduce

lint: $(STAMP)
	$(BIN)/ruff check dissil_jax tests examples benchmarks

bench: $(STAMP)
	OPENBLAS_NUM_THREADS=1 $(BIN)/python benchmarks/bench_projection.py

docs: $(STAMP)
	$(BIN)/mkdocs build --strict

clean:
	rm -rf $(VENV) .pytest_cache
