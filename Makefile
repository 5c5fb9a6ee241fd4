PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: test test-kernels demo reproduce install lint typecheck bench docs constraints clean

# Exact, tested versions from constraints.txt, so that a fresh `make test` resolves the same
# packages today and later; `pip install dissil_jax` alone uses pyproject's lower bounds.
$(STAMP): pyproject.toml constraints.txt
	test -x $(BIN)/python || $(PY) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q -c constraints.txt -e ".[dev]"
	touch $(STAMP)

install: $(STAMP)

# Two pytest workers (the tests are mostly single-threaded compilation); the docs tests share
# one worker so that the site is built once. Compilation is about two thirds of the tests' CPU
# time, so the workers and the subprocesses they start (examples, CLI runs) share one JAX
# compilation cache, fresh for every run and removed after it: an executable one process
# compiled is loaded, not recompiled, by the others.
PYTEST := OPENBLAS_NUM_THREADS=1 JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS=0 \
	$(BIN)/python -m pytest -q -n 2 --dist loadgroup
WITH_CACHE = cache=$$(mktemp -d) && trap 'rm -rf "$$cache"' EXIT && \
	export JAX_COMPILATION_CACHE_DIR="$$cache" &&

# The suite compiles at XLA's cheapest settings (the CPU backend's older loop emitters, LLVM
# at -O0): a training loop compiles about 3x faster and runs about 2x slower
# (benchmarks/bench_test_xla.py), and the tests' arithmetic is small, so the suite takes half
# the time (measured: 8 min 53 s -> 4 min 31 s). The semantics are XLA's either way; the
# rounding differs, which the tolerances allow for. `test-kernels` runs the numerically tight
# tests at XLA's default settings, so that CI covers both. (A setting of the test run only:
# the library sets no XLA configuration.)
FAST_XLA := --xla_cpu_use_fusion_emitters=false --xla_backend_optimization_level=0

test: $(STAMP)
	$(WITH_CACHE) export XLA_FLAGS="$${XLA_FLAGS:-} $(FAST_XLA)" && \
		$(PYTEST) -m "not slow" tests

# The numerically tight tests again under other CPUs' BLAS kernels (numpy's and scipy's
# OpenBLAS pick them by OPENBLAS_CORETYPE): with the native run they cover the Haswell-,
# SkylakeX- and Zen-class kernels. CI runs this after `make test`, and at XLA's default
# compilation settings (`make test` uses FAST_XLA).
KERNELS ?= Haswell SkylakeX Zen
test-kernels: $(STAMP)
	$(WITH_CACHE) for k in $(KERNELS); do \
		echo "== OPENBLAS_CORETYPE=$$k"; \
		OPENBLAS_CORETYPE=$$k $(PYTEST) -p no:cacheprovider -m "numerics and not slow" tests \
			|| exit 1; \
	done

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

# ruff, and pyright in basic mode on dissil_jax/ (configured in pyproject.toml).
lint: $(STAMP)
	$(BIN)/ruff check dissil_jax tests examples benchmarks
	$(BIN)/pyright

typecheck: $(STAMP)
	$(BIN)/pyright

bench: $(STAMP)
	OPENBLAS_NUM_THREADS=1 $(BIN)/python benchmarks/bench_projection.py

docs: $(STAMP)
	$(BIN)/mkdocs build --strict

# Re-pin constraints.txt to what the venv has now (after an upgrade; then run `make test`).
constraints: $(STAMP)
	{ sed -n '1,3p' constraints.txt; $(BIN)/python -m pip freeze --exclude-editable \
		| grep -v '^dissil' ; } > constraints.tmp && mv constraints.tmp constraints.txt

clean:
	rm -rf $(VENV) .pytest_cache
