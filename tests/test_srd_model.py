"""Tests for bench.models.SRDNet: every table switch, gradients, recurrence, streaming, cascade, MACs."""
import itertools

import pytest
import torch
import torch.nn as nn

from bench.models import SRDNet
from bench.nn import CFM, DeformConv2d
from conftest import perturbed

torch.set_num_threads(1)
TINY = dict(channels=8)


def _inputs(b=1, t=2, h=13, w=7, seed=0):
    g = torch.Generator().manual_seed(seed)
    return torch.rand(b, t, 3, h, w, generator=g), torch.rand(b, t, 7, h, w, generator=g)


def _check_shapes(model, x, g, scale=2):
    out = model(x, g)
    b, t, _, h, w = x.shape
    assert out["final"].shape == (b, t, 3, scale * h, scale * w)
    if model.emit_intermediate:
        assert out["intermediate"].shape == (b, t, 3, 2 * h, 2 * w)
    else:
        assert "intermediate" not in out
    assert torch.isfinite(out["final"]).all()
    return out


# paper Table 3 / 6 switches: stage order x coupling x channel aug x skip
@pytest.mark.parametrize("stage_order,gbuffer_mode,channel_aug,skip",
                         list(itertools.product(("sr_dn", "dn_sr"), ("cfm", "concat"), (True, False), (True, False))))
def test_switch_combinations_shapes(stage_order, gbuffer_mode, channel_aug, skip):
    model = SRDNet(stage_order=stage_order, gbuffer_mode=gbuffer_mode, channel_aug=channel_aug, skip=skip, **TINY)
    x, g = _inputs()
    _check_shapes(model, x, g)
    assert model.emit_intermediate == (stage_order == "sr_dn")


@pytest.mark.parametrize("dn_deform_blocks", range(6))  # Table 7: 0, u1, u1+u2, ..., u1..u5
def test_deform_block_count_and_naming(dn_deform_blocks):
    model = SRDNet(dn_deform_blocks=dn_deform_blocks, **TINY)
    # decoder[i] is u_{5-i}; the deformable ones are u1..u_n, the blocks nearest the output
    deformable = {5 - i for i, blk in enumerate(model.dn.decoder) if isinstance(blk.conv2, DeformConv2d)}
    assert deformable == set(range(1, dn_deform_blocks + 1))
    _check_shapes(model, *_inputs(h=9, w=6))


@pytest.mark.parametrize("sr_deform_blocks,dilation", [(0, 1), (0, 2), (0, 3), (0, 5), (4, 1), (2, 2)])
def test_sr_stage_dilation_and_deform(sr_deform_blocks, dilation):  # Table 2 (dilation), Table 4 (two-stage)
    model = SRDNet(sr_deform_blocks=sr_deform_blocks, dilation=dilation, **TINY)
    convs = [blk.conv2 for blk in model.sr.trunk.body]
    assert sum(isinstance(c, DeformConv2d) for c in convs) == sr_deform_blocks
    assert all(c.dilation in (dilation, (dilation, dilation)) for c in convs)
    _check_shapes(model, *_inputs())


@pytest.mark.parametrize("kwargs", [dict(scale=1), dict(scale=1, gbuffer_mode="concat"), dict(gbuffer_channels=0),
                                    dict(gbuffer_channels=6), dict(dn_levels=3), dict(intermediate=False),
                                    dict(sr_blocks=1, dn_deform_blocks=0)])
def test_other_configurations(kwargs):
    torch.manual_seed(0)
    model = SRDNet(**kwargs, **TINY)
    x, g = _inputs(h=5, w=11)
    _check_shapes(model, x, g, scale=kwargs.get("scale", 2))
    if kwargs.get("gbuffer_channels") == 0:   # untrained, every SRDNet ignores its gBuffer: perturbed, only this one
        perturbed(model)
        torch.testing.assert_close(model(x, None)["final"], model(x, g)["final"])


@pytest.mark.parametrize("h,w", [(13, 7), (1, 1), (16, 16), (33, 2)])
def test_any_input_size(h, w):
    _check_shapes(SRDNet(**TINY), *_inputs(h=h, w=w))


@pytest.mark.parametrize("kwargs", [dict(), dict(stage_order="dn_sr"), dict(gbuffer_mode="concat", channel_aug=False),
                                    dict(sr_deform_blocks=2, dn_deform_blocks=5, dilation=2)])
