"""Baselines: output contract, gradients, recurrence, kernel normalization, receptive field, classical and
OIDN rows. Small models and images only (the whole file runs in seconds on 2 cores)."""
import pytest
import torch
import torch.nn.functional as F

from baselines.classical import Bicubic, Bilinear
from baselines.edsr import EDSR
from baselines.kpcn import KPCN
from baselines.oidn import OIDN
from baselines.rae import RAE
from conftest import SMALL, inputs, perturbed

torch.set_num_threads(1)


@pytest.mark.parametrize("scale", [1, 2])
@pytest.mark.parametrize("name", sorted(SMALL))
def test_output_shape_odd_size_multi_frame(name, scale):
    cls, kwargs = SMALL[name]
    torch.manual_seed(0)
    model = cls(scale=scale, **kwargs)
    x, g = inputs()
    out = model(x, g)["final"]
    assert out.shape == (2, 3, 3, 13 * scale, 17 * scale)
    assert torch.isfinite(out).all()
    assert isinstance(cls.recurrent, bool)


@pytest.mark.parametrize("scale", [1, 2])
@pytest.mark.parametrize("name", sorted(SMALL))
def test_tiled_inference_gives_the_untiled_output_at_every_scale(name, scale):
    """Tiled inference allocates the output at the model's scale: a denoise-only (scale 1) EDSR or CFM
    ended in a shape error (they did not say their scale). With an overlap covering the frame, every tile
    sees it whole and the stitched output is the untiled one."""
    from bench.infer import tiled_predict
    cls, kwargs = SMALL[name]
    model = perturbed(cls(scale=scale, **kwargs)).eval()
    x, g = inputs(b=1)
    with torch.no_grad():
        whole = model(x, g)["final"]
    tiled = tiled_predict(model, x, g, tile=8, overlap=32, align=1)
    assert tiled.shape == whole.shape == (1, 3, 3, 13 * scale, 17 * scale)
    torch.testing.assert_close(tiled, whole, atol=1e-5, rtol=0)


@pytest.mark.parametrize("name", sorted(SMALL))
def test_gradients_reach_every_parameter(name):
    cls, kwargs = SMALL[name]
    torch.manual_seed(0)
    model = perturbed(cls(**kwargs), std=0.01)  # zero-initialized layers (CFM gamma/beta, offsets) block gradients
    x, g = inputs(b=1, t=2)
    target = torch.rand(1, 2, 3, 26, 34)
    F.mse_loss(model(x, g)["final"], target).backward()
    missing = [n for n, p in model.named_parameters() if p.grad is None or not p.grad.abs().sum() > 0]
    assert not missing, f"no gradient for {missing}"


def test_models_without_gbuffer():
    x, _ = inputs(t=1)
    for cls, kwargs in (SMALL["edsr"], SMALL["rae"], SMALL["kpcn"]):
        assert cls(gbuffer_channels=0, **kwargs)(x, None)["final"].shape == (2, 1, 3, 26, 34)


def test_rae_streaming_equals_forward_and_state_matters():
    torch.manual_seed(0)
    model = RAE(width=8, input_residual=False).eval()  # a zero output conv would hide the state at init
    x, g = inputs(b=1, t=4)
    with torch.no_grad():
        full = model(x, g)["final"]
        state = model.init_state(x[:, 0])
        streamed = []
        for t in range(4):
            out, state = model.step(x[:, t], g[:, t], state)
            streamed.append(out["final"])
        alone = model(x[:, 3:], g[:, 3:])["final"][:, 0]  # frame 3 from a zero state
    assert torch.allclose(torch.stack(streamed, 1), full, atol=1e-6)
    assert not torch.allclose(alone, full[:, 3], atol=1e-4), "hidden state has no effect"


@pytest.mark.parametrize("name", ["edsr", "cfm", "cfm_deform", "kpcn"])
def test_non_recurrent_models_treat_frames_independently(name):
    cls, kwargs = SMALL[name]
    torch.manual_seed(0)
    model = perturbed(cls(**kwargs))   # untrained, EDSR and CFM return the bilinear upsample of each frame
    x, g = inputs(b=1, t=3)
    with torch.no_grad():
        out = model(x, g)["final"]
        assert (out - Bilinear()(x)["final"]).abs().max() > 1e-3, "the network adds nothing to the bilinear base"
        assert torch.allclose(out[:, 1], model(x[:, 1:2], g[:, 1:2])["final"][:, 0], atol=1e-6)


