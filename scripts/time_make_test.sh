#!/bin/bash
# Times `make test` as the README quotes it: a clean clone of this checkout at REV (default HEAD), its
# setup included (uv's cache as this machine has it), Inductor's compile cache empty; then one line with
# the figures and the machine they were measured on (model, family/model/stepping, vector ISA, CPUs, and
# the load average before the run: the README's figures are on an idle machine).
#   scripts/time_make_test.sh [REV]
#   scripts/as_avx2.sh scripts/time_make_test.sh [REV]     the same with an AVX2-only CPU's vector ISA
# Kept as on any machine's second run: Dr.Jit's kernels (~/.drjit), the C++ kernels and Triton builds
# (~/.cache/srd-bench). The clone goes under TMPDIR (else /tmp): on another filesystem than uv's cache,
# setup copies the packages instead of linking them and takes longer. The clone is removed afterwards;
# make's output stays in the folder printed last. Exits with make's status; 3 where this script fails.
set -uo pipefail
if [[ "${1:-}" == -h || "${1:-}" == --help ]]; then
    sed -n '2,11p' "$0" | sed 's/^# \{0,1\}//'; echo "usage: scripts/time_make_test.sh [REV]"; exit 0
fi
unset GIT_DIR GIT_WORK_TREE GIT_INDEX_FILE   # as a git hook would set them: the clone is its own repository
fail() { echo "time_make_test: $*" >&2; exit 3; }
python=${PYTHON:-$(command -v python3.11 || command -v python3)} || fail "no python3 (set PYTHON)"
root=$(git -C "$(dirname "$0")/.." rev-parse --show-toplevel) || fail "not in a git checkout"
rev=$(git -C "$root" rev-parse --short "${1:-HEAD}^{commit}" 2>/dev/null) || fail "no commit ${1:-HEAD}"
load=$(cut -d' ' -f1 /proc/loadavg 2>/dev/null || echo unknown)
work=$(mktemp -d "${TMPDIR:-/tmp}/srd-bench-make-test.XXXXXX") || fail "cannot make a folder in ${TMPDIR:-/tmp}"
trap 'rm -rf "$work/clone" "$work/inductor"' EXIT
trap 'exit 130' INT TERM
git clone -q "$root" "$work/clone" && git -C "$work/clone" checkout -q "$rev" || fail "cannot clone $root at $rev"
export TORCHINDUCTOR_CACHE_DIR="$work/inductor"   # empty, as on a machine that never compiled
start=$(date +%s%N)
(cd "$work/clone" && make test) > "$work/make-test.log" 2>&1
rc=$?
wall=$(( ($(date +%s%N) - start + 500000000) / 1000000000 ))
summary=$(sed 's/\x1b\[[0-9;]*m//g' "$work/make-test.log" \
          | grep -E "^(=+ )?([0-9]+ [a-z]+|no tests ran).* in [0-9.]+s" | tail -n 1 | sed -E 's/^=+ //; s/ =+$//')
# named by this checkout's bench.machine (no torch): REV may predate it
machine=$(cd "$root" && "$python" -c "
import os
from bench.machine import cpu_identity, cpu_isa, cpu_model
print(f'{cpu_model().strip()} ({cpu_identity()}), {cpu_isa()}, {os.cpu_count()} CPUs')") || machine="(not named)"
if grep -q ' /proc/cpuinfo ' /proc/self/mountinfo 2>/dev/null; then
    machine+=" as /proc/cpuinfo is mounted over it (scripts/as_avx2.sh: the vector ISA capped, not the CPU's)"
fi
echo "make test at $rev: ${wall} s wall, rc $rc; pytest: ${summary:-no summary line}"
echo "on $machine; load average before: $load; $(date -u +%Y-%m-%dT%H:%MZ)"
echo "make's output: $work/make-test.log"
exit $rc
