"""The network domains: bench.hdr's pixelwise transforms, and `exposure`, which divides each frame by its
exposure before one of them.

- `exposure`: each frame is divided by its exposure (`frame_exposure` of the LR input: the
  geometric mean luminance of its lit 8x8 blocks, as OIDN's autoexposure), then log(1 + x); the output is
  decoded and multiplied back. A frame k times brighter enters the network unchanged and leaves it k
  times brighter; there is no ceiling (log1p is unbounded); an all-black frame has exposure
  BLACK_EXPOSURE, so whatever the network adds to it is scaled to radiance ~1e-30.
- `exposure_pass` (the default: `train.hdr` in conf/config.yaml): `exposure`, and where the input is far brighter than its
  frame's exposure over a region, the output there is the input upsampled (`pass_highlights`). A lamp or a
  window seen directly is noise-free and lies far outside what a network learns from the renders: one
  trained without lamps returned a radiance-3000 lamp 14-29% too bright (KPCN 45% too dark), and one trained
  with lamps pasted in lost 0.24-0.39 of val PSNR everywhere else (docs/studies.md, emitters).
- `clamp`, `log1p`, `pu`: bench.hdr, pixel by pixel, no exposure.

The exposure is computed once per frame from the LR input and shared by every image of that frame
(input, target, output): `encode(x, domain, e)` and `decode(y, domain, e)` with e = frame_exposure(x_lr,
domain). Training, evaluation and predict all go through them (bench.train.batch_loss,
bench.evaluate.predict). A separate module from bench.hdr so that adopt's replay of recorded code (which
rebuilds bench/hdr.py as it was) still finds everything today's evaluator imports.
"""
from __future__ import annotations

import math

import torch
import torch.nn.functional as F

from bench.hdr import MODES, from_network, to_network

EXPOSURE_DOMAINS = ("exposure", "exposure_pass")
DOMAINS = (*MODES, *EXPOSURE_DOMAINS)
NAMES = {"clamp": "clamp to [0, 1]", "log1p": "log1p", "pu": "PU21", "exposure": "per-frame exposure + log1p",
         "exposure_pass": "per-frame exposure + log1p, highlights passed through"}

EXPOSURE_BLOCK = 8                   # LR pixels per side of the blocks whose luminances are averaged
EXPOSURE_LIT = 1e-4                  # a block is lit above this fraction of the brightest block's luminance
BLACK_EXPOSURE = 1e-30               # the exposure of a frame without light
LOG_MAX = 70.0                       # largest log1p value decoded: keeps exposure * expm1(.) finite in float32
# `exposure_pass`: the input passes where all of a 3x3 block is above 30x the frame's exposure, fully from
# 100x (the stability cases' lamps are 1e2x and 1e4x). The cpu renders' LR pixels passed in part / whole:
# val 0.57% / 0, test 0.25% / 0.05% (scripts/lamp_cost_probe.py passed).
PASS_FROM, PASS_FULL = math.log1p(30.0), math.log1p(100.0)   # in the network domain


def transfer(domain: str) -> str:
    """The pixelwise transform (a bench.hdr mode) the domain applies after dividing by the exposure."""
    return "log1p" if domain in EXPOSURE_DOMAINS else domain


def frame_exposure(x: torch.Tensor, domain: str) -> torch.Tensor | None:
    """Exposure of each frame of linear LR radiance x (..., C, H, W), shaped (..., 1, 1, 1) so that it
    broadcasts over that frame's LR and HR images; None for the pixelwise domains.

    The geometric mean of the luminance of the frame's lit blocks of EXPOSURE_BLOCK^2 pixels. "Lit" is
    relative to the brightest block, so exposure(k x) = k exposure(x) for every k > 0; a frame with no
    light (all blocks 0) gets BLACK_EXPOSURE."""
    if domain not in EXPOSURE_DOMAINS:
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


def highlights(x_net: torch.Tensor) -> torch.Tensor:
    """The weight in [0, 1] with which `pass_highlights` takes the input, per pixel of the network-domain LR
    input (N, C, h, w) -> (N, 1, h, w): the brightest channel after a grey opening over 3x3 pixels (a
    region the block fits in keeps its level to its rim; a firefly, or a cluster narrower than 3 pixels,
    drops to its surroundings), from 0 at PASS_FROM to 1 at PASS_FULL."""
    brightest = x_net[:, :3].amax(1, keepdim=True)
    opened = F.max_pool2d(-F.max_pool2d(-brightest, 3, 1, 1), 3, 1, 1)
    return ((opened - PASS_FROM) / (PASS_FULL - PASS_FROM)).clamp(0.0, 1.0)


def pass_highlights(y: torch.Tensor, x: torch.Tensor, x_net: torch.Tensor, domain: str,
                    exposure: torch.Tensor | None) -> torch.Tensor:
    """The network's output y (B, T, 3, H, W, network domain) of the LR input x (B, T, C, h, w; linear, and
    x_net as the network saw it), as the domain finishes it: for `exposure_pass`, blended towards the input's
    bilinear upsampling (taken on linear radiance, then encoded) by `highlights` of x_net, nearest-upsampled;
    unchanged for every other domain. Training's loss and evaluation both see the blend, so no gradient
    reaches the network where it passes."""
    if domain != "exposure_pass":
        return y
    rgb = x[..., :3, :, :].flatten(0, 1)
    size = y.shape[-2:]
    weight = F.interpolate(highlights(x_net.flatten(0, 1)), size=size)
    upsampled = F.interpolate(rgb, size=size, mode="bilinear", align_corners=False).unflatten(0, x.shape[:2])
    passed = encode(upsampled, domain, exposure)
    return torch.lerp(y, passed.to(y.dtype), weight.unflatten(0, x.shape[:2]).to(y.dtype))
