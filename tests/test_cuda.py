"""The GPU path (device=cuda): every learned model, the deformable conv, the fast paths and the trainer
give on a CUDA GPU what they give on the CPU. CI has no GPU, so this file skips there; on a machine with
one, `pytest tests/test_cuda.py` runs it (12 s on an H200 before the fused kernels' tests).

CUDA runs other code than the CPU: the deformable conv samples with grid_sample in training and a gather
in inference (bench.nn.deform), or with the fused Triton kernels (bench.nn.triton_kernels, with
SRD_BENCH_FUSED_GPU=1 or fused.forced()), instead of the compiled column kernels; CFM runs its eager ops
or the fused kernel; cuDNN picks its own conv algorithms. TF32 is turned off while comparing, so fp32
on both devices agrees to float rounding. The tests that take a `fused` parameter run both samplers; the
fused kernels' bf16 path and the race-freedom of their input-gradient scatter are checked only here
(Triton's interpreter, which runs tests/test_fused_gpu.py in CI, cannot)."""
import copy

import pandas as pd
import pytest
import torch
import torch.nn.functional as F

from bench.infer import max_abs_diff, prepare
from bench.models import SRDNet
from bench.nn import CFM, DeformConv2d, deform_conv2d, fused
from bench.tasks import get_task
from bench.train import load_weights, train
from conftest import SMALL, inputs, perturbed
from test_train import TASK, SyntheticSequences, _model, _recipe

pytestmark = pytest.mark.skipif(not torch.cuda.is_available(),
                                reason="no CUDA GPU here (the GPU path runs where there is one: pytest tests/test_cuda.py)")

MODELS = {**SMALL, "srd": (SRDNet, dict(channels=8)),
          "srd_cascade_concat": (SRDNet, dict(channels=8, stage_order="dn_sr", gbuffer_mode="concat"))}


@pytest.fixture(params=[False, True], ids=["pytorch_ops", "fused"])
def sampler(request):
    """Each test that takes it runs with the PyTorch-op samplers and with the fused Triton kernels on
    CUDA (the CPU side of a comparison keeps its own kernels)."""
    with fused.on_cuda(request.param):
        yield request.param


@pytest.fixture(autouse=True)
def exact_fp32():
    """TF32 convs and matmuls round to 10 mantissa bits: off, so fp32 means fp32 on both devices."""
    saved = torch.backends.cuda.matmul.allow_tf32, torch.backends.cudnn.allow_tf32
    torch.backends.cuda.matmul.allow_tf32 = torch.backends.cudnn.allow_tf32 = False
    yield
    torch.backends.cuda.matmul.allow_tf32, torch.backends.cudnn.allow_tf32 = saved


def _perturbed(name, scale=2):
    """The model with N(0, 0.02) on every weight: zero-initialised branches (CFM, offsets) compute."""
    cls, kwargs = MODELS[name]
    torch.manual_seed(0)
    return perturbed(cls(scale=scale, **kwargs))


def _close(cuda, cpu, rtol=1e-4):
    """Agreement relative to the tensor's scale (sums over many terms round differently per device)."""
    scale = cpu.abs().max().item() or 1.0
    err = (cuda.cpu() - cpu).abs().max().item()
    assert err <= rtol * scale, f"max |cuda - cpu| = {err:.3g} against scale {scale:.3g}"


@pytest.mark.parametrize("name", sorted(MODELS))
def test_model_forward_and_gradients_match_cpu(name, sampler):
    model = _perturbed(name)
    x, g = inputs(b=1, t=3)
    target = torch.rand(1, 3, 3, 26, 34, generator=torch.Generator().manual_seed(1))
    results = {}
    for device in ("cpu", "cuda"):
        net = model.to(device)
        net.zero_grad()
        out = net(x.to(device), g.to(device))
        F.l1_loss(out["final"], target.to(device)).backward()
        results[device] = ({k: v.detach().cpu() for k, v in out.items()},
                           {n: p.grad.detach().cpu() for n, p in net.named_parameters() if p.grad is not None})
    (out_cpu, grad_cpu), (out_cuda, grad_cuda) = results["cpu"], results["cuda"]
    assert out_cpu.keys() == out_cuda.keys()
    for key in out_cpu:
        _close(out_cuda[key], out_cpu[key])
    assert grad_cpu.keys() == grad_cuda.keys()
    for n in grad_cpu:
        _close(grad_cuda[n], grad_cpu[n], rtol=1e-3)


