"""Deformable convolution (DCNv1, optionally DCNv2-modulated) in plain PyTorch.

The paper (Sec. 3.3) replaces the second conv of a decoder block by a deformable conv whose offsets
come from an "offset generator", a 1x1 conv of the current features.

Offset channel layout (same as torchvision.ops.deform_conv2d): `offset` has 2*kh*kw channels,
`offset[:, 2*k] = dy_k` and `offset[:, 2*k + 1] = dx_k` for kernel tap k = i*kw + j (row-major).
Tap k of output pixel (y, x) reads the input at
    (y - padding + i*dilation + dy_k,  x - padding + j*dilation + dx_k)
with bilinear interpolation; every bilinear corner outside the image contributes zero.

Implementation: for each strip of output rows, the kh*kw sampling positions of all its pixels are
built at once, ONE F.grid_sample call gathers every tap of every pixel of the strip, and the result, laid
out as (B, C*kh*kw, pixels), is contracted with the weight in one matmul (an im2col whose columns are
bilinear samples). No Python loop over taps or pixels (only over row strips, for cache locality);
autograd gives gradients for input, offsets, mask, weight and bias.
Stride 1 and groups 1 only (all the networks here use "same"-size convs).
"""
import torch
import torch.nn as nn
import torch.nn.functional as F


def _sampling_grid(offset, kh, kw, padding, dilation, in_h, in_w, row0=0):
    """Normalized grid_sample coordinates (B, kh*kw*rows, W_out, 2) for output rows row0..row0+rows-1,
    where offset holds those rows: (B, 2*kh*kw, rows, W_out). Row-major over (tap, row, column)."""
    b, _, rows, out_w = offset.shape
    dtype, device = offset.dtype, offset.device
    offset = offset.view(b, kh * kw, 2, rows, out_w)
    tap_i = torch.arange(kh, dtype=dtype, device=device).repeat_interleave(kw) * dilation  # (K,)
    tap_j = torch.arange(kw, dtype=dtype, device=device).repeat(kh) * dilation
    ys = torch.arange(row0, row0 + rows, dtype=dtype, device=device) - padding
    xs = torch.arange(out_w, dtype=dtype, device=device) - padding
    y = ys.view(1, 1, rows, 1) + tap_i.view(1, -1, 1, 1) + offset[:, :, 0]  # (B, K, rows, W)
    x = xs.view(1, 1, 1, out_w) + tap_j.view(1, -1, 1, 1) + offset[:, :, 1]
    # align_corners=False convention: pixel centre p maps to (2p + 1) / size - 1 (no division by
    # size - 1, so 1-pixel-wide inputs work).
    grid = torch.stack(((2 * x + 1) / in_w - 1, (2 * y + 1) / in_h - 1), dim=-1)
    return grid.view(b, kh * kw * rows, out_w, 2)


# Output rows are processed in strips whose sampled block holds about this many values: a 4 MB strip
# stays in cache and reuses allocator memory, ~2x faster on CPU than one image-sized gather.
_STRIP_VALUES = 1 << 20


