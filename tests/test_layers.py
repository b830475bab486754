"""Tests for bench.nn: deformable conv, CFM, residual blocks, pixel shuffle, VGG16 features."""
import contextlib
import inspect
import itertools
import os
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from bench.nn import (CFM, ConditionNet, DeformConv2d, PixelShuffleUp, ResBlock, VGG16Features, conv3x3,
                      deform_conv2d, load_vgg16_features, random_vgg16_features)
from bench.nn.vgg import LAYER_NAMES
from conftest import VGG16_WEIGHTS_DIR

torch.set_num_threads(1)


# ---- deformable convolution ---------------------------------------------------------------------

def brute_force_deform(x, offset, weight, bias, padding, dilation, mask=None):
    """Per-pixel, per-tap numpy reference with explicit bilinear interpolation (zero outside)."""
    x, offset, weight = x.numpy(), offset.numpy(), weight.numpy()
    b, c, h, w = x.shape
    o, _, kh, kw = weight.shape
    out_h, out_w = offset.shape[-2:]
    out = np.zeros((b, o, out_h, out_w))

    def pixel(n, yy, xx):
        if 0 <= yy < h and 0 <= xx < w:
            return x[n, :, yy, xx]
        return np.zeros(c)

    for n, i, j in itertools.product(range(b), range(out_h), range(out_w)):
        for ki, kj in itertools.product(range(kh), range(kw)):
            k = ki * kw + kj
            py = i - padding + ki * dilation + offset[n, 2 * k, i, j]
            px = j - padding + kj * dilation + offset[n, 2 * k + 1, i, j]
            y0, x0 = int(np.floor(py)), int(np.floor(px))
            fy, fx = py - y0, px - x0
            v = ((1 - fy) * (1 - fx) * pixel(n, y0, x0) + (1 - fy) * fx * pixel(n, y0, x0 + 1)
                 + fy * (1 - fx) * pixel(n, y0 + 1, x0) + fy * fx * pixel(n, y0 + 1, x0 + 1))
            if mask is not None:
                v = v * mask[n, k, i, j].item()
            out[n, :, i, j] += weight[:, :, ki, kj] @ v
    if bias is not None:
        out += bias.numpy()[None, :, None, None]
    return torch.from_numpy(out)


@pytest.mark.parametrize("k,padding,dilation", [(3, 1, 1), (3, 2, 2), (3, 0, 1), (5, 2, 1), (3, 5, 5)])
def test_deform_zero_offsets_equal_conv2d(k, padding, dilation):
    g = torch.Generator().manual_seed(0)
    x = torch.randn(2, 3, 11, 9, generator=g, dtype=torch.float64)
    w = torch.randn(4, 3, k, k, generator=g, dtype=torch.float64)
    bias = torch.randn(4, generator=g, dtype=torch.float64)
    ref = F.conv2d(x, w, bias, padding=padding, dilation=dilation)
    offset = torch.zeros(2, 2 * k * k, *ref.shape[-2:], dtype=torch.float64)
    out = deform_conv2d(x, offset, w, bias, padding=padding, dilation=dilation)
    torch.testing.assert_close(out, ref, atol=1e-12, rtol=0)


@pytest.mark.parametrize("dilation,modulated", [(1, False), (2, False), (1, True)])
def test_deform_matches_brute_force_reference(dilation, modulated):
    g = torch.Generator().manual_seed(1)
    x = torch.randn(2, 3, 6, 5, generator=g, dtype=torch.float64)
    w = torch.randn(2, 3, 3, 3, generator=g, dtype=torch.float64)
    bias = torch.randn(2, generator=g, dtype=torch.float64)
    # fractional offsets up to +-3 px: many taps fall partly or wholly outside the 6x5 image
    offset = (torch.rand(2, 18, 6, 5, generator=g, dtype=torch.float64) - 0.5) * 6
    mask = torch.rand(2, 9, 6, 5, generator=g, dtype=torch.float64) if modulated else None
    out = deform_conv2d(x, offset, w, bias, padding=dilation, dilation=dilation, mask=mask)
    ref = brute_force_deform(x, offset, w, bias, dilation, dilation, mask)
    torch.testing.assert_close(out, ref, atol=1e-10, rtol=0)


def test_deform_strips_cover_all_rows(monkeypatch):
    """Force one-row strips in both samplers; the result must not change. Offsets of up to +-5 rows make
    each gather strip's table span rows far outside the strip (and batch items differ)."""
    import bench.nn.deform as deform
    g = torch.Generator().manual_seed(2)
    x = torch.randn(2, 2, 7, 5, generator=g, dtype=torch.float64)
    w = torch.randn(3, 2, 3, 3, generator=g, dtype=torch.float64)
    offset = torch.randn(2, 18, 7, 5, generator=g, dtype=torch.float64) * 2.5
    whole = deform_conv2d(x, offset, w)
    torch.testing.assert_close(whole, brute_force_deform(x, offset, w, None, 1, 1, None), atol=1e-10, rtol=0)
    monkeypatch.setattr(deform, "_STRIP_VALUES", 1)
    monkeypatch.setattr(deform, "_GATHER_INDICES", 1)
    torch.testing.assert_close(deform_conv2d(x, offset, w), whole, atol=1e-14, rtol=0)
    with torch.enable_grad():
        torch.testing.assert_close(deform_conv2d(x, offset, w.requires_grad_()).detach(), whole, atol=1e-12, rtol=0)


