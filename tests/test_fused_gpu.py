"""The fused Triton kernels (bench/nn/triton_kernels.py): the deformable conv, forward and every
gradient, and CFM, against float64 references, in float32 (TF32 off).

Without a GPU they run in Triton's interpreter (conftest sets TRITON_INTERPRET=1): the interpreter's
bf16 dot is wrong, and it runs one program at a time, so the input gradient's atomic scatter cannot
race here; with a GPU the same tests run compiled on it, and tests/test_cuda.py adds bf16, sizes with
thousands of programs, and repeatability.
Tolerances, relative to the reference's largest magnitude: forward and gradients 1e-5 against float64
(float32 sums of up to K*C terms; measured 1e-7 to 1e-6); finite differences 2e-3 (central differences
of float32 outputs, step 1e-3).
"""
from pathlib import Path

import pytest
import torch
import torch.nn.functional as F

from bench.nn import CFM, DeformConv2d, deform_conv2d, fused, inference_sampler, triton_kernels
from bench.nn.triton_kernels import cfm_fused, deform_conv_fused, deform_conv_fused_backward
from test_layers import brute_force_deform

DEVICE = "cuda" if torch.cuda.is_available() else "cpu"   # cpu: Triton's interpreter


@pytest.fixture(autouse=True)
def exact_fp32():
    """fp32 means IEEE fp32 (the kernels follow cuDNN's TF32 flag, as convs do)."""
    saved = torch.backends.cudnn.allow_tf32
    torch.backends.cudnn.allow_tf32 = False
    yield
    torch.backends.cudnn.allow_tf32 = saved

# (batch, channels, height, width, out channels, kernel, padding, dilation): odd sizes, a batch of
# several frames, more channels than one block (70 > 64) and more outputs than one forward block (72)
SHAPES = [(3, 5, 7, 9, 6, 3, 1, 1), (2, 16, 9, 7, 16, 3, 2, 2), (1, 70, 5, 6, 72, 3, 1, 1), (2, 4, 6, 5, 3, 1, 0, 1)]


def _inputs(shape, seed=0, offset_scale=3.0):
    b, c, h, w, o, k, pad, dil = shape
    gen = torch.Generator().manual_seed(seed)
    out_h, out_w = h + 2 * pad - dil * (k - 1), w + 2 * pad - dil * (k - 1)
    tensors = dict(x=torch.randn(b, c, h, w, generator=gen),
                   offset=offset_scale * torch.randn(b, 2 * k * k, out_h, out_w, generator=gen),
                   weight=torch.randn(o, c, k, k, generator=gen), bias=torch.randn(o, generator=gen),
                   mask=torch.rand(b, k * k, out_h, out_w, generator=gen))
    return {name: t.to(DEVICE) for name, t in tensors.items()}


def _relative(got, want):
    got, want = got.double().cpu(), want.double().cpu()
    return ((got - want).abs().max() / want.abs().max().clamp_min(1e-30)).item()


def _brute_force(t, pad, dil, mask=None, offset=None):
    """The per-pixel numpy reference (tests/test_layers.py) of inputs t, on the CPU in float64."""
    return brute_force_deform(*(v.double().cpu() for v in (t["x"], t["offset"] if offset is None else offset,
                                                           t["weight"], t["bias"])), pad, dil,
                              None if mask is None else mask.double().cpu())


def _gradients(fn, tensors, grad_out):
    """fn(**tensors)'s output and the gradient of <output, grad_out> for every tensor."""
    leaves = {k: v.clone().requires_grad_() for k, v in tensors.items()}
    out = fn(**leaves)
    out.backward(grad_out.to(out.dtype))
    return out.detach(), {k: v.grad for k, v in leaves.items()}


@pytest.mark.parametrize("shape,modulated", [(shape, i % 2 == 1) for i, shape in enumerate(SHAPES)],
                         ids=lambda v: "x".join(map(str, v)) if isinstance(v, tuple) else ("mask" if v else "no_mask"))