def deform_conv2d(x, offset, weight, bias=None, padding=1, dilation=1, mask=None):
    """Deformable 2D convolution, stride 1, groups 1.

    x: (B, C, H, W); offset: (B, 2*kh*kw, H_out, W_out) in the layout of the module docstring;
    weight: (O, C, kh, kw); bias: (O,) or None; mask: optional (B, kh*kw, H_out, W_out) modulation
    (DCNv2), multiplied onto each tap's sample. H_out = H + 2*padding - dilation*(kh-1), same for W.
    With zero offsets and no mask this equals F.conv2d(x, weight, bias, padding=padding, dilation=dilation).
    """
    b, c, in_h, in_w = x.shape
    out_ch, in_ch, kh, kw = weight.shape
    taps = kh * kw
    if in_ch != c:
        raise ValueError(f"weight expects {in_ch} input channels, x has {c}")
    out_h = in_h + 2 * padding - dilation * (kh - 1)
    out_w = in_w + 2 * padding - dilation * (kw - 1)
    if offset.shape != (b, 2 * taps, out_h, out_w):
        raise ValueError(f"offset must be {(b, 2 * taps, out_h, out_w)}, got {tuple(offset.shape)}")
    weight_matrix = weight.reshape(out_ch, c * taps)  # column c*K + k
    strip = max(1, _STRIP_VALUES // (b * c * taps * out_w))
    if x.is_meta:  # shape-only runs (MAC counting): no cache to fit, and meta ops cost per call
        strip = out_h
    offset = offset.to(x.dtype)
    outs = []
    for r0 in range(0, out_h, strip):
        rows = min(strip, out_h - r0)
        grid = _sampling_grid(offset[:, :, r0:r0 + rows], kh, kw, padding, dilation, in_h, in_w, r0)
        # one bilinear gather for all taps and pixels of the strip: (B, C, K*rows, W_out)
        samples = F.grid_sample(x, grid, mode="bilinear", padding_mode="zeros", align_corners=False)
        samples = samples.view(b, c, taps, rows * out_w)
        if mask is not None:
            samples = samples * mask[:, :, r0:r0 + rows].reshape(b, 1, taps, rows * out_w)
        outs.append(torch.matmul(weight_matrix, samples.view(b, c * taps, rows * out_w)))
    out = torch.cat(outs, dim=2) if len(outs) > 1 else outs[0]
    if bias is not None:
        out = out + bias.view(1, out_ch, 1)
    return out.view(b, out_ch, out_h, out_w)


class DeformConv2d(nn.Module):
    """Deformable conv with its own offset generator (a 1x1 conv of the input, as in the paper).

    The offset generator (and the optional mask generator) is zero-initialized, so a fresh layer is
    exactly a plain conv (the mask is 2*sigmoid(.), which is 1 at init). `modulated=True` adds the
    DCNv2 per-tap mask; the paper uses DCNv1 (modulated=False).
    """

    def __init__(self, in_ch, out_ch, kernel_size=3, padding=1, dilation=1, bias=True, modulated=False):
        super().__init__()
        if 2 * padding != dilation * (kernel_size - 1):
            # the 1x1 offset generator yields offsets at input size, so only "same"-size convs line up
            raise ValueError("DeformConv2d supports same-size convs only: padding = dilation*(k-1)/2")
        self.padding, self.dilation = padding, dilation
        taps = kernel_size * kernel_size
        self.weight = nn.Parameter(torch.empty(out_ch, in_ch, kernel_size, kernel_size))
        self.bias = nn.Parameter(torch.zeros(out_ch)) if bias else None
        nn.init.kaiming_uniform_(self.weight, a=5 ** 0.5)  # nn.Conv2d's default init
        self.offset_conv = nn.Conv2d(in_ch, 2 * taps, 1)
        nn.init.zeros_(self.offset_conv.weight)
        nn.init.zeros_(self.offset_conv.bias)
        self.mask_conv = None
        if modulated:
            self.mask_conv = nn.Conv2d(in_ch, taps, 1)
            nn.init.zeros_(self.mask_conv.weight)
            nn.init.zeros_(self.mask_conv.bias)

    def extra_macs(self, inputs, output):
        """MACs of the bilinear sampling (4 per sampled value), which MAC counters that see only
        conv/matmul miss; the weight product itself is the usual conv count (out_elements * C * k*k)."""
        taps = self.weight.shape[2] * self.weight.shape[3]
        return 4 * (output.numel() // output.shape[1]) * inputs[0].shape[1] * taps

    def forward(self, x):
        offset = self.offset_conv(x)
        mask = 2 * torch.sigmoid(self.mask_conv(x)) if self.mask_conv is not None else None
        return deform_conv2d(x, offset, self.weight, self.bias, self.padding, self.dilation, mask)