def test_deform_gradcheck():
    g = torch.Generator().manual_seed(3)
    x = torch.randn(1, 2, 4, 4, generator=g, dtype=torch.float64, requires_grad=True)
    w = torch.randn(2, 2, 3, 3, generator=g, dtype=torch.float64, requires_grad=True)
    bias = torch.randn(2, generator=g, dtype=torch.float64, requires_grad=True)
    # keep positions away from integers, where bilinear interpolation has a kink
    offset = (0.2 + 0.6 * torch.rand(1, 18, 4, 4, generator=g, dtype=torch.float64)).requires_grad_()
    mask = torch.rand(1, 9, 4, 4, generator=g, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda *a: deform_conv2d(a[0], a[1], a[2], a[3], 1, 1, a[4]),
                                    (x, offset, w, bias, mask))


@pytest.mark.parametrize("dy,dx", [(0.0, 1.0), (1.0, 0.0), (-1.0, 0.0)])
def test_deform_offset_layout_is_dy_dx(dy, dx):
    """A constant integer offset (dy, dx) on every tap reads x[i - 1 + ki + dy, j - 1 + kj + dx]: a plain
    conv over a wider zero padding, read out at a window shifted by (dy, dx)."""
    layer = DeformConv2d(2, 3).double()
    layer.offset_conv.bias.data = torch.tensor([dy, dx] * 9, dtype=torch.float64)
    x = torch.randn(1, 2, 6, 7, dtype=torch.float64)
    wide = F.conv2d(x, layer.weight, layer.bias, padding=2)  # wide[m] reads x[m - 2 + k]
    sy, sx = 1 + int(dy), 1 + int(dx)
    ref = wide[..., sy:sy + 6, sx:sx + 7]
    torch.testing.assert_close(layer(x), ref, atol=1e-12, rtol=0)


def test_deform_module_starts_as_plain_conv_and_learns_offsets():
    for modulated in (False, True):
        layer = DeformConv2d(4, 5, modulated=modulated)
        x = torch.randn(2, 4, 8, 6)
        torch.testing.assert_close(layer(x), F.conv2d(x, layer.weight, layer.bias, padding=1),
                                   atol=1e-5, rtol=1e-5)
        layer(x).square().sum().backward()
        assert layer.offset_conv.weight.grad.abs().sum() > 0
        if modulated:
            assert layer.mask_conv.weight.grad.abs().sum() > 0


def test_deform_rejects_non_same_padding():
    with pytest.raises(ValueError, match="same-size convs only"):
        DeformConv2d(2, 2, kernel_size=3, padding=0)



@pytest.mark.parametrize("dilation,modulated", [(1, False), (2, True)])
def test_deform_inference_and_training_samplers_agree(dilation, modulated):
    """Without autograd (float64: the eager gather sampler) and with it (grid_sample), see
    bench/nn/deform.py: the two must agree, with offsets reaching far outside the image."""
    g = torch.Generator().manual_seed(4)
    x = torch.randn(2, 3, 9, 11, generator=g, dtype=torch.float64)
    w = torch.randn(4, 3, 3, 3, generator=g, dtype=torch.float64)
    bias = torch.randn(4, generator=g, dtype=torch.float64)
    offset = (torch.rand(2, 18, 9, 11, generator=g, dtype=torch.float64) - 0.5) * 30
    mask = torch.rand(2, 9, 9, 11, generator=g, dtype=torch.float64) if modulated else None
    with torch.no_grad():
        inference = deform_conv2d(x, offset, w, bias, dilation, dilation, mask)
    training = deform_conv2d(x, offset, w.clone().requires_grad_(), bias, dilation, dilation, mask)
    torch.testing.assert_close(inference, training.detach(), atol=1e-12, rtol=0)


def test_deform_channels_last_input_gives_channels_last_output():
    layer = DeformConv2d(5, 6)
    torch.nn.init.normal_(layer.offset_conv.weight, std=0.3)
    x = torch.randn(2, 5, 7, 9)
    with torch.no_grad():
        plain, nhwc = layer(x), layer(x.contiguous(memory_format=torch.channels_last))
    assert nhwc.is_contiguous(memory_format=torch.channels_last)
    torch.testing.assert_close(nhwc, plain, atol=1e-5, rtol=1e-5)


def test_deform_bf16_autocast_keeps_positions_in_float32():
    """Under autocast the offsets are bfloat16, which cannot represent x = 299.25 (its spacing there is
    2): sampling positions must still be computed in float32, or columns shift by a pixel."""
    layer = DeformConv2d(4, 4)
    torch.nn.init.zeros_(layer.offset_conv.weight)
    torch.nn.init.constant_(layer.offset_conv.bias, 0.25)
    x = torch.randn(1, 4, 3, 300)
    with torch.no_grad():
        ref = layer(x)
        with torch.autocast("cpu", dtype=torch.bfloat16):
            low = layer(x).float()
    assert float((low - ref).abs().max()) < 0.05 * float(ref.abs().max())


def test_deform_propagates_nan_offsets_to_their_pixel_only():
    x, w = torch.randn(1, 2, 6, 6), torch.randn(3, 2, 3, 3)
    offset = torch.zeros(1, 18, 6, 6)
    offset[0, 4, 2, 3] = float("nan")
    with torch.no_grad():
        out = deform_conv2d(x, offset, w)
    assert torch.isnan(out[0, :, 2, 3]).all() and torch.isnan(out).sum() == 3



