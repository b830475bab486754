"""bench/nn's compiled CPU kernels (cpu_kernels.cpp: the deformable conv's sampling and its gradient,
the fused CFM), built on first use, and called as torch.library custom ops (`torch.ops.srd_bench.*`),
which check shapes, dtypes, devices and layouts at the boundary: the kernels take raw pointers.

The kernels have a plain C ABI and no torch headers, so they compile in a few seconds with the
system's C++ compiler, for this CPU (-march=native), into a cache keyed by the source, the flags, the
compiler and the CPU. Where there is no compiler, or SRD_BENCH_NATIVE=0, `kernels_available()` is False
and the layers fall back to eager PyTorch (same results, slower).

The kernels parallelise with OpenMP and are linked against libgomp by soname. torch is imported
before they are loaded (this module imports it), and torch's wheel ships libgomp.so.1, so the loader
binds them to that already-loaded copy: their parallel regions run on torch's own worker threads. A second thread pool would fight torch's spinning workers for the cores after every torch
op (measured: 1.5x slower layer).

Environment: SRD_BENCH_NATIVE=0 turns the kernels off; SRD_BENCH_CACHE sets the cache folder
(default ~/.cache/srd-bench); CXX picks the compiler. `built_for(march)` makes the ops call the kernels
built for another target (x86-64-v3 is AVX2, x86-64 is SSE2): the tests run them for each target this CPU runs.
"""
import contextlib
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
from typing import Optional

import torch  # also loads torch's libgomp before the kernels (see above)

SOURCE = Path(__file__).with_name("cpu_kernels.cpp")
FLAGS = ("-O3", "-std=c++20", "-shared", "-fPIC", "-fopenmp")  # and -march=<target>

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


def _compile(compiler: str, flags: tuple, target: Path) -> None:
    target.parent.mkdir(parents=True, exist_ok=True)
    # build next to the target, then rename: concurrent processes never load a half-written file
    with tempfile.TemporaryDirectory(dir=target.parent) as tmp:
        built = Path(tmp) / target.name
        subprocess.run([compiler, *flags, str(SOURCE), "-o", str(built)], check=True, capture_output=True,
                       text=True)
        os.replace(built, target)


@functools.cache
def cpu_kernels(march: str) -> ctypes.CDLL | None:
    """The compiled kernels for `march` ("native": this CPU; built once per source, flags, compiler and
    CPU), or None where they cannot be."""
    if os.environ.get("SRD_BENCH_NATIVE", "1") == "0":
        return None
    compiler = os.environ.get("CXX") or shutil.which("g++") or shutil.which("c++")
    if compiler is None:
        warnings.warn("no C++ compiler found: deformable conv and CFM run their slower eager code", stacklevel=2)
        return None
    flags = (*FLAGS, f"-march={march}")
    key = hashlib.sha256("\n".join([SOURCE.read_text(), *flags, compiler, _cpu_identity()]).encode()).hexdigest()
    target = Path(os.environ.get("SRD_BENCH_CACHE", Path.home() / ".cache" / "srd-bench")) / f"cpu_kernels-{key[:16]}.so"
    try:
        if not target.exists():
            _compile(compiler, flags, target)
        lib = ctypes.CDLL(str(target))
    except (OSError, subprocess.CalledProcessError) as err:
        detail = getattr(err, "stderr", "") or str(err)
        warnings.warn(f"cpu_kernels.cpp did not build ({detail.strip()[:500]}): deformable conv and CFM "
                      "run their slower eager code", stacklevel=2)
        return None
    for name, (argtypes, restype) in _SIGNATURES.items():
        getattr(lib, name).argtypes, getattr(lib, name).restype = argtypes, restype
    return lib


# ---- which build the ops call ----------------------------------------------------------------------

_march = "native"


@contextlib.contextmanager
def built_for(march: str):
    """Inside, the ops (and kernels_available) use the kernels built for `march` (tests: each target
    this CPU runs, e.g. x86-64-v3 = AVX2 on an AVX-512 machine)."""
    global _march
    previous, _march = _march, march
    try:
        yield
    finally:
        _march = previous


def kernels_available() -> bool:
    """The kernels the ops call are built (not switched off, a compiler, no build error); False while
    torch.compile traces: they are ctypes calls it cannot put in a graph (each broke it: 24 breaks in the
    proposed model's forward), so compiled code takes the ops' pure-torch path."""
    if torch.compiler.is_compiling():
        return False
    return cpu_kernels(_march) is not None


def _kernels() -> ctypes.CDLL:
    lib = cpu_kernels(_march)
    if lib is None:
        raise RuntimeError("bench/nn/cpu_kernels.cpp is not built here (see kernels_available())")
    return lib


# ---- the ops: shapes, dtypes and layouts checked here, then the kernel's raw pointers -------------

def _require(ok: bool, message: str) -> None:
    if not ok:
        raise ValueError(message)


