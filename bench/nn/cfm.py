"""Conditioned feature modulation (CFM, Xu et al. 2019) and the gBuffer conditioning network.

CFM modulates features with a per-pixel affine transform predicted from auxiliary (gBuffer) features:
    CFM(x, cond) = x * (1 + gamma(cond)) + beta(cond)
Xu et al. write x * gamma + beta; predicting 1 + gamma with zero-initialized 1x1 convs makes a fresh
module the identity, so adding CFM does not perturb the He-initialized backbone at the start.

The blocks here follow CFM by ReLU, so CFM takes `relu=True` to apply it in the same pass. Inference on
CPU with channels-last features of 16, 32 or 64 channels runs the whole thing as one compiled kernel
(cpu_kernels.cpp, see bench.nn.native): 1.8-3.5x faster than the eager ops for the proposed model's CFM
(32 channels, 16 conditioning) at 1080p, which are memory-bound there.
"""
import torch
import torch.nn as nn
import torch.nn.functional as F

from . import fused, native
from .native import CFM_CHANNELS, DTYPE_CODES, kernels_available


class CFM(nn.Module):
    """x * (1 + gamma(cond)) + beta(cond); gamma and beta are 1x1 convs of the conditioning features."""

    def __init__(self, channels, cond_channels):
        super().__init__()
        self.gamma = nn.Conv2d(cond_channels, channels, 1)
        self.beta = nn.Conv2d(cond_channels, channels, 1)
        for conv in (self.gamma, self.beta):
            nn.init.zeros_(conv.weight)
            nn.init.zeros_(conv.bias)

    def macs(self, inputs, output):
        """The gamma and beta 1x1 convs, which forward runs as one functional conv (bench.macs protocol)."""
        cond = inputs[1]
        return (cond.numel() // cond.shape[1]) * (self.gamma.out_channels + self.beta.out_channels) * cond.shape[1]

    def forward(self, x, cond, relu=False):
        """CFM(x, cond), then ReLU when relu (every CFM here but a ResBlock's second one is followed by ReLU)."""
        if _triton_cfm_applies(x, cond):
            return _triton_cfm(x, cond, self.gamma, self.beta, relu)
        if _fused_kernel_applies(x, cond, self.gamma.weight):
            return _fused_cfm(x, cond, self.gamma, self.beta, relu)
        # gamma and beta as ONE conv and the affine as x + beta + x * gamma (two passes over x, not four):
        # the same function, about 3x faster at full HR resolution on CPU
        gamma_beta = F.conv2d(cond, torch.cat((self.gamma.weight, self.beta.weight)),
                              torch.cat((self.gamma.bias, self.beta.bias)))
        gamma, beta = gamma_beta.chunk(2, dim=1)
        y = torch.addcmul(x + beta, x, gamma)
        return F.relu(y, inplace=True) if relu else y


def _triton_cfm_applies(x, cond):
    """The fused Triton CFM takes channels-last x and cond only: on NCHW features the layout copies cost
    more than the kernel saves (H100, CFM baseline frame fp32: fused 58.0 ms against eager 47.1 in NCHW;
    30.3 against 36.8 channels-last)."""
    return (fused.applies(x, max(x.shape[1], cond.shape[1]))
            and x.is_contiguous(memory_format=torch.channels_last)
            and cond.is_contiguous(memory_format=torch.channels_last))


def _fused_kernel_applies(x, cond, weight):
    """Inference on CPU with channels-last x and cond of one dtype (float32/bfloat16), x of 16, 32 or 64
    channels (the widths the kernel is compiled for, and where it wins: 1.2-5x faster than eager at
    540p/1080p; at 35 channels eager's blocked conv wins), kernel built."""
    return (not (torch.is_grad_enabled() and (x.requires_grad or cond.requires_grad or weight.requires_grad))
            and x.device.type == "cpu" and x.dtype in DTYPE_CODES and cond.dtype == x.dtype
            and x.shape[1] in CFM_CHANNELS
            and x.is_contiguous(memory_format=torch.channels_last)
            and cond.is_contiguous(memory_format=torch.channels_last) and kernels_available())


def _fused_cfm(x, cond, gamma, beta, relu):
    """The whole CFM (and ReLU) in one pass per pixel (cpu_kernels.cpp: gamma and beta stay in
    registers; eager writes the 2C-channel gamma/beta map and two intermediates at full resolution).
    Output: x's dtype, channels-last; sums in float32 (under bf16 autocast eager rounds gamma, beta and
    x + beta to bf16 on the way: the kernel is the more exact of the two)."""
    b, c, h, w = x.shape
    cond_ch = cond.shape[1]
    weight = torch.cat((gamma.weight, beta.weight)).view(2 * c, cond_ch).t().float().contiguous()
    bias = torch.cat((gamma.bias, beta.bias)).float().contiguous()
    out = torch.empty_like(x, memory_format=torch.channels_last)
    native.cfm_affine(x, cond, weight, bias, relu, out)
    return out


def _triton_cfm(x, cond, gamma, beta, relu):
    """The whole CFM (and ReLU) as one Triton kernel (bench.nn.triton_kernels.cfm_fused), training too."""
    dtype = fused.compute_dtype(x)
    weight = torch.cat((gamma.weight, beta.weight)).to(dtype)
    bias = torch.cat((gamma.bias, beta.bias)).to(dtype)
    with torch.autocast(x.device.type, enabled=False):
        out = fused.kernels().cfm_fused(x.to(dtype), cond.to(dtype), weight, bias, relu)
    return fused.same_layout(out, x)


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