@pytest.mark.parametrize("grad", [False, True])
def test_deform_on_an_empty_input_does_what_conv2d_does(grad):
    """An empty batch gives the empty output nn.Conv2d gives, with and without autograd (gradients flow,
    as zeros); no rows or columns raise conv2d's own error (not the samplers' internals)."""
    w = torch.randn(3, 4, 3, 3, requires_grad=grad)
    x = torch.randn(0, 4, 6, 5, requires_grad=grad)
    with torch.set_grad_enabled(grad):
        out = deform_conv2d(x, torch.zeros(0, 18, 6, 5), w)
    assert out.shape == (0, 3, 6, 5)
    if grad:
        out.sum().backward()
        assert x.grad.shape == x.shape and w.grad.abs().sum() == 0
    for shape in ((1, 4, 0, 5), (1, 4, 6, 0)):
        x = torch.randn(*shape)
        with pytest.raises(RuntimeError) as conv_error:
            F.conv2d(x, w.detach(), padding=1)
        with torch.set_grad_enabled(grad), pytest.raises(RuntimeError) as deform_error:
            deform_conv2d(x.requires_grad_(grad), torch.zeros(1, 18, *shape[2:]), w)
        assert str(deform_error.value) == str(conv_error.value)
    # no input rows but output pixels (a 1x1 kernel over the padding alone): conv2d's error too
    x, w1 = torch.randn(1, 4, 0, 5), torch.randn(3, 4, 1, 1)
    with pytest.raises(RuntimeError) as conv_error:
        F.conv2d(x, w1, padding=1)
    with pytest.raises(RuntimeError) as deform_error:
        deform_conv2d(x, torch.zeros(1, 2, 2, 7), w1, padding=1)
    assert str(deform_error.value) == str(conv_error.value)


# ---- the compiled columns sampler (bench/nn/cpu_kernels.cpp, the CPU inference default) -------

def require_cpu_kernels():
    """Skips where the compiled kernels are switched off or no compiler exists (the eager code then
    runs, and the other tests cover it); fails where a compiler exists but the kernels did not build."""
    from bench.nn.native import kernels_available
    if not kernels_available():
        if os.environ.get("SRD_BENCH_NATIVE") == "0" or not (shutil.which("g++") or shutil.which("c++")):
            pytest.skip("the compiled kernels are off or there is no C++ compiler")
        pytest.fail("a C++ compiler is here, but bench/nn/cpu_kernels.cpp did not build")


def _runs_here(march: str) -> bool:
    """This CPU runs code built for `march` (x86-64 levels by their /proc/cpuinfo flags)."""
    from bench.machine import cpu_flags
    needs = {"x86-64": set(), "x86-64-v3": {"avx2", "fma", "bmi2", "movbe"},
             "x86-64-v4": {"avx512f", "avx512bw", "avx512cd", "avx512dq", "avx512vl"}}
    flags = cpu_flags()
    return march == "native" or (bool(flags) and "sse2" in flags and needs[march] <= flags)


# Every kernel test runs the kernels built for each x86-64 level this CPU runs: native, AVX-512
# (x86-64-v4: 16-float vectors), AVX2 (x86-64-v3: 8-float vectors, most laptops), SSE2 (x86-64).
KERNEL_TARGETS = ["native", "x86-64-v4", "x86-64-v3", "x86-64"]


@pytest.fixture(params=KERNEL_TARGETS)
def kernel_target(request):
    """The ops call the kernels built for this target (require_cpu_kernels); skipped where this CPU
    cannot run that target."""
    from bench.nn.native import built_for
    if not _runs_here(request.param):
        pytest.skip(f"this CPU does not run {request.param} code")
    with built_for(request.param):
        require_cpu_kernels()
        yield request.param


@pytest.fixture
def columns_only(monkeypatch, kernel_target):
    """The compiled kernels for each target (kernel_target), and a failure if anything falls back to
    the eager gather sampler."""
    import bench.nn.deform as deform

    def no_gather(*args, **kwargs):
        raise AssertionError("the eager gather sampler ran instead of the compiled one")
    monkeypatch.setattr(deform, "_deform_by_gather", no_gather)
    return deform


