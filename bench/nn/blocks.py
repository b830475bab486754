"""Residual blocks, the EDSR trunk, pixel-shuffle upsampling and the frame-by-frame recurrence shared by
the proposed network and the baselines."""
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


class EDSRTrunk(nn.Module):
    """EDSR's feature trunk (Lim et al. 2017): head conv, residual blocks, body conv, and a global skip
    from the head: returns head + body_conv(blocks(head)), where head = head_conv(x) [+ skip].

    The last `deform_blocks` blocks have a deformable conv2; `dilation`, `cond_channels` and `res_scale`
    are the ResBlock's. Used by EDSR, CFM and the proposed network's SR stage."""

    def __init__(self, in_ch, channels, blocks, dilation=1, deform_blocks=0, cond_channels=0, res_scale=1.0):
        super().__init__()
        self.head = conv3x3(in_ch, channels)
        self.body = nn.ModuleList(
            ResBlock(channels, dilation=dilation, deformable=i >= blocks - deform_blocks,
                     cond_channels=cond_channels, res_scale=res_scale) for i in range(blocks))
        self.body_conv = conv3x3(channels, channels)

    def forward(self, x, cond=None, skip=None):
        head = self.head(x)
        if skip is not None:
            head = head + skip
        y = head
        for block in self.body:
            y = block(y, cond)
        return head + self.body_conv(y)


def upsampled_input(x, scale, domain=None):
    """Bilinear upsampling of the radiance (first 3 channels) of x (B, C, h, w) by `scale`: the base that
    a model with `input_residual` adds its output to, so such a model starts near the "Input bilinear"
    row and learns a correction (VDSR-style global residual learning). x is in the network domain; with
    `domain`, that domain's (to_linear, from_linear) pair (bench.hdr.transforms), it is interpolated as
    linear radiance, which makes the base exactly that row. Interpolating PU21 values instead loses the
    mean where samples are sparse: on a dark val scene whose LR pixels are 60% zeros, about 35%."""
    if domain is None:
        return bilinear(x[:, :3], scale)
    to_linear, from_linear = domain
    return from_linear(bilinear(to_linear(x[:, :3]), scale))


def bilinear(x, scale):
    """(N, C, h, w) -> (N, C, scale*h, scale*w), bilinear with align_corners=False (x itself at scale 1):
    the one bilinear upsampling of images and gBuffers."""
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


class RGBUpsampler(nn.Module):
    """EDSR's output: PixelShuffleUp, then a tail conv to RGB; with `input_residual` the bilinear
    upsampling of the input radiance is added and the tail starts at zero (see upsampled_input)."""

    def __init__(self, channels, scale, input_residual=True, domain=None):
        super().__init__()
        self.up = PixelShuffleUp(channels, channels, scale)
        self.tail = conv3x3(channels, 3)
        self.scale, self.input_residual, self.domain = scale, input_residual, domain
        if input_residual:
            zero_init(self.tail)

    def forward(self, features, x):
        """features (N, channels, h, w), x (N, C, h, w) the network input -> (N, 3, scale*h, scale*w)."""
        out = self.tail(self.up(features))
        return out + upsampled_input(x, self.scale, self.domain) if self.input_residual else out


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


def run_sequence(init_state, step, x, g):
    """Run a streaming model over a sequence: x (B, T, C, h, w), g (B, T, G, h, w) or None. step(x_t, g_t,
    state) -> (dict of outputs, state) is applied frame by frame from init_state(x[:, 0]); each output
    key is stacked along T. The one recurrence of the recurrent models (RAE, SRDNet)."""
    state = init_state(x[:, 0])
    outs = []
    for t in range(x.shape[1]):
        out_t, state = step(x[:, t], g[:, t] if g is not None else None, state)
        outs.append(out_t)
    return {k: torch.stack([o[k] for o in outs], dim=1) for k in outs[0]}