def test_fused_deform_matches_the_float64_reference(shape, modulated):
    """Forward against the per-pixel numpy reference; every gradient (input, offsets, mask, weight,
    bias) against autograd of the float64 sampler (itself checked against that reference and by
    gradcheck in tests/test_layers.py)."""
    pad, dil = shape[-2:]
    t = _inputs(shape)
    if not modulated:
        t.pop("mask")
    mask = t.get("mask")
    out = deform_conv_fused(t["x"], t["offset"], mask, t["weight"], t["bias"], pad, dil)
    assert out.dtype == torch.float32 and out.is_contiguous(memory_format=torch.channels_last)
    ref = _brute_force(t, pad, dil, mask)
    assert _relative(out, ref) < 1e-5

    grad_out = torch.randn(ref.shape, generator=torch.Generator().manual_seed(1), dtype=torch.float64).to(DEVICE)
    _, grads = _gradients(lambda **a: deform_conv_fused(a["x"], a["offset"], a.get("mask"), a["weight"], a["bias"],
                                                        pad, dil), t, grad_out)
    _, ref_grads = _gradients(lambda **a: deform_conv2d(a["x"], a["offset"], a["weight"], a["bias"], pad, dil,
                                                        a.get("mask")),
                              {k: v.double() for k, v in t.items()}, grad_out)
    for name, want in ref_grads.items():
        assert _relative(grads[name], want) < 1e-5, name


def test_fused_deform_gradients_match_finite_differences():
    """<grad, v> against (f(t + h v) - f(t - h v)) / 2h for a random direction v of each input, with the
    samples away from pixel boundaries (bilinear sampling is only piecewise smooth)."""
    shape = (2, 6, 7, 8, 5, 3, 1, 1)
    t = _inputs(shape, seed=3)
    fraction = torch.rand(t["offset"].shape, generator=torch.Generator().manual_seed(4)).to(DEVICE)
    t["offset"] = t["offset"].round() + 0.2 + 0.6 * fraction
    grad_out = torch.randn(2, 5, 7, 8, generator=torch.Generator().manual_seed(5)).to(DEVICE)

    def f(**a):
        return deform_conv_fused(a["x"], a["offset"], a["mask"], a["weight"], a["bias"], 1, 1)

    _, grads = _gradients(f, t, grad_out)
    h = 1e-3
    for name, value in t.items():
        v = torch.randn(value.shape, generator=torch.Generator().manual_seed(6)).to(DEVICE)
        plus, minus = f(**{**t, name: value + h * v}), f(**{**t, name: value - h * v})
        numeric = ((plus - minus) * grad_out).sum().item() / (2 * h)
        analytic = (grads[name] * v).sum().item()
        assert abs(numeric - analytic) <= 2e-3 * max(abs(analytic), 1.0), (name, numeric, analytic)


def test_fused_deform_extreme_and_infinite_offsets_read_zero_with_zero_offset_gradient():
    shape = (2, 4, 5, 6, 3, 3, 1, 1)
    t = _inputs(shape, seed=7)
    far = t["offset"].clone()
    far[0, 0::2, 1:3] = float("inf")     # some pixels' taps off every edge: +-inf, +-1e30, +-1e4
    far[0, 1::2, 3:] = -float("inf")
    far[1, :, :2] = 1e30                 # (rows of batch 1)
    far[1, :, 2:4] = -1e4
    out, grads = _gradients(lambda **a: deform_conv_fused(a["x"], a["offset"], a["mask"], a["weight"], a["bias"], 1, 1),
                            {**t, "offset": far}, torch.ones(2, 3, 5, 6, device=DEVICE))
    assert torch.isfinite(out).all()
    ref = _brute_force(t, 1, 1, t["mask"], offset=far.clamp(-1e6, 1e6))
    assert _relative(out, ref) < 1e-5
    # a sample outside [-1, H] x [-1, W] is constant zero: no gradient reaches its offset
    assert (grads["offset"][0, 0::2, 1:3] == 0).all() and (grads["offset"][0, 1::2, 3:] == 0).all()
    assert (grads["offset"][1, :, :4] == 0).all()
    assert torch.isfinite(grads["x"]).all() and torch.isfinite(grads["weight"]).all()
    # every tap of batch 1's first four rows reads zero: those outputs are the bias alone
    torch.testing.assert_close(out[1, :, :4], t["bias"].view(3, 1, 1).expand(3, 4, 6))


def test_fused_deform_propagates_a_nan_offset_to_its_pixel_only():
    t = _inputs((1, 3, 5, 5, 2, 3, 1, 1), seed=8)
    t["offset"][0, 4, 2, 3] = float("nan")
    out = deform_conv_fused(t["x"], t["offset"], None, t["weight"], t["bias"], 1, 1)
    assert torch.isnan(out[0, :, 2, 3]).all()
    out[0, :, 2, 3] = 0
    assert torch.isfinite(out).all()


