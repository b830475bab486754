import math

import pytest
import torch

from bench.hdr import from_network, to_network


@pytest.mark.parametrize("mode,lo,hi", [("clamp", 0.0, 1.0), ("log1p", 0.0, 1e4), ("pu", 1e-4, 100.0)])
def test_round_trip_on_valid_range(mode, lo, hi):
    x = torch.logspace(torch.log10(torch.tensor(max(lo, 1e-4))), torch.log10(torch.tensor(hi)), 200,
                       dtype=torch.float64)
    back = from_network(to_network(x, mode), mode)
    assert torch.allclose(back, x, rtol=1e-6, atol=1e-9)


def test_pu_maps_one_to_one_and_is_monotonic():
    x = torch.logspace(-4, 2, 500, dtype=torch.float64)
    y = to_network(x, "pu")
    assert to_network(torch.tensor(1.0, dtype=torch.float64), "pu").item() == pytest.approx(1.0)
    assert (y[1:] > y[:-1]).all()


def test_unknown_mode_is_rejected():
    with pytest.raises(ValueError, match="unknown HDR transform"):
        to_network(torch.zeros(1), "gamma")


@pytest.mark.parametrize("mode", ["clamp", "pu"])
def test_bounded_domains_invert_any_network_output_to_a_finite_radiance(mode):
    """A network can output anything; far above PU21's range its inverse formula has a pole.
    (log1p is unbounded by design: its inverse overflows only past radiance 3e38.)"""
    y = torch.tensor([-1e6, -5.0, 0.0, 0.5, 3.0, 10.0, 1e3, 1e9, float("inf")])
    assert torch.isfinite(from_network(y, mode)).all()
    top = from_network(torch.tensor([1e9, float("inf")]), mode)
    assert top.tolist() == pytest.approx([100.0, 100.0] if mode == "pu" else [1.0, 1.0])


# ---------------------------------------------------------------- the exposure domain (the default)

from bench.evaluate import predict  # noqa: E402  (the one inference path: training, evaluation and predict)
from bench.exposure import (BLACK_EXPOSURE, EXPOSURE_DOMAINS, PASS_FROM, PASS_FULL, decode, encode,  # noqa: E402
                            frame_exposure, highlights, pass_highlights, transfer)
from bench.hdr import transforms  # noqa: E402
from bench.models.srd import SRDNet  # noqa: E402
from conftest import SMALL, inputs  # noqa: E402

LEARNED = {**SMALL, "srd": (SRDNet, dict(channels=8, sr_blocks=1, dn_levels=2, dn_deform_blocks=1))}
EXPOSURE_RTOL = 1e-4  # f(kx) = k f(x) up to float32 rounding (the network sees the same values)


def _learned(name):
    cls, kwargs = LEARNED[name]
    torch.manual_seed(0)
    model = cls(**kwargs).eval()
    with torch.no_grad():  # zero-initialised layers (CFM, deform offsets) would hide part of the network
        for p in model.parameters():
            p.add_(0.05 * torch.randn_like(p))
    return model


def _scene(seed=0):
    """LR radiance with a dark half, a highlight of 3000, a lamp block of 500 and exact zeros; a gBuffer."""
    x, g = inputs(b=1, t=2, h=16, w=24, seed=seed)
    x = x ** 3
    x[..., :8, :] *= 1e-3
    x[..., 2, 3] = 3000.0
    x[..., 10:14, 14:20] = 500.0
    x[..., 10:, :4] = 0.0
    return x, g


@pytest.mark.parametrize("domain", EXPOSURE_DOMAINS)
def test_frame_exposure_scales_with_the_frame_and_is_black_exposure_for_a_black_frame(domain):
    x, _ = _scene()
    e = frame_exposure(x, domain)
    assert e.shape == (1, 2, 1, 1, 1) and (e > 0).all()
    for k in (1e-4, 1e-2, 1e2, 1e4):
        assert torch.allclose(frame_exposure(k * x, domain), k * e, rtol=1e-5)
    assert frame_exposure(torch.zeros(1, 1, 3, 8, 8), domain).item() == pytest.approx(BLACK_EXPOSURE)
    assert frame_exposure(x, "pu") is None


@pytest.mark.parametrize("domain", EXPOSURE_DOMAINS)
def test_the_exposure_domain_inverts_without_a_ceiling(domain):
    x = torch.logspace(-8, 6, 300, dtype=torch.float64).reshape(1, 1, 3, 10, 10)
    e = frame_exposure(x, domain)
    assert torch.allclose(decode(encode(x, domain, e), domain, e), x, rtol=1e-9)
    assert torch.equal(encode(x, "pu", None), to_network(x, "pu"))  # the pixelwise domains: bench.hdr as it was
    assert torch.equal(decode(x, "pu", None), from_network(x, "pu"))
    to_linear, from_linear = transforms(domain)  # the models' linear base: radiance / exposure
    y = torch.rand(5, dtype=torch.float64) * 3
    assert torch.allclose(to_linear(from_linear(y)), y)
    assert torch.equal(from_linear(y), to_network(y, transfer(domain)))  # bench.hdr knows it by its prefix


