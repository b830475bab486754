#!/bin/bash
# Runs a command on an AVX-512 host with the vector ISA an AVX2-only CPU (most laptops) would get, to time
# it where no such machine is at hand:  scripts/as_avx2.sh make test
# What it caps at AVX2:
# - /proc/cpuinfo loses its avx512*/amx* flags: the suite's own ISA checks (bench.machine) see AVX2 only,
#   so bf16 counts as emulated, and the tests of AVX-512 code paths skip as they would there;
# - ATen and Inductor (ATEN_CPU_CAPABILITY), oneDNN, MKL, OpenBLAS and numpy's SIMD dispatch;
# - every C++ build that asks for -march=native (bench/nn/native.py, Inductor) gets -march=haswell.
# What it leaves: Dr.Jit (Mitsuba's renderer) and OIDN pick their ISA from cpuid, so they keep AVX-512;
# clock, caches and memory are this host's. So it times the ISA, not a laptop.
# The compiler wrapper lives at a fixed path (under the kernel cache), so builds cached by one run are
# found by the next, as they are without the script. Needs a private mount namespace: root, or
# unprivileged user namespaces (then the command runs as a mapped uid 0).
set -euo pipefail
[ $# -gt 0 ] || { echo "usage: $0 COMMAND [ARG...]" >&2; exit 2; }
grep -qw avx2 /proc/cpuinfo || { echo "as_avx2: this CPU has no AVX2" >&2; exit 2; }
compiler=${CXX:-$(command -v g++ || command -v c++ || true)}
[ -n "$compiler" ] || { echo "as_avx2: no C++ compiler (g++ or c++, or CXX)" >&2; exit 2; }
compiler=$(command -v "$compiler")

dir="${SRD_BENCH_CACHE:-$HOME/.cache/srd-bench}/as_avx2"
mkdir -p "$dir"
tmp=$(mktemp -d "$dir/.tmp.XXXXXX")
trap 'rm -rf "$tmp"' EXIT
sed -E 's/ (avx512[a-z0-9_]*|amx[a-z0-9_]*)//g' /proc/cpuinfo > "$tmp/cpuinfo"
wrapper="$dir/$(basename "$compiler")"   # named like the compiler: Inductor tells gcc from clang by the name
{
    echo '#!/bin/bash'
    echo 'args=()'
    echo 'for a in "$@"; do case "$a" in -march=native) args+=(-march=haswell);; *) args+=("$a");; esac; done'
    printf 'exec %q "${args[@]}"\n' "$compiler"
} > "$tmp/wrapper"
chmod +x "$tmp/wrapper"
mv -f "$tmp/wrapper" "$wrapper"          # a rename: a concurrent run never sees half a file

export CXX="$wrapper" ATEN_CPU_CAPABILITY=avx2 ONEDNN_MAX_CPU_ISA=AVX2 DNNL_MAX_CPU_ISA=AVX2 \
    MKL_ENABLE_INSTRUCTIONS=AVX2 OPENBLAS_CORETYPE=Haswell
export NPY_DISABLE_CPU_FEATURES="${NPY_DISABLE_CPU_FEATURES:-X86_V4 AVX512_ICL AVX512_SPR}"   # numpy 2.x dispatch names

unshare=(unshare -m)
[ "$(id -u)" = 0 ] || unshare+=(-r)
"${unshare[@]}" true 2>/dev/null || { echo "as_avx2: no private mount namespace here (${unshare[*]})" >&2; exit 3; }
mount_and_run='mount --bind "$0" /proc/cpuinfo || { echo "as_avx2: cannot mount over /proc/cpuinfo" >&2; exit 3; }
exec "$@"'
"${unshare[@]}" bash -c "$mount_and_run" "$tmp/cpuinfo" "$@"
