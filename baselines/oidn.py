"""Intel Open Image Denoise (OIDN 2, via pyoidn) as a non-learned SRD row, with albedo and normal.

OIDN is a pretrained denoiser, not a super-resolver, so we give it the two obvious ways to produce the
2x output:
  - 'lr_then_up': denoise at LR with the LR albedo/normal, then bilinear-upscale the result;
  - 'up_then_hr': bilinear-upscale the noisy input and the gBuffer, then denoise at HR.
With scale=1 (denoise-only task) both are plain OIDN.

OIDN's filters are trained on LINEAR HDR radiance (hdr=True), so this class takes and returns linear
radiance: the trainer/evaluator must hand it linear values, not the network-domain (log/PU) transform
the learned models see, and must not apply the inverse transform to its output. The class attribute
`linear_hdr = True` marks this. Quality 'high' by default; runs on the CPU (pyoidn's default device);
not differentiable and has no parameters, so the trainer skips it.

gBuffer layout (ARCHITECTURE.md): albedo RGB, normal XYZ in [-1, 1], roughness. OIDN uses albedo when
gbuffer_channels >= 3 and normal when >= 6 (OIDN accepts a normal only together with an albedo);
roughness is not an OIDN input. Normals upscaled bilinearly are not renormalized (OIDN does not need
unit normals).
"""
import numpy as np
import pyoidn
import torch
import torch.nn as nn

from bench.nn.blocks import bilinear

VARIANTS = ("lr_then_up", "up_then_hr")


def _hwc(x):
    """(3, H, W) tensor -> contiguous float32 (H, W, 3) NumPy array for pyoidn."""
    return np.ascontiguousarray(x.detach().float().permute(1, 2, 0).cpu().numpy())


class OIDN(nn.Module):
    """OIDN 'RT' filter with albedo + normal, applied frame by frame (it has no temporal model)."""

    recurrent = False
    linear_hdr = True  # takes and returns linear HDR radiance, see the module docstring

    def __init__(self, in_channels=3, gbuffer_channels=7, scale=2, variant="lr_then_up",
                 quality="high", clean_aux=False):
        super().__init__()
        if in_channels != 3:
            raise ValueError("OIDN denoises RGB radiance: in_channels must be 3")
        if variant not in VARIANTS:
            raise ValueError(f"variant must be one of {VARIANTS}, got {variant!r}")
        self.scale, self.variant, self.quality = scale, variant, quality
        self.use_albedo = gbuffer_channels >= 3
        self.use_normal = gbuffer_channels >= 6
        # cleanAux=True tells OIDN the aux images are noise-free and skips its prefiltering; our
        # gBuffers are averaged over the pixel's samples, so we leave it to OIDN by default.
        self.clean_aux = clean_aux

    def denoise_frame(self, x, g):
        """Denoise one frame: x (3, H, W) linear radiance, g (C, H, W) gBuffer at the same size."""
        albedo = _hwc(g[0:3].clamp(0, 1)) if self.use_albedo else None
        normal = _hwc(g[3:6].clamp(-1, 1)) if self.use_normal else None
        out = pyoidn.denoise(_hwc(x.clamp_min(0)), albedo, normal, hdr=True, clean_aux=self.clean_aux,
                             quality=self.quality)
        return torch.from_numpy(out).permute(2, 0, 1).to(x.dtype)

    @torch.no_grad()
    def forward(self, x, g):
        b, t, c, h, w = x.shape
        frames = x.reshape(b * t, c, h, w)
        gbuf = g.reshape(b * t, g.shape[2], h, w)
        if self.variant == "up_then_hr":
            frames, gbuf = bilinear(frames, self.scale), bilinear(gbuf, self.scale)
        out = torch.stack([self.denoise_frame(f, gb) for f, gb in zip(frames.cpu(), gbuf.cpu())])
        if self.variant == "lr_then_up":
            out = bilinear(out, self.scale)
        return {"final": out.to(x.device).reshape(b, t, 3, self.scale * h, self.scale * w)}