@pytest.mark.parametrize("scale", [1, 2])
def test_kpcn_kernels_are_normalized(scale):
    torch.manual_seed(0)
    model = KPCN(scale=scale, channels=8, layers=3, filter_size=7)
    _, g = inputs(b=1, t=2, h=9, w=11)  # smaller than the kernel's reach: exercises the border padding
    x = torch.full((1, 2, 3, 9, 11), 0.37)
    x[:, :, 1] = 1.5
    with torch.no_grad():
        weights = model.kernels(x, g)
        out = model(x, g)["final"]
    assert torch.allclose(weights.sum(dim=2), torch.ones(()), atol=1e-5)
    expected = x[:, :, :, :1, :1].expand(-1, -1, -1, 9 * scale, 11 * scale)
    assert torch.allclose(out, expected, atol=1e-5)


@pytest.mark.parametrize("scale", [2, 3, 4])
def test_kpcn_bilinear_start_is_the_input_bilinear_row(scale):
    """share -> 1 gives F.interpolate(bilinear) exactly, border included; a smaller share mixes in a box."""
    torch.manual_seed(0)
    x, g = inputs(b=1, t=2, h=9, w=11)
    with torch.no_grad():
        near = KPCN(scale=scale, channels=4, layers=3, filter_size=7, bilinear_start=1 - 1e-7)(x, g)["final"]
        mixed = KPCN(scale=scale, channels=4, layers=3, filter_size=7, bilinear_start=0.9)
        weights = mixed.kernels(x, g)
    assert torch.allclose(near, Bilinear(scale=scale)(x)["final"], atol=1e-5)
    centre_tap = weights[0, :, 7 * 3 + 3]  # the pixel itself; the bilinear stencil gives it the most weight
    assert torch.allclose(weights.sum(dim=2), torch.ones(()), atol=1e-5)
    assert (weights.amin(dim=2) >= 0.1 / 49 - 1e-6).all() and (centre_tap > 0.25).all()


def test_kpcn_filter_matches_explicit_sum():
    """Each HR sub-pixel is the kernel-weighted sum of the LR neighbourhood (checked at one pixel)."""
    torch.manual_seed(0)
    model = KPCN(channels=4, layers=2, filter_size=3)
    x, g = inputs(b=1, t=1, h=6, w=7)
    with torch.no_grad():
        weights = model.kernels(x, g)[0]  # (4, 9, h, w)
        out = model(x, g)["final"][0, 0]
    y0, x0 = 2, 3
    patch = x[0, 0, :, y0 - 1 : y0 + 2, x0 - 1 : x0 + 2].reshape(3, 9)
    for sub in range(4):
        i, j = divmod(sub, 2)
        expected = patch @ weights[sub, :, y0, x0]
        assert torch.allclose(out[:, 2 * y0 + i, 2 * x0 + j], expected, atol=1e-5)


def receptive_field(model, scale, size=65):
    """Width, in LR pixels, of the input region that the output of the centre LR pixel depends on.

    Weights and biases are made positive so no ReLU is ever off and no gradient cancels; the output of
    the centre LR pixel is its scale x scale HR block.
    """
    with torch.no_grad():
        for p in model.parameters():
            p.copy_(p.abs() + 1e-3)
    x = torch.rand(1, 1, 3, size, size, requires_grad=True)
    g = torch.rand(1, 1, 7, size, size)
    c = size // 2
    model(x, g)["final"][..., c * scale : (c + 1) * scale, c * scale : (c + 1) * scale].sum().backward()
    cols = (x.grad[0, 0].abs().sum(dim=(0, 1)) > 0).nonzero().flatten()
    return int(cols.max() - cols.min() + 1)


@pytest.mark.parametrize("scale", [1, 2])
def test_edsr_receptive_field_matches_paper_table2(scale):
    """Paper Table 2: 4 blocks with atrous second convs give RF 25/33/41/57 for rates 1/2/3/5."""
    torch.manual_seed(0)
    found = {rate: receptive_field(EDSR(scale=scale, channels=4, blocks=4, dilation=rate), scale)
             for rate in (1, 2, 3, 5)}
    assert found == {1: 25, 2: 33, 3: 41, 5: 57}