def _require_float(name: str, t: torch.Tensor, dims: int) -> None:
    _require(t.dim() == dims and t.dtype in DTYPE_CODES,
             f"{name}: a {dims}-D float32 or bfloat16 tensor expected, got {tuple(t.shape)} {t.dtype}")


def _require_taps(tap_y: torch.Tensor, tap_x: torch.Tensor, taps: int) -> None:
    for name, t in (("tap_y", tap_y), ("tap_x", tap_x)):
        _require(t.dtype == torch.int64 and t.shape == (taps,) and t.is_contiguous(),
                 f"{name}: {taps} contiguous int64 tap positions expected, got {tuple(t.shape)} {t.dtype}")


def _strides(t: torch.Tensor):
    return (ctypes.c_int64 * 4)(*t.stride())


@torch.library.custom_op("srd_bench::deform_columns", mutates_args=("cols",), device_types="cpu")
def deform_columns(image: torch.Tensor, offset: torch.Tensor, mask: Optional[torch.Tensor], cols: torch.Tensor,
                   row0: int, rows: int, tap_y: torch.Tensor, tap_x: torch.Tensor) -> None:
    """The deformable conv's im2col columns of output rows row0..row0+rows-1 into cols[:B*rows*W_out]
    (pixel-major, column k*C + c): image (B, H, W, C) contiguous (a channels-last image permuted);
    offset (B, 2K, H_out, W_out) and mask (B, K, H_out, W_out) or None, any strides; tap_y/tap_x the
    K taps' row/column offsets from the output pixel (int64). float32 or bfloat16, each its own."""
    _require_float("image", image, 4)
    _require_float("offset", offset, 4)
    _require_float("cols", cols, 2)
    b, in_h, in_w, c = image.shape
    _, two_taps, out_h, out_w = offset.shape
    taps = two_taps // 2
    _require(image.is_contiguous(), "image: (B, H, W, C) contiguous expected")
    _require(c <= 1024, f"image: at most 1024 channels, got {c}")
    _require(offset.shape[0] == b and two_taps % 2 == 0, f"offset: (B={b}, 2K, H_out, W_out) expected, got {tuple(offset.shape)}")
    if mask is not None:
        _require_float("mask", mask, 4)
        _require(mask.shape == (b, taps, out_h, out_w), f"mask: {(b, taps, out_h, out_w)} expected, got {tuple(mask.shape)}")
    _require_taps(tap_y, tap_x, taps)
    _require(0 <= row0 and rows >= 1 and row0 + rows <= out_h, f"rows {row0}..{row0 + rows - 1} outside 0..{out_h - 1}")
    _require(cols.is_contiguous() and cols.shape[0] >= b * rows * out_w and cols.shape[1] == taps * c,
             f"cols: contiguous (>= {b * rows * out_w}, {taps * c}) expected, got {tuple(cols.shape)}")
    status = _kernels().deform_columns(
        image.data_ptr(), DTYPE_CODES[image.dtype], c, b, in_h, in_w,
        offset.data_ptr(), DTYPE_CODES[offset.dtype], _strides(offset),
        None if mask is None else mask.data_ptr(), 0 if mask is None else DTYPE_CODES[mask.dtype],
        None if mask is None else _strides(mask), cols.data_ptr(), DTYPE_CODES[cols.dtype], row0, rows, out_w,
        taps, tap_y.data_ptr(), tap_x.data_ptr(), torch.get_num_threads())
    _require(status == 0, f"deform_columns failed ({status}) for {c} channels at {in_h}x{in_w}")


@torch.library.custom_op("srd_bench::deform_columns_backward", mutates_args=("grad_image", "grad_offset", "grad_mask"),
                         device_types="cpu")
