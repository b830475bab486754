"""Training losses of the paper (Sec. 3.5): spatial L1, HFEN edge loss, temporal L1, perceptual loss;
and two the paper does not use, off unless a recipe names them: `ssim`, an SSIM term (1 - SSIM) in the
network domain (the cpu preset's, evidence: docs/studies.md), and `relmse`, relative MSE on linear
radiance (the relMSE metric), an L2 term that learns the mean (only the dark_bias study uses it:
conf/study/dark_bias.yaml).

Pure functions on tensors shaped (B, T, C, H, W) or (N, C, H, W). This module imports no network:
the perceptual loss takes the feature extractor as a `features` callable (e.g. bench.nn.VGG16Features).

Weights. The paper gives ratios g:t:s:p = 1:1:8:0 (intermediate head) and 1:1:8:10 (final output).
They become absolute weights by dividing every ratio by g + t + s, so 1:1:8 is exactly Chaitanya et
al.'s 0.1 / 0.1 / 0.8 and the perceptual weight is measured on that scale (10 -> 1.0). The SSIM
ratio is on the same scale: 42 next to 1:1:8 puts 1 - SSIM at 0.84 / 0.16 times the L1 weight, the
L1 : MS-SSIM mix that OIDN trains with (Zhao et al. 2017).
"""
import torch
import torch.nn.functional as F

PAPER_WEIGHTS = {
    "intermediate": {"edge": 1, "temporal": 1, "spatial": 8, "perceptual": 0},
    "final": {"edge": 1, "temporal": 1, "spatial": 8, "perceptual": 10},
}

# HFEN (Ravishankar & Bresler 2011, used by Chaitanya et al. 2017): a 15x15 Laplacian-of-Gaussian
# kernel with sigma 1.5, i.e. radius 7 (about 4.7 sigma).
HFEN_SIGMA = 1.5
HFEN_KERNEL_SIZE = 15
# SSIM (Wang et al. 2004): an 11x11 Gaussian window with sigma 1.5, K1 = 0.01, K2 = 0.03 for data range
# 1: the SSIM metric's definition (bench.metrics.ssim), and scikit-image's, which the tests check it against.
SSIM_SIGMA = 1.5
SSIM_WINDOW = 11
SSIM_C1, SSIM_C2 = 0.01 ** 2, 0.03 ** 2
# relMSE (Rousselle et al. 2011): (x - r)^2 / (r^2 + eps), eps = 0.01 as the relMSE metric (bench.metrics;
# not imported from there: losses sit on the bottom floor, which imports nothing of the project's).
RELMSE_EPS = 0.01


def _as_images(x):
    """Fold (B, T, C, H, W) into (B*T, C, H, W); pass (N, C, H, W) through."""
    if x.dim() == 5:
        return x.flatten(0, 1)
    if x.dim() == 4:
        return x
    raise ValueError(f"expected a (B, T, C, H, W) or (N, C, H, W) tensor, got shape {tuple(x.shape)}")


def spatial_l1(pred, target):
    """Mean absolute error over all elements."""
    return (pred - target).abs().mean()


def _gaussian_kernels_1d(sigma, size, dtype, device):
    """Sampled 1D Gaussian (normalized to sum 1) and its second derivative, both of length `size`."""
    radius = size // 2
    x = torch.arange(-radius, radius + 1, dtype=torch.float64)
    g0 = torch.exp(-0.5 * x ** 2 / sigma ** 2)
    g0 = g0 / g0.sum()
    g2 = g0 * (x ** 2 / sigma ** 4 - 1 / sigma ** 2)  # d^2/dx^2 of the Gaussian, same normalization
    return g0.to(dtype=dtype, device=device), g2.to(dtype=dtype, device=device)


def _band(kernel, n):
    """(n, n - k + 1) matrix M with M[i + j, i] = kernel[j]: x @ M is x's valid correlation with kernel
    along its last axis."""
    out = n - kernel.numel() + 1
    m = kernel.new_zeros(n, out)
    cols = torch.arange(out, device=kernel.device)
    for j, tap in enumerate(kernel):
        m[cols + j, cols] = tap
    return m


