"""The GPU path (device=cuda): every learned model, the deformable conv, the fast paths and the trainer
give on a CUDA GPU what they give on the CPU. CI has no GPU, so this file skips there; on a machine with
one, `pytest tests/test_cuda.py` runs it (12 s on an H200).

CUDA runs other code than the CPU: the deformable conv samples with grid_sample in training and a gather
in inference (bench.nn.deform) instead of the compiled column kernels, CFM runs its eager ops, and cuDNN
picks its own conv algorithms. TF32 is turned off while comparing, so fp32 on both devices agrees to
float rounding."""
import pytest
import torch
import torch.nn.functional as F

from bench.infer import max_abs_diff, prepare
from bench.models import SRDNet
from bench.nn import DeformConv2d
from bench.tasks import get_task
from bench.train import load_weights, train
from conftest import SMALL, inputs
from test_train import SyntheticSequences, _model, _recipe

pytestmark = pytest.mark.skipif(not torch.cuda.is_available(),
                                reason="no CUDA GPU here (the GPU path runs where there is one: pytest tests/test_cuda.py)")

MODELS = {**SMALL, "srd": (SRDNet, dict(channels=8)),
          "srd_cascade_concat": (SRDNet, dict(channels=8, stage_order="dn_sr", gbuffer_mode="concat"))}


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
    model = cls(scale=scale, **kwargs)
    with torch.no_grad():
        for p in model.parameters():
            p.add_(0.02 * torch.randn_like(p))
    return model


def _close(cuda, cpu, rtol=1e-4):
    """Agreement relative to the tensor's scale (sums over many terms round differently per device)."""
    scale = cpu.abs().max().item() or 1.0
    err = (cuda.cpu() - cpu).abs().max().item()
    assert err <= rtol * scale, f"max |cuda - cpu| = {err:.3g} against scale {scale:.3g}"


@pytest.mark.parametrize("name", sorted(MODELS))
def test_model_forward_and_gradients_match_cpu(name):
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
def test_deform_conv_matches_cpu_kernels(dilation, modulated):
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
def test_fast_paths_on_cuda(name, path):
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