@pytest.mark.parametrize("dilation,modulated", [(1, False), (2, True)])
def test_deform_conv_matches_cpu_kernels(dilation, modulated, sampler):
    """grid_sample on CUDA against the CPU's compiled columns, forward and every gradient, with offsets
    of several pixels (samples land between pixels and outside the image)."""
    torch.manual_seed(0)
    layer = DeformConv2d(16, 8, padding=dilation, dilation=dilation, modulated=modulated)
    with torch.no_grad():
        for p in layer.parameters():
            p.add_(0.5 * torch.randn_like(p))
    x = torch.randn(2, 16, 23, 31)
    grads = {}
    for device in ("cpu", "cuda"):
        net = layer.to(device)
        net.zero_grad()
        xd = x.to(device, copy=True).requires_grad_()
        out = net(xd)
        (out * torch.linspace(-1, 1, out.numel(), device=device).view_as(out)).sum().backward()
        # detach(): Module.to moves each .grad in place, so a kept CPU .grad would follow the layer to the GPU
        grads[device] = (out.detach().cpu(), xd.grad.detach().cpu(),
                         {n: p.grad.detach().cpu() for n, p in net.named_parameters()})
    _close(grads["cuda"][0], grads["cpu"][0])
    _close(grads["cuda"][1], grads["cpu"][1], rtol=1e-3)
    for n, grad in grads["cpu"][2].items():
        _close(grads["cuda"][2][n], grad, rtol=1e-3)


@pytest.mark.parametrize("path", ["inference_mode", "channels_last", "bf16"])
@pytest.mark.parametrize("name", ["srd", "edsr", "rae", "kpcn", "cfm_deform"])
def test_fast_paths_on_cuda(name, path, sampler):
    """bench.infer's fast paths run on CUDA and stay near the fp32 reference (bf16: its rounding)."""
    model = _perturbed(name).cuda().eval()
    x, g = (t.cuda() for t in inputs(b=1, t=2))
    reference = prepare(model)(x, g)
    fast = prepare(model, path)(x, g)
    scale = reference["final"].abs().max().item()
    tolerance = 5e-2 if path == "bf16" else 1e-5
    assert max_abs_diff(fast, reference) <= tolerance * scale


def test_trainer_on_cuda_matches_cpu_and_resumes(tmp_path):
    """The shared trainer on CUDA: the same batches as on the CPU give the same losses, its checkpoint
    loads on either device, and a resumed run continues where it stopped."""
    task, data = get_task("srd"), SyntheticSequences()
    cpu = train(_model(), data, task, tmp_path / "cpu", _recipe(steps=6), progress=False)
    cuda_model = _model()
    cuda = train(cuda_model, data, task, tmp_path / "cuda", _recipe(steps=6), device="cuda", progress=False)
    assert next(cuda_model.parameters()).is_cuda
    assert cuda["final_loss"] == pytest.approx(cpu["final_loss"], rel=1e-3)
    halves = tmp_path / "halves"
    train(_model(), data, task, halves, _recipe(steps=3), device="cuda", progress=False)
    resumed = train(_model(), data, task, halves, _recipe(steps=6), device="cuda", progress=False)
    assert resumed["final_loss"] == pytest.approx(cuda["final_loss"], rel=1e-4)
    on_cpu = load_weights(_model(), tmp_path / "cuda", device="cpu")
    assert all(p.device.type == "cpu" for p in on_cpu.parameters())
    x, g = inputs(b=1, t=2, g=7)
    _close(on_cpu(x, g)["final"], cuda_model.cpu()(x, g)["final"].detach())


def test_training_frames_held_on_the_gpu_are_the_host_items_and_train_alike(tmp_path):
    """At device=cuda the trainer's split is held in GPU memory (bench.device_frames): every item of
    every draw is the host's, bit for bit, and a training on it takes the host path's steps."""
    from bench.dataset import SequenceDataset
    from bench.device_frames import DeviceFrames, training_frames
    from test_dataset import ALL, _write_synthetic
    _write_synthetic(tmp_path / "data")
    options = dict(seq_len=2, crop=4, augment=True, seed=3, permute_colours=True)
    host = SequenceDataset(tmp_path / "data", "train", ALL, **options)
    held = training_frames(tmp_path / "data", "train", ALL, device="cuda", **options)
    assert isinstance(held, DeviceFrames) and held.nbytes() > 0
    for index in range(len(host)):
        for draw in range(8):
            want, got = host.item(index, draw), held.item(index, draw)
            for key in ALL:
                assert got[key].is_cuda and torch.equal(got[key].cpu(), want[key]), (index, draw, key)
    recipe = _recipe(steps=4, crop=4, val_every=0)
    curves = {}
    for name, data in (("host", host), ("held", held)):
        summary = train(_model(), data, TASK, tmp_path / name, recipe, device="cuda", progress=False)
        assert 0 <= summary["data_share"] < 1
        curves[name] = pd.read_csv(tmp_path / name / "curve.csv")
    assert curves["held"]["loss"].tolist() == pytest.approx(curves["host"]["loss"].tolist(), rel=1e-5)