def test_gradients_reach_every_parameter(kwargs):
    torch.manual_seed(0)
    model = SRDNet(**kwargs, **TINY)
    x, g = _inputs(h=12, w=10)
    # Two zero-initialised links (the output convs of input_residual, then CFM gamma/beta) hold the
    # ConditionNets' gradient at zero for two steps by construction; check the third step's gradients.
    optimizer = torch.optim.Adam(model.parameters(), lr=6e-4)  # the paper's optimizer
    for _ in range(3):
        optimizer.zero_grad()
        out = model(x, g)
        sum(v.square().mean() for v in out.values()).backward()
        optimizer.step()
    for name, p in model.named_parameters():
        assert p.grad is not None, name
        assert torch.isfinite(p.grad).all() and p.grad.abs().sum() > 0, name


def test_recurrent_state_carried_within_and_reset_between_calls():
    torch.manual_seed(0)
    model = SRDNet(input_residual=False, **TINY)  # zero output convs would hide the recurrence at init
    x, g = _inputs(t=3, h=8, w=8)
    out = model(x, g)["final"]
    # frame 1 of a 3-frame sequence equals a single-frame call: the state starts at zero every call
    torch.testing.assert_close(model(x[:, :1], g[:, :1])["final"][:, 0], out[:, 0])
    torch.testing.assert_close(model(x, g)["final"], out)
    # changing frame 1 changes the output of frame 2 (and the intermediate SR head does not recur)
    x2 = x.clone()
    x2[:, 0] = torch.rand_like(x2[:, 0])
    out2 = model(x2, g)
    assert (out2["final"][:, 1] - out[:, 1]).abs().max() > 1e-6
    torch.testing.assert_close(out2["intermediate"][:, 1], model(x, g)["intermediate"][:, 1])


@pytest.mark.parametrize("stage_order", ["sr_dn", "dn_sr"])
def test_streaming_step_equals_forward(stage_order):
    """step() frame by frame, carrying its state, gives forward()'s every output exactly; the state it carries
    matters (a frame stepped from a fresh state comes out otherwise)."""
    torch.manual_seed(0)
    model = perturbed(SRDNet(stage_order=stage_order, **TINY))  # untrained, the output ignores the state
    x, g = _inputs(t=3, h=13, w=7)
    with torch.no_grad():
        ref = model(x, g)
        state = model.init_state(x[:, 0])
        for t in range(3):
            out_t, state = model.step(x[:, t], g[:, t], state)
            for key in ref:
                torch.testing.assert_close(out_t[key], ref[key][:, t], atol=0, rtol=0)
        fresh, _ = model.step(x[:, 2], g[:, 2], model.init_state(x[:, 0]))
    assert (fresh["final"] - ref["final"][:, 2]).abs().max() > 1e-4


@pytest.mark.parametrize("stage_order,gbuffer_mode", [("sr_dn", "concat"), ("dn_sr", "concat"), ("sr_dn", "cfm")])
def test_cascade_stages_compose_to_full_model(stage_order, gbuffer_mode):
    """Running the two stages separately through forward_stage reproduces the end-to-end forward
    (exactly, for a size that needs no padding)."""
    torch.manual_seed(0)
    model = SRDNet(stage_order=stage_order, gbuffer_mode=gbuffer_mode, channel_aug=False, skip=False, **TINY)
    perturbed(model)  # untrained, both stages return their input's bilinear upsample: any composition would pass
    x, g = _inputs(t=2, h=32, w=32)  # a multiple of 2^dn_levels: no padding in either stage
    full = model(x, g)
    bilinear = torch.nn.functional.interpolate(x.flatten(0, 1), scale_factor=2, mode="bilinear", align_corners=False)
    assert (full["final"].flatten(0, 1) - bilinear).abs().max() > 1e-3
    first, second = ("sr", "dn") if stage_order == "sr_dn" else ("dn", "sr")
    mid = model.forward_stage(first, x, g)["final"]
    out = model.forward_stage(second, mid, g)["final"]
    torch.testing.assert_close(out, full["final"], atol=1e-5, rtol=1e-5)
    if stage_order == "sr_dn":
        torch.testing.assert_close(mid, full["intermediate"])
        assert mid.shape == (1, 2, 3, 64, 64)
    else:
        assert mid.shape == (1, 2, 3, 32, 32)
    # odd sizes work too (each stage pads and crops on its own)
    x, g = _inputs(t=1, h=13, w=7)
    mid = model.forward_stage(first, x, g)["final"]
    assert model.forward_stage(second, mid, g)["final"].shape == (1, 1, 3, 26, 14)
    if stage_order == "sr_dn":  # the denoiser alone also takes a gBuffer at its own (HR) size
        hr_g = torch.rand(1, 1, 7, 26, 14)
        assert model.forward_stage("dn", mid, hr_g)["final"].shape == (1, 1, 3, 26, 14)


