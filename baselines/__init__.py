"""Baselines adapted to SRD (paper Sec. 4.1 / Table 5) and the non-learned rows.

Learned (all follow the ARCHITECTURE.md model contract and take noisy LR radiance + LR gBuffer):
  edsr.EDSR (Lim et al. 2017), rae.RAE (Chaitanya et al. 2017), kpcn.KPCN (Bako et al. 2017),
  cfm.CFMNet (Xu et al. 2019).
Non-learned: classical.Bilinear, classical.Bicubic, oidn.OIDN.

The paper adapts denoisers by attaching a pixel-shuffle layer at the end and SR models by training them on
noisy inputs, and matches their compute (~260 GMac at 960x540) by changing channel counts only; the
width arguments here are what bench/experiments/macs.py fits.

This file also holds the two small helpers the baselines share.
"""
import torch


def fold_time(x):
    """(B, T, C, h, w) -> (B*T, C, h, w): non-recurrent models treat frames independently."""
    return x.reshape(-1, *x.shape[2:])


def unfold_time(x, batch):
    """(B*T, C, H, W) -> (B, T, C, H, W)."""
    return x.reshape(batch, -1, *x.shape[1:])


def gbuffer_prefix(g, gbuffer_channels):
    """The first gbuffer_channels channels of g (ARCHITECTURE.md: a model built with fewer gBuffer
    channels takes a prefix of albedo, normal, roughness)."""
    if g.shape[-3] < gbuffer_channels:
        raise ValueError(f"model built for {gbuffer_channels} gBuffer channels, got {g.shape[-3]}")
    return g[..., :gbuffer_channels, :, :]


def with_gbuffer(x, g, gbuffer_channels):
    """Concatenate radiance and gBuffer along channels (the classic way to feed a gBuffer)."""
    if gbuffer_channels == 0 or g is None:
        return x
    return torch.cat([x, gbuffer_prefix(g, gbuffer_channels)], dim=-3)
