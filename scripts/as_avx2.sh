#!/bin/bash
# Runs a command on this AVX-512 host as on a CPU with AVX2 only (most laptops), to time it where no such
# machine is at hand:  scripts/as_avx2.sh make test
# - /proc/cpuinfo without its avx512*/amx* flags: the suite's own ISA checks (bench.measure.cpu_isa) see
#   AVX2 only, so bf16 counts as emulated and the fast paths skip it;
# - ATen's and Inductor's kernels at AVX2 (ATEN_CPU_CAPABILITY), oneDNN capped at AVX2;
# - every C++ build (bench/nn/native.py, Inductor) at -march=haswell where it asked for -march=native.
# What it cannot change: clock, caches and memory are this host's. Needs a private mount namespace
# (root, or unprivileged user namespaces: unshare -r).
set -euo pipefail
[ $# -gt 0 ] || { echo "usage: $0 COMMAND [ARG...]" >&2; exit 2; }
grep -qw avx2 /proc/cpuinfo || { echo "as_avx2: this CPU has no AVX2" >&2; exit 2; }
dir=$(mktemp -d)
trap 'rm -rf "$dir"' EXIT
sed -E 's/ (avx512[a-z0-9_]*|amx[a-z0-9_]*)//g' /proc/cpuinfo > "$dir/cpuinfo"
compiler=${CXX:-$(command -v g++ || command -v c++)}
wrapper="$dir/$(basename "$compiler")"   # the same name: Inductor tells gcc from clang by it
cat > "$wrapper" <<EOF
#!/bin/bash
args=()
for a in "\$@"; do case "\$a" in -march=native) args+=(-march=haswell);; *) args+=("\$a");; esac; done
exec "$compiler" "\${args[@]}"
EOF
chmod +x "$wrapper"
export ATEN_CPU_CAPABILITY=avx2 ONEDNN_MAX_CPU_ISA=AVX2 DNNL_MAX_CPU_ISA=AVX2 CXX="$wrapper"
mount_and_run='mount --bind "$0" /proc/cpuinfo && exec "$@"'
if [ "$(id -u)" = 0 ]; then
    unshare -m bash -c "$mount_and_run" "$dir/cpuinfo" "$@"
else
    unshare -m -r bash -c "$mount_and_run" "$dir/cpuinfo" "$@"
fi
