#!/usr/bin/env bash
# Installs the project with its test dependencies into the venv of python $1 (`make setup`).
# uv installs the wheels in parallel from its cache; pip goes one package at a time, and this registry's
# answers are not cached for it. Clean-clone make test minus pytest's time, on 2 AVX-512 cores: pip 89 s,
# uv 40 s (uv's cache warm).
# uv compiles the bytecode of every installed module (15,000), on every core: 23 s on 2 cores (AMD EPYC,
# AVX-512). Compiling only what `make setup` imported (2,600 modules, one process) took 12 s, but then the
# suite's first run compiled the rest (MLflow, SciPy, NetworkX, SQLAlchemy, ...) in whichever processes
# imported them first, often several at once (a pair of joblib or render workers, a launcher's shards):
# pytest took 311 s against 262 s once every module had its bytecode, and test_tracking.py alone 56 s
# against 35 s with uv's. pip (the fallback) compiles every module too.
# uv reads no pip configuration, so pip's find-links (where the torch CPU wheel lies), from its config files
# or the environment, go along; where uv cannot install, pip does, and says so.
set -euo pipefail
py=$1
uv=$(dirname "$py")/uv
links=$("$py" -m pip config list 2>/dev/null | sed -n "s/^[^=]*find-links='\(.*\)'$/\1/p" | tr -s ' ' '\n' | sort -u | paste -sd, -)
links=${UV_FIND_LINKS:-$links}
if "$py" -m pip install -q uv==0.13.9 &&
        env ${links:+UV_FIND_LINKS="$links"} "$uv" pip install --python "$py" -q --compile-bytecode -e '.[test]'; then
    exit 0
fi
echo "setup: uv could not install the project; installing it with pip instead (slower)" >&2
"$py" -m pip install -q -e '.[test]'
