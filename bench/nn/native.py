"""bench/nn's compiled CPU inference kernels (cpu_kernels.cpp: the deformable conv's sampling, the
fused CFM), built on first use.

The kernels have a plain C ABI and no torch headers, so they compile in a few seconds with the
system's C++ compiler, for this CPU (-march=native), into a cache keyed by the source, the flags, the
compiler and the CPU. Where there is no compiler, or SRD_BENCH_NATIVE=0, `cpu_kernels()` is None and
the layers fall back to eager PyTorch (same results, slower).

The kernels parallelise with OpenMP and are linked against libgomp by soname. torch is imported
before they are loaded (this module imports it), and torch's wheel ships libgomp.so.1, so the loader
binds them to that already-loaded copy: their parallel regions run on torch's own worker threads. A second thread pool would fight torch's spinning workers for the cores after every torch
op (measured: 1.5x slower layer).

Environment: SRD_BENCH_NATIVE=0 turns the kernels off; SRD_BENCH_CACHE sets the cache folder
(default ~/.cache/srd-bench); CXX picks the compiler.
"""
import ctypes
import functools
import hashlib
import os
import platform
import shutil
import subprocess
import tempfile
import warnings
from pathlib import Path

import torch  # also loads torch's libgomp before the kernels (see above)

SOURCE = Path(__file__).with_name("cpu_kernels.cpp")
FLAGS = ("-O3", "-march=native", "-std=c++20", "-shared", "-fPIC", "-fopenmp")

DTYPE_CODES = {torch.float32: 0, torch.bfloat16: 1}  # the kernels' dtype codes (enum Dtype in the .cpp)

_i64, _i32, _ptr = ctypes.c_int64, ctypes.c_int32, ctypes.c_void_p
_SIGNATURES = {  # name: (argument types, result type), as in cpu_kernels.cpp
    "deform_columns": ([_ptr, _i32, _i64, _i64, _i64, _i64, _ptr, _i32, _ptr, _ptr, _i32, _ptr, _ptr, _i32, _i64,
                        _i64, _i64, _i64, _ptr, _ptr, _i32], _i32),
    "cfm_affine": ([_ptr, _ptr, _i32, _i64, _i64, _i64, _ptr, _ptr, _i32, _ptr, _i32], _i32),
    "deform_columns_backward": ([_ptr, _i64, _i64, _i64, _i64, _ptr, _ptr, _ptr, _i64, _i64, _i64, _ptr, _ptr,
                                 _ptr, _ptr, _ptr, _i32], _i32),
}


def _cpu_identity() -> str:
    """What -march=native compiles for: the model name and feature flags of this CPU."""
    try:
        text = Path("/proc/cpuinfo").read_text()
    except OSError:
        return platform.machine()
    wanted = [line for line in text.splitlines() if line.startswith(("model name", "flags"))]
    return platform.machine() + "\n".join(sorted(set(wanted)))


def _compile(compiler: str, target: Path) -> None:
    target.parent.mkdir(parents=True, exist_ok=True)
    # build next to the target, then rename: concurrent processes never load a half-written file
    with tempfile.TemporaryDirectory(dir=target.parent) as tmp:
        built = Path(tmp) / target.name
        subprocess.run([compiler, *FLAGS, str(SOURCE), "-o", str(built)], check=True, capture_output=True,
                       text=True)
        os.replace(built, target)


@functools.cache
def cpu_kernels() -> ctypes.CDLL | None:
    """The compiled kernel (built once per source, flags, compiler and CPU), or None where it cannot be."""
    if os.environ.get("SRD_BENCH_NATIVE", "1") == "0":
        return None
    compiler = os.environ.get("CXX") or shutil.which("g++") or shutil.which("c++")
    if compiler is None:
        warnings.warn("no C++ compiler found: deformable conv and CFM run their slower eager code", stacklevel=2)
        return None
    key = hashlib.sha256("\n".join([SOURCE.read_text(), *FLAGS, compiler, _cpu_identity()]).encode()).hexdigest()
    target = Path(os.environ.get("SRD_BENCH_CACHE", Path.home() / ".cache" / "srd-bench")) / f"cpu_kernels-{key[:16]}.so"
    try:
        if not target.exists():
            _compile(compiler, target)
        lib = ctypes.CDLL(str(target))
    except (OSError, subprocess.CalledProcessError) as err:
        detail = getattr(err, "stderr", "") or str(err)
        warnings.warn(f"cpu_kernels.cpp did not build ({detail.strip()[:500]}): deformable conv and CFM "
                      "run their slower eager code", stacklevel=2)
        return None
    for name, (argtypes, restype) in _SIGNATURES.items():
        getattr(lib, name).argtypes, getattr(lib, name).restype = argtypes, restype
    return lib
