#!/bin/bash
# Times `make test` as the README quotes it: a clean clone of this checkout at REV (default HEAD), its
# setup included (uv's cache as this machine has it), Inductor's compile cache empty; then one line with
# the figures and the machine they were measured on (model, family/model/stepping, vector ISA, CPUs, and
# the load average before the run: the README's figures are on an idle machine).
#   scripts/time_make_test.sh [REV]
#   scripts/as_avx2.sh scripts/time_make_test.sh [REV]     the same with an AVX2-only CPU's vector ISA
# Kept as on any machine's second run: Dr.Jit's kernels (~/.drjit), the C++ kernels and Triton builds
# (~/.cache/srd-bench). The clone is removed afterwards; make's output stays in the folder printed last.
# Exits with make's status.
set -uo pipefail
if [[ "${1:-}" == -h || "${1:-}" == --help ]]; then
    sed -n '2,10p' "$0" | sed 's/^# \{0,1\}//'; echo "usage: scripts/time_make_test.sh [REV]"; exit 0
fi
root=$(git -C "$(dirname "$0")/.." rev-parse --show-toplevel) || exit 2
rev=$(git -C "$root" rev-parse --short "${1:-HEAD}") || { echo "time_make_test: no commit ${1:-HEAD}" >&2; exit 2; }
work=$(mktemp -d "${TMPDIR:-/tmp}/srd-bench-make-test.XXXXXX")
git clone -q "$root" "$work/clone" && git -C "$work/clone" checkout -q "$rev" || exit 2
load=$(cut -d' ' -f1 /proc/loadavg 2>/dev/null || echo unknown)
export TORCHINDUCTOR_CACHE_DIR="$work/inductor"   # empty, as on a machine that never compiled
start=$(date +%s.%N)
(cd "$work/clone" && make test) > "$work/make-test.log" 2>&1
rc=$?
wall=$(python3 -c "import sys; print(f'{float(sys.argv[2]) - float(sys.argv[1]):.0f}')" "$start" "$(date +%s.%N)")
summary=$(grep -E "^=* *[0-9]+ [a-z]+.* in [0-9.]+s" "$work/make-test.log" | tail -n 1 | sed -E 's/^=+ //; s/ =+$//')
# named by this checkout's bench.machine (no torch): REV may predate it
machine=$(cd "$root" && python3 -c "
import os
from bench.machine import cpu_identity, cpu_isa, cpu_model
print(f'{cpu_model().strip()} ({cpu_identity()}), {cpu_isa()}, {os.cpu_count()} CPUs')")
rm -rf "$work/clone" "$work/inductor"
echo "make test at $rev: ${wall} s wall, rc $rc; pytest: ${summary:-no summary line}"
echo "on $machine; load average before: $load; $(date -u +%Y-%m-%dT%H:%MZ)"
echo "make's output: $work/make-test.log"
exit $rc
