"""Tests for bench.losses against independent NumPy/SciPy computations and the paper's numbers."""
import functools
import math
import re

import numpy as np
import pytest
import scipy.ndimage
import torch
from skimage.metrics import structural_similarity

from bench.losses import (HFEN_KERNEL_SIZE, HFEN_SIGMA, PAPER_WEIGHTS, absolute_weights, hfen,
                          laplacian_of_gaussian, perceptual, relmse_loss, separable_filter, soft_knee,
                          spatial_l1, ssim_loss, temporal_l1, weighted_loss)
from conftest import PAPER_TEXT



def _scipy_log(img, sigma=1.5):
    """SciPy LoG with the same 15x15 support (radius 7) and replicate ('nearest') borders."""
    return scipy.ndimage.gaussian_laplace(img, sigma, mode="nearest", truncate=7 / sigma)


def test_hfen_matches_scipy_gaussian_laplace():
    rng = np.random.default_rng(0)
    pred, target = rng.random((2, 3, 3, 21, 17)), rng.random((2, 3, 3, 21, 17))  # (B, T, C, H, W)
    ref = np.mean([np.abs(_scipy_log(p) - _scipy_log(t)).mean()
                   for p, t in zip(pred.reshape(-1, 21, 17), target.reshape(-1, 21, 17))])
    out = hfen(torch.from_numpy(pred), torch.from_numpy(target))
    assert abs(out.item() - ref) < 1e-12 * max(1.0, ref)
    assert HFEN_SIGMA == 1.5 and HFEN_KERNEL_SIZE == 15


def test_log_interior_matches_explicit_2d_kernel():
    """Away from borders, the separable filter equals a correlation with the explicit 15x15 kernel
    built from scipy.ndimage's 1D Gaussian derivative weights."""
    import scipy.signal  # here, not at collection: 1 s of every pytest-xdist worker's start, for two tests
    impulse = np.zeros((15, 15))
    impulse[7, 7] = 1
    kernel = _scipy_log(impulse)  # impulse response = the 2D LoG kernel (symmetric)
    assert abs(kernel.sum()) < 1e-3  # a Laplacian kernel integrates to ~0
    img = np.random.default_rng(1).random((30, 28))
    ref = scipy.signal.correlate2d(img, kernel, mode="valid")
    out = laplacian_of_gaussian(torch.from_numpy(img)[None, None])[0, 0, 7:-7, 7:-7].numpy()
    np.testing.assert_allclose(out, ref, atol=1e-12)


def test_separable_filter_and_its_gradient_match_scipy_valid_correlation():
    """The banded-matrix filter (used for speed on training crops) is a valid 2D correlation with
    ky (rows) x kx (columns), different lengths and a non-square plane included; its gradient is the
    adjoint, a full convolution with the same kernel (checked through SciPy too)."""
    import scipy.signal
    rng = np.random.default_rng(2)
    planes, ky, kx = rng.random((3, 20, 13)), rng.random(7), rng.random(5)
    kernel = np.outer(ky, kx)
    x = torch.from_numpy(planes).requires_grad_()
    out = separable_filter(x, torch.from_numpy(ky), torch.from_numpy(kx))
    ref = np.stack([scipy.signal.correlate2d(p, kernel, mode="valid") for p in planes])
    np.testing.assert_allclose(out.detach().numpy(), ref, atol=1e-12)
    upstream = rng.random(ref.shape)
    out.backward(torch.from_numpy(upstream))
    grad_ref = np.stack([scipy.signal.convolve2d(u, kernel, mode="full") for u in upstream])
    np.testing.assert_allclose(x.grad.numpy(), grad_ref, atol=1e-12)


