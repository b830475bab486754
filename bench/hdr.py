"""HDR transforms between linear radiance and the network domain, each with its inverse.

Only the trainer and evaluator apply them (models see network-domain values; metrics see linear ones).

- `clamp`: clip to [0, 1] (the paper normalises its images to [0, 1]); inverse is the identity on [0, 1].
- `log1p`: log(1 + x), x >= 0; inverse expm1. Keeps highlights instead of clipping them.
- `pu`: PU21 (Mantiuk et al. 2021, "banding+glare" fit) applied per channel to x * 100 cd/m^2
  (radiance 1.0 displays at 100 cd/m^2), divided by its value at radiance 1.0 so that 1.0 maps to 1.0.
  Valid for radiance in [5e-5, 100] (the fit's 0.005..10000 cd/m^2); values outside are clipped.
- `exposure`: per-frame exposure normalisation, then log(1 + x): each frame is divided by its exposure
  (`frame_exposure` of the LR input: the geometric mean luminance of its lit 8x8 blocks, as OIDN's
  autoexposure), so that a frame k times brighter enters the network unchanged and leaves it k times
  brighter; the output is multiplied back. No ceiling (log1p is unbounded) and no floor: an all-black
  frame has exposure `BLACK_EXPOSURE`, so whatever the network adds to it is scaled to radiance ~1e-30.

The first three are functions of each pixel. `exposure` needs the frame's exposure, computed once from
the LR input and applied to every image of that frame (input, target, output): `to_network(x, mode, e)`
with `e = frame_exposure(x_lr, mode)` (None for the pixelwise modes).
"""
from __future__ import annotations

import functools

import torch

_PU = (0.353487901, 0.3734658629, 8.277049286e-05, 0.9062562627, 0.09150303166, 0.9099517204, 596.3148142)
_PU_SCALE = 100.0                     # cd/m^2 for radiance 1.0
_PU_RANGE = (0.005, 10000.0)          # cd/m^2


def _pu21(y: torch.Tensor) -> torch.Tensor:
    p1, p2, p3, p4, p5, p6, p7 = _PU
    yp = y ** p4
    return p7 * (((p1 + p2 * yp) / (1 + p3 * yp)) ** p5 - p6)


def _pu21_inverse(v: torch.Tensor) -> torch.Tensor:
    p1, p2, p3, p4, p5, p6, p7 = _PU
    q = (v / p7 + p6).clamp_min(0) ** (1 / p5)
    return ((q - p1).clamp_min(0) / (p2 - p3 * q)) ** (1 / p4)


_PU_ONE = float(_pu21(torch.tensor(_PU_SCALE, dtype=torch.float64)))
_PU_ZERO = float(_pu21(torch.tensor(_PU_RANGE[0], dtype=torch.float64)))
_PU_TOP = float(_pu21(torch.tensor(_PU_RANGE[1], dtype=torch.float64)))

MODES = ("clamp", "log1p", "pu", "exposure")
NAMES = {"clamp": "clamp to [0, 1]", "log1p": "log1p", "pu": "PU21", "exposure": "per-frame exposure + log1p"}
EXPOSED = ("exposure",)              # the modes that need a frame's exposure

EXPOSURE_BLOCK = 8                   # LR pixels per side of the blocks whose luminances are averaged
EXPOSURE_LIT = 1e-4                  # a block is lit above this fraction of the brightest block's luminance
BLACK_EXPOSURE = 1e-30               # the exposure of a frame without light
_LOG_MAX = 70.0                      # largest log1p value inverted: keeps s * expm1(.) finite in float32


