"""Residual blocks and pixel-shuffle upsampling shared by the proposed network and the baselines."""
import torch
import torch.nn as nn
import torch.nn.functional as F

from .cfm import CFM
from .deform import DeformConv2d


def conv3x3(in_ch, out_ch, dilation=1, bias=True):
    """3x3 conv that keeps the spatial size (padding = dilation)."""
    return nn.Conv2d(in_ch, out_ch, 3, padding=dilation, dilation=dilation, bias=bias)


class ResBlock(nn.Module):
    """EDSR residual block: conv1 -> [CFM] -> ReLU -> conv2 -> [CFM] -> x + res_scale * y.

    conv2 is atrous when dilation > 1 (the receptive-field study, paper Table 2) and deformable when
    deformable=True (a "deformable CFM block", paper Sec. 3.3); conv1 is always a plain 3x3.
    CFM layers exist iff cond_channels > 0; `cond` is then the conditioning features at x's size.
    """

    def __init__(self, channels, dilation=1, deformable=False, cond_channels=0, res_scale=1.0):
        super().__init__()
        self.conv1 = conv3x3(channels, channels)
        if deformable:
            self.conv2 = DeformConv2d(channels, channels, 3, padding=dilation, dilation=dilation)
        else:
            self.conv2 = conv3x3(channels, channels, dilation=dilation)
        self.cfm1 = CFM(channels, cond_channels) if cond_channels > 0 else None
        self.cfm2 = CFM(channels, cond_channels) if cond_channels > 0 else None
        self.act = nn.ReLU(inplace=True)
        self.res_scale = res_scale

    def forward(self, x, cond=None):
        y = self.conv1(x)
        y = self.cfm1(y, cond, relu=True) if self.cfm1 is not None else self.act(y)
        y = self.conv2(y)
        if self.cfm2 is not None:
            y = self.cfm2(y, cond)
        return x + self.res_scale * y


def upsampled_input(x, scale):
    """Bilinear upsampling of the radiance (first 3 channels) of x (B, C, h, w) by `scale`: the base that
    a model with `input_residual` adds its output to. It is the "Input bilinear" row of the tables, so
    such a model starts as that row and learns a correction (VDSR-style global residual learning)."""
    x = x[:, :3]
    if scale == 1:
        return x
    return F.interpolate(x, scale_factor=scale, mode="bilinear", align_corners=False)


def zero_init(conv):
    """Zero a conv's weight and bias, so a residual branch ending in it starts as the identity."""
    nn.init.zeros_(conv.weight)
    if conv.bias is not None:
        nn.init.zeros_(conv.bias)
    return conv


class PixelShuffleUp(nn.Module):
    """Sub-pixel upsampling (Shi et al. 2016): conv3x3 to out_ch*scale^2 channels, then PixelShuffle."""

    def __init__(self, in_ch, out_ch, scale=2):
        super().__init__()
        self.conv = conv3x3(in_ch, out_ch * scale * scale)
        self.shuffle = nn.PixelShuffle(scale)

    def forward(self, x):
        return self.shuffle(self.conv(x))


class RecurrentBlock(nn.Module):
    """An encoder level of the recurrent auto-encoder (Chaitanya et al. 2017):
    act(conv_in(x)) [+ skip] -> concat with the previous hidden state -> conv -> act -> conv -> act.
    The output is both the new hidden state and the level's skip to the decoder.
    `negative_slope` 0.1 is RAE's leaky ReLU; 0 is a plain ReLU (the proposed network)."""

    def __init__(self, in_ch, channels, negative_slope=0.0):
        super().__init__()
        self.conv_in = conv3x3(in_ch, channels)
        self.conv_rec = conv3x3(2 * channels, channels)
        self.conv_out = conv3x3(channels, channels)
        self.negative_slope = negative_slope

    def forward(self, x, hidden, skip=None):
        y = F.leaky_relu(self.conv_in(x), self.negative_slope)
        if skip is not None:
            y = y + skip
        # the state in y's dtype: a zero state made from a float32 input would turn the concat (and
        # under bf16 autocast, a copy back for the conv) into float32 at the level's full size
        y = F.leaky_relu(self.conv_rec(torch.cat((y, hidden.to(y.dtype)), dim=1)), self.negative_slope)
        return F.leaky_relu(self.conv_out(y), self.negative_slope)
