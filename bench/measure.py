"""Measurements of this machine: the one timing loop, whether bf16 is native here (bench.machine names
the CPU and its ISA), the fast path chosen by measurement (`fast_path=auto`), and the fused GPU kernels
taken where they were tested.

`choose_fast_path` times the candidate paths of bench.infer on the input a model will see and returns
the fastest whose output stays within `TOLERANCE` of fp32's. Candidates are the paths this device runs
natively: fp32 and channels_last everywhere, their bf16 variants only where bf16 is native (a CUDA GPU,
or a CPU with AVX512-BF16 or AMX-BF16), never where it is emulated (AVX2 only: several times slower than
fp32). Which path wins depends on the CPU, the model and its width (on one 2-core AVX2 machine
channels_last was 1.4x slower than fp32 at cpu widths and 2x faster at the paper's), so it is measured,
not assumed, and cached per machine, model, weights, input size, threads and torch version in a JSON
file: bf16's error depends on the weights (untrained ones can fail the tolerance that trained ones pass),
so a choice made with one set of weights is never reused for another.
"""
from __future__ import annotations

import contextlib
import hashlib
import json
import os
import statistics
import sys
import time
from pathlib import Path

import torch

from bench.atomic import write_atomic
from bench.evaluate import sync
from bench.infer import REFERENCE, max_abs_diff, prepare
from bench.machine import cpu_flags, cpu_isa, cpu_model
from bench.nn import fused
from bench.runs import acquire

TOLERANCE = 0.02       # max |fast - fp32| relative to fp32's output range: bf16 rounding passes, a bug does not
AUTO = "auto"


FUSED_GPU = "SRD_BENCH_FUSED_GPU"


def error_summary(err: BaseException, width: int | None = None) -> str:
    """An error in one line for a table's cell or a log: its type and the first line of its message (at
    most `width` characters of it)."""
    return f"{type(err).__name__}: {(str(err).splitlines() or [''])[0][:width]}"


@contextlib.contextmanager
def fused_kernels_on_cuda():
    """Inside, a command's CUDA calls take the fused Triton kernels (bench/nn/triton_kernels.py) for the
    deformable conv and CFM, unless SRD_BENCH_FUSED_GPU is 0 (or false, off): tests/test_cuda.py passed
    with them on an H200 (results/gpu/cuda_tests/; their speed: results/gpu/speed/). Only on GPUs of
    compute capability 8.0 or more (bf16 tensor-core dots; older ones keep the eager samplers). Entered
    by the entry points (python -m bench, srd-bench) for the whole command; the variable is set meanwhile,
    so the processes they spawn (DDP workers) take the kernels too."""
    off = os.environ.get(FUSED_GPU, "").strip().lower() in ("0", "false", "off")
    if off or not torch.cuda.is_available() or torch.cuda.get_device_capability() < (8, 0):
        yield
        return
    previous = os.environ.get(FUSED_GPU)
    os.environ[FUSED_GPU] = "1"
    try:
        with fused.on_cuda(True):
            yield
    finally:
        if previous is None:
            os.environ.pop(FUSED_GPU, None)
        else:
            os.environ[FUSED_GPU] = previous


def fused_kernels_used(device: str) -> str | None:
    """For a run's record: the digest of bench/nn/triton_kernels.py where a run on `device` takes the
    fused kernels (CUDA, switched on as SRD_BENCH_FUSED_GPU=1 or fused_kernels_on_cuda, Triton
    installed), else None (PyTorch's samplers). Not in any identity: the kernels match the samplers to
    tests/test_fused_gpu.py's tolerances, not bit for bit."""
    if torch.device(device).type != "cuda" or os.environ.get(FUSED_GPU) != "1" or fused.kernels() is None:
        return None
    return hashlib.sha256((Path(fused.__file__).parent / "triton_kernels.py").read_bytes()).hexdigest()[:16]


def time_call(fn, device: str, repeats: int = 5, warmup: int = 1) -> dict:
    """Median, min and max milliseconds of `repeats` calls of fn() after `warmup` untimed ones (the
    device synchronised around each), and the last call's result (to compare outputs without an extra
    call). The one timing loop of the suite's measurements."""
    result = None
    for _ in range(warmup):
        result = fn()
    sync(device)
    times = []
    for _ in range(max(1, repeats)):
        t0 = time.perf_counter()
        result = fn()
        sync(device)
        times.append(1000 * (time.perf_counter() - t0))
    return {"ms": statistics.median(times), "ms min": min(times), "ms max": max(times), "result": result}


