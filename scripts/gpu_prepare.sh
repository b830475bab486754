#!/usr/bin/env bash
# Prepares THIS checkout for scripts/gpu_job.sh on a lent GPU machine (README, "On a GPU"):
#  1. wheels for the machine's Python 3.12 that its image lacks: .whl/ (hydra-core, omegaconf,
#     antlr4, OpenEXR: 2.2 MB) and .whl-render/ (mitsuba without its spectral, mono and polarized
#     variants and headers, and drjit: about 57 MB, for the sota step's rendering);
#  2. the run archive results/cpu/runs (127 MiB, over the 64 MiB a call may carry) taken out of the
#     index and ignored, so the working tree travels; `scripts/gpu_prepare.sh --undo` puts it back.
#     Commit nothing between the two (git status shows the archive as deleted while prepared).
set -euo pipefail
cd "$(dirname "$0")/.."
exclude=.git/info/exclude
if [ "${1:-}" = "--undo" ]; then
    git reset -q -- results/cpu/runs
    sed -i '\#^/results/cpu/runs/$#d' "$exclude"
    echo "gpu_prepare: the run archive is tracked again"; exit 0
fi
platforms=(--platform manylinux_2_28_x86_64 --platform manylinux_2_27_x86_64 --platform manylinux_2_17_x86_64)
download() { python3 -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
    "${platforms[@]}" -d "$1" "${@:2}"; }
mkdir -p .whl .whl-render
download .whl hydra-core==1.3.8 omegaconf==2.3.1 OpenEXR==3.5.3
python3 -m pip wheel -q --no-deps -w .whl antlr4-python3-runtime==4.9.3   # an sdist only: a pure-Python wheel
download .whl-render drjit==1.5.0 mitsuba==3.9.1
python3 - <<'PY'
"""Drop the mitsuba variants the suite never selects (it renders with scalar_rgb, llvm_ad_rgb or cuda_ad_rgb)."""
import glob, os, re, zipfile
path = glob.glob(".whl-render/mitsuba-*.whl")[0]
drop = re.compile(r"mitsuba/(include/|(scalar|llvm_ad|cuda_ad)_(spectral|mono)[a-z_]*\.cpython)")
with zipfile.ZipFile(path) as src, zipfile.ZipFile(path + ".tmp", "w", zipfile.ZIP_DEFLATED) as dst:
    for item in src.infolist():
        if drop.match(item.filename):
            continue
        data = src.read(item)
        if item.filename.endswith("RECORD"):
            data = "".join(line for line in data.decode().splitlines(True) if not drop.match(line)).encode()
        dst.writestr(item, data)
os.replace(path + ".tmp", path)
PY
grep -qx '/results/cpu/runs/' "$exclude" || echo '/results/cpu/runs/' >> "$exclude"
git rm -r -q --cached results/cpu/runs 2>/dev/null || true
tree=$(git ls-files -z | xargs -0 du -cb | tail -1 | cut -f1)
echo "gpu_prepare: tracked tree $((tree / 1048576)) MiB; .whl $(du -sm .whl | cut -f1) MiB; .whl-render $(du -sm .whl-render | cut -f1) MiB"
echo "gpu_prepare: run with carry [.whl-render] 'bash scripts/gpu_job.sh install', then at once (the machine stays warm 30 s)"
echo "             carry [.whl] (and runs, from an earlier call) 'bash scripts/gpu_job.sh tests speed sota'"
