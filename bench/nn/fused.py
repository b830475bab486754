"""Which calls take the fused Triton kernels (bench.nn.triton_kernels): the deformable conv and CFM.

On CUDA they are taken where SRD_BENCH_FUSED_GPU=1 or inside `on_cuda()`, which the entry points enter
by default (bench.measure.fused_kernels_on_cuda: tests/test_cuda.py passed with them on an H200,
results/gpu/cuda_tests/); `forced()` makes every call on any device take them (CPU tensors
need Triton's interpreter, TRITON_INTERPRET=1: the tests) or none. Triton ships with CUDA builds of
torch; the CPU wheel has none, and then nothing here applies.

The kernels' module is imported when they are switched on (at import with SRD_BENCH_FUSED_GPU=1, or on
entering forced()/on_cuda()), never inside a call: torch.compile cannot trace an import, and importing
Triton costs about a second that runs without the kernels never pay.
"""
import contextlib
import importlib
import os

import torch

_on_cuda = False
_forced = None    # True or False inside forced()
_module = None    # bench.nn.triton_kernels once loaded
_absent = False   # Triton is not installed


def _load() -> None:
    global _module, _absent
    if _module is None and not _absent:
        try:
            _module = importlib.import_module("bench.nn.triton_kernels")
        except ImportError:
            _absent = True


@contextlib.contextmanager
def forced(enabled: bool = True):
    """Inside, every deformable conv and CFM call takes the fused kernels (enabled), or none does."""
    global _forced
    if enabled:
        _load()
    previous, _forced = _forced, enabled
    try:
        yield
    finally:
        _forced = previous


@contextlib.contextmanager
def on_cuda(enabled: bool = True):
    """Inside, CUDA calls take the fused kernels (enabled) or not, as SRD_BENCH_FUSED_GPU says outside;
    CPU calls never do."""
    global _on_cuda
    if enabled:
        _load()
    previous, _on_cuda = _on_cuda, enabled
    try:
        yield
    finally:
        _on_cuda = previous


if os.environ.get("SRD_BENCH_FUSED_GPU", "0") == "1":
    _on_cuda = True
    _load()


def kernels():
    """bench.nn.triton_kernels where the kernels are switched on and Triton is installed, else None."""
    return _module


def available() -> bool:
    """Triton is installed here (imports the kernels' module: not for traced code)."""
    _load()
    return _module is not None


MAX_CHANNELS = 128  # the kernels keep a pixel's output (or CFM's conditioning) channels in registers


def applies(x: torch.Tensor, channels: int) -> bool:
    """The fused kernels take a call on x: asked for (forced(), or CUDA inside on_cuda() or with
    SRD_BENCH_FUSED_GPU=1),
    computing in float32/bfloat16 (not float16 autocast), at most MAX_CHANNELS `channels` (the call's
    widest), Triton installed."""
    wanted = _forced if _forced is not None else (_on_cuda and x.is_cuda)
    return (bool(wanted) and _module is not None and not x.is_meta
            and compute_dtype(x) in (torch.float32, torch.bfloat16) and channels <= MAX_CHANNELS)


def compute_dtype(x: torch.Tensor) -> torch.dtype:
    """The dtype a fused call computes in: autocast's where it is on (autocast does not see custom
    ops, so the caller casts), else x's."""
    device = x.device.type
    return torch.get_autocast_dtype(device) if torch.is_autocast_enabled(device) else x.dtype


def same_layout(out: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    """The kernels' channels-last output, kept so where x is channels-last, made contiguous elsewhere."""
    channels_last = not x.is_contiguous() and x.is_contiguous(memory_format=torch.channels_last)
    return out if channels_last else out.contiguous()
