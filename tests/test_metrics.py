import math

import numpy as np
import pytest
import torch
from skimage.metrics import peak_signal_noise_ratio, structural_similarity

from bench.metrics import (HIGHER_IS_BETTER, LOWER_IS_BETTER, METRICS, hdr_flip, ldr_flip, psnr, reference_error, relmse,
                           robust_relmse, ssim, temporal_relmse)


def _pair(seed, shape=(3, 40, 33)):
    g = torch.Generator().manual_seed(seed)
    ref = torch.rand(shape, generator=g, dtype=torch.float64)
    pred = (ref + 0.1 * torch.randn(shape, generator=g, dtype=torch.float64)).clamp(0, 1)
    return pred, ref


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_psnr_matches_skimage(seed):
    pred, ref = _pair(seed)
    expected = peak_signal_noise_ratio(ref.numpy(), pred.numpy(), data_range=1.0)
    assert psnr(pred, ref).item() == pytest.approx(expected, rel=1e-10)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_ssim_matches_skimage(seed):
    pred, ref = _pair(seed)
    expected = structural_similarity(ref.permute(1, 2, 0).numpy(), pred.permute(1, 2, 0).numpy(),
                                     channel_axis=2, gaussian_weights=True, sigma=1.5,
                                     use_sample_covariance=False, data_range=1.0)
    assert ssim(pred, ref).item() == pytest.approx(expected, abs=1e-9)


def test_metrics_are_per_image():
    pred, ref = _pair(0, (4, 3, 24, 24))
    assert relmse(pred, ref).shape == (4,)
    assert torch.allclose(ssim(pred, ref)[1], ssim(pred[1], ref[1]))


def test_relmse_formula_and_zero_reference():
    ref = torch.zeros(3, 8, 8, dtype=torch.float64)
    pred = torch.full_like(ref, 0.1)
    # all-zero reference: the epsilon keeps it finite: 0.01 / 0.01 = 1
    assert relmse(pred, ref).item() == pytest.approx(1.0)
    ref2 = torch.full_like(ref, 2.0)
    assert relmse(ref2 + 1, ref2).item() == pytest.approx(1 / 4.01)


def test_identical_images_give_infinite_psnr_and_unit_ssim():
    img = torch.rand(3, 16, 16)
    assert math.isinf(psnr(img, img).item()) and psnr(img, img).item() > 0
    assert ssim(img, img).item() == pytest.approx(1.0)
    const = torch.full((3, 16, 16), 0.5)
    assert np.isfinite(ssim(const, const).item())


def test_ssim_rejects_tiny_images():
    with pytest.raises(ValueError, match="larger than"):
        ssim(torch.rand(3, 8, 8), torch.rand(3, 8, 8))


@pytest.mark.parametrize("seed", [0, 1])
def test_robust_relmse_matches_a_numpy_trimmed_mean(seed):
    pred, ref = _pair(seed, shape=(3, 50, 40))
    err = ((pred.numpy() - ref.numpy()) ** 2 / (ref.numpy() ** 2 + 0.01)).mean(0).ravel()
    expected = np.sort(err)[: err.size - int(err.size * 0.001)].mean()  # 2000 pixels: the worst 2 go
    assert float(robust_relmse(pred, ref)[0]) == pytest.approx(expected, rel=1e-12)
    assert float(robust_relmse(pred, ref, discard=0.0)[0]) == pytest.approx(float(relmse(pred, ref)[0]))


def test_robust_relmse_ignores_a_firefly_that_dominates_relmse():
    ref = torch.full((1, 3, 40, 50), 0.5, dtype=torch.float64)
    pred = ref + 0.01
    firefly = pred.clone()
    firefly[..., 7, 9] = 1000.0
    assert relmse(firefly, ref) > 1000 * relmse(pred, ref)
    assert float(robust_relmse(firefly, ref)[0]) == pytest.approx(float(robust_relmse(pred, ref)[0]))