def test_classical_rows_equal_torch_interpolate():
    x, g = inputs(t=2)
    up = Bilinear()(x, g)["final"]
    ref = F.interpolate(x.flatten(0, 1), scale_factor=2, mode="bilinear", align_corners=False)
    assert torch.equal(up, ref.view(2, 2, 3, 26, 34))
    up = Bicubic()(x, g)["final"]
    ref = F.interpolate(x.flatten(0, 1), scale_factor=2, mode="bicubic", align_corners=False)
    assert torch.equal(up, ref.clamp_min(0).view(2, 2, 3, 26, 34))
    assert torch.equal(Bilinear(scale=1)(x, g)["final"], x)
    assert not list(Bilinear().parameters()) and not list(Bicubic().parameters())


def test_bicubic_clamps_ringing():
    x = torch.zeros(1, 1, 3, 8, 8)
    x[..., 3:5, 3:5] = 10.0
    raw = F.interpolate(x[0], scale_factor=2, mode="bicubic", align_corners=False)
    assert raw.min() < 0  # the cubic kernel rings below zero next to the bright square
    out = Bicubic()(x, None)["final"]
    assert out.min() == 0 and torch.equal(out[0], raw.clamp_min(0))


def smooth_scene(h, w, seed=0):
    """A smooth clean HDR image, its noisy version, and a flat gBuffer (albedo 0.5, normal +z)."""
    yy, xx = torch.meshgrid(torch.linspace(0, 1, h), torch.linspace(0, 1, w), indexing="ij")
    clean = torch.stack([0.5 + 0.4 * torch.sin(3 * xx), 0.5 + 0.3 * torch.cos(2 * yy), 0.3 + 0.2 * xx * yy])
    gen = torch.Generator().manual_seed(seed)
    noisy = (clean + 0.15 * torch.randn(clean.shape, generator=gen)).clamp_min(0)
    normal = torch.tensor([0.0, 0.0, 1.0]).view(3, 1, 1).expand(3, h, w)
    g = torch.cat([torch.full((3, h, w), 0.5), normal, torch.full((1, h, w), 0.5)])
    return clean, noisy, g


@pytest.mark.parametrize("variant, max_ratio", [("lr_then_up", 0.3), ("up_then_hr", 0.99)])
def test_oidn_reduces_error(variant, max_ratio):
    """MSE vs bilinear-upscaled noisy input. Denoising at LR removes most noise (~0.08-0.17x); denoising
    after upscaling barely helps (~0.97x): bilinear upscaling correlates the noise spatially and OIDN,
    trained on per-pixel noise, keeps it as detail."""
    clean, noisy, g = smooth_scene(32, 48)
    clean_hr = F.interpolate(clean[None], scale_factor=2, mode="bilinear", align_corners=False)[0]
    model = OIDN(variant=variant)
    assert OIDN.linear_hdr and not list(model.parameters())
    out = model(noisy[None, None], g[None, None])["final"]
    assert out.shape == (1, 1, 3, 64, 96)
    baseline = F.mse_loss(Bilinear()(noisy[None, None], None)["final"][0, 0], clean_hr)
    assert F.mse_loss(out[0, 0], clean_hr) < max_ratio * baseline


def test_oidn_denoise_only():
    clean, noisy, g = smooth_scene(24, 32, seed=1)
    out = OIDN(scale=1)(noisy[None, None], g[None, None])["final"][0, 0]
    assert F.mse_loss(out, clean) < 0.2 * F.mse_loss(noisy, clean)


def test_fewer_gbuffer_channels_take_a_prefix():
    """ARCHITECTURE.md: a model built with gbuffer_channels=6 uses albedo + normal of a 7-channel gBuffer:
    the first six channels change its output, the seventh (roughness) does not."""
    x, g = inputs(t=1)
    for cls, kwargs in (SMALL["edsr"], SMALL["cfm"]):
        torch.manual_seed(0)
        model = perturbed(cls(gbuffer_channels=6, **kwargs))   # untrained, the output ignores the gBuffer
        other_roughness, other_normal = g.clone(), g.clone()
        other_roughness[:, :, 6] = 1 - g[:, :, 6]
        other_normal[:, :, 5] = 1 - g[:, :, 5]
        with torch.no_grad():
            out = model(x, g)["final"]
            assert torch.equal(out, model(x, g[:, :, :6])["final"])
            assert torch.equal(out, model(x, other_roughness)["final"])
            assert (out - model(x, other_normal)["final"]).abs().max() > 1e-4


