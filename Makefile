# The two commands a newcomer needs: `make run` and `make test`. Both set everything up first.
PYTHON ?= $(shell command -v python3.11 || command -v python3)
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed

.PHONY: setup run test test-slow clean clean-runs

setup: $(STAMP)
	@bash scripts/ensure_llvm.sh

# Reinstall when the dependency list changes.
$(STAMP): pyproject.toml
	@$(PYTHON) -c 'import sys; assert sys.version_info[:2] == (3, 11), sys.version' 2>/dev/null || \
		{ echo "SRD-Bench needs Python 3.11 (torch==2.13.0 CPU wheel); set PYTHON=/path/to/python3.11"; exit 1; }
	@test -x $(PY) || $(PYTHON) -m venv $(VENV)
	@# uv installs the wheels in parallel from its cache and compiles their bytecode on every core; pip goes
	@# one package at a time and this registry's answers are not cached for it. Clean-clone make test, minus
	@# pytest's time, on 2 AVX-512 cores: pip 89 s, uv 40 s (warm uv cache). The bytecode matters: where
	@# PYTHONDONTWRITEBYTECODE=1 (CI here), every process would compile every import. uv reads no pip.conf,
	@# so pip's find-links (the torch CPU wheel) go along; where uv cannot resolve, pip installs.
	$(PY) -m pip install -q uv==0.13.9
	UV_FIND_LINKS="$${UV_FIND_LINKS:-$$(echo $${PIP_FIND_LINKS:-} | tr ' ' ',')}" $(VENV)/bin/uv pip install \
		--python $(PY) -q --compile-bytecode -e '.[test]' || $(PY) -m pip install -q -e '.[test]'
	@touch $(STAMP)

run: setup
	$(PY) -m bench +experiment=smoke

# two processes, each test file whole on one (module fixtures run once; files that share a path do not
# overlap in time), the longest files first (tests/conftest.py); pytest alone runs them on one
test: setup
	$(PY) -m pytest -q -n 2 --dist loadfile --no-loadscope-reorder

test-slow: setup
	$(PY) -m pytest -q -m slow

# Removes the environment only; trained runs and rendered data are kept (see clean-runs).
clean:
	rm -rf $(VENV)

# Deletes the run store: every recorded render job, checkpoint and evaluation.
clean-runs:
	rm -rf runs
