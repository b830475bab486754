"""EDSR (Lim et al., "Enhanced Deep Residual Networks for Single Image Super-Resolution", CVPRW 2017),
adapted to SRD.

Topology as in EDSR: head conv, `blocks` residual blocks without batch norm (scaled by res_scale), a body
conv with a global skip from the head, an upsampler (conv to C*s^2 + pixel shuffle) and a tail conv to RGB.
SRD adaptation (paper Sec. 4.1): the input is the noisy LR radiance concatenated with the LR gBuffer and
the network is trained against the clean HR reference; width (`channels`) is chosen to the compute budget.
scale=1 (denoise-only task) keeps the upsampler conv but has no pixel shuffle, so the topology and the
receptive field stay the same.

`dilation` makes the second conv of every block atrous (paper Sec. 4.2, Table 2: with 4 blocks the
receptive field is 25/33/41/57 input pixels for rates 1/2/3/5, i.e. 9 + blocks * (2 + 2 * rate): the
output of one LR pixel, its scale x scale HR block, depends on that many LR pixels per axis, at scale 1
and 2 alike) without changing parameters or MACs.
`deformable` replaces that second conv with a deformable conv.
`input_residual` (default, as for every learned model here; not in the original) adds the bilinear
upsampling of the input radiance to the output, from a zero-initialised last conv (see SRDNet);
`linear_base` interpolates it as linear radiance (see SRDNet).
"""
import torch.nn as nn

from baselines import fold_time, unfold_time, with_gbuffer
from bench.hdr import transforms
from bench.nn.blocks import EDSRTrunk, RGBUpsampler



class EDSR(nn.Module):
    recurrent = False

    def __init__(self, in_channels=3, gbuffer_channels=7, scale=2, channels=64, blocks=16, dilation=1,
                 deformable=False, res_scale=1.0, input_residual=True, linear_base=None):
        super().__init__()
        self.gbuffer_channels, self.scale = gbuffer_channels, scale  # scale: what tiled inference allocates
        self.trunk = EDSRTrunk(in_channels + gbuffer_channels, channels, blocks, dilation=dilation,
                               deform_blocks=blocks if deformable else 0, res_scale=res_scale)
        self.output = RGBUpsampler(channels, scale, input_residual, transforms(linear_base))

    def forward(self, x, g):
        features = self.trunk(fold_time(with_gbuffer(x, g, self.gbuffer_channels)))
        return {"final": unfold_time(self.output(features, fold_time(x)), x.shape[0])}
