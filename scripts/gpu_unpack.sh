#!/usr/bin/env bash
# Unpacks what scripts/gpu_job.sh brought back (the device tool's files_at folder) into this checkout:
# results/gpu (commit it) and the run store runs/ (carry it to the next call to resume).
#     bash scripts/gpu_unpack.sh /work/.device/<files_at>
set -euo pipefail
from=${1:?usage: scripts/gpu_unpack.sh FOLDER}
cd "$(dirname "$0")/.."
[ -f "$from/results.tar.gz" ] && tar xzf "$from/results.tar.gz"
if compgen -G "$from/runs.tar.gz.part-*" > /dev/null; then cat "$from"/runs.tar.gz.part-* | tar xzf -; fi
[ -f "$from/log.txt" ] && tail -20 "$from/log.txt"
git status --short results/gpu | head -20
