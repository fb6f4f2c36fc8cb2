# The two commands: `make demo` and `make test`. Both create .venv and install the package.
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
EXTRAS ?= test,bench,sim,dask
OUT ?= demo_output

.PHONY: install lint test test-slow demo bench clean

$(VENV)/.installed: pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q -e '.[$(EXTRAS)]'
	touch $@

install: $(VENV)/.installed

# Compilation dominates the test run: two workers compile in parallel. JAX's persistent cache
# (also used by the tests' subprocesses) shares programs without host callbacks between the
# workers, the test modules (each clears JAX's in-memory caches) and `make test-slow`: the
# registration engine's programs (no callbacks since its assignments run in JAX) and the
# hundreds of small one-operation programs that eager code compiles per shape, once they are
# cached whatever their compile time (JAX's default skips programs compiled in under a second).
# The cache lives in the checkout unless the environment names another folder (CI keeps one
# between its runs: .ci/run).
JAX_COMPILATION_CACHE_DIR ?= $(CURDIR)/.jax_cache
PYTEST := JAX_COMPILATION_CACHE_DIR="$(JAX_COMPILATION_CACHE_DIR)" JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS=0 \
	$(PY) -m pytest -q -n 2 --dist loadfile

# ruff: lint, import order and formatting (configured in pyproject.toml); part of `make test`.
lint: $(VENV)/.installed
	$(VENV)/bin/ruff check rootshape_jax tests benchmarks
	$(VENV)/bin/ruff format --check rootshape_jax tests benchmarks

test: lint
	$(PYTEST) -m "not slow"

test-slow: $(VENV)/.installed
	$(PYTEST) -rs -m slow || [ $$? -eq 5 ]  # 5: no slow test selected

demo: $(VENV)/.installed
	$(PY) -m rootshape_jax demo --out $(OUT) --overwrite  # make demo regenerates its folder

bench: $(VENV)/.installed
	for b in curves trees stats assignment dask; do $(PY) benchmarks/bench_$$b.py || exit 1; done

clean:
	rm -rf $(VENV) $(OUT) .jax_cache