@pytest.mark.parametrize("name", ["edsr", "rae", "cfm"])
@pytest.mark.parametrize("scale", [1, 2])
def test_input_residual_starts_at_bilinear(name, scale):
    cls, kwargs = SMALL[name]
    x, g = inputs(b=1, t=2)
    out = cls(scale=scale, **kwargs)(x, g)["final"][0]
    base = x[0] if scale == 1 else F.interpolate(x[0], scale_factor=2, mode="bilinear", align_corners=False)
    torch.testing.assert_close(out, base, atol=1e-6, rtol=0)
    assert (cls(scale=scale, input_residual=False, **kwargs)(x, g)["final"][0] - base).abs().max() > 1e-3


@pytest.mark.parametrize("name", ["edsr", "rae", "cfm", "srd"])
def test_linear_base_starts_at_the_input_bilinear_row_and_keeps_a_sparse_frames_mean(name):
    """With linear_base, an untrained model's output is the Input bilinear row of linear HDR radiance
    (mapped to the network domain): on a dark frame with 60% zero samples its mean is the input's,
    where the network-domain base loses about a third of it."""
    from bench.hdr import from_network, to_network
    from bench.models.srd import SRDNet
    cls, kwargs = (SRDNet, dict(channels=8, sr_blocks=1, dn_levels=2, dn_deform_blocks=1)) if name == "srd" \
        else SMALL[name]
    gen = torch.Generator().manual_seed(5)
    lin = 0.03 * torch.rand(1, 2, 3, 16, 16, generator=gen) * (torch.rand(1, 2, 1, 16, 16, generator=gen) > 0.6)
    x, g = to_network(lin, "pu"), torch.rand(1, 2, 7, 16, 16, generator=gen)
    with torch.no_grad():
        out = from_network(cls(linear_base="pu", **kwargs)(x, g)["final"][0], "pu")
        default = from_network(cls(**kwargs)(x, g)["final"][0], "pu")
    row = F.interpolate(lin[0], scale_factor=2, mode="bilinear", align_corners=False)
    torch.testing.assert_close(out, row, atol=1e-4, rtol=1e-4)   # PU21's floor: a zero reads as 5e-5
    assert abs(out.mean() / lin.mean() - 1) < 0.01 and default.mean() / lin.mean() < 0.8


def test_kpcn_filter_bands_equal_one_pass():
    """Filtering in bands of rows (bounded memory) gives the one-pass result, gradients included."""
    from baselines.kpcn import KernelFilter
    torch.manual_seed(0)
    x = torch.rand(2, 3, 11, 9, dtype=torch.float64, requires_grad=True)
    w = torch.rand(2, 4, 25, 11, 9, dtype=torch.float64).softmax(2).requires_grad_()
    whole = KernelFilter(5)(x, w)
    banded = KernelFilter(5, max_elements=2 * 3 * 25 * 9 * 2)(x, w)  # two rows per band
    torch.testing.assert_close(banded, whole)
    gx, gw = torch.autograd.grad(whole.square().sum(), (x, w))
    bx, bw = torch.autograd.grad(banded.square().sum(), (x, w))
    torch.testing.assert_close(bx, gx)
    torch.testing.assert_close(bw, gw)


def test_kpcn_forward_by_bands_equals_whole_kernels():
    """forward runs the last conv, softmax and filter band by band; one-row bands give the result of
    the whole-frame kernels() + KernelFilter, gradients included."""
    torch.manual_seed(0)
    model = KPCN(channels=4, layers=3, filter_size=5, bilinear_start=0.5).double()
    for p in model.parameters():
        p.data.add_(torch.randn_like(p) * 0.1)
    x = torch.rand(1, 2, 3, 7, 6, dtype=torch.float64, requires_grad=True)
    g = torch.rand(1, 2, 7, 7, 6, dtype=torch.float64)
    radiance = x.reshape(2, 3, 7, 6)
    filtered = model.filter(radiance, model.kernels(x, g))  # (N, 4, 3, h, w)
    whole = F.pixel_shuffle(filtered.transpose(1, 2).reshape(2, 12, 7, 6), 2).view(1, 2, 3, 14, 12)
    model.band_elements = 1  # one row per band
    banded = model(x, g)["final"]
    torch.testing.assert_close(banded, whole)
    gx = torch.autograd.grad(whole.square().sum(), x)[0]
    torch.testing.assert_close(torch.autograd.grad(banded.square().sum(), x)[0], gx)
