"""Input sanitation, the one place it happens: the trainer and the evaluator call `sanitize_inputs` on
every batch before any model (learned or not) sees it, as OIDN asks of its users.

- radiance: a NaN or +-Inf sample becomes the mean of the finite samples in its 3x3 neighbourhood (same
  channel; 0 when it has none), the rule the renderer uses (bench.render.repair_nonfinite); negative
  values become 0 (radiance is non-negative; a negative value is a reconstruction-filter artefact).
  Finite fireflies are kept: they are part of the Monte Carlo estimate.
- albedo (gBuffer channels 0-2): non-finite -> 0, clamped to [0, 1].
- normal (3-5): non-finite -> 0, normalised to unit length; a zero-length normal stays 0 (no surface).
- roughness (6): non-finite -> 0, clamped to [0, 1].
A gBuffer with fewer channels is the prefix of that layout (ARCHITECTURE.md); extra channels only get
their non-finite values zeroed.
"""
from __future__ import annotations

import torch
import torch.nn.functional as F

ALBEDO, NORMAL, ROUGHNESS = slice(0, 3), slice(3, 6), slice(6, 7)


def repair_nonfinite(x: torch.Tensor) -> torch.Tensor:
    """(..., H, W): non-finite values -> mean of the finite values of their 3x3 neighbourhood, else 0."""
    bad = ~torch.isfinite(x)
    if not torch.compiler.is_compiling() and not bad.any():  # compiled: no host sync, the same values
        return x
    shape = x.shape
    flat = x.reshape(-1, 1, *shape[-2:])
    good = (~bad).reshape(flat.shape).to(flat.dtype)
    values = torch.where(good.bool(), flat, torch.zeros_like(flat)).double()
    sums = F.avg_pool2d(values, 3, stride=1, padding=1, divisor_override=1)
    counts = F.avg_pool2d(good.double(), 3, stride=1, padding=1, divisor_override=1)
    fill = torch.where(counts > 0, sums / counts.clamp_min(1), torch.zeros_like(sums)).to(x.dtype)
    return torch.where(bad, fill.reshape(shape), x)


def sanitize_radiance(x: torch.Tensor) -> torch.Tensor:
    return repair_nonfinite(x).clamp_min(0)


def sanitize_gbuffer(g: torch.Tensor) -> torch.Tensor:
    """(..., G, H, W) with the documented channel layout."""
    g = torch.nan_to_num(g, nan=0.0, posinf=0.0, neginf=0.0)
    channels = g.shape[-3]
    parts = [g[..., ALBEDO, :, :].clamp(0, 1)]
    if channels > 3:
        n = g[..., NORMAL, :, :]
        length = n.norm(dim=-3, keepdim=True)
        parts.append(torch.where(length > 1e-12, n / length.clamp_min(1e-12), torch.zeros_like(n)))
    if channels > 6:
        parts.append(g[..., ROUGHNESS, :, :].clamp(0, 1))
    if channels > 7:
        parts.append(g[..., 7:, :, :])
    return torch.cat(parts, dim=-3)[..., :channels, :, :]


def sanitize_inputs(x: torch.Tensor, g: torch.Tensor | None):
    """(radiance, gBuffer) ready for any model; see the module docstring."""
    return sanitize_radiance(x), (None if g is None else sanitize_gbuffer(g))
