#!/usr/bin/env bash
# The GPU work as ONE call per machine start (the machine goes back about 30 s after a call, less than a
# reply takes to read; docs/gpu.md, "The GPU job"; prepared here by scripts/gpu_prepare.sh). Run from the
# repository root there, carrying .whl (and runs, from an earlier call):
#     bash scripts/gpu_job.sh [tests] [render] [speed] [concurrency] [profile] [sweep] [plan] [sota]   (none: tests speed sota)
# It installs the carried wheels, then runs the steps in order within JOB_S seconds in all (default 560,
# for a run timeout_s of 600), each within STEP_S (default 540) and what is left; a step whose result is
# already in the working tree is skipped (a speed table or sweep that says PARTIAL is not done), so the
# next call, carrying what the last one brought back, goes on where it stopped:
#   tests    tests/test_cuda.py and tests/test_fused_gpu.py with the fused kernels on
#            -> results/gpu/cuda_tests/<device>.txt (pytest-xdist's 4 workers where it is installed)
#   render   (optional) the gpu data preset's first scenes rendered twice with cuda_ad_rgb, then by 4
#            processes at once, and with llvm_ad_rgb: frames/s, set-up per scene, bit-identity, digests
#            (scripts/gpu_render_probe.py; the .digests.json kept: a later machine's are compared with it)
#            -> results/gpu/data/<device>-render-probe.md and .digests.json
#   speed    +experiment=speed preset=gpu device=cuda, with the fused kernels on only if `tests` passed, and
#            every model's training step and the conv stack's also CUDA-graphed (train.compile=reduce-overhead)
#            -> results/gpu/speed/<device>/
#   concurrency (optional) 1, 2 and 4 processes taking training steps at once, per model, eager and graphed:
#            what jobs=N can gain (scripts/gpu_step_concurrency.py) -> results/gpu/profile/<device>-concurrency.md
#   profile  (optional) Ours' training step under torch.profiler, eager and compiled
#            (scripts/gpu_profile_step.py) -> results/gpu/profile/<device>.md
#   sweep    (optional) the fused deformable conv's tile sizes against nn.Conv2d (scripts/gpu_deform_sweep.py)
#            -> results/gpu/profile/<device>-deform-sweep.md
#   plan     (optional) what Table 5 at the preset (with $SOTA_ARGS) costs here, projected from the render
#            probe's and the speed table's rates with the scoring timed on this host's CPU
#            (scripts/gpu_speedrun_plan.py)
#            -> results/gpu/profile/<device>-speedrun-plan.md
#   sota     +experiment=sota preset=gpu device=cuda $SOTA_ARGS (rendering: needs the mitsuba wheel),
#            interrupted at its limit and resumed from its checkpoints by the next call (carry `runs`)
#            -> results/gpu/sota/, runs/{train,eval}
# Everything comes back in $OUT as at most 8 files: log.txt, results.tar.gz (results/gpu), and
# runs.tar.gz.part-* (the unfinished trainings' run folders, 15 MiB parts). Unpack them here with
# scripts/gpu_unpack.sh. Environment: PYTHON (.venv/bin/python where `make` made one, else python3), DEVICE (cuda), PRESET (gpu), JOB_S, STEP_S, RENDER_S,
# SPEED_ARGS, SOTA_ARGS, PROFILE_ARGS, RENDER_ARGS, CONCURRENCY_ARGS. tests/test_gpu_job.py (make test) dry-runs `tests sota` on a CPU at the
# smoke preset in a copy of the project. A dry run by hand (its records land in results/gpu: delete them after):
#     DEVICE=cpu PROFILE_ARGS="--batch 1 --frames 2 --crop 16 --channels 8 --no-compile" OUT=/tmp/x \
#         bash scripts/gpu_job.sh tests profile
set -uo pipefail
OUT=${OUT:-/tmp/gpu_job_out}
PYTHON=${PYTHON:-$([ -x .venv/bin/python ] && echo .venv/bin/python || echo python3)}
DEVICE=${DEVICE:-cuda}
PRESET=${PRESET:-gpu}
JOB_S=${JOB_S:-560}
STEP_S=${STEP_S:-540}
# the training steps at the preset's batch, frames and crop (each null: the preset's), every model's also
# graphed (whether the gpu preset should train them so), no 4K tiles; not experiment.train=null, which
# would also drop the compile the speed step asks for
SPEED_ARGS=${SPEED_ARGS:-experiment.train.batch=null experiment.train.frames=null experiment.train.crop=null experiment.train.compiled=[Ours,EDSR,RAE,KPCN,CFM] experiment.tiled.uhd=false}
RENDER_ARGS=${RENDER_ARGS:---families 4 --per-family 2 --workers 4 --compare llvm_ad_rgb}
RENDER_S=${RENDER_S:-180}   # the render probe's share: a measurement, not the data
CONCURRENCY_ARGS=${CONCURRENCY_ARGS:---models srd edsr rae kpcn cfm --processes 1 2 4 --compile none reduce-overhead}
SOTA_ARGS=${SOTA_ARGS:-}
PROFILE_ARGS=${PROFILE_ARGS:-}
VARIANT=$([[ $DEVICE == cuda* ]] && echo cuda_ad_rgb || echo llvm_ad_rgb)
STEPS=${*:-tests speed sota}
for step in $STEPS; do   # every name checked first: a typo after a long step would lose its packing
    case $step in
        tests|render|speed|concurrency|profile|sweep|plan|sota) ;;
        *) echo "gpu_job: unknown step $step (tests, render, speed, concurrency, profile, sweep, plan, sota)"; exit 2 ;;
    esac