def frame_exposure(x: torch.Tensor, mode: str) -> torch.Tensor | None:
    """Exposure of each frame of linear LR radiance x (..., C, H, W), shaped (..., 1, 1, 1) so that it
    broadcasts over that frame's LR and HR images; None for the pixelwise modes.

    The geometric mean of the luminance of the frame's lit blocks of EXPOSURE_BLOCK^2 pixels. "Lit" is
    relative to the brightest block, so exposure(k x) = k exposure(x) for every k > 0; a frame with no
    light (all blocks 0) gets BLACK_EXPOSURE."""
    if mode not in EXPOSED:
        return None
    lead, (h, w) = x.shape[:-3], x.shape[-2:]
    rgb = x.reshape(-1, *x.shape[-3:])[:, :3].float().clamp_min(0.0)
    luminance = (0.2126 * rgb[:, 0] + 0.7152 * rgb[:, 1] + 0.0722 * rgb[:, 2]).unsqueeze(1)
    grid = (max(1, h // EXPOSURE_BLOCK), max(1, w // EXPOSURE_BLOCK))
    blocks = torch.nn.functional.adaptive_avg_pool2d(luminance, grid).flatten(1)
    brightest = blocks.amax(1, keepdim=True)
    lit = blocks > EXPOSURE_LIT * brightest
    log_mean = torch.where(lit, blocks.clamp_min(torch.finfo(blocks.dtype).tiny).log(), 0.0).sum(1) \
        / lit.sum(1).clamp_min(1)
    exposure = torch.where(brightest[:, 0] > 0, log_mean.exp(), torch.full_like(log_mean, BLACK_EXPOSURE))
    return exposure.to(x.dtype).reshape(*lead, 1, 1, 1)


def _exposure_of(exposure: torch.Tensor | None, mode: str) -> torch.Tensor:
    if exposure is None:
        raise ValueError(f"HDR transform {mode!r} needs the frame's exposure: bench.hdr.frame_exposure(x_lr, mode)")
    return exposure


def to_network(x: torch.Tensor, mode: str = "clamp", exposure: torch.Tensor | None = None) -> torch.Tensor:
    """Linear radiance -> network domain (`exposure`: the frame's, for the modes in EXPOSED)."""
    if mode == "clamp":
        return x.clamp(0.0, 1.0)
    if mode == "log1p":
        return torch.log1p(x.clamp_min(0.0))
    if mode == "exposure":
        return torch.log1p(x.clamp_min(0.0) / _exposure_of(exposure, mode))
    if mode == "pu":
        y = (x * _PU_SCALE).clamp(*_PU_RANGE)
        return (_pu21(y) - _PU_ZERO) / (_PU_ONE - _PU_ZERO)
    raise ValueError(f"unknown HDR transform {mode!r}; choose one of {MODES}")


def transforms(mode: str | None):
    """(to linear, from linear) callables of a network domain, for layers that must not import this
    module (bench.nn.upsampled_input); None for None. For `exposure` they map to and from radiance
    divided by the frame's exposure, which is linear too (an interpolation of it is the interpolation of
    the radiance, scaled)."""
    if mode is None:
        return None
    if mode not in MODES:
        raise ValueError(f"unknown HDR transform {mode!r}; choose one of {MODES}")
    if mode in EXPOSED:
        return (functools.partial(from_network, mode=mode, exposure=1.0),
                functools.partial(to_network, mode=mode, exposure=1.0))
    return functools.partial(from_network, mode=mode), functools.partial(to_network, mode=mode)


def from_network(y: torch.Tensor, mode: str = "clamp", exposure: torch.Tensor | None = None) -> torch.Tensor:
    """Network domain -> linear radiance (the inverse of `to_network` on its valid range)."""
    if mode == "clamp":
        return y.clamp(0.0, 1.0)
    if mode == "log1p":
        return torch.expm1(y.clamp_min(0.0))
    if mode == "exposure":
        return torch.expm1(y.clamp(0.0, _LOG_MAX)) * _exposure_of(exposure, mode)
    if mode == "pu":
        # clip to the fit's range first: far above it the inverse has a pole (NaN), not a saturation
        v = (y * (_PU_ONE - _PU_ZERO) + _PU_ZERO).clamp(_PU_ZERO, _PU_TOP)
        return _pu21_inverse(v) / _PU_SCALE
    raise ValueError(f"unknown HDR transform {mode!r}; choose one of {MODES}")
