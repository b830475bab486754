"""Non-learned upsampling rows: bilinear and bicubic interpolation of the noisy LR input.

The paper's Table 5 lists "Input Bilinear" (resize the noisy 540p input to 1080p) as the floor every
learned method must beat. Both classes follow the model contract of ARCHITECTURE.md (call with x, g;
return {"final": ...}), ignore the gBuffer and have no parameters, so the trainer skips them. They run
on linear HDR radiance (`linear_hdr`: the evaluator hands them the linear input, never a clamped or
tone-mapped one), so the rows score interpolation itself, highlights included.
"""
import torch.nn as nn
import torch.nn.functional as F

from baselines import fold_time


class _Interpolate(nn.Module):
    """Upsample x by `scale` with F.interpolate(mode, align_corners=False); T is folded into the batch."""

    recurrent = False
    linear_hdr = True
    mode = "bilinear"

    def __init__(self, in_channels=3, gbuffer_channels=7, scale=2):
        super().__init__()
        if in_channels != 3:
            raise ValueError(f"{type(self).__name__} upsamples the RGB radiance itself: in_channels must be 3")
        self.scale = scale

    def upsample(self, x):
        """(N, 3, h, w) -> (N, 3, scale*h, scale*w)."""
        if self.scale == 1:
            return x
        return F.interpolate(x, scale_factor=self.scale, mode=self.mode, align_corners=False)

    def forward(self, x, g=None):
        b, t = x.shape[:2]
        out = self.upsample(fold_time(x))
        return {"final": out.reshape(b, t, *out.shape[1:])}


class Bilinear(_Interpolate):
    """Bilinear upsampling of the noisy input (the paper's "Input Bilinear" row)."""

    mode = "bilinear"


class Bicubic(_Interpolate):
    """Bicubic upsampling (a = -0.75, torch's kernel) of the noisy input.

    The cubic kernel has negative lobes, so next to bright edges it rings below zero; radiance cannot be
    negative, so the result is clamped at 0 (the only difference from plain F.interpolate).
    """

    mode = "bicubic"

    def upsample(self, x):
        return super().upsample(x).clamp_min(0)
