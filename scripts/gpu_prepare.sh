#!/usr/bin/env bash
# Prepares THIS checkout for scripts/gpu_job.sh on a lent GPU machine (docs/gpu.md, "The GPU job"): the
# whole job travels in ONE call (the machine goes back ~30 s after a call), tree and wheels within 64 MiB.
#  0. first, the job's dry run on this CPU, `make test-gpu-job`: the tests of tests/test_gpu_job.py marked
#     slow (its steps at the smoke preset on tiny frames, about 2-3 min on 2 cores; CI runs them after
#     make test), so a change that breaks the job stops here, not on the lent machine. --no-dry-run skips
#     it (just run).
#  1. .whl/: wheels for the machine's Python 3.12 that its image lacks: hydra-core, omegaconf, antlr4,
#     OpenEXR, flip-evaluator (the FLIP scores of every evaluation), drjit and mitsuba, the last trimmed to the variants and plugins the suite loads and both
#     recompressed with LZMA (scripts/trim_mitsuba_wheel.py; about 24 MiB in all);
#  2. the run archive results/cpu/runs taken out of the index and ignored, so the working tree travels;
#     `scripts/gpu_prepare.sh --undo` puts it back. Commit nothing between the two (git status shows
#     the archive as deleted while prepared).
# It prints the sizes and fails when tree and wheels would not fit 64 MiB.
#   scripts/gpu_prepare.sh [--no-dry-run] | --undo
set -euo pipefail
self=$(realpath "$0")
cd "$(dirname "$self")/.."
exclude=.git/info/exclude
[ $# -le 1 ] || { echo "gpu_prepare: one option at most (--no-dry-run or --undo), not: $*"; exit 2; }
case "${1:-}" in
    -h|--help) sed -n '2,15p' "$self" | sed 's/^# \{0,1\}//'; exit 0 ;;
    --undo) git reset -q -- results/cpu/runs
            sed -i '\#^/results/cpu/runs/$#d' "$exclude"
            echo "gpu_prepare: the run archive is tracked again"; exit 0 ;;
    --no-dry-run|"") ;;
    *) echo "gpu_prepare: unknown option $1 (--no-dry-run, --undo)"; exit 2 ;;
esac
if [ "${1:-}" != --no-dry-run ]; then
    echo "gpu_prepare: the GPU job's dry run (make test-gpu-job) ..."
    make test-gpu-job || { echo "gpu_prepare: the job's dry run failed: fix it before a GPU call"; exit 1; }
fi
platforms=(--platform manylinux_2_28_x86_64 --platform manylinux_2_27_x86_64 --platform manylinux_2_17_x86_64)
download() { python3 -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
    "${platforms[@]}" -d "$1" "${@:2}"; }
mkdir -p .whl
download .whl hydra-core==1.3.8 omegaconf==2.3.1 OpenEXR==3.5.3 flip-evaluator==1.7 drjit==1.5.0 mitsuba==3.9.1
python3 -m pip wheel -q --no-deps -w .whl antlr4-python3-runtime==4.9.3   # an sdist only: a pure-Python wheel
# LZMA takes minutes here; a wheel already trimmed (its RECORD lists no headers) is left as it is
mitsuba=$(ls .whl/mitsuba-*.whl)
if python3 -c "import sys, zipfile; sys.exit(not any(n.startswith('mitsuba/include/') for n in zipfile.ZipFile('$mitsuba').namelist()))"; then
    python3 scripts/trim_mitsuba_wheel.py "$mitsuba" .whl/drjit-*.whl
fi
grep -qx '/results/cpu/runs/' "$exclude" || echo '/results/cpu/runs/' >> "$exclude"
git rm -r -q --cached results/cpu/runs 2>/dev/null || true
# du reads the names itself: through xargs, a list past its buffer (91 KiB of names now) would be summed
# in batches, and the last batch's total taken for the whole
tree=$(git ls-files -z | du -cb --files0-from=- | tail -1 | cut -f1)
untracked=$(git ls-files -z --others --exclude-standard | du -cb --files0-from=- | tail -1 | cut -f1)
wheels=$(du -cb .whl/*.whl | tail -1 | cut -f1)
total=$(( (tree + ${untracked:-0} + wheels) / 1048576 ))
echo "gpu_prepare: tracked tree $((tree / 1048576)) MiB, untracked $((${untracked:-0} / 1048576)) MiB, .whl $((wheels / 1048576)) MiB: $total MiB of 64"
[ "$total" -lt 64 ] || { echo "gpu_prepare: over the 64 MiB a call carries"; exit 1; }
echo "gpu_prepare: one call, timeout_s 600, carry [.whl] (and runs, from an earlier call):"
echo "             bash scripts/gpu_job.sh tests speed profile sota"