def test_spatial_and_temporal_l1():
    rng = np.random.default_rng(2)
    p, t = rng.random((2, 4, 3, 5, 6)), rng.random((2, 4, 3, 5, 6))
    assert spatial_l1(torch.from_numpy(p), torch.from_numpy(t)).item() == pytest.approx(np.abs(p - t).mean())
    ref = np.abs(np.diff(p, axis=1) - np.diff(t, axis=1)).mean()
    assert temporal_l1(torch.from_numpy(p), torch.from_numpy(t)).item() == pytest.approx(ref)
    assert temporal_l1(torch.from_numpy(p[:, :1]), torch.from_numpy(t[:, :1])).item() == 0
    with pytest.raises(ValueError, match=r"needs \(B, T, C, H, W\) tensors"):
        temporal_l1(torch.from_numpy(p[0]), torch.from_numpy(t[0]))


def test_perceptual_is_mean_squared_feature_difference():
    torch.manual_seed(0)
    conv = torch.nn.Conv2d(3, 5, 3, stride=2)
    pred = torch.rand(2, 2, 3, 9, 9, requires_grad=True)
    target = torch.rand(2, 2, 3, 9, 9)
    out = perceptual(pred, target, conv)
    fp, ft = conv(pred.reshape(4, 3, 9, 9)), conv(target.reshape(4, 3, 9, 9))
    c, h, w = fp.shape[1:]
    ref = sum(((fp[i] - ft[i]) ** 2).sum() / (c * h * w) for i in range(4)) / 4
    torch.testing.assert_close(out, ref)
    out.backward()
    assert pred.grad.abs().sum() > 0


def test_paper_weights():
    assert PAPER_WEIGHTS["intermediate"] == {"edge": 1, "temporal": 1, "spatial": 8, "perceptual": 0}
    assert PAPER_WEIGHTS["final"] == {"edge": 1, "temporal": 1, "spatial": 8, "perceptual": 10}
    # Chaitanya et al. 2017 use 0.1 / 0.1 / 0.8 for edge / temporal / spatial
    assert absolute_weights(PAPER_WEIGHTS["final"]) == pytest.approx(
        {"edge": 0.1, "temporal": 0.1, "spatial": 0.8, "perceptual": 1.0})
    # what the trainer uses: the root config's loss is the paper's (presets and rows change it from there)
    from omegaconf import OmegaConf
    from conftest import REPO
    assert OmegaConf.to_container(OmegaConf.load(REPO / "conf" / "config.yaml").train.loss) == PAPER_WEIGHTS


def test_paper_weights_against_paper_text():
    if not PAPER_TEXT.is_file():
        pytest.skip(f"the paper's text is not at {PAPER_TEXT} (set SRD_PAPER_TEXT to its path)")
    text = PAPER_TEXT.read_text(encoding="utf-8")
    # "For the intermediate supervision, the ratio is set as $1:1:8:0$ ... final ... $1:1:8:10$"
    ratios = re.findall(r"ratio is (?:empirically )?set as \$([\d:]+)\$", text)
    assert len(ratios) == 2
    assert "w_g L_g+w_t L_t+w_s L_s+w_p L_p" in text  # order of the ratios: g : t : s : p
    for key, ratio in zip(("intermediate", "final"), ratios):
        g, t, s, p = (int(v) for v in ratio.split(":"))
        assert PAPER_WEIGHTS[key] == {"edge": g, "temporal": t, "spatial": s, "perceptual": p}


def test_weighted_loss_combines_terms():
    torch.manual_seed(1)
    pred, target = torch.rand(1, 3, 3, 10, 10, requires_grad=True), torch.rand(1, 3, 3, 10, 10)
    feats = torch.nn.Conv2d(3, 4, 3)
    total, parts = weighted_loss(pred, target, PAPER_WEIGHTS["final"], features=feats)
    expected = (0.1 * hfen(pred, target) + 0.1 * temporal_l1(pred, target) + 0.8 * spatial_l1(pred, target)
                + 1.0 * perceptual(pred, target, feats))
    torch.testing.assert_close(total, expected)
    assert set(parts) == {"edge", "temporal", "spatial", "perceptual"}
    total.backward()
    assert pred.grad.abs().sum() > 0

    total, parts = weighted_loss(pred, target, PAPER_WEIGHTS["intermediate"])  # perceptual weight 0
    assert set(parts) == {"edge", "temporal", "spatial"}
    total4, parts4 = weighted_loss(pred[0], target[0], PAPER_WEIGHTS["intermediate"])  # (N, C, H, W)
    assert set(parts4) == {"edge", "spatial"}
    with pytest.raises(ValueError):
        weighted_loss(pred, target, PAPER_WEIGHTS["final"])  # perceptual needs features