done
PACK_S=20   # kept back for packing what comes back
mkdir -p "$OUT"
exec > >(tee -a "$OUT/log.txt") 2>&1
export PYTHONUNBUFFERED=1 SRD_TRACKING=none

# seconds the next step may run: STEP_S, or what is left of JOB_S after packing
step_limit() {
    local left=$((JOB_S - SECONDS - PACK_S))
    echo $((left < STEP_S ? left : STEP_S))
}

# the carried wheels (scripts/gpu_prepare.sh: hydra, omegaconf, antlr4, OpenEXR, flip-evaluator, drjit, trimmed mitsuba)
if compgen -G ".whl/*.whl" > /dev/null; then
    "$PYTHON" -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl \
        || { echo "gpu_job: installing .whl failed"; exit 1; }
    echo "gpu_job: wheels installed in ${SECONDS} s"
fi
export PYTHONPATH=/tmp/site:$PWD${PYTHONPATH:+:$PYTHONPATH}

# what the job asks of Python, in one start (each imports torch, 2-3 s): the machine's directory name; the
# kernels' digest: a record counts for these kernels only, so a change to their code (not a comment or
# docstring: the syntax tree, as run fingerprints hash it) is tested again before they are used; the
# versions and the GPU the tests record names
probe=$("$PYTHON" - "$DEVICE" <<'PY'
import hashlib, sys, traceback
from pathlib import Path
try:
    import torch
    import bench.experiments.speed  # noqa: F401 - what the steps import: a missing package stops the job here
    from bench.machine import device_tag
    from bench.runs import source_hash
except Exception as err:  # noqa: BLE001 - any failure to import is this one message, as before
    traceback.print_exc()
    sys.exit(f"gpu_job: bench does not import (missing packages? carry them as wheels): {err}")
try:
    joined = "".join(source_hash(Path(p)) for p in ("bench/nn/triton_kernels.py", "bench/nn/fused.py",
                                                    "bench/nn/deform.py", "bench/nn/cfm.py"))
except Exception as err:  # noqa: BLE001 - a file missing or not Python
    traceback.print_exc()
    sys.exit(f"gpu_job: the kernels' sources do not parse: {err}")
try:
    import triton
    triton_version = triton.__version__
except ImportError:
    triton_version = "none"
gpu = torch.cuda.get_device_name() if torch.cuda.is_available() else ""
print(device_tag(sys.argv[1]))
print(hashlib.sha256((joined + "\n").encode()).hexdigest()[:16])  # as `print(joined) | sha256sum` gave it
print(gpu)
print("torch", torch.__version__, "triton", triton_version, gpu)
PY
) || exit 1
{ read -r tag; read -r kernels; read -r gpu; read -r versions; } <<< "$probe"
# the values come by line: a line printed by an import would shift them
[[ $kernels =~ ^[0-9a-f]{16}$ ]] || { echo "gpu_job: the start-up probe printed more than its four lines: $probe"; exit 1; }
echo "gpu_job: $(date -u +%FT%TZ) on $tag, steps: $STEPS"
tests_record=results/gpu/cuda_tests/$tag.txt
tests_passed() { grep -q "^passed" "$tests_record" 2>/dev/null && grep -q "^kernels: $kernels" "$tests_record"; }