def separable_filter(planes, ky, kx):
    """Valid 2D correlation of (N, H, W) planes with the kernel ky (rows) x kx (columns).

    As two matrix products with banded matrices, not conv2d: on the training crops (64-128 px) a
    one-channel conv2d's backward ran at a fraction of a GEMM's speed, and these filters took half of a
    training step with the SSIM term (forward and backward 28x faster this way, AVX512 EPYC). The cost
    per pixel grows with the image's side, so this is for crops, not whole frames (bench.metrics)."""
    n, h, w = planes.shape
    return _band(ky, h).t() @ (planes @ _band(kx, w))


def laplacian_of_gaussian(x, sigma=HFEN_SIGMA, size=HFEN_KERNEL_SIZE):
    """Per-channel LoG filter of (N, C, H, W) images, same size, replicate ("nearest") borders.

    The 2D kernel g2(y) g0(x) + g0(y) g2(x) is applied as two separable passes (4 x 15 taps instead
    of 225); it equals scipy.ndimage.gaussian_laplace(sigma, truncate=7/1.5, mode="nearest").
    """
    n, c, h, w = x.shape
    radius = size // 2
    g0, g2 = _gaussian_kernels_1d(sigma, size, x.dtype, x.device)
    planes = F.pad(x.reshape(n * c, 1, h, w), (radius,) * 4, mode="replicate").view(n * c, h + 2 * radius, -1)
    out = separable_filter(planes, g2, g0) + separable_filter(planes, g0, g2)
    return out.view(n, c, h, w)


def hfen(pred, target, sigma=HFEN_SIGMA):
    """Edge loss: mean |LoG(pred) - LoG(target)| (HFEN with an L1 norm, as Chaitanya et al. 2017).

    LoG is linear, so it is applied once to the difference.
    """
    diff = _as_images(pred - target)
    return laplacian_of_gaussian(diff, sigma).abs().mean()


def temporal_l1(pred, target):
    """Mean |d pred/dt - d target/dt| with frame-to-frame differences along T of (B, T, C, H, W).

    Zero (still differentiable) when T == 1: a single frame has no temporal change to match.
    """
    if pred.dim() != 5:
        raise ValueError(f"temporal_l1 needs (B, T, C, H, W) tensors, got shape {tuple(pred.shape)}")
    if pred.shape[1] < 2:
        return (pred - target).sum() * 0
    dpred = pred[:, 1:] - pred[:, :-1]
    dtarget = target[:, 1:] - target[:, :-1]
    return (dpred - dtarget).abs().mean()


def ssim_loss(pred, target):
    """1 - mean SSIM over the valid (un-padded) region, per channel, of (B, T, C, H, W) or (N, C, H, W).

    Unlike the metric it does not clamp: it is computed in whatever domain the trainer hands it (the
    network domain, where a value of 1 is radiance 1), so highlights keep their gradient.
    """
    p, t = _as_images(pred), _as_images(target)
    n, c, h, w = p.shape
    if h < SSIM_WINDOW or w < SSIM_WINDOW:
        raise ValueError(f"the SSIM loss needs crops of at least {SSIM_WINDOW}x{SSIM_WINDOW} px, got {h}x{w}")
    g0, _ = _gaussian_kernels_1d(SSIM_SIGMA, SSIM_WINDOW, p.dtype, p.device)
    # the five blurred maps in one batched separable filter
    planes = separable_filter(torch.stack([p, t, p * p, t * t, p * t]).reshape(5 * n * c, h, w), g0, g0)
    mu_p, mu_t, pp, tt, pt = planes.view(5, n * c, *planes.shape[-2:])
    var_p, var_t, cov = pp - mu_p ** 2, tt - mu_t ** 2, pt - mu_p * mu_t
    s = ((2 * mu_p * mu_t + SSIM_C1) * (2 * cov + SSIM_C2)) / (
        (mu_p ** 2 + mu_t ** 2 + SSIM_C1) * (var_p + var_t + SSIM_C2))
    return 1 - s.mean()


