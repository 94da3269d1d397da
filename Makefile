# Two commands do all the set-up on a fresh machine:
#   make demo   -> creates .venv, installs cohflash, runs the demo on the built-in staircase scene
#   make test   -> creates .venv, installs cohflash with test extras, runs the linter and the test suite
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.cohflash-installed

.PHONY: demo test lint format bench bytecode native clean

$(STAMP): pyproject.toml setup.py cohflash_jax/native_kernels.c
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q -e ".[test]"
	touch $(STAMP)

# the native I/Q kernel (optional: cohflash_jax/native_kernels.c): the install builds it; where
# it has gone since (deleted, or a venv of another Python) or does not load, and a C compiler is
# here, install again to build it, rather than let every run fall back to XLA's slower I/Q programs
native: $(STAMP)
	@$(PY) -c "import sys; from cohflash_jax import native; sys.exit(0 if native.available() or native.turned_off() else 3)" \
		|| ! command -v $${CC:-cc} > /dev/null \
		|| (echo "the native I/Q kernel is missing or does not load: building it" && $(PY) -m pip install -q --no-deps -e .)

# the packages' bytecode, as a regular install leaves it (an editable install runs the
# sources; where Python may not write bytecode, every process would compile them again)
bytecode: native
	$(PY) -c "from cohflash_jax.process import compile_package_bytecode; compile_package_bytecode()"

demo: bytecode
	$(VENV)/bin/cohflash demo --out out/demo

test: lint
	$(PY) -m pytest -q -n 2 --dist loadgroup

lint: bytecode
	$(VENV)/bin/ruff check .
	$(VENV)/bin/ruff format --check .

format: $(STAMP)
	$(VENV)/bin/ruff format .
	$(VENV)/bin/ruff check --fix .

bench: bytecode
	$(PY) benchmarks/bench_simulate.py
	$(PY) benchmarks/bench_reconstruct.py
	$(PY) benchmarks/bench_process.py

clean:
	rm -rf $(VENV) out