def test_temporal_relmse_scores_flicker_not_a_steady_error():
    """Two sequences with the same per-frame relMSE: an error that stays put, and one that flickers."""
    g = torch.Generator().manual_seed(0)
    t = torch.linspace(0, 1, 6).view(6, 1, 1, 1)
    ref = 0.2 + 0.5 * t * torch.rand(1, 3, 32, 32, generator=g, dtype=torch.float64)  # a changing scene
    noise = 0.05 * torch.randn(6, 3, 32, 32, generator=g, dtype=torch.float64)
    steady, flicker = ref + noise[:1], ref + noise
    assert float(relmse(steady, ref).mean()) == pytest.approx(float(relmse(flicker, ref).mean()), rel=0.1)
    steady_t, flicker_t = temporal_relmse(steady, ref), temporal_relmse(flicker, ref)
    assert math.isnan(steady_t[0]) and math.isnan(flicker_t[0])
    assert steady_t[1:].abs().max() < 1e-20
    # independent errors: the change has twice the variance of one frame's error
    assert float(flicker_t[1:].mean()) == pytest.approx(2 * float(relmse(flicker[1:], ref[1:]).mean()), rel=0.1)


@pytest.mark.parametrize("noise", [0.02, 0.1])
def test_reference_error_estimates_the_mean_of_two_halves_against_the_truth(noise):
    """Two independent noisy halves of a known image: the estimate from the halves alone matches the
    relMSE of their mean against the truth (which a real reference never knows)."""
    gen = torch.Generator().manual_seed(0)
    truth = 0.05 + 3 * torch.rand(2, 3, 256, 256, generator=gen, dtype=torch.float64)
    a = truth + noise * truth * torch.randn(truth.shape, generator=gen, dtype=torch.float64)
    b = truth + noise * truth * torch.randn(truth.shape, generator=gen, dtype=torch.float64)
    estimate, actual = reference_error(a, b), relmse((a + b) / 2, truth)
    torch.testing.assert_close(estimate, actual, rtol=0.05, atol=0)
    assert (reference_error(truth, truth) == 0).all()


# ---------------------------------------------------------------- FLIP

def _flip_fixture():
    """A reference with a highlight of 50 and a prediction that halves it and adds noise elsewhere."""
    gen = torch.Generator().manual_seed(3)
    ref = torch.rand(2, 3, 40, 56, generator=gen) ** 2
    ref[:, :, 10:14, 20:26] = 50.0
    pred = (ref + 0.05 * torch.randn(ref.shape, generator=gen)).clamp_min(0)
    pred[:, :, 10:14, 20:26] = 25.0
    return pred, ref


def test_flip_equals_flip_evaluators_own_api_on_each_image():
    """The suite's LDR- and HDR-FLIP against flip_evaluator.evaluate called directly on (H, W, C) arrays:
    the same layout, clamping and dynamic range, image by image."""
    import flip_evaluator
    pred, ref = _flip_fixture()
    ldr, hdr = ldr_flip(pred, ref), hdr_flip(pred, ref)
    for i in range(2):
        p, r = (t[i].permute(1, 2, 0).numpy() for t in (pred, ref))
        assert ldr[i].item() == pytest.approx(flip_evaluator.evaluate(
            r.clip(0, 1), p.clip(0, 1), "LDR", inputsRGB=False, applyMagma=False)[1], rel=1e-6)
        assert hdr[i].item() == pytest.approx(flip_evaluator.evaluate(
            r, p, "HDR", inputsRGB=False, applyMagma=False)[1], rel=1e-6)
    assert ldr_flip(ref, ref).tolist() == [0.0, 0.0] and hdr_flip(ref, ref).tolist() == [0.0, 0.0]


def test_hdr_flip_sees_a_highlight_that_ldr_metrics_cannot():
    """Halving a highlight of 50 moves nothing in [0, 1] (PSNR, SSIM, LDR-FLIP unchanged) and raises HDR-FLIP."""
    pred, ref = _flip_fixture()
    intact = pred.clone()
    intact[:, :, 10:14, 20:26] = 50.0
    assert psnr(pred, ref).tolist() == psnr(intact, ref).tolist()
    assert ldr_flip(pred, ref).tolist() == pytest.approx(ldr_flip(intact, ref).tolist())
    assert (hdr_flip(pred, ref) > hdr_flip(intact, ref) + 1e-3).all()


def test_every_metric_is_in_the_evaluators_scores_with_its_direction():
    assert {"LDR-FLIP", "HDR-FLIP"} <= set(METRICS)
    assert set(METRICS) | {"temporal relMSE"} == set(LOWER_IS_BETTER) | set(HIGHER_IS_BETTER)