def deform_columns_backward(image: torch.Tensor, offset: torch.Tensor, mask: Optional[torch.Tensor],
                            grad_cols: torch.Tensor, tap_y: torch.Tensor, tap_x: torch.Tensor,
                            grad_image: torch.Tensor, grad_offset: torch.Tensor,
                            grad_mask: Optional[torch.Tensor]) -> None:
    """The gradients of deform_columns over all H_out rows, float32, everything contiguous: grad_image
    (like image, zeroed by the caller) is accumulated, grad_offset and grad_mask (like offset and mask)
    written, from grad_cols (B*H_out*W_out, K*C)."""
    b, in_h, in_w, c = image.shape
    _, two_taps, out_h, out_w = offset.shape
    taps = two_taps // 2
    pairs = [("image", image, grad_image), ("offset", offset, grad_offset), ("mask", mask, grad_mask)]
    for name, t, grad in pairs:
        _require((t is None) == (grad is None), f"{name} and its gradient: both or neither")
        for label, u in ((name, t), (f"grad_{name}", grad)) if t is not None else ():
            _require(u.dtype == torch.float32 and u.is_contiguous() and u.shape == t.shape,
                     f"{label}: contiguous float32 of shape {tuple(t.shape)} expected, got {tuple(u.shape)} {u.dtype}")
    _require(image.dim() == 4 and offset.dim() == 4 and offset.shape[0] == b and two_taps % 2 == 0,
             f"image (B, H, W, C) and offset (B, 2K, H_out, W_out) expected, got {tuple(image.shape)}, {tuple(offset.shape)}")
    _require(mask is None or mask.shape == (b, taps, out_h, out_w), f"mask: {(b, taps, out_h, out_w)} expected")
    _require(c <= 1024, f"image: at most 1024 channels, got {c}")
    _require(grad_cols.dtype == torch.float32 and grad_cols.is_contiguous()
             and grad_cols.shape == (b * out_h * out_w, taps * c),
             f"grad_cols: contiguous float32 {(b * out_h * out_w, taps * c)} expected, got {tuple(grad_cols.shape)}")
    _require_taps(tap_y, tap_x, taps)
    status = _kernels().deform_columns_backward(
        image.data_ptr(), c, b, in_h, in_w, offset.data_ptr(), None if mask is None else mask.data_ptr(),
        grad_cols.data_ptr(), out_h, out_w, taps, tap_y.data_ptr(), tap_x.data_ptr(), grad_image.data_ptr(),
        grad_offset.data_ptr(), None if grad_mask is None else grad_mask.data_ptr(), torch.get_num_threads())
    _require(status == 0, f"deform_columns_backward failed ({status}) for {c} channels")


CFM_CHANNELS = (16, 32, 64)  # the widths cfm_affine is compiled for


@torch.library.custom_op("srd_bench::cfm_affine", mutates_args=("out",), device_types="cpu")
def cfm_affine(x: torch.Tensor, cond: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor, relu: bool,
               out: torch.Tensor) -> None:
    """out = x * (1 + gamma) + beta (then ReLU when relu), gamma|beta = bias + cond . weight per pixel:
    x, cond and out channels-last (B, C, H, W) / (B, G, H, W) of one dtype (float32 or bfloat16), C in
    CFM_CHANNELS; weight (G, 2C) and bias (2C,) float32 contiguous, gamma's columns then beta's."""
    _require_float("x", x, 4)
    b, c, h, w = x.shape
    g = cond.shape[1] if cond.dim() == 4 else -1
    _require(c in CFM_CHANNELS, f"x: {CFM_CHANNELS} channels expected, got {c}")
    for name, t, shape in (("x", x, (b, c, h, w)), ("cond", cond, (b, g, h, w)), ("out", out, (b, c, h, w))):
        _require(t.dtype == x.dtype and t.shape == shape and t.is_contiguous(memory_format=torch.channels_last),
                 f"{name}: channels-last {x.dtype} {shape} expected, got {tuple(t.shape)} {t.dtype}")
    _require(weight.dtype == torch.float32 and weight.is_contiguous() and weight.shape == (g, 2 * c),
             f"weight: contiguous float32 {(g, 2 * c)} expected, got {tuple(weight.shape)}")
    _require(bias.dtype == torch.float32 and bias.is_contiguous() and bias.shape == (2 * c,),
             f"bias: contiguous float32 ({2 * c},) expected, got {tuple(bias.shape)}")
    status = _kernels().cfm_affine(x.data_ptr(), cond.data_ptr(), DTYPE_CODES[x.dtype], b * h * w, c, g,
                                   weight.data_ptr(), bias.data_ptr(), int(relu), out.data_ptr(),
                                   torch.get_num_threads())
    _require(status == 0, f"cfm_affine failed ({status}) for {c} channels")


# ---- on meta tensors (shape-only runs: MAC counting) and under torch.compile's fake tensors --------
# the ops do nothing. A mutating op that returns None gets a do-nothing fake kernel by default, and the
# dispatcher sends a call that mixes CPU and meta tensors there too; these refuse the mix, as aten ops
# do (fake tensors under torch.compile report the device they stand for, so one device is the test).

def _one_device(op: str, *tensors: Optional[torch.Tensor]) -> None:
    devices = {t.device.type for t in tensors if t is not None}
    _require(len(devices) == 1, f"{op}: tensors on one device expected, got {sorted(devices)}")


@deform_columns.register_fake
def _(image, offset, mask, cols, row0, rows, tap_y, tap_x):
    _one_device("deform_columns", image, offset, mask, cols)


@deform_columns_backward.register_fake
def _(image, offset, mask, grad_cols, tap_y, tap_x, grad_image, grad_offset, grad_mask):
    _one_device("deform_columns_backward", image, offset, mask, grad_cols, grad_image, grad_offset, grad_mask)


@cfm_affine.register_fake
def _(x, cond, weight, bias, relu, out):
    _one_device("cfm_affine", x, cond, weight, bias, out)
