# Two commands do all the set-up on a fresh machine:
#   make demo   -> creates .venv, installs cohflash, runs the demo on the built-in staircase scene
#   make test   -> creates .venv, installs cohflash with test extras, runs the linter and the test suite
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.cohflash-installed

.PHONY: demo test lint format bench bytecode clean

$(STAMP): pyproject.toml setup.py cohflash_jax/native_kernels.c
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q -e ".[test]"
	touch $(STAMP)

# the packages' bytecode, as a regular install leaves it (an editable install runs the
# sources; where Python may not write bytecode, every process would compile them again)
bytecode: $(STAMP)
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
