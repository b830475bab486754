# The two commands a newcomer needs: `make run` and `make test`. Both set everything up first.
PYTHON ?= $(shell command -v python3.11 || command -v python3)
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed
# Python writes the bytecode of each module it imports, once (setup compiles none but what every command
# imports: scripts/install_deps.sh), also where PYTHONDONTWRITEBYTECODE=1 is set (CI here), which would make
# every process compile every import again: make's own commands write it whatever that variable says
PYC    := env -u PYTHONDONTWRITEBYTECODE

.PHONY: setup run test test-slow test-gpu-job clean clean-runs

setup: $(STAMP)
	@bash scripts/ensure_llvm.sh

# Reinstall when the dependency list changes.
$(STAMP): pyproject.toml
	@$(PYTHON) -c 'import sys; assert sys.version_info[:2] == (3, 11), sys.version' 2>/dev/null || \
		{ echo "SRD-Bench needs Python 3.11 (torch==2.13.0 CPU wheel); set PYTHON=/path/to/python3.11"; exit 1; }
	@test -x $(PY) || $(PYTHON) -m venv $(VENV)
	@# uv where it can (parallel, cached), else pip: scripts/install_deps.sh
	bash scripts/install_deps.sh $(PY)
	@# the bytecode of what every command imports, for commands run without make too
	$(PYC) $(PY) -c 'import torch._dynamo, bench.cli, bench.train, bench.evaluate, bench.experiments.table'
	@touch $(STAMP)

run: setup
	$(PYC) $(PY) -m bench +experiment=smoke

# two processes, each test file whole on one (module fixtures run once; files that share a path do not
# overlap in time), the longest files first (tests/conftest.py); pytest alone runs them on one
test: setup
	$(PYC) $(PY) -m pytest -q -n 2 --dist loadfile --no-loadscope-reorder

test-slow: setup
	$(PYC) $(PY) -m pytest -q -m slow

# the GPU job's steps run on this CPU (the slow tests of tests/test_gpu_job.py, 2-3 min on 2 cores): CI
# runs them after make test, and scripts/gpu_prepare.sh before a GPU call
test-gpu-job: setup
	$(PYC) $(PY) -m pytest -q -m slow tests/test_gpu_job.py

# Removes the environment only; trained runs and rendered data are kept (see clean-runs).
clean:
	rm -rf $(VENV)

# Deletes the run store: every recorded render job, checkpoint and evaluation.
clean-runs:
	rm -rf runs