def test_deform_conv2d_and_the_layer_take_the_fused_kernels_when_asked():
    """deform_conv2d under fused.forced() takes the kernels (the sampler says so) and keeps its
    contract: NCHW in, NCHW out; channels-last in, channels-last out; zero offsets = conv2d."""
    torch.manual_seed(0)
    layer = DeformConv2d(6, 5, modulated=True).to(DEVICE)
    torch.nn.init.normal_(layer.offset_conv.weight, std=0.5)
    x = torch.randn(2, 6, 9, 7, device=DEVICE)
    with fused.forced(False):
        default = layer(x)
    with fused.forced():
        assert inference_sampler(x, layer.weight) == "fused"
        with torch.autocast(DEVICE, dtype=torch.float16):  # float16 autocast: not the kernels' dtypes
            assert inference_sampler(x, layer.weight) != "fused"
        out = layer(x)
        out_cl = layer(x.contiguous(memory_format=torch.channels_last))
        zero = deform_conv2d(x, torch.zeros(2, 18, 9, 7, device=DEVICE), layer.weight, layer.bias)
    assert out.is_contiguous() and out_cl.is_contiguous(memory_format=torch.channels_last)
    torch.testing.assert_close(out, default, rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(out_cl, default, rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(zero, F.conv2d(x, layer.weight, layer.bias, padding=1), rtol=1e-5, atol=1e-5)
    with fused.forced(False):
        assert inference_sampler(x, layer.weight) != "fused"


def test_the_fused_ops_pass_torch_library_opcheck():
    """Schema, fake kernels (shapes AND strides, as torch.compile's Inductor checks them), autograd
    registration of each op, the backward op included, with contiguous and channels-last offsets and mask
    (a DeformConv2d on a channels-last input makes them channels-last)."""
    checks = ("test_schema", "test_faketensor", "test_autograd_registration")
    t = _inputs((1, 3, 4, 5, 2, 3, 1, 1), seed=9)
    channels_last = {k: t[k].contiguous(memory_format=torch.channels_last) for k in ("offset", "mask")}
    for offset, mask in ((t["offset"], None), (t["offset"], t["mask"]), (channels_last["offset"], channels_last["mask"])):
        args = (t["x"].requires_grad_(), offset.requires_grad_(), mask, t["weight"].requires_grad_(), t["bias"], 1, 1)
        torch.library.opcheck(deform_conv_fused, args, test_utils=checks)
        for need_input_grad in (True, False):
            torch.library.opcheck(deform_conv_fused_backward, (torch.randn(1, 2, 4, 5, device=DEVICE), t["x"], offset,
                                                               mask, t["weight"], 1, 1, need_input_grad),
                                  test_utils=("test_schema", "test_faketensor"))
    x, cond = torch.randn(1, 4, 3, 5, device=DEVICE), torch.randn(1, 3, 3, 5, device=DEVICE)
    torch.library.opcheck(cfm_fused, (x, cond, torch.randn(8, 3, 1, 1, device=DEVICE), torch.randn(8, device=DEVICE),
                                      True), test_utils=checks)


@pytest.mark.parametrize("relu", [False, True])
@pytest.mark.parametrize("channels,cond_channels", [(16, 16), (5, 7), (32, 70)])
def test_fused_cfm_matches_the_module_forward_and_gradients(channels, cond_channels, relu):
    """CFM under fused.forced() against the eager module in float64, forward and every gradient."""
    torch.manual_seed(1)
    module = CFM(channels, cond_channels).to(DEVICE)
    for p in module.parameters():
        torch.nn.init.normal_(p, std=0.3)
    # channels-last: the layout the fused CFM takes (bench.nn.cfm)
    x, cond = (torch.randn(2, c, 5, 7, device=DEVICE).to(memory_format=torch.channels_last)
               for c in (channels, cond_channels))
    grad_out = torch.randn(2, channels, 5, 7, dtype=torch.float64, device=DEVICE)

    def run(m, dtype, force):
        xs, cs = x.to(dtype).requires_grad_(), cond.to(dtype).requires_grad_()
        with fused.forced(force):
            out = m.to(dtype)(xs, cs, relu=relu)
        m.zero_grad()
        out.backward(grad_out.to(dtype))
        return [out.detach(), xs.grad, cs.grad] + [p.grad.clone() for p in m.parameters()]

    want = run(module, torch.float64, False)
    got = run(module, torch.float32, True)
    for name, g, w in zip(["out", "x", "cond", "gamma.w", "gamma.b", "beta.w", "beta.b"], got, want):
        assert _relative(g, w) < 1e-5, name


def test_fused_cfm_takes_channels_last_features_only(monkeypatch):
    """NCHW features run eager (the layout copies cost more than the kernel saves); channels-last x and
    cond take the kernel."""
    calls = []
    monkeypatch.setattr(triton_kernels, "cfm_fused", lambda *args: calls.append(args) or cfm_fused(*args))
    module = CFM(4, 3).to(DEVICE)
    x, cond = torch.randn(1, 4, 3, 5, device=DEVICE), torch.randn(1, 3, 3, 5, device=DEVICE)
    last = torch.channels_last
    for xs, cs, taken in ((x, cond, False), (x.to(memory_format=last), cond, False),
                          (x.to(memory_format=last), cond.to(memory_format=last), True)):
        calls.clear()
        with fused.forced():
            module(xs, cs, relu=True)
        assert bool(calls) == taken


_COMPILE_FOR_HOPPER = '''
import inspect, triton
from triton.backends.compiler import GPUTarget
from triton.compiler import ASTSource
import bench.nn.triton_kernels as kernels

def compile_for_sm90(fn, pointers, constexprs):
    params = list(inspect.signature(fn.fn).parameters)
    signature = {p: pointers.get(p, "i32") for p in params}
    signature.update({p: "constexpr" for p in constexprs})
    source = ASTSource(fn=fn, signature=signature, constexprs={(params.index(k),): v for k, v in constexprs.items()})
    compiled = triton.compile(source, target=GPUTarget("cuda", 90, 32), options=dict(num_warps=kernels.NUM_WARPS))
    # Triton compares shared memory with the device's only when it loads a kernel on one: 227 KiB a block on sm_90
    assert compiled.metadata.shared <= 227 * 1024, (fn.fn.__name__, compiled.metadata.shared)

for dtype in ("fp32", "bf16"):
    data = "*" + dtype
    blocks = dict(KH=3, KW=3, BLOCK_P=64, BLOCK_C=32, BLOCK_O=32, PRECISION="ieee")
    compile_for_sm90(kernels._deform_forward, dict(x_ptr=data, off_ptr="*fp32", mask_ptr="*fp32", w_ptr=data,
                     bias_ptr=data, out_ptr=data), dict(HAS_MASK=True, HAS_BIAS=True, **blocks))
    compile_for_sm90(kernels._deform_backward, dict(x_ptr=data, off_ptr="*fp32", mask_ptr="*fp32", w_ptr=data,
                     gout_ptr=data, gx_ptr="*fp32", goff_ptr="*fp32", gmask_ptr="*fp32", gw_ptr="*fp32"),
                     dict(HAS_MASK=True, NEED_GX=True, **blocks))
    compile_for_sm90(kernels._cfm_forward, dict(x_ptr=data, cond_ptr=data, w_ptr="*fp32", bias_ptr="*fp32",
                     out_ptr=data), dict(RELU=True, BLOCK_P=64, BLOCK_C=32, BLOCK_G=16, PRECISION="ieee"))
print("compiled")
'''


def test_the_kernels_compile_for_hopper_without_a_gpu():
    """The interpreter runs the kernels as Python: what only the compiler checks (types, a size of 1
    passed as a constant, dot shapes and dtypes, shared memory per program) is checked by compiling
    every kernel for sm_90 (H100/H200) in fp32 and bf16, which Triton does without a GPU (8-10 s on 2 cores),
    and holding each kernel's shared memory to sm_90's limit. Triton keeps what compiled in its cache, keyed
    by the kernel's source (the functions it calls too), the target, the options and Triton's own code; a
    failed compile leaves nothing: kept with the C++ kernels (bench/nn/native.py's folder, never pruned: a
    kernel edit adds its build), a later run compiles only kernels that changed (about 2 s otherwise)."""
    import os
    import subprocess
    import sys
    cache = Path(os.environ.get("SRD_BENCH_CACHE", Path.home() / ".cache" / "srd-bench")) / "triton-sm90"
    env = {k: v for k, v in os.environ.items() if k != "TRITON_INTERPRET"}
    env.update(TRITON_CACHE_DIR=str(cache), TRITON_DEFAULT_FP_FUSION="1")
    done = subprocess.run([sys.executable, "-c", _COMPILE_FOR_HOPPER], env=env, capture_output=True, text=True,
                          timeout=600)
    assert done.returncode == 0 and "compiled" in done.stdout, done.stderr[-3000:]
