"""Image metrics as pure functions on tensors of shape (N, C, H, W); each returns one value per image.

- relMSE (Rousselle et al. 2011) on linear HDR radiance:
  mean over pixels and channels of (x - r)^2 / (r^2 + eps), eps = 0.01.
- PSNR and SSIM on images normalised to [0, 1] (clamped), as the paper reports them.
  SSIM is Wang et al. 2004: 11x11 Gaussian window (sigma 1.5), K1 = 0.01, K2 = 0.03, per channel, averaged
  over the valid (un-padded) region; it equals scikit-image's
  `structural_similarity(..., gaussian_weights=True, sigma=1.5, use_sample_covariance=False, data_range=1)`.
"""
from __future__ import annotations

import math

import torch
import torch.nn.functional as F

RELMSE_EPS = 0.01
RELMSE_FORMULA = "relMSE = mean over pixels and channels of (x-r)^2/(r^2+0.01) on linear HDR"


def _as_batch(x: torch.Tensor) -> torch.Tensor:
    return x.unsqueeze(0) if x.dim() == 3 else x


def relmse(pred: torch.Tensor, ref: torch.Tensor, eps: float = RELMSE_EPS) -> torch.Tensor:
    pred, ref = _as_batch(pred).double(), _as_batch(ref).double()
    return ((pred - ref) ** 2 / (ref ** 2 + eps)).flatten(1).mean(1)


def mse(pred: torch.Tensor, ref: torch.Tensor) -> torch.Tensor:
    pred, ref = _as_batch(pred).double(), _as_batch(ref).double()
    return ((pred - ref) ** 2).flatten(1).mean(1)


def psnr(pred: torch.Tensor, ref: torch.Tensor, data_range: float = 1.0) -> torch.Tensor:
    """PSNR in dB of clamp(pred, 0, 1) vs clamp(ref, 0, 1); identical images give +inf (not NaN)."""
    pred, ref = _as_batch(pred).double().clamp(0, data_range), _as_batch(ref).double().clamp(0, data_range)
    err = ((pred - ref) ** 2).flatten(1).mean(1)
    with torch.no_grad():
        out = 10 * torch.log10(data_range ** 2 / err)
    return torch.where(err == 0, torch.full_like(err, math.inf), out)


def _gaussian_window(sigma: float = 1.5, truncate: float = 3.5) -> torch.Tensor:
    radius = int(truncate * sigma + 0.5)
    x = torch.arange(-radius, radius + 1, dtype=torch.float64)
    w = torch.exp(-0.5 * (x / sigma) ** 2)
    return w / w.sum()


def ssim(pred: torch.Tensor, ref: torch.Tensor, data_range: float = 1.0) -> torch.Tensor:
    """Mean SSIM per image of clamp(pred, 0, 1) vs clamp(ref, 0, 1) (see module docstring)."""
    pred, ref = _as_batch(pred).double().clamp(0, data_range), _as_batch(ref).double().clamp(0, data_range)
    n, c, h, w = pred.shape
    win = _gaussian_window()
    r = win.numel() // 2
    if h <= 2 * r or w <= 2 * r:
        raise ValueError(f"SSIM needs images larger than {2 * r + 1}x{2 * r + 1} pixels, got {h}x{w}")

    def blur(img):  # separable valid convolution: the border pixels scikit-image crops are never computed
        img = img.reshape(n * c, 1, *img.shape[-2:])
        img = F.conv2d(img, win.view(1, 1, 1, -1))
        img = F.conv2d(img, win.view(1, 1, -1, 1))
        return img.reshape(n, c, *img.shape[-2:])

    c1, c2 = (0.01 * data_range) ** 2, (0.03 * data_range) ** 2
    mu_x, mu_y = blur(pred), blur(ref)
    var_x = blur(pred * pred) - mu_x ** 2
    var_y = blur(ref * ref) - mu_y ** 2
    cov = blur(pred * ref) - mu_x * mu_y
    s = ((2 * mu_x * mu_y + c1) * (2 * cov + c2)) / ((mu_x ** 2 + mu_y ** 2 + c1) * (var_x + var_y + c2))
    return s.flatten(1).mean(1)


METRICS = {"relMSE": relmse, "PSNR": psnr, "SSIM": ssim}
LOWER_IS_BETTER = ("relMSE",)
HIGHER_IS_BETTER = ("PSNR", "SSIM")


def all_metrics(pred: torch.Tensor, ref: torch.Tensor) -> dict[str, torch.Tensor]:
    """relMSE on the linear values given; PSNR/SSIM on them clamped to [0, 1]."""
    return {name: fn(pred, ref) for name, fn in METRICS.items()}