def test_the_kernel_ops_check_their_arguments():
    """The custom ops refuse what the kernels' raw pointers would misread: wrong dtypes, shapes,
    layouts, row ranges, a gradient without its tensor, CPU and meta tensors mixed. On meta tensors
    alone (shape-only MAC counting) they do nothing."""
    from bench.nn import native
    require_cpu_kernels()
    image, offset = torch.randn(1, 5, 6, 8), torch.zeros(1, 18, 5, 6)
    taps = torch.arange(9, dtype=torch.int64) % 3 - 1
    cols = torch.empty(30, 72)
    native.deform_columns(image, offset, None, cols, 0, 5, taps, taps)  # well-formed
    columns = lambda img=image, off=offset, mask=None, out=cols, r0=0, rows=5, ty=taps: \
        native.deform_columns(img, off, mask, out, r0, rows, ty, taps)
    nhwc = lambda t: t.contiguous(memory_format=torch.channels_last)
    bad_calls = {  # what: (the error it must give, the call)
        "cols too small": (r"cols: contiguous \(>= 30, 72\) expected", lambda: columns(out=cols[:20])),
        "rows past the end": (r"rows 3\.\.5 outside 0\.\.4", lambda: columns(r0=3, rows=3)),
        "float64 image": (r"image: a 4-D float32 or bfloat16 tensor", lambda: columns(img=image.double())),
        "strided image": (r"image: \(B, H, W, C\) contiguous", lambda: columns(img=image.transpose(1, 2))),
        "int32 taps": (r"tap_y: 9 contiguous int64", lambda: columns(ty=taps.int())),
        "mask of 8 taps": (r"mask: \(1, 9, 5, 6\) expected", lambda: columns(mask=torch.ones(1, 8, 5, 6))),
        "mask without its gradient": (r"mask and its gradient: both or neither", lambda: native.deform_columns_backward(
            image, offset, torch.ones(1, 9, 5, 6), torch.zeros(30, 72), taps, taps, torch.zeros_like(image),
            torch.zeros_like(offset), None)),
        "CFM at 35 channels": (r"x: \(16, 32, 64\) channels expected, got 35", lambda: native.cfm_affine(
            nhwc(torch.randn(1, 35, 4, 4)), nhwc(torch.randn(1, 8, 4, 4)), torch.zeros(8, 70), torch.zeros(70),
            False, nhwc(torch.empty(1, 35, 4, 4)))),
        "CFM on NCHW": (r"x: channels-last", lambda: native.cfm_affine(
            torch.randn(1, 16, 4, 4), torch.randn(1, 8, 4, 4), torch.zeros(8, 32), torch.zeros(32), False,
            torch.empty(1, 16, 4, 4))),
        # the dispatcher sends a CPU/meta mix to the meta (do-nothing) kernel: it must refuse, not skip
        "offsets on meta": (r"deform_columns: tensors on one device expected, got \['cpu', 'meta'\]",
                            lambda: columns(off=offset.to("meta"))),
        "CFM output on meta": (r"cfm_affine: tensors on one device expected", lambda: native.cfm_affine(
            nhwc(torch.randn(1, 16, 4, 4)), nhwc(torch.randn(1, 8, 4, 4)), torch.zeros(8, 32), torch.zeros(32),
            False, torch.empty(1, 16, 4, 4, device="meta"))),
        "gradient on meta": (r"deform_columns_backward: tensors on one device expected", lambda:
                             native.deform_columns_backward(image, offset, None, torch.zeros(30, 72), taps, taps,
                                                            torch.zeros_like(image), offset.to("meta"), None)),
    }
    for what, (message, call) in bad_calls.items():
        with pytest.raises(ValueError, match=message):
            call()
            pytest.fail(f"accepted: {what}")
    native.deform_columns(image.to("meta"), offset.to("meta"), None, cols[:1].to("meta"), 0, 5, taps, taps)


def test_the_kernel_ops_trace_under_torch_compile():
    """torch.compile runs the ops' fake kernels on fake tensors (which report the CPU, not meta): they
    must trace (the `compile` fast path of every model with deformable convs or CFMs), and give the
    eager result. backend="eager": tracing only, seconds."""
    from bench.nn import native
    require_cpu_kernels()
    nhwc = lambda t: t.contiguous(memory_format=torch.channels_last)
    taps = torch.arange(9, dtype=torch.int64) % 3 - 1

    def ops(image, offset, x, cond):
        cols = torch.empty(30, 72)
        native.deform_columns(image, offset, None, cols, 0, 5, taps, taps)
        out = torch.empty_like(x)
        native.cfm_affine(x, cond, torch.ones(8, 32), torch.zeros(32), True, out)
        return cols, out

    args = (torch.randn(1, 5, 6, 8), torch.randn(1, 18, 5, 6), nhwc(torch.randn(1, 16, 4, 4)),
            nhwc(torch.randn(1, 8, 4, 4)))
    torch._dynamo.reset()
    for compiled, eager in zip(torch.compile(ops, backend="eager", fullgraph=True)(*args), ops(*args)):
        torch.testing.assert_close(compiled, eager)


def test_the_avx512_bf16_branch_compiles():
    """The AVX512-BF16 code (bf16 rounding and pair interleave intrinsics) builds, even on a CPU that
    cannot run it; its results are checked by the tests above on a machine that has it. Built once per
    source, build command and compiler, kept where the kernels this CPU runs are (as bench.nn.native keeps
    those): g++ takes 6-9 s on 2 cores, and the same inputs build the same way."""
    import hashlib
    from bench.nn import native
    compiler = shutil.which("g++") or shutil.which("c++")
    if compiler is None or os.environ.get("SRD_BENCH_NATIVE") == "0":
        pytest.skip("no C++ compiler, or the compiled kernels are off")
    flags = (*native.FLAGS, "-march=sapphirerapids")
    version = subprocess.run([compiler, "--version"], capture_output=True, text=True).stdout
    how = inspect.getsource(native._compile)   # the command line it builds from the flags
    key = hashlib.sha256("\n".join([native.SOURCE.read_text(), how, *flags, compiler, version]).encode()).hexdigest()
    built = Path(os.environ.get("SRD_BENCH_CACHE", Path.home() / ".cache" / "srd-bench")) / f"spr-build-check-{key[:16]}.so"
    if not built.exists():                 # never loaded here: this CPU may not run it
        native._compile(compiler, flags, built)
    assert built.stat().st_size > 0