step_tests() {
    if tests_passed; then echo "gpu_job: tests already passed with these kernels ($tests_record)"; return; fi
    mkdir -p "$(dirname "$tests_record")"
    local log=/tmp/cuda_tests.log workers=()
    # on a GPU the compiled-step tests compile in parallel; without one (a dry run) 4 workers only start up
    [ -n "$gpu" ] && "$PYTHON" -c "import xdist" 2>/dev/null && workers=(-n 4)
    SRD_BENCH_FUSED_GPU=1 timeout "$(step_limit)" "$PYTHON" -m pytest -q -p no:cacheprovider ${workers[@]+"${workers[@]}"} \
        tests/test_cuda.py tests/test_fused_gpu.py > "$log" 2>&1
    local rc=$?
    [ -n "$gpu" ] || rc="no CUDA GPU: the CUDA tests skipped"   # never a "passed" without a GPU
    { [ "$rc" = 0 ] && echo passed || echo "failed ($rc)"
      echo "kernels: $kernels"
      echo "command: SRD_BENCH_FUSED_GPU=1 pytest -q ${workers[*]+${workers[*]}} tests/test_cuda.py tests/test_fused_gpu.py"
      echo "date: $(date -u +%FT%TZ)"
      echo "$versions"
      tail -40 "$log"; } > "$tests_record"
    tail -5 "$log"
}

# a record is done when it exists and does not say PARTIAL (a run stopped at its limit leaves one that
# does); a PARTIAL one is run again $2 times in all (default 2): a step that cannot finish within STEP_S
# would otherwise take STEP_S of every later call and the steps after it never run (it is kept, and says
# PARTIAL). The speed table goes on from its last section, so each of its tries adds to it: it gets 4
finished() {
    [ -f "$1" ] || return 1
    grep -q "^PARTIAL: " "$1" || return 0
    [ "$(cat "$1.tries" 2>/dev/null || echo 0)" -lt "${2:-2}" ] && return 1
    echo "gpu_job: $1 is still PARTIAL after ${2:-2} tries: kept (remove $1.tries to go on; or raise STEP_S, or time less)"
}
# whether every module named imports here; else the step says which do not and is skipped (the GPU image
# has neither mitsuba nor flip_evaluator: scripts/gpu_prepare.sh downloads their wheels, carry .whl)
imports() {
    local step=$1 missing
    shift
    # one Python start for them all
    missing=$("$PYTHON" - "$@" <<'PY' 2>/dev/null
import importlib, sys
missing = []
for name in sys.argv[1:]:
    try:
        importlib.import_module(name)
    except Exception:
        missing.append(name)
print(" or ".join(missing))
PY
) || missing="$*"
    [ -z "$missing" ] && return 0
    echo "gpu_job: no $missing here (carry .whl): $step skipped"
    return 1
}
# counted before the step runs: a call killed at its limit counts too
tried() { mkdir -p "$(dirname "$1")"; echo $(( $(cat "$1.tries" 2>/dev/null || echo 0) + 1 )) > "$1.tries"; }

step_speed() {
    if finished "results/gpu/speed/$tag/table.md" 4; then echo "gpu_job: speed table already there"; return; fi
    tried "results/gpu/speed/$tag/table.md"
    local fused=0
    tests_passed && fused=1
    echo "gpu_job: speed with SRD_BENCH_FUSED_GPU=$fused"
    # results/gpu whatever the preset: what the job checks and packs (a dry run's smoke table included)
    SRD_BENCH_FUSED_GPU=$fused timeout "$(step_limit)" "$PYTHON" -m bench +experiment=speed preset="$PRESET" device="$DEVICE" \
        results_dir=results/gpu \
        experiment.oidn=false experiment.train.compile=reduce-overhead $SPEED_ARGS
}

step_sota() {
    if [ -f "results/gpu/sota/table.md" ]; then echo "gpu_job: sota table already there"; return; fi
    # rendering needs mitsuba, scoring flip_evaluator: said now, not after the trainings
    imports sota mitsuba flip_evaluator || return 0
    local fused=0
    tests_passed && fused=1
    # SIGTERM at the limit: the trainer checkpoints and stops; the next call resumes it. OIDN's rows need
    # pyoidn, whose wheel (88 MB) does not fit a call: where it does not import they are left out, and the
    # caption names them
    SRD_BENCH_FUSED_GPU=$fused timeout "$(step_limit)" "$PYTHON" -m bench +experiment=sota preset="$PRESET" \
        results_dir=results/gpu runs_archive=results/gpu/runs \
        device="$DEVICE" +experiment.leave_out_unavailable=true $SOTA_ARGS
    echo "gpu_job: sota exit $?"
}