def relmse_loss(pred, target):
    """Mean of (pred - target)^2 / (target^2 + 0.01) over all elements: the relMSE metric without its
    float64, in whatever domain it is handed (linear radiance for the trainer's `relmse` term). Being
    an L2 loss it learns the mean where the input leaves the radiance uncertain; L1 learns the median,
    below the mean where radiance is sparse and skewed (a dark scene's few lit samples)."""
    return ((pred - target) ** 2 / (target ** 2 + RELMSE_EPS)).mean()


def perceptual(pred, target, features):
    """Mean over elements of (features(pred) - features(target))^2, i.e. ||phi(y^) - phi(y)||^2 / (C H W)
    averaged over the batch. `features` maps (N, 3, H, W) to (N, C, H', W')."""
    pred, target = _as_images(pred), _as_images(target)
    with torch.set_grad_enabled(torch.is_grad_enabled() and target.requires_grad):
        target_features = features(target)
    return (features(pred) - target_features).pow(2).mean()


def soft_knee(x, knee):
    """x up to `knee`, knee + log1p(x - knee) above it: continuous, slope 1 at the knee, 1 / (1 + x - knee)
    beyond. What the losses see with `train.loss_knee` (the network domain's values above it compressed
    again), so that a lamp pasted into a training item (2.4-10.3 in the exposure domain, a room about 0.7)
    pulls the fit less per pixel; the minimum of every term stays at pred == target."""
    return torch.where(x > knee, knee + torch.log1p((x - knee).clamp_min(0)), x)


def absolute_weights(weights):
    """Ratios {edge, temporal, spatial, perceptual[, ssim, relmse]} -> absolute weights, normalized by
    edge+temporal+spatial."""
    norm = weights.get("edge", 0) + weights.get("temporal", 0) + weights.get("spatial", 0)
    if norm <= 0:
        raise ValueError(f"edge + temporal + spatial ratios must be positive, got {weights}")
    unknown = set(weights) - {"edge", "temporal", "spatial", "perceptual", "ssim", "relmse"}
    if unknown:
        raise ValueError(f"unknown loss terms {sorted(unknown)}")
    return {name: ratio / norm for name, ratio in weights.items()}


def weighted_loss(pred, target, weights, features=None, to_linear=None, knee=None):
    """Weighted sum of the loss terms named in `weights` (ratios, see absolute_weights).

    Returns (total, parts): parts maps each term with a nonzero weight to its UNweighted value, so
    total = sum(absolute_weight[name] * parts[name]). Terms with weight 0 are not computed.
    The temporal term needs (B, T, ...) input with T >= 2; on (N, C, H, W) input it is skipped.
    `to_linear` maps the network domain back to linear radiance, for `relmse`. With `knee`, every term but
    `relmse` (which is on linear radiance) sees soft_knee(pred) and soft_knee(target).
    """
    seen = (pred, target) if knee is None else (soft_knee(pred, knee), soft_knee(target, knee))
    terms = {"spatial": spatial_l1, "edge": hfen, "temporal": temporal_l1, "ssim": ssim_loss,
             "perceptual": lambda p, t: perceptual(p, t, features),
             "relmse": lambda p, t: relmse_loss(to_linear(p), to_linear(t))}
    if weights.get("perceptual", 0) and features is None:
        raise ValueError("a nonzero perceptual weight needs a `features` callable")
    if weights.get("relmse", 0) and to_linear is None:
        raise ValueError("a nonzero relmse weight needs a `to_linear` callable")
    total, parts = pred.new_zeros(()), {}
    for name, weight in absolute_weights(weights).items():
        if weight == 0 or (name == "temporal" and pred.dim() != 5):
            continue
        parts[name] = terms[name](*((pred, target) if name == "relmse" else seen))
        total = total + weight * parts[name]
    return total, parts