# channels 3: the scalar loop; 16: one vector per corner; 32, 64: bfloat16 pairs (see the .cpp)
@pytest.mark.parametrize("channels,dilation,modulated", [(3, 1, False), (16, 2, True), (32, 1, True), (64, 1, False)])
def test_columns_sampler_matches_brute_force(columns_only, monkeypatch, channels, dilation, modulated):
    g = torch.Generator().manual_seed(7)
    x = torch.randn(2, channels, 6, 7, generator=g)
    w = torch.randn(5, channels, 3, 3, generator=g) / channels ** 0.5
    bias = torch.randn(5, generator=g)
    # up to +-4 px: many corners outside the 6x7 image, on every side
    offset = (torch.rand(2, 18, 6, 7, generator=g) - 0.5) * 8
    mask = torch.rand(2, 9, 6, 7, generator=g) if modulated else None
    ref = brute_force_deform(x.double(), offset.double(), w.double(), bias.double(), dilation, dilation,
                             None if mask is None else mask.double()).float()
    with torch.no_grad():
        out = deform_conv2d(x, offset, w, bias, dilation, dilation, mask)
        torch.testing.assert_close(out, ref, atol=2e-5, rtol=1e-5)
        # channels-last input and offsets (as DeformConv2d gives them), one-row strips
        monkeypatch.setattr(columns_only, "_COLUMN_PIXELS", 1)
        nhwc = lambda t: t.contiguous(memory_format=torch.channels_last)
        out_cl = deform_conv2d(nhwc(x), nhwc(offset), w, bias, dilation, dilation, mask)
        assert out_cl.is_contiguous(memory_format=torch.channels_last)
        torch.testing.assert_close(out_cl, ref, atol=2e-5, rtol=1e-5)


@pytest.mark.parametrize("channels", [5, 16, 32, 64])
@pytest.mark.parametrize("input_dtype", [torch.float32, torch.bfloat16])
def test_columns_sampler_bf16_autocast(columns_only, channels, input_dtype):
    """Under bf16 autocast: float32 or bfloat16 features in, bfloat16 columns and output, within
    bfloat16 rounding of the float64 reference (a channel permuted in the bf16 pair path would not be)."""
    g = torch.Generator().manual_seed(8)
    x = torch.randn(1, channels, 9, 40, generator=g).to(input_dtype).contiguous(memory_format=torch.channels_last)
    w = torch.randn(6, channels, 3, 3, generator=g) / channels ** 0.5
    offset = (torch.rand(1, 18, 9, 40, generator=g) - 0.5) * 4
    ref = brute_force_deform(x.double(), offset.double(), w.double(), None, 1, 1)
    with torch.no_grad(), torch.autocast("cpu", dtype=torch.bfloat16):
        out = deform_conv2d(x, offset.to(input_dtype), w)
    assert out.dtype == torch.bfloat16
    offset_rounding = 0 if input_dtype == torch.float32 else 1  # bf16 offsets move positions too
    err = float((out.double() - ref).abs().max() / ref.abs().max())
    assert err < 0.02 + 0.03 * offset_rounding, err


def test_columns_sampler_extreme_offsets(columns_only):
    """Huge and infinite offsets clamp to the border and read zeros; NaN spoils its own pixel only."""
    x, w = torch.randn(1, 32, 6, 6), torch.randn(4, 32, 3, 3)
    offset = torch.zeros(1, 18, 6, 6)
    offset[0, 0, 1, 1], offset[0, 1, 2, 2], offset[0, 2, 3, 3] = 1e9, float("-inf"), float("inf")
    far = offset.clone()
    far[0, 0, 1, 1], far[0, 1, 2, 2], far[0, 2, 3, 3] = 100.0, -100.0, 100.0
    with torch.no_grad():
        torch.testing.assert_close(deform_conv2d(x, offset, w), deform_conv2d(x, far, w))
        torch.testing.assert_close(deform_conv2d(x, far, w), brute_force_deform(x.double(), far.double(),
                                   w.double(), None, 1, 1).float(), atol=1e-4, rtol=1e-5)
        offset[0, 7, 4, 5] = float("nan")
        out = deform_conv2d(x, offset, w)
    assert torch.isnan(out[0, :, 4, 5]).all() and torch.isnan(out).sum() == 4


def test_columns_and_gather_samplers_agree():
    """The compiled sampler and the eager gather (its fallback) give the same layer output."""
    from bench.nn import eager_gather, inference_sampler
    layer = DeformConv2d(32, 32, modulated=True)
    torch.nn.init.normal_(layer.offset_conv.weight, std=0.5)
    torch.nn.init.normal_(layer.mask_conv.weight, std=0.5)
    x = torch.randn(2, 32, 11, 13).contiguous(memory_format=torch.channels_last)
    if not (shutil.which("g++") or shutil.which("c++")) or os.environ.get("SRD_BENCH_NATIVE") == "0":
        pytest.skip("no compiled sampler here (no C++ compiler, or SRD_BENCH_NATIVE=0): nothing to compare")
    assert inference_sampler(x) == "columns"   # else this compared the gather sampler with itself
    with torch.no_grad():
        default = layer(x)
        with eager_gather():
            assert inference_sampler(x) == "gather"
            eager = layer(x)
    torch.testing.assert_close(default, eager, atol=1e-5, rtol=1e-5)


