"""The network domains: bench.hdr's pixelwise transforms, and `exposure`, which divides each frame by its
exposure before one of them.

- `exposure` (the default): each frame is divided by its exposure (`frame_exposure` of the LR input: the
  geometric mean luminance of its lit 8x8 blocks, as OIDN's autoexposure), then log(1 + x); the output is
  decoded and multiplied back. A frame k times brighter enters the network unchanged and leaves it k
  times brighter; there is no ceiling (log1p is unbounded); an all-black frame has exposure
  BLACK_EXPOSURE, so whatever the network adds to it is scaled to radiance ~1e-30.
- `clamp`, `log1p`, `pu`: bench.hdr, pixel by pixel, no exposure.

The exposure is computed once per frame from the LR input and shared by every image of that frame
(input, target, output): `encode(x, domain, e)` and `decode(y, domain, e)` with e = frame_exposure(x_lr,
domain). Training, evaluation and predict all go through them (bench.train.batch_loss,
bench.evaluate.predict). A separate module from bench.hdr so that adopt's replay of recorded code (which
rebuilds bench/hdr.py as it was) still finds everything today's evaluator imports.
"""
from __future__ import annotations

import torch

from bench.hdr import MODES, from_network, to_network

DOMAINS = (*MODES, "exposure")
NAMES = {"clamp": "clamp to [0, 1]", "log1p": "log1p", "pu": "PU21", "exposure": "per-frame exposure + log1p"}

EXPOSURE_BLOCK = 8                   # LR pixels per side of the blocks whose luminances are averaged
EXPOSURE_LIT = 1e-4                  # a block is lit above this fraction of the brightest block's luminance
BLACK_EXPOSURE = 1e-30               # the exposure of a frame without light
LOG_MAX = 70.0                       # largest log1p value decoded: keeps exposure * expm1(.) finite in float32


def transfer(domain: str) -> str:
    """The pixelwise transform (a bench.hdr mode) the domain applies after dividing by the exposure."""
    return "log1p" if domain == "exposure" else domain


def frame_exposure(x: torch.Tensor, domain: str) -> torch.Tensor | None:
    """Exposure of each frame of linear LR radiance x (..., C, H, W), shaped (..., 1, 1, 1) so that it
    broadcasts over that frame's LR and HR images; None for the pixelwise domains.

    The geometric mean of the luminance of the frame's lit blocks of EXPOSURE_BLOCK^2 pixels. "Lit" is
    relative to the brightest block, so exposure(k x) = k exposure(x) for every k > 0; a frame with no
    light (all blocks 0) gets BLACK_EXPOSURE."""
    if domain != "exposure":
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


def encode(x: torch.Tensor, domain: str, exposure: torch.Tensor | None) -> torch.Tensor:
    """Linear radiance -> the network domain (`exposure`: `frame_exposure` of the frame's LR input)."""
    return to_network(x if exposure is None else x / exposure, transfer(domain))


def decode(y: torch.Tensor, domain: str, exposure: torch.Tensor | None) -> torch.Tensor:
    """The network domain -> linear radiance (the inverse of `encode` with the same exposure)."""
    if exposure is None:
        return from_network(y, transfer(domain))
    return from_network(y.clamp(max=LOG_MAX), transfer(domain)) * exposure