@pytest.mark.parametrize("domain", EXPOSURE_DOMAINS)
@pytest.mark.parametrize("name", sorted(LEARNED))
def test_a_learned_model_in_the_exposure_domain_scales_with_the_input_and_keeps_black_black(name, domain):
    """f(k x) = k f(x) for k from 1e-4 to 1e4 (within EXPOSURE_RTOL of the output's peak), so a bright
    frame comes out above PU21's ceiling of 100, and an all-black frame gives at most 1e-6. (Random
    weights: whether a trained model reproduces a highlight is the stability table's energy rule.)"""
    model = _learned(name)
    x, g = _scene()
    out = predict(model, x, g, domain)
    for k in (1e-4, 1e-2, 1e2, 1e4):
        scaled = predict(model, k * x, g, domain)
        assert (scaled - k * out).abs().max() <= EXPOSURE_RTOL * k * out.abs().max(), k
    assert predict(model, 1e4 * x, g, domain).max() > 100
    assert predict(model, 1e4 * x, g, "pu").max() <= 100  # the ceiling the old domain has
    black = predict(model, torch.zeros_like(x), g, domain)
    assert black.abs().max() <= 1e-6
    assert predict(model, torch.zeros_like(x), g, "pu").abs().max() > 1e-6  # the floor the old domain has


# ---------------------------------------------------------------- exposure_pass: highlights pass through

def test_highlights_take_a_block_to_its_rim_and_neither_a_firefly_nor_a_line_two_pixels_wide():
    x = torch.zeros(1, 3, 12, 16)                                   # network domain, LR
    x[..., 2:6, 3:8] = math.log1p(1e3)                              # a 4x5 block at 1e3x the exposure
    x[..., 9, 2] = math.log1p(1e4)                                  # a firefly
    x[..., 7:12, 12:14] = math.log1p(1e4)                           # a line 2 pixels wide
    x[0, 1, 0, 15] = math.log1p(1e4)                                # one channel of one pixel
    expected = torch.zeros(1, 1, 12, 16)
    expected[..., 2:6, 3:8] = 1.0
    assert torch.equal(highlights(x), expected)


def test_highlights_ramp_from_30x_to_100x_the_exposure_by_the_brightest_channel():
    levels = torch.tensor([10.0, 30.0, 50.0, 100.0, 1e3, 1e5])
    x = torch.zeros(len(levels), 3, 5, 5)
    x[:, 1] = torch.log1p(levels)[:, None, None]                    # green alone: a coloured lamp passes too
    w = highlights(x)[:, 0, 2, 2]
    expected = ((torch.log1p(levels) - PASS_FROM) / (PASS_FULL - PASS_FROM)).clamp(0, 1)
    assert torch.allclose(w, expected) and w[:2].eq(0).all() and w[3:].eq(1).all() and 0 < w[2] < 1


def _lamp_in_a_room(k=1.0):
    """LR frames (1, 2, 3, 24, 32): a room of radiance 0.2-0.8 with a 4x5 lamp of 3000, times k."""
    x = 0.2 + 0.6 * torch.rand(1, 2, 3, 24, 32, generator=torch.Generator().manual_seed(0))
    x[..., 2:6, 4:9] = 3000.0
    return k * x


def _passed(y, x, domain, e):
    """pass_highlights of y for the linear LR input x, encoded as the network sees it."""
    return pass_highlights(y, x, encode(x, domain, e), domain, e)


def test_pass_highlights_returns_a_lamp_whatever_the_network_outputs_and_passes_no_gradient_there():
    x = _lamp_in_a_room()
    e = frame_exposure(x, "exposure_pass")
    y = torch.zeros(1, 2, 3, 48, 64, requires_grad=True)           # a network that outputs black
    out = decode(_passed(y, x, "exposure_pass", e), "exposure_pass", e)
    assert torch.allclose(out[..., 5:11, 9:17], torch.tensor(3000.0), rtol=1e-4)   # bilinear: its inside
    rim = out[..., 4, 9:17].detach()                                  # bilinear: 3/4 lamp, 1/4 room
    assert rim.ge(0.75 * 3000 + 0.25 * 0.2 - 1e-3).all() and rim.le(0.75 * 3000 + 0.25 * 0.8 + 1e-3).all()
    assert out[..., :, :6].abs().max() < 1e-6 and out[..., :2, :].abs().max() < 1e-6  # the room: y's
    out.sum().backward()
    assert y.grad[..., 4:12, 8:18].eq(0).all() and y.grad[..., :, :6].gt(0).all()
    assert _passed(y, x, "exposure", e) is y                 # other domains: the network's output
    for k in (1e-4, 1e4):                                            # the blend is the exposure's: invariant
        ek = frame_exposure(k * x, "exposure_pass")
        assert torch.allclose(_passed(y, k * x, "exposure_pass", ek), _passed(y, x, "exposure_pass", e),
                              rtol=1e-5, atol=1e-5)