def native_bf16(device: str, flags: set[str] | None = None) -> bool:
    if str(device).startswith("cuda"):
        return True
    flags = cpu_flags() if flags is None else flags
    return bool(flags & {"avx512_bf16", "amx_bf16"})


def candidate_paths(device: str, flags: set[str] | None = None) -> list[str]:
    """The paths worth timing on `device`: never bf16 where it is emulated."""
    paths = [REFERENCE, "channels_last"]
    return paths + ["bf16", "channels_last+bf16"] if native_bf16(device, flags) else paths


def choose_fast_path(model, x: torch.Tensor, g: torch.Tensor | None, device: str, cache: str | Path | None,
                     key: dict, repeats: int = 3) -> tuple[str, dict]:
    """(the fastest correct path for `model` on inputs like `x`, `g`; {path: ms or reason}). `key`
    names the model (its config) for the cache; the machine, input size, threads and torch version are
    added here. A model without parameters (bilinear, OIDN) runs its own way: fp32."""
    if not any(True for _ in model.parameters()):
        return REFERENCE, {}
    key = {**key, "weights": weights_digest(model),
           "cpu": cpu_model(), "isa": cpu_isa(), "device": str(device),
           "input": list(x.shape), "threads": torch.get_num_threads(), "torch": torch.__version__}
    if str(device).startswith("cuda"):  # the fused kernels or the eager samplers: other times, other errors
        key["fused"] = fused.applies(x, 0)
    text = json.dumps(key, sort_keys=True, default=str)
    cached = _read_cache(cache)
    if text in cached:
        return cached[text]["path"], cached[text]["ms"]
    reference = None
    times = {}
    for name in candidate_paths(device):
        try:
            run = prepare(model, name)
            timed = time_call(lambda: run(x, g), device, repeats=repeats, warmup=1)
        except Exception as err:  # a path this machine cannot run (no compiler, say) is not a candidate
            times[name] = f"failed: {error_summary(err, 120)}"
            continue
        out = timed["result"]["final"].float()
        if reference is None:
            reference = out
        scale = float(reference.abs().max()) or 1.0
        error = max_abs_diff(out, reference) / scale
        times[name] = timed["ms"] if error <= TOLERANCE else f"off by {error:.3g} of the output range (tolerance {TOLERANCE})"
    ran = [(ms, name) for name, ms in times.items() if isinstance(ms, float)]
    if not ran:
        raise RuntimeError(f"no fast path runs this model here: {times}")
    fastest = min(ran)[1]
    if cache is not None:
        try:
            Path(cache).parent.mkdir(parents=True, exist_ok=True)
            # read again under a lock: another process (jobs=N) may add its choice meanwhile; never half a file
            with contextlib.closing(acquire(Path(f"{cache}.lock"), "writing the fast-path cache")):
                cached = {**_read_cache(cache), text: {"path": fastest, "ms": times}}
                write_atomic(Path(cache), lambda tmp: tmp.write_text(json.dumps(cached, indent=1, sort_keys=True)))
        except OSError as err:  # e.g. an unwritable HOME: the choice stands, it is only not remembered
            print(f"note: the fast path chosen ({fastest}) is not remembered in {cache} ({err.strerror}): it is "
                  "measured again next time, unless a fixed fast path is given or that folder is writable",
                  file=sys.stderr)
    return fastest, times


def weights_digest(model) -> str:
    """A short hash of the model's parameters and buffers (names, dtypes, values)."""
    digest = hashlib.sha256()
    for name, t in model.state_dict().items():
        digest.update(f"{name}:{t.dtype}:{tuple(t.shape)}".encode())
        digest.update(t.detach().cpu().contiguous().view(torch.uint8).numpy().tobytes())
    return digest.hexdigest()[:16]


def _read_cache(cache: str | Path | None) -> dict:
    if cache is None or not Path(cache).exists():
        return {}
    try:
        return json.loads(Path(cache).read_text())
    except (OSError, ValueError):  # a damaged cache is measured again
        return {}
