"""Conditioned feature modulation (CFM, Xu et al. 2019) and the gBuffer conditioning network.

CFM modulates features with a per-pixel affine transform predicted from auxiliary (gBuffer) features:
    CFM(x, cond) = x * (1 + gamma(cond)) + beta(cond)
Xu et al. write x * gamma + beta; predicting 1 + gamma with zero-initialized 1x1 convs makes a fresh
module the identity, so adding CFM does not perturb the He-initialized backbone at the start.
"""
import torch.nn as nn


class CFM(nn.Module):
    """x * (1 + gamma(cond)) + beta(cond); gamma and beta are 1x1 convs of the conditioning features."""

    def __init__(self, channels, cond_channels):
        super().__init__()
        self.gamma = nn.Conv2d(cond_channels, channels, 1)
        self.beta = nn.Conv2d(cond_channels, channels, 1)
        for conv in (self.gamma, self.beta):
            nn.init.zeros_(conv.weight)
            nn.init.zeros_(conv.bias)

    def forward(self, x, cond):
        return x * (1 + self.gamma(cond)) + self.beta(cond)


class ConditionNet(nn.Module):
    """Maps the raw gBuffer (B, G, H, W) to conditioning features (B, cond_channels, H, W).

    Two 3x3 convs with ReLU: a small shared encoder, evaluated once per stage and reused by all the
    CFM layers of that stage (each CFM only adds its own 1x1 gamma/beta convs).
    """

    def __init__(self, gbuffer_channels, cond_channels=32, hidden=32):
        super().__init__()
        self.body = nn.Sequential(
            nn.Conv2d(gbuffer_channels, hidden, 3, padding=1), nn.ReLU(inplace=True),
            nn.Conv2d(hidden, cond_channels, 3, padding=1), nn.ReLU(inplace=True),
        )

    def forward(self, g):
        return self.body(g)