def test_forward_stage_needs_rgb_between_stages():
    model = SRDNet(**TINY)  # channel_aug=True, skip=True
    with pytest.raises(ValueError, match=r"channel_aug=False and skip=False \(RGB between stages\)"):
        model.forward_stage("sr", *_inputs())


def test_he_initialization():
    torch.manual_seed(0)
    model = SRDNet()
    w = model.dn.encoder[0].conv_rec.weight  # fan_in = 64 * 9
    assert abs(w.std().item() - (2 / (64 * 9)) ** 0.5) < 0.05 * (2 / (64 * 9)) ** 0.5
    assert model.dn.encoder[0].conv_rec.bias.abs().max() == 0
    for m in model.modules():  # CFM and offset generators start at zero (identity / plain conv)
        if isinstance(m, CFM):
            assert m.gamma.weight.abs().max() == 0 and m.beta.weight.abs().max() == 0
        if isinstance(m, DeformConv2d):
            assert m.offset_conv.weight.abs().max() == 0 and m.weight.abs().max() > 0


def _conv_macs(module, run):
    """Analytic MACs of the convs in `module` during run(): out_elements * in_ch * kh * kw per conv
    (deformable: the same for its weight product; bilinear sampling left out)."""
    total = [0]

    def hook(m, inputs, out):
        weight = m.weight
        total[0] += out.numel() * weight.shape[1] * weight.shape[2] * weight.shape[3]

    def cfm_hook(m, inputs, out):  # CFM runs its gamma and beta 1x1 convs as one functional conv
        cond = inputs[1]
        total[0] += cond.numel() // cond.shape[1] * (m.gamma.out_channels + m.beta.out_channels) * cond.shape[1]

    handles = [m.register_forward_hook(hook) for m in module.modules() if isinstance(m, (nn.Conv2d, DeformConv2d))]
    handles += [m.register_forward_hook(cfm_hook) for m in module.modules() if isinstance(m, CFM)]
    with torch.no_grad():
        run()
    for handle in handles:
        handle.remove()
    return total[0]


def test_default_model_macs_near_paper():
    """Paper Table 5: 258.29 GMac at 960x540 input; ours is within 5% (267.8, see the SRDNet docstring).
    Counted on the meta device (shapes only)."""
    with torch.device("meta"):
        model = SRDNet()
        x, g = torch.zeros(1, 1, 3, 540, 960), torch.zeros(1, 1, 7, 540, 960)
        gmac = _conv_macs(model, lambda: model(x, g)) / 1e9
        assert abs(gmac / 258.29 - 1) < 0.05, gmac
        # the counter against a hand count: 4 SR ResBlocks at LR, each 2 convs 3x3 32->32 + 2 CFMs (2 1x1 convs)
        y, cond = torch.zeros(1, 32, 540, 960), torch.zeros(1, 16, 540, 960)
        macs = _conv_macs(model.sr.trunk.body, lambda: [blk(y, cond) for blk in model.sr.trunk.body])
    assert macs == 4 * 540 * 960 * (2 * 32 * 32 * 9 + 2 * 2 * 16 * 32)


@pytest.mark.parametrize("stage_order,channel_aug", [("sr_dn", True), ("sr_dn", False), ("dn_sr", True),
                                                     ("dn_sr", False)])
def test_input_residual_starts_at_bilinear(stage_order, channel_aug):
    """With input_residual the untrained network is exactly the "Input bilinear" row (and its
    intermediate head the same); without it, it is not."""
    x, g = _inputs(t=2, h=12, w=10)
    bilinear = torch.nn.functional.interpolate(x[0], scale_factor=2, mode="bilinear", align_corners=False)
    out = SRDNet(stage_order=stage_order, channel_aug=channel_aug, skip=False, **TINY)(x, g)
    for key in out:
        torch.testing.assert_close(out[key][0], bilinear, atol=1e-6, rtol=0)
    plain = SRDNet(stage_order=stage_order, channel_aug=channel_aug, input_residual=False, **TINY)(x, g)
    assert (plain["final"][0] - bilinear).abs().max() > 1e-2


def test_torch_compile_traces_the_whole_model_in_one_graph():
    """train.compile: Dynamo traces the proposed model (deformable blocks, CFM, recurrence) without a
    graph break. The CPU kernels are ctypes calls it cannot trace; kernels_available() said True while it
    traced, and each call broke the graph (24 breaks), each piece recompiled per feature size until
    Dynamo's limit sent it back to eager (docs/speed.md)."""
    torch._dynamo.reset()
    explained = torch._dynamo.explain(SRDNet(**TINY))(*_inputs(h=16, w=16))
    assert explained.graph_break_count == 0, [b.reason[:200] for b in explained.break_reasons]