def test_columns_kernel_build_cache_and_fallback(monkeypatch, tmp_path):
    """Built once into SRD_BENCH_CACHE; off with SRD_BENCH_NATIVE=0; a failed build warns and returns
    None (the eager sampler then runs), and the layer still computes the same thing."""
    from bench.nn import native
    if not (shutil.which("g++") or shutil.which("c++")):
        pytest.skip("no C++ compiler")
    monkeypatch.setenv("SRD_BENCH_CACHE", str(tmp_path))
    try:
        native.cpu_kernels.cache_clear()
        assert native.cpu_kernels("native") is not None
        assert len(list(tmp_path.glob("cpu_kernels-*.so"))) == 1
        native.cpu_kernels.cache_clear()
        monkeypatch.setenv("SRD_BENCH_NATIVE", "0")
        assert native.cpu_kernels("native") is None
        native.cpu_kernels.cache_clear()
        monkeypatch.delenv("SRD_BENCH_NATIVE")
        monkeypatch.setenv("CXX", str(tmp_path / "no-such-compiler"))
        monkeypatch.setenv("SRD_BENCH_CACHE", str(tmp_path / "empty"))
        with pytest.warns(UserWarning, match="eager code"):
            assert native.cpu_kernels("native") is None
        x, w, offset = torch.randn(1, 4, 5, 5), torch.randn(3, 4, 3, 3), torch.rand(1, 18, 5, 5)
        with torch.no_grad():
            out = deform_conv2d(x, offset, w)
        torch.testing.assert_close(out, brute_force_deform(x.double(), offset.double(), w.double(), None, 1, 1).float(),
                                   atol=1e-5, rtol=1e-5)
    finally:
        native.cpu_kernels.cache_clear()

# ---- CFM, residual blocks, pixel shuffle ----------------------------------------------------------

def test_cfm_identity_at_init_and_formula():
    cfm = CFM(4, 3)
    x, cond = torch.randn(2, 4, 5, 5), torch.randn(2, 3, 5, 5)
    torch.testing.assert_close(cfm(x, cond), x)
    for p in cfm.parameters():
        torch.nn.init.normal_(p)
    gamma = torch.einsum("oc,bchw->bohw", cfm.gamma.weight[:, :, 0, 0], cond) + cfm.gamma.bias.view(1, -1, 1, 1)
    beta = torch.einsum("oc,bchw->bohw", cfm.beta.weight[:, :, 0, 0], cond) + cfm.beta.bias.view(1, -1, 1, 1)
    torch.testing.assert_close(cfm(x, cond), x * (1 + gamma) + beta, atol=1e-5, rtol=1e-5)


@pytest.mark.parametrize("channels", [16, 32, 64])
def test_cfm_fused_kernel_matches_formula(kernel_target, channels):
    """Channels-last inference on CPU takes the compiled CFM (+ ReLU): the formula to float rounding in
    float32, to bfloat16 rounding under autocast; NaN in x stays in its pixel, through the ReLU too."""
    from bench.nn import cfm as cfm_module
    g = torch.Generator().manual_seed(9)
    cfm = CFM(channels, 16)
    for p in cfm.parameters():
        torch.nn.init.normal_(p, std=0.3, generator=g)
    nhwc = lambda t: t.contiguous(memory_format=torch.channels_last)
    x, cond = nhwc(torch.randn(2, channels, 5, 7, generator=g)), nhwc(torch.randn(2, 16, 5, 7, generator=g))
    x[1, 3, 2, 4] = float("nan")
    gamma = torch.einsum("oc,bchw->bohw", cfm.gamma.weight[:, :, 0, 0], cond) + cfm.gamma.bias.view(1, -1, 1, 1)
    beta = torch.einsum("oc,bchw->bohw", cfm.beta.weight[:, :, 0, 0], cond) + cfm.beta.bias.view(1, -1, 1, 1)
    ref = (x * (1 + gamma) + beta).detach()
    with torch.no_grad():
        assert cfm_module._fused_kernel_applies(x, cond, cfm.gamma.weight)
        plain, relu = cfm(x, cond), cfm(x, cond, relu=True)
        with torch.autocast("cpu", dtype=torch.bfloat16):
            low = cfm(x.bfloat16(), cond.bfloat16(), relu=True)
    assert plain.is_contiguous(memory_format=torch.channels_last) and low.dtype == torch.bfloat16
    torch.testing.assert_close(plain, ref, atol=1e-5, rtol=1e-5, equal_nan=True)
    torch.testing.assert_close(relu, F.relu(ref), atol=1e-5, rtol=1e-5, equal_nan=True)
    assert torch.isnan(relu).sum() == 1 and torch.isnan(low).sum() == 1
    finite = ~torch.isnan(ref)
    assert float((low.float() - F.relu(ref))[finite].abs().max()) < 0.02 * float(ref[finite].abs().max())


def test_cfm_eager_where_the_kernel_does_not_apply():
    """Other widths (eager's blocked conv is faster there), contiguous inputs and autograd stay eager,
    and give the same function."""
    from bench.nn import cfm as cfm_module
    cfm = CFM(35, 8)
    for p in cfm.parameters():
        torch.nn.init.normal_(p, std=0.3)
    x, cond = torch.randn(1, 35, 4, 6), torch.randn(1, 8, 4, 6)
    nhwc = lambda t: t.contiguous(memory_format=torch.channels_last)
    assert not cfm_module._fused_kernel_applies(nhwc(x), nhwc(cond), cfm.gamma.weight)
    cfm32 = CFM(32, 8)
    x32 = torch.randn(1, 32, 4, 6)
    with torch.no_grad():
        assert not cfm_module._fused_kernel_applies(x32, cond, cfm32.gamma.weight)  # not channels-last
    assert not cfm_module._fused_kernel_applies(nhwc(x32), nhwc(cond), cfm32.gamma.weight)  # autograd on
    out = cfm32(nhwc(x32), nhwc(cond), relu=True)
    out.sum().backward()
    assert cfm32.gamma.weight.grad is not None
    with torch.no_grad():
        torch.testing.assert_close(cfm32(nhwc(x32), nhwc(cond), relu=True), out.detach(), atol=1e-5, rtol=1e-5)


