#!/usr/bin/env bash
# The GPU work as one resumable job for a lent GPU machine (README, "On a GPU"; prepared here by
# scripts/gpu_prepare.sh). Run from the repository root there:
#     bash scripts/gpu_job.sh [tests] [speed] [sota]        (no argument: all three, in that order)
#     bash scripts/gpu_job.sh install                       (only install the carried wheels)
# Each step ends within STEP_S seconds (default 540) and is skipped when its result is already in the
# working tree, so the next call, carrying what the last one brought back, goes on where it stopped:
#   tests  tests/test_cuda.py and tests/test_fused_gpu.py with the fused kernels on
#          -> results/gpu/cuda_tests/<device>.txt
#   speed  +experiment=speed preset=gpu device=cuda, with the fused kernels on only if `tests` passed
#          -> results/gpu/speed/<device>/
#   sota   +experiment=sota preset=gpu device=cuda $SOTA_ARGS (rendering included: needs mitsuba there),
#          interrupted at STEP_S and resumed from its checkpoints by the next call (carry `runs`)
#          -> results/gpu/sota/, runs/{train,eval}
# Everything comes back in $OUT as at most 8 files: log.txt, results.tar.gz (results/gpu), and
# runs.tar.gz.part-* (the run store without rendered data, 15 MiB parts). Unpack them here with
# scripts/gpu_unpack.sh. Environment: PYTHON (python3), DEVICE (cuda), PRESET (gpu), STEP_S, SOTA_ARGS.
set -uo pipefail
OUT=${OUT:-/tmp/gpu_job_out}
PYTHON=${PYTHON:-python3}
DEVICE=${DEVICE:-cuda}
PRESET=${PRESET:-gpu}
STEP_S=${STEP_S:-540}
SOTA_ARGS=${SOTA_ARGS:-}
STEPS=${*:-tests speed sota}
mkdir -p "$OUT"
exec > >(tee -a "$OUT/log.txt") 2>&1
export PYTHONUNBUFFERED=1 SRD_TRACKING=none

# Wheels carried in .whl/ (and .whl-render/: mitsuba, drjit) install into /tmp/site, which a warm
# machine keeps between calls: two calls can bring more than one call's 64 MiB.
for dir in .whl .whl-render; do
    if compgen -G "$dir/*.whl" > /dev/null; then
        "$PYTHON" -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site "$dir"/*.whl \
            || { echo "gpu_job: installing $dir failed"; exit 1; }
    fi
done
export PYTHONPATH=/tmp/site:$PWD${PYTHONPATH:+:$PYTHONPATH}
if [ "$STEPS" = install ]; then ls /tmp/site; exit 0; fi

tag=$("$PYTHON" -c "from bench.experiments.speed import device_tag; print(device_tag('$DEVICE'))") \
    || { echo "gpu_job: bench does not import (missing packages? carry them as wheels)"; exit 1; }
echo "gpu_job: $(date -u +%FT%TZ) on $tag, steps: $STEPS"
tests_record=results/gpu/cuda_tests/$tag.txt
# the record counts for these kernels only: a change to them is tested again before they are used
kernels=$(cat bench/nn/triton_kernels.py bench/nn/fused.py bench/nn/deform.py bench/nn/cfm.py | sha256sum | cut -c1-16)
tests_passed() { grep -q "^passed" "$tests_record" 2>/dev/null && grep -q "^kernels: $kernels" "$tests_record"; }

step_tests() {
    if tests_passed; then echo "gpu_job: tests already passed with these kernels ($tests_record)"; return; fi
    mkdir -p "$(dirname "$tests_record")"
    local log=/tmp/cuda_tests.log
    SRD_BENCH_FUSED_GPU=1 timeout "$STEP_S" "$PYTHON" -m pytest -q -p no:cacheprovider tests/test_cuda.py \
        tests/test_fused_gpu.py > "$log" 2>&1
    local rc=$?
    local gpu
    gpu=$("$PYTHON" -c "import torch; print(torch.cuda.get_device_name() if torch.cuda.is_available() else '')")
    [ -n "$gpu" ] || rc="no CUDA GPU: the CUDA tests skipped"   # never a "passed" without a GPU
    { [ "$rc" = 0 ] && echo passed || echo "failed ($rc)"
      echo "kernels: $kernels"
      echo "command: SRD_BENCH_FUSED_GPU=1 pytest -q tests/test_cuda.py tests/test_fused_gpu.py"
      echo "date: $(date -u +%FT%TZ)"
      "$PYTHON" -c "import torch, triton; print('torch', torch.__version__, 'triton', triton.__version__, '$gpu')"
      tail -40 "$log"; } > "$tests_record"
    tail -5 "$log"
}

step_speed() {
    if [ -f "results/gpu/speed/$tag/table.md" ]; then echo "gpu_job: speed table already there"; return; fi
    local fused=0
    tests_passed && fused=1
    echo "gpu_job: speed with SRD_BENCH_FUSED_GPU=$fused"
    SRD_BENCH_FUSED_GPU=$fused timeout "$STEP_S" "$PYTHON" -m bench +experiment=speed preset="$PRESET" device="$DEVICE" \
        experiment.oidn=false
}

step_sota() {
    if [ -f "results/gpu/sota/table.md" ]; then echo "gpu_job: sota table already there"; return; fi
    "$PYTHON" -c "import mitsuba" 2>/dev/null || { echo "gpu_job: no mitsuba here (carry .whl-render): sota skipped"; return; }
    local fused=0
    tests_passed && fused=1
    # SIGTERM at the limit: the trainer checkpoints and stops; the next call resumes it
    SRD_BENCH_FUSED_GPU=$fused timeout "$STEP_S" "$PYTHON" -m bench +experiment=sota preset="$PRESET" \
        device="$DEVICE" $SOTA_ARGS
    echo "gpu_job: sota exit $?"
}

for step in $STEPS; do
    case $step in
        tests|speed|sota) "step_$step" ;;
        *) echo "gpu_job: unknown step $step (tests, speed, sota)"; exit 2 ;;
    esac
done

# what comes back: results/gpu and the run store without rendered data, in parts under 16 MiB
[ -d results/gpu ] && tar czf "$OUT/results.tar.gz" results/gpu
if [ -d runs ]; then
    rm -f "$OUT"/runs.tar.gz.part-*
    tar czf - --exclude=runs/data runs | split -b 15m -a 1 - "$OUT/runs.tar.gz.part-"
fi
ls -l "$OUT"
