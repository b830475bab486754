"""Image metrics as pure functions on tensors of shape (N, C, H, W); each returns one value per image.

- relMSE (Rousselle et al. 2011) on linear HDR radiance:
  mean over pixels and channels of (x - r)^2 / (r^2 + eps), eps = 0.01.
- robust relMSE: relMSE without the 0.1% of pixels with the highest error (per-pixel error averaged over
  channels), so a few fireflies do not decide a ranking; the outlier rejection of SimpleImageIO's
  `RelMSE_OutlierRejection` (Grittmann, used with the SeeSharp renderer's papers), whose default also
  discards 0.1% of the pixels.
- temporal relMSE (sequences): relMSE of the frame-to-frame change, ((x_t - x_t-1) - (r_t - r_t-1))^2 /
  (r_t^2 + eps). An error that stays put from frame to frame scores 0; an error that changes (flicker,
  popping, a recurrent state that drifts) scores its change. The first frame of a sequence has none.
- reference error: the relMSE a reference made of two independent half-sample renders is expected to
  have against the converged image, estimated from the halves (`reference_error`).
- PSNR and SSIM on images normalised to [0, 1] (clamped), as the paper reports them.
  SSIM is Wang et al. 2004: 11x11 Gaussian window (sigma 1.5), K1 = 0.01, K2 = 0.03, per channel, averaged
  over the valid (un-padded) region; it equals scikit-image's
  `structural_similarity(..., gaussian_weights=True, sigma=1.5, use_sample_covariance=False, data_range=1)`.
- FLIP (Andersson et al. 2020, 2021), NVIDIA's perceptual error of an image against its reference, through
  `flip-evaluator` at its defaults (67 pixels per degree): the mean of the per-pixel FLIP map, in [0, 1].
  LDR-FLIP scores the images PSNR/SSIM see (clamped to [0, 1], taken as linear RGB: inputsRGB=False);
  HDR-FLIP scores linear radiance (negatives set to 0) tone-mapped (ACES) at the exposures FLIP derives
  from the reference, so highlights above 1 count.
"""
from __future__ import annotations

import math

import torch
import torch.nn.functional as F

RELMSE_EPS = 0.01
ROBUST_DISCARD = 0.001   # fraction of pixels robust relMSE leaves out (the highest errors)
RELMSE_FORMULA = "relMSE = mean over pixels and channels of (x-r)^2/(r^2+0.01) on linear HDR"


def _as_batch(x: torch.Tensor) -> torch.Tensor:
    return x.unsqueeze(0) if x.dim() == 3 else x


def relmse(pred: torch.Tensor, ref: torch.Tensor, eps: float = RELMSE_EPS) -> torch.Tensor:
    pred, ref = _as_batch(pred).double(), _as_batch(ref).double()
    return ((pred - ref) ** 2 / (ref ** 2 + eps)).flatten(1).mean(1)


def robust_relmse(pred: torch.Tensor, ref: torch.Tensor, eps: float = RELMSE_EPS,
                  discard: float = ROBUST_DISCARD) -> torch.Tensor:
    """relMSE over all but the `discard` fraction of pixels with the highest (channel-mean) error."""
    pred, ref = _as_batch(pred).double(), _as_batch(ref).double()
    per_pixel = ((pred - ref) ** 2 / (ref ** 2 + eps)).mean(1).flatten(1)
    keep = per_pixel.shape[1] - int(per_pixel.shape[1] * discard)
    return per_pixel.sort(1).values[:, :keep].mean(1)


def temporal_relmse(pred: torch.Tensor, ref: torch.Tensor, eps: float = RELMSE_EPS) -> torch.Tensor:
    """Per frame of a sequence (T, C, H, W): relMSE of the change since the previous frame against the
    reference's change; NaN for the first frame (nothing to compare with)."""
    pred, ref = pred.double(), ref.double()
    change = (pred[1:] - pred[:-1]) - (ref[1:] - ref[:-1])
    scores = (change ** 2 / (ref[1:] ** 2 + eps)).flatten(1).mean(1)
    return torch.cat([torch.full((1,), math.nan, dtype=scores.dtype), scores])


def reference_error(half_a: torch.Tensor, half_b: torch.Tensor, eps: float = RELMSE_EPS) -> torch.Tensor:
    """Estimated relMSE of a reference rendered as the mean of two independent half-sample renders,
    against the converged image: the halves differ by 2 var(half) in expectation and their mean errs
    by var(half) / 2, so a quarter of their squared difference, normalised as relMSE is (by the mean)."""
    a, b = _as_batch(half_a).double(), _as_batch(half_b).double()
    mean = (a + b) / 2
    return ((a - b) ** 2 / (mean ** 2 + eps)).flatten(1).mean(1) / 4


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


def _flip(pred: torch.Tensor, ref: torch.Tensor, dynamic_range: str) -> torch.Tensor:
    import flip_evaluator  # only where images are scored (its import is not free)
    pred, ref = _as_batch(pred).float(), _as_batch(ref).float()
    means = [flip_evaluator.evaluate(r.permute(1, 2, 0).contiguous().numpy(), p.permute(1, 2, 0).contiguous().numpy(),
                                     dynamic_range, inputsRGB=False, applyMagma=False)[1]
             for p, r in zip(pred.cpu(), ref.cpu())]
    return torch.tensor(means, dtype=torch.float64)


def ldr_flip(pred: torch.Tensor, ref: torch.Tensor) -> torch.Tensor:
    """Mean LDR-FLIP per image of clamp(pred, 0, 1) against clamp(ref, 0, 1) (see module docstring)."""
    return _flip(_as_batch(pred).clamp(0, 1), _as_batch(ref).clamp(0, 1), "LDR")


def hdr_flip(pred: torch.Tensor, ref: torch.Tensor) -> torch.Tensor:
    """Mean HDR-FLIP per image of linear radiance pred against ref (see module docstring)."""
    return _flip(_as_batch(pred).clamp_min(0), _as_batch(ref).clamp_min(0), "HDR")


METRICS = {"relMSE": relmse, "PSNR": psnr, "SSIM": ssim, "LDR-FLIP": ldr_flip, "HDR-FLIP": hdr_flip,
           "robust relMSE": robust_relmse}
SEQUENCE_METRICS = {"temporal relMSE": temporal_relmse}
LOWER_IS_BETTER = ("relMSE", "robust relMSE", "temporal relMSE", "LDR-FLIP", "HDR-FLIP")
HIGHER_IS_BETTER = ("PSNR", "SSIM")


def all_metrics(pred: torch.Tensor, ref: torch.Tensor, names=None) -> dict[str, torch.Tensor]:
    """Per frame of a sequence (T, C, H, W): relMSEs and HDR-FLIP on the linear values given, PSNR/SSIM and
    LDR-FLIP on them clamped to [0, 1], and the temporal relMSE (NaN for the first frame); `names`: only
    these (None: every one)."""
    return {name: fn(pred, ref) for name, fn in {**METRICS, **SEQUENCE_METRICS}.items()
            if names is None or name in names}