def test_condition_net_shape():
    assert ConditionNet(7, 16, 8)(torch.randn(1, 7, 9, 5)).shape == (1, 16, 9, 5)


def test_conv3x3_keeps_size():
    for d in (1, 2, 3, 5):
        conv = conv3x3(3, 4, dilation=d, bias=False)
        assert conv.bias is None and conv(torch.randn(1, 3, 13, 7)).shape == (1, 4, 13, 7)


@pytest.mark.parametrize("dilation,with_cfm", [(1, False), (2, False), (3, True), (5, True)])
def test_resblock_matches_functional(dilation, with_cfm):
    block = ResBlock(4, dilation=dilation, cond_channels=3 if with_cfm else 0, res_scale=0.5)
    for p in block.parameters():
        torch.nn.init.normal_(p, std=0.2)
    x, cond = torch.randn(1, 4, 12, 11), torch.randn(1, 3, 12, 11)
    y = F.conv2d(x, block.conv1.weight, block.conv1.bias, padding=1)
    if with_cfm:
        y = block.cfm1(y, cond)
    y = F.conv2d(F.relu(y), block.conv2.weight, block.conv2.bias, padding=dilation, dilation=dilation)
    if with_cfm:
        y = block.cfm2(y, cond)
    torch.testing.assert_close(block(x, cond if with_cfm else None), x + 0.5 * y, atol=1e-5, rtol=1e-5)


def test_deformable_resblock_starts_like_plain_resblock():
    plain, deform = ResBlock(4, dilation=2, cond_channels=3), ResBlock(4, dilation=2, deformable=True,
                                                                       cond_channels=3)
    assert isinstance(deform.conv2, DeformConv2d)
    deform.conv2.weight.data.copy_(plain.conv2.weight)
    deform.conv2.bias.data.copy_(plain.conv2.bias)
    deform.conv1.load_state_dict(plain.conv1.state_dict())
    x, cond = torch.randn(1, 4, 9, 10), torch.randn(1, 3, 9, 10)
    torch.testing.assert_close(deform(x, cond), plain(x, cond), atol=1e-5, rtol=1e-5)


def test_pixel_shuffle_up_layout():
    up = PixelShuffleUp(3, 2, scale=2)
    x = torch.randn(1, 3, 4, 5)
    pre = up.conv(x)  # (1, 8, 4, 5): channel c*4 + a*2 + b goes to output (c, 2i+a, 2j+b)
    out = up(x)
    assert out.shape == (1, 2, 8, 10)
    for c, a, b in itertools.product(range(2), range(2), range(2)):
        torch.testing.assert_close(out[0, c, a::2, b::2], pre[0, c * 4 + a * 2 + b])


# ---- VGG16 features ------------------------------------------------------------------------------

def test_vgg_layer_indices_match_torchvision():
    # torchvision vgg16().features: relu1_2 = 3, relu2_2 = 8, relu3_3 = 15, relu4_3 = 22, relu5_3 = 29
    for name, index in [("relu1_2", 3), ("relu2_2", 8), ("relu3_3", 15), ("relu4_3", 22), ("relu5_3", 29)]:
        assert LAYER_NAMES.index(name) == index
    assert len(LAYER_NAMES) == 31
    assert VGG16Features("relu3_3")(torch.rand(1, 3, 16, 16)).shape == (1, 256, 4, 4)


def test_vgg_state_dict_round_trip(tmp_path):
    model = random_vgg16_features("relu2_2", seed=1)
    assert not any(p.requires_grad for p in model.parameters())
    x = torch.rand(2, 3, 12, 12)
    ref = model(x)
    stripped = {k[len("features."):]: v for k, v in model.state_dict().items()}
    full = dict(model.state_dict(), **{"classifier.0.weight": torch.zeros(1)})  # torchvision-style file
    for name, state in [("prefixed.pth", model.state_dict()), ("plain.pth", stripped), ("full.pth", full)]:
        torch.save(state, tmp_path / name)
        torch.testing.assert_close(load_vgg16_features(tmp_path / name, "relu2_2")(x), ref)
    with pytest.raises(ValueError, match="relu3_3"):
        load_vgg16_features(tmp_path / "plain.pth", "relu3_3")
    # fixed seed: reproducible; other seed: different
    torch.testing.assert_close(random_vgg16_features("relu2_2", seed=1)(x), ref)
    assert not torch.allclose(random_vgg16_features("relu2_2", seed=2)(x), ref)


def test_vgg_normalizes_and_passes_input_gradients():
    model = random_vgg16_features("conv1_1", seed=0)
    x = torch.rand(1, 3, 6, 6, requires_grad=True)
    mean = torch.tensor([0.485, 0.456, 0.406]).view(1, 3, 1, 1)
    std = torch.tensor([0.229, 0.224, 0.225]).view(1, 3, 1, 1)
    conv = model.features[0]
    torch.testing.assert_close(model(x), F.conv2d((x - mean) / std, conv.weight, conv.bias, padding=1))
    model.train()
    assert not model.training
    model(x).sum().backward()
    assert x.grad.abs().sum() > 0