def test_ssim_loss_matches_scikit_image_without_clamping():
    """1 - SSIM against scikit-image's Wang et al. SSIM (Gaussian window, sigma 1.5, no sample-covariance
    correction) per image and channel, on values up to 3 (the loss does not clamp, the metric does)."""
    rng = np.random.default_rng(2)
    pred = rng.random((2, 2, 3, 23, 19)) * 3          # (B, T, C, H, W)
    target = np.clip(pred + rng.normal(0, 0.3, pred.shape), 0, None)
    ref = np.mean([
        structural_similarity(p, t, gaussian_weights=True, sigma=1.5, use_sample_covariance=False,
                              data_range=1.0, channel_axis=0, full=True)[1][:, 5:-5, 5:-5].mean()
        for p, t in zip(pred.reshape(-1, 3, 23, 19), target.reshape(-1, 3, 23, 19))])
    out = ssim_loss(torch.from_numpy(pred), torch.from_numpy(target))
    assert abs(out.item() - (1 - ref)) < 1e-10
    assert ssim_loss(torch.from_numpy(target), torch.from_numpy(target)).item() == pytest.approx(0, abs=1e-12)
    with pytest.raises(ValueError, match="11x11"):
        ssim_loss(torch.zeros(1, 3, 10, 30), torch.zeros(1, 3, 10, 30))


def test_ssim_term_is_off_unless_named_and_weighted_on_the_l1_scale():
    torch.manual_seed(3)
    pred, target = torch.rand(1, 3, 3, 16, 16, requires_grad=True), torch.rand(1, 3, 3, 16, 16)
    weights = {"edge": 1, "temporal": 1, "spatial": 8, "perceptual": 0}
    assert "ssim" not in weighted_loss(pred, target, weights)[1]
    total, parts = weighted_loss(pred, target, {**weights, "ssim": 42})
    expected = (0.1 * hfen(pred, target) + 0.1 * temporal_l1(pred, target) + 0.8 * spatial_l1(pred, target)
                + 4.2 * ssim_loss(pred, target))
    torch.testing.assert_close(total, expected)
    total.backward()
    assert torch.isfinite(pred.grad).all() and pred.grad.abs().sum() > 0
    with pytest.raises(ValueError, match="unknown loss terms"):
        weighted_loss(pred, target, {**weights, "msssim": 1})


def test_relmse_term_is_the_relmse_metric_on_linear_radiance_and_learns_the_mean():
    """`relmse` maps network-domain values back to linear radiance and takes the relMSE metric's
    formula there (checked against NumPy); over draws of a sparse, skewed radiance (60% zeros) the
    constant that minimises it is near their mean (weighted by 1 / (r^2 + eps)), where L1's minimiser is
    their median, zero."""
    from bench.hdr import from_network, to_network
    rng = np.random.default_rng(6)
    lin_target = rng.random((1, 2, 3, 8, 8)) * 2
    lin_pred = np.clip(lin_target + rng.normal(0, 0.2, lin_target.shape), 0, None)
    to_linear = functools.partial(from_network, mode="pu")
    pred = to_network(torch.from_numpy(lin_pred), "pu").requires_grad_()
    target = to_network(torch.from_numpy(lin_target), "pu")
    parts = weighted_loss(pred, target, {"spatial": 1, "relmse": 8}, to_linear=to_linear)[1]
    p, t = to_linear(pred).detach().numpy(), to_linear(target).numpy()
    assert abs(parts["relmse"].item() - ((p - t) ** 2 / (t ** 2 + 0.01)).mean()) < 1e-12
    parts["relmse"].backward()
    assert torch.isfinite(pred.grad).all() and pred.grad.abs().sum() > 0
    with pytest.raises(ValueError, match="relmse weight needs a `to_linear`"):
        weighted_loss(pred, target, {"spatial": 1, "relmse": 8})
    draws = torch.from_numpy(0.05 * rng.random(1000) * (rng.random(1000) > 0.6))     # dark, sparse
    constants = torch.linspace(0, 0.05, 501)
    rel = torch.stack([relmse_loss(c.expand_as(draws), draws) for c in constants])
    l1 = torch.stack([spatial_l1(c.expand_as(draws), draws) for c in constants])
    weights = 1 / (draws ** 2 + 0.01)                      # its minimiser: the mean weighted by 1 / (r^2 + eps)
    assert abs(constants[rel.argmin()] - (weights * draws).sum() / weights.sum()) <= 1e-4
    assert constants[rel.argmin()] > 0.9 * draws.mean() and constants[l1.argmin()] == 0