step_render() {
    local record=results/gpu/data/$tag-render-probe.md
    if finished "$record"; then echo "gpu_job: render probe already there ($record)"; return; fi
    imports render mitsuba || return 0
    tried "$record"
    local limit
    limit=$(step_limit)
    limit=$((limit < RENDER_S ? limit : RENDER_S))
    # passes 1 and 2 start no sequence after a quarter and a half of the step's time; the 4-process pass
    # and the comparison then run only if they start before three quarters (the record says PARTIAL
    # until they are in)
    timeout "$limit" "$PYTHON" scripts/gpu_render_probe.py --data "$PRESET" --variant "$VARIANT" \
        --seconds $((limit / 4)) --out "$record" $RENDER_ARGS
    echo "gpu_job: render exit $?"
}

step_concurrency() {
    local record=results/gpu/profile/$tag-concurrency.md
    if finished "$record"; then echo "gpu_job: concurrency already there ($record)"; return; fi
    tried "$record"
    local fused=0
    tests_passed && fused=1
    # the record is rewritten after each configuration, under a PARTIAL line until the last
    SRD_BENCH_FUSED_GPU=$fused timeout "$(step_limit)" "$PYTHON" scripts/gpu_step_concurrency.py --device "$DEVICE" \
        --preset "$PRESET" --out "$record" $CONCURRENCY_ARGS
    echo "gpu_job: concurrency exit $?"
}

step_sweep() {
    local record=results/gpu/profile/$tag-deform-sweep.md
    if finished "$record"; then echo "gpu_job: sweep already there ($record)"; return; fi
    tried "$record"
    timeout "$(step_limit)" "$PYTHON" scripts/gpu_deform_sweep.py --device "$DEVICE" --out "$record"
    echo "gpu_job: sweep exit $?"
}

step_plan() {
    local record=results/gpu/profile/$tag-speedrun-plan.md
    if [ -f "$record" ]; then echo "gpu_job: plan already there ($record)"; return; fi
    imports plan flip_evaluator || return 0
    # SOTA_ARGS too: the projection is of the table the sota step would run
    timeout "$(step_limit)" "$PYTHON" scripts/gpu_speedrun_plan.py --preset "$PRESET" --machine "$tag" --out "$record" \
        ${SOTA_ARGS:+--set $SOTA_ARGS}
    echo "gpu_job: plan exit $?"
}

step_profile() {
    local record=results/gpu/profile/$tag.md
    if [ -f "$record" ]; then echo "gpu_job: profile already there ($record)"; return; fi
    mkdir -p "$(dirname "$record")"
    local fused=0
    tests_passed && fused=1
    SRD_BENCH_FUSED_GPU=$fused timeout "$(step_limit)" "$PYTHON" scripts/gpu_profile_step.py --device "$DEVICE" \
        --out "$record" $PROFILE_ARGS
    echo "gpu_job: profile exit $?"
}

for step in $STEPS; do
    if [ "$(step_limit)" -lt 30 ]; then echo "gpu_job: no time left for $step (JOB_S=$JOB_S)"; break; fi
    "step_$step"
done

# what comes back: results/gpu (with its run archive, every finished run in compact form) and the
# trainings that did not finish (their checkpoints, to resume), in parts under 16 MiB
[ -d results/gpu ] && tar czf "$OUT/results.tar.gz" results/gpu
rm -f "$OUT"/runs.tar.gz.part-*
unfinished=$("$PYTHON" - <<'PY'
import json, pathlib
for run in sorted(pathlib.Path("runs/train").glob("*/")):
    try:
        status = json.loads((run / "run.json").read_text()).get("status")
    except (OSError, ValueError):
        status = None
    if status != "complete" and (run / "checkpoint.pt").exists():
        print(run)
PY
)
if [ -n "$unfinished" ]; then
    echo "gpu_job: packing unfinished trainings: $(echo $unfinished | wc -w)"
    tar czf - $unfinished | split -b 15m -a 1 - "$OUT/runs.tar.gz.part-"
fi
ls -l "$OUT"