@pytest.mark.parametrize("filename,layer,too_deep", [
    ("vgg16_imagenet_conv1_1-conv2_2.pth", "relu2_2", "relu3_3"),
    ("vgg16_voc_finetuned_conv1_1-conv3_3.pth", "relu3_3", "relu4_1"),
])
def test_vgg_loads_shared_partial_files(filename, layer, too_deep):
    path = VGG16_WEIGHTS_DIR / filename
    if not path.exists():
        pytest.skip(f"{path} not present (set SRD_VGG16_WEIGHTS_DIR to the directory holding it)")
    model = load_vgg16_features(path, layer)
    state = torch.load(path, map_location="cpu", weights_only=True)
    torch.testing.assert_close(model.features[0].weight, state["0.weight"])
    x = torch.rand(1, 3, 16, 16)
    assert torch.isfinite(model(x)).all() and model(x).abs().sum() > 0
    with pytest.raises(ValueError, match="lacks"):
        load_vgg16_features(path, too_deep)


def test_recurrent_block_takes_a_float32_zero_state_under_bf16_autocast():
    """The first frame's zero state is float32 (made from the input); under bf16 autocast the level's
    concat must stay bf16 (a float32 concat at full size cost 0.4 s per 1080p frame) and equal the
    result with a bf16 zero state."""
    from torch.utils._python_dispatch import TorchDispatchMode

    from bench.nn.blocks import RecurrentBlock

    class ConcatDtypes(TorchDispatchMode):
        def __init__(self):
            super().__init__()
            self.dtypes = []

        def __torch_dispatch__(self, func, types, args=(), kwargs=None):
            out = func(*args, **(kwargs or {}))
            if func is torch.ops.aten.cat.default:
                self.dtypes.append(out.dtype)
            return out

    block = RecurrentBlock(4, 8).eval()
    x = torch.randn(1, 4, 16, 16)
    with torch.no_grad(), torch.autocast("cpu", dtype=torch.bfloat16):
        with ConcatDtypes() as seen:
            out32 = block(x, torch.zeros(1, 8, 16, 16))
        out16 = block(x, torch.zeros(1, 8, 16, 16, dtype=torch.bfloat16))
    assert seen.dtypes == [torch.bfloat16]
    torch.testing.assert_close(out32, out16, atol=0, rtol=0)


@pytest.mark.parametrize("sampler", ["compiled", "grid_sample"])
def test_training_sampler_reads_zeros_for_huge_and_infinite_offsets(sampler):
    """Both differentiable paths (the compiled columns sampler where it builds, grid_sample) agree with
    inference on extreme offsets: zeros, not NaN, and finite gradients."""
    from bench.nn import grid_sample_training
    with contextlib.nullcontext() if sampler == "compiled" else grid_sample_training():
        _extreme_offsets_read_zeros()


def _extreme_offsets_read_zeros():
    torch.manual_seed(0)
    x, w = torch.randn(1, 8, 6, 6, requires_grad=True), torch.randn(4, 8, 3, 3)
    offset = torch.zeros(1, 18, 6, 6)
    offset[0, 0, 1, 1], offset[0, 1, 2, 2], offset[0, 2, 3, 3] = 1e9, float("-inf"), float("inf")
    far = offset.clone()
    far[0, 0, 1, 1], far[0, 1, 2, 2], far[0, 2, 3, 3] = 100.0, -100.0, 100.0
    offset.requires_grad_(True)
    out = deform_conv2d(x, offset, w)
    assert torch.isfinite(out).all()
    with torch.no_grad():
        torch.testing.assert_close(out.detach(), deform_conv2d(x, far, w))  # inference path, same result
    out.square().sum().backward()
    assert torch.isfinite(x.grad).all() and torch.isfinite(offset.grad).all()


@pytest.mark.parametrize("channels,modulated,dilation", [(16, False, 1), (32, True, 1), (64, False, 1), (5, True, 2)])
def test_compiled_training_sampler_matches_grid_sample_forward_and_gradients(columns_only, channels, modulated,
                                                                             dilation):
    """The compiled training path (columns forward + compiled backward) against grid_sample's autograd:
    output and the gradients of input, offsets, mask, weight and bias, with offsets reaching outside
    the image, clamped far outside and infinite."""
    from bench.nn import grid_sample_training
    torch.manual_seed(0)
    x = torch.randn(2, channels, 7, 9)
    offset = 3 * torch.randn(2, 18, 7, 9)
    offset[0, 0, 1, 1], offset[1, 3, 2, 2], offset[0, 5, 3, 3] = 1e9, float("-inf"), float("inf")
    mask = torch.rand(2, 9, 7, 9) * 2 if modulated else None
    w, bias = torch.randn(4, channels, 3, 3), torch.randn(4)
    grads = []
    for context in (contextlib.nullcontext, grid_sample_training):
        leaves = [t.clone().requires_grad_(True) if t is not None else None for t in (x, offset, mask, w, bias)]
        with context():
            out = deform_conv2d(leaves[0], leaves[1], leaves[3], leaves[4], dilation, dilation, leaves[2])
        (out * torch.linspace(-1, 1, out.numel()).view_as(out)).sum().backward()
        grads.append([out.detach()] + [t.grad for t in leaves if t is not None])
    for fast, reference in zip(*grads):
        assert torch.isfinite(fast).all()
        torch.testing.assert_close(fast, reference, atol=2e-4, rtol=1e-4)


def test_compiled_training_sampler_is_what_a_model_trains_with(columns_only, monkeypatch):
    """DeformConv2d in training on CPU float32 takes the compiled path (no grid_sample call)."""
    layer = DeformConv2d(16, 16)
    x = torch.randn(1, 16, 8, 8, requires_grad=True)
    calls, original = [], F.grid_sample
    monkeypatch.setattr(F, "grid_sample", lambda *a, **k: calls.append(1) or original(*a, **k))
    layer(x).sum().backward()
    assert not calls and x.grad is not None
