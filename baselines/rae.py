"""Recurrent denoising auto-encoder (Chaitanya et al., "Interactive Reconstruction of Monte Carlo Image
Sequences using a Recurrent Denoising Autoencoder", SIGGRAPH 2017), adapted to SRD.

Topology as in the original: a U-Net-like encoder of 5 levels, each a 3x3 conv followed by a recurrent
block (the level's features concatenated with its own hidden state from the previous frame, then two 3x3
convs; the result is the new hidden state and the skip), with 2x2 max pooling between levels and a
bottleneck conv at 1/32 resolution; a decoder with nearest-neighbour upsampling, concatenated skips and
two 3x3 convs per level; leaky ReLU (slope 0.1). Channels grow as 32, 43, 57, 76, 101 (x width/32).
SRD adaptation (paper Sec. 4.1): input is the noisy LR radiance concatenated with the LR gBuffer, and the
original final conv to RGB becomes a pixel-shuffle head (conv to 3*s^2 + pixel shuffle) for 2x; with
scale=1 it is the original final conv. Inputs are padded (replicate) to a multiple of 32 and cropped back.

Recurrent: the hidden state is zero at the start of every forward call and carried along T; streaming
inference uses init_state(x0) / step(x_t, g_t, state).
`input_residual` (default, as for every learned model here; not in the original) adds the bilinear
upsampling of the input radiance to the output, from a zero-initialised last conv (see SRDNet);
`linear_base` interpolates it as linear radiance (see SRDNet).
"""
import torch
import torch.nn as nn
import torch.nn.functional as F

from baselines import with_gbuffer
from bench.hdr import transforms
from bench.nn.blocks import PixelShuffleUp, RecurrentBlock, conv3x3, run_sequence, upsampled_input, zero_init

BASE_CHANNELS = (32, 43, 57, 76, 101)  # Chaitanya et al.'s encoder widths at width=32
LEVELS = len(BASE_CHANNELS)


def _act(x):
    return F.leaky_relu(x, 0.1)


def level_channels(width):
    """Per-level channel counts: the original growth scaled by width / 32."""
    return [max(1, round(c * width / 32)) for c in BASE_CHANNELS]


class DecoderLevel(nn.Module):
    """Nearest 2x upsampling, concat the encoder skip, two convs."""

    def __init__(self, in_ch, skip_ch, channels):
        super().__init__()
        self.conv1 = conv3x3(in_ch + skip_ch, channels)
        self.conv2 = conv3x3(channels, channels)

    def forward(self, x, skip):
        x = torch.cat([F.interpolate(x, scale_factor=2, mode="nearest"), skip], dim=1)
        return _act(self.conv2(_act(self.conv1(x))))


class RAE(nn.Module):
    recurrent = True

    def __init__(self, in_channels=3, gbuffer_channels=7, scale=2, width=32, input_residual=True,
                 linear_base=None):
        super().__init__()
        self.gbuffer_channels, self.scale = gbuffer_channels, scale
        chans = level_channels(width)
        self.channels = chans
        ins = [in_channels + gbuffer_channels] + chans[:-1]
        self.encoder = nn.ModuleList(RecurrentBlock(i, c, negative_slope=0.1) for i, c in zip(ins, chans))
        self.bottleneck = conv3x3(chans[-1], chans[-1])
        outs = chans[::-1]  # decoder level l (deepest first) outputs the channels of encoder level l
        dec_ins = [chans[-1]] + outs[:-1]
        self.decoder = nn.ModuleList(DecoderLevel(i, c, c) for i, c in zip(dec_ins, outs))
        self.head = PixelShuffleUp(chans[0], 3, scale)
        self.input_residual, self.base_domain = input_residual, transforms(linear_base)
        if input_residual:
            zero_init(self.head.conv)

    @staticmethod
    def padded_size(h, w):
        """Smallest size >= (h, w) divisible by 2^LEVELS, so every pooling level is exact."""
        m = 2 ** LEVELS
        return -(-h // m) * m, -(-w // m) * m

    def init_state(self, x0):
        """Zero hidden states for frames shaped like x0 (B, C, h, w)."""
        b, (hp, wp) = x0.shape[0], self.padded_size(*x0.shape[-2:])
        return [x0.new_zeros(b, c, hp >> l, wp >> l) for l, c in enumerate(self.channels)]

    def step(self, x_t, g_t, state):
        """One frame: x_t (B, C, h, w), g_t (B, G, h, w) -> ({"final": (B, 3, s*h, s*w)}, new state)."""
        h, w = x_t.shape[-2:]
        hp, wp = self.padded_size(h, w)
        z = F.pad(with_gbuffer(x_t, g_t, self.gbuffer_channels), (0, wp - w, 0, hp - h), mode="replicate")
        skips = []
        for level, block in enumerate(self.encoder):
            z = block(z, state[level])
            skips.append(z)
            z = F.max_pool2d(z, 2)
        z = _act(self.bottleneck(z))
        for level, skip in zip(self.decoder, reversed(skips)):
            z = level(z, skip)
        out = self.head(z)[..., : self.scale * h, : self.scale * w]
        if self.input_residual:
            out = out + upsampled_input(x_t, self.scale, self.base_domain)
        return {"final": out}, skips

    def forward(self, x, g):
        return run_sequence(self.init_state, self.step, x, g)