# ---- the fused Triton kernels at sizes and in dtypes the interpreter cannot run ---------------------

def _deform_inputs(b, c, h, w, o, seed=0, offset_scale=2.0, device="cuda"):
    gen = torch.Generator().manual_seed(seed)
    t = dict(x=torch.randn(b, c, h, w, generator=gen), offset=offset_scale * torch.randn(b, 18, h, w, generator=gen),
             weight=torch.randn(o, c, 3, 3, generator=gen) / (3 * c ** 0.5), bias=torch.randn(o, generator=gen),
             mask=2 * torch.rand(b, 9, h, w, generator=gen))
    return {k: v.to(device) for k, v in t.items()}


def _run_deform(t, dtype=torch.float32, grad_out=None):
    leaves = {k: v.clone().requires_grad_() for k, v in t.items()}
    with torch.autocast("cuda", dtype=torch.bfloat16, enabled=dtype == torch.bfloat16):
        out = deform_conv2d(leaves["x"], leaves["offset"], leaves["weight"], leaves["bias"], 1, 1, leaves["mask"])
    out.backward(grad_out.to(out.dtype) if grad_out is not None else torch.ones_like(out))
    return out.detach().float(), {k: v.grad.float() for k, v in leaves.items()}


def _relative(got, want):
    return ((got.double() - want.double()).norm() / want.double().norm()).item()


def test_a_cuda_graphed_training_step_equals_eager(tmp_path):
    """train.compile=reduce-overhead (forward, losses and backward as CUDA graphs, bench/train.py): the
    same per-step losses as eager on the GPU within test_train's COMPILED_RTOL, and the copies of the
    reported losses survive the graphs' next replays (every step's value differs)."""
    from test_train import COMPILED_RTOL
    curves = {}
    for mode in (None, "reduce-overhead"):
        train(_model(), SyntheticSequences(), TASK, tmp_path / str(mode), _recipe(6, compile=mode, val_every=0),
              device="cuda", progress=False)
        curves[mode] = pd.read_csv(tmp_path / str(mode) / "curve.csv")
    for column in ("loss", "grad_norm"):
        assert curves["reduce-overhead"][column].tolist() == pytest.approx(curves[None][column].tolist(),
                                                                          rel=COMPILED_RTOL)
    assert curves["reduce-overhead"]["loss"].nunique() == 6


@pytest.mark.parametrize("shape", [(2, 32, 67, 121, 32), (1, 64, 33, 40, 16), (3, 16, 17, 9, 72)])
def test_fused_deform_matches_the_pytorch_sampler_at_size(shape):
    """fp32 (TF32 off): the fused forward and every gradient against the grid_sample sampler in float64
    on the GPU, at sizes with thousands of programs and overlapping scatters."""
    t = _deform_inputs(*shape)
    grad_out = torch.randn(shape[0], shape[4], shape[2], shape[3], generator=torch.Generator().manual_seed(1)).cuda()
    with fused.forced():
        out, grads = _run_deform(t, grad_out=grad_out)
    with fused.forced(False):
        ref, ref_grads = _run_deform({k: v.double() for k, v in t.items()}, torch.float64, grad_out.double())
    assert _relative(out, ref) < 1e-5
    for name in grads:
        assert _relative(grads[name], ref_grads[name]) < 1e-5, name


def test_fused_deform_bf16_matches_float64_on_the_same_rounded_operands():
    """bf16 autocast: x, weight and (as autocast makes them) offsets and mask in bf16, sums in float32.
    Against float64 on the very same bf16-rounded values the forward differs by float32 sums and the one
    rounding of the sampled tile to bf16 before its dot (about 2^-9): relative L2 under 5e-3; the
    gradients, which round grad_out and the samples too, under 1e-2."""
    t = _deform_inputs(2, 32, 45, 64, 32, seed=2)
    t = {k: v.to(torch.bfloat16) for k, v in t.items()}   # the operands as bf16 autocast sees them
    # bf16 offsets of 1-4 px have 5-7 fraction bits, so every 64-128th sample lands on a whole pixel, a
    # bilinear kink where the offset's derivative is a convention: move those a quarter pixel (exact in bf16)
    on_pixel = t["offset"] == t["offset"].round()
    t["offset"] = torch.where(on_pixel, t["offset"] + 0.25, t["offset"])
    grad_out = torch.randn(2, 32, 45, 64, generator=torch.Generator().manual_seed(3)).cuda()
    with fused.forced():
        out, grads = _run_deform(t, torch.bfloat16, grad_out)
    with fused.forced(False):
        ref, ref_grads = _run_deform({k: v.double() for k, v in t.items()}, torch.float64, grad_out.double())
    assert _relative(out, ref) < 5e-3
    for name in ("x", "offset", "weight", "mask", "bias"):
        assert _relative(grads[name], ref_grads[name]) < 1e-2, name


