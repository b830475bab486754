import math

import numpy as np
import pytest
import torch
from skimage.metrics import peak_signal_noise_ratio, structural_similarity

from bench.metrics import psnr, relmse, ssim


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
    a, b = _pair(0, (4, 3, 24, 24)), None
    pred, ref = a
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
