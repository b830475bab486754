"""CFM denoiser (Xu et al., "Adversarial Monte Carlo Denoising with Conditioned Auxiliary Feature
Modulation", SIGGRAPH Asia 2019), adapted to SRD.

Xu et al.'s generator feeds the noisy radiance to a residual trunk and the auxiliary features (gBuffer)
to a separate condition network whose features scale and shift (gamma, beta) the trunk's features in
every residual block (conditioned feature modulation). SRD adaptation (paper Sec. 4.1): LR input, a
pixel-shuffle upsampler and tail conv at the end for 2x, no adversarial loss (all methods share the same
losses), and a trunk width (`channels`) chosen to the compute budget; the condition network keeps its
original 32 channels. `deformable_blocks` makes the second conv of the last n blocks deformable: the
paper's "CFM+deform" row (Table 4) replaces it in every block (deformable_blocks = blocks).
`input_residual` (default, as for every learned model here; not in the original) adds the bilinear
upsampling of the input radiance to the output, from a zero-initialised last conv (see SRDNet);
`linear_base` interpolates it as linear radiance (see SRDNet).
"""
import torch.nn as nn

from baselines import fold_time, gbuffer_prefix, unfold_time
from bench.hdr import transforms
from bench.nn.blocks import EDSRTrunk, RGBUpsampler
from bench.nn.cfm import ConditionNet


class CFMNet(nn.Module):
    recurrent = False

    def __init__(self, in_channels=3, gbuffer_channels=7, scale=2, channels=64, blocks=16,
                 cond_channels=32, cond_hidden=32, deformable_blocks=0, input_residual=True,
                 linear_base=None):
        super().__init__()
        if gbuffer_channels == 0:
            raise ValueError("CFM modulates features by the gBuffer: gbuffer_channels must be > 0")
        if not 0 <= deformable_blocks <= blocks:
            raise ValueError(f"deformable_blocks must be in [0, {blocks}]")
        self.gbuffer_channels, self.scale = gbuffer_channels, scale  # scale: what tiled inference allocates
        self.condition = ConditionNet(gbuffer_channels, cond_channels, cond_hidden)
        self.trunk = EDSRTrunk(in_channels, channels, blocks, deform_blocks=deformable_blocks,
                               cond_channels=cond_channels)
        self.output = RGBUpsampler(channels, scale, input_residual, transforms(linear_base))

    def forward(self, x, g):
        cond = self.condition(fold_time(gbuffer_prefix(g, self.gbuffer_channels)))
        features = self.trunk(fold_time(x), cond)
        return {"final": unfold_time(self.output(features, fold_time(x)), x.shape[0])}