def test_fused_deform_tf32_where_cudnn_allows_it():
    """With TF32 convs allowed (PyTorch's default for cuDNN) the fused fp32 path takes TF32 dots:
    within TF32 rounding (relative L2 under 5e-3) of float64."""
    t = _deform_inputs(1, 32, 40, 52, 32, seed=4)
    torch.backends.cudnn.allow_tf32 = True   # the exact_fp32 fixture restores it
    with fused.forced():
        out, _ = _run_deform(t)
    with fused.forced(False):
        ref, _ = _run_deform({k: v.double() for k, v in t.items()}, torch.float64)
    assert _relative(out, ref) < 5e-3


@pytest.mark.parametrize("channels", [32, 96])
def test_fused_deform_gradients_repeat_and_agree_with_float64(channels):
    """Zero offsets send every input pixel's gradient from 9 taps of 9 programs' pixels by atomics; then
    offsets pull every sample between a few pixels (about 10^5 adds each). Atomics lose no update but add
    in another order each run: grad x agrees across runs and with float64 to float32 reordering (5e-5).
    The offset, mask and weight gradients are written without atomics (96 channels: in two channel
    blocks, read-modify-write): bit-identical across runs."""
    for offset_scale, pile_up in ((0.0, False), (1.0, True)):
        t = _deform_inputs(2, channels, 96, 128, 32, seed=3, offset_scale=offset_scale)
        if pile_up:  # every tap of every pixel samples near (5.5, 7.5) of the image
            ys, xs = torch.meshgrid(torch.arange(96.0), torch.arange(128.0), indexing="ij")
            tap_y = torch.arange(3.0).repeat_interleave(3) - 1
            tap_x = torch.arange(3.0).repeat(3) - 1
            t["offset"][:, 0::2] = (5.5 - ys - tap_y.view(9, 1, 1)).cuda()
            t["offset"][:, 1::2] = (7.5 - xs - tap_x.view(9, 1, 1)).cuda()
        with fused.forced():
            runs = [_run_deform(t)[1] for _ in range(3)]
        with fused.forced(False):
            ref = _run_deform({k: v.double() for k, v in t.items()}, torch.float64)[1]
        for grads in runs:
            assert _relative(grads["x"], ref["x"]) < 5e-5
            assert _relative(grads["x"], runs[0]["x"]) < 5e-5
            for name in ("offset", "mask", "weight"):
                # (zero offsets sample at whole pixels, where bilinear sampling has a kink: the offsets'
                # one-sided derivatives there are a convention, so they are compared off it only)
                if name == "weight" or pile_up:
                    assert _relative(grads[name], ref[name]) < 1e-5, name
                assert torch.equal(grads[name], runs[0][name]), name


@pytest.mark.parametrize("dtype,tolerance", [(torch.float32, 1e-5), (torch.bfloat16, 1e-2)])
def test_fused_cfm_on_cuda(dtype, tolerance):
    """fp32: the fused CFM (channels-last) against eager, forward and every gradient. bf16: against float64 on the same
    bf16-rounded operands (eager autocast rounds gamma and beta to bf16 too, which flips the ReLU mask near
    zero: a different function, not a reference)."""
    torch.manual_seed(0)
    module = CFM(32, 16).cuda()
    for p in module.parameters():
        torch.nn.init.normal_(p, std=0.3)
    # channels-last: the layout the fused CFM takes (bench.nn.cfm)
    x, cond = (torch.randn(2, c, 50, 70, device="cuda").to(memory_format=torch.channels_last) for c in (32, 16))
    if dtype == torch.bfloat16:   # the operands as the fused bf16 call sees them
        x, cond = x.bfloat16().float(), cond.bfloat16().float()
        with torch.no_grad():
            for p in module.parameters():
                p.copy_(p.bfloat16().float())
    results = {}
    for force in (False, True):
        reference = not force and dtype == torch.bfloat16
        run = copy.deepcopy(module).double() if reference else module
        xs, cs = (v.double() if reference else v.clone() for v in (x, cond))
        xs.requires_grad_(), cs.requires_grad_()
        with fused.forced(force), torch.autocast("cuda", dtype=torch.bfloat16, enabled=force and dtype == torch.bfloat16):
            out = run(xs, cs, relu=True)
        run.zero_grad()
        out.sum().backward()
        results[force] = [out, xs.grad, cs.grad] + [p.grad.clone() for p in run.parameters()]
    for got, want in zip(results[True], results[False]):
        assert _relative(got, want) < tolerance
