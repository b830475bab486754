#!/usr/bin/env bash
# Installs the project with its test dependencies into the venv of python $1 (`make setup`).
# uv installs the wheels in parallel from its cache; pip goes one package at a time, and this registry's
# answers are not cached for it. Clean-clone make test minus pytest's time, on 2 AVX-512 cores: pip 89 s,
# uv 40 s (uv's cache warm). No bytecode is compiled here: compiling all 15,000 modules took 21 of uv's 26 s
# (2 cores), and a run imports a fraction of them. `make setup` then imports what every command imports,
# and make's commands the rest as they need it, writing its bytecode once, even where
# PYTHONDONTWRITEBYTECODE=1 (CI here), without which every process would compile every import (the
# Makefile, PYC).
# uv reads no pip configuration, so pip's find-links (where the torch CPU wheel lies), from its config files
# or the environment, go along; where uv cannot install, pip does, and says so.
set -euo pipefail
py=$1
uv=$(dirname "$py")/uv
links=$("$py" -m pip config list 2>/dev/null | sed -n "s/^[^=]*find-links='\(.*\)'$/\1/p" | tr -s ' ' '\n' | sort -u | paste -sd, -)
links=${UV_FIND_LINKS:-$links}
if "$py" -m pip install -q uv==0.13.9 &&
        env ${links:+UV_FIND_LINKS="$links"} "$uv" pip install --python "$py" -q -e '.[test]'; then
    exit 0
fi
echo "setup: uv could not install the project; installing it with pip instead (slower)" >&2
"$py" -m pip install -q -e '.[test]'