def test_soft_knee_is_the_identity_below_the_knee_and_log1p_above_it():
    """bench.losses.soft_knee: x up to the knee; knee + log1p(x - knee) above (checked against NumPy), so
    continuous with slope 1 at the knee and slope 1 / (1 + x - knee) beyond."""
    x = torch.linspace(-1.0, 12.0, 1301, dtype=torch.float64, requires_grad=True)
    out = soft_knee(x, 2.0)
    v = x.detach().numpy()
    np.testing.assert_allclose(out.detach().numpy(), np.where(v > 2.0, 2.0 + np.log1p(np.clip(v - 2.0, 0, None)), v),
                               rtol=0, atol=1e-12)
    out.sum().backward()
    np.testing.assert_allclose(x.grad.numpy(), np.where(v > 2.0, 1 / (1 + np.clip(v - 2.0, 0, None)), 1.0), rtol=1e-12)
    assert soft_knee(torch.tensor([10.3], dtype=torch.float64), 2.0).item() == pytest.approx(2 + math.log1p(8.3))


def test_the_loss_knee_compresses_what_every_term_but_relmse_sees():
    """weighted_loss(knee=k): every term is that of soft_knee(pred), soft_knee(target), except `relmse`,
    which decodes the values as given; without a knee nothing changes, and with a knee above every value
    neither does the total."""
    from bench.hdr import from_network
    torch.manual_seed(4)
    pred, target = torch.rand(1, 3, 3, 16, 16) * 6, torch.rand(1, 3, 3, 16, 16) * 6
    weights = {"edge": 1, "temporal": 1, "spatial": 8, "perceptual": 0, "ssim": 8, "relmse": 1}
    to_linear = functools.partial(from_network, mode="log1p")
    kneed, kneed_parts = weighted_loss(pred, target, weights, to_linear=to_linear, knee=2.0)
    seen, seen_parts = weighted_loss(soft_knee(pred, 2.0), soft_knee(target, 2.0), weights, to_linear=to_linear)
    plain, plain_parts = weighted_loss(pred, target, weights, to_linear=to_linear)
    for name in ("edge", "temporal", "spatial", "ssim"):
        torch.testing.assert_close(kneed_parts[name], seen_parts[name])
    assert kneed_parts["spatial"] < plain_parts["spatial"]    # 1-Lipschitz: values above 2 differ less
    torch.testing.assert_close(kneed_parts["relmse"], plain_parts["relmse"])
    # without a knee every term sees pred and target as given, and the total is the weighted sum of them
    as_given = {"spatial": spatial_l1(pred, target), "edge": hfen(pred, target),
                "temporal": temporal_l1(pred, target), "ssim": ssim_loss(pred, target),
                "relmse": relmse_loss(to_linear(pred), to_linear(target))}
    for name, value in as_given.items():
        torch.testing.assert_close(plain_parts[name], value)
    torch.testing.assert_close(plain, sum(w * as_given[n] for n, w in absolute_weights(weights).items() if w))
    torch.testing.assert_close(weighted_loss(pred, target, weights, to_linear=to_linear, knee=7.0)[0], plain)
