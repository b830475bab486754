"""Deformable convolution (DCNv1, optionally DCNv2-modulated) in plain PyTorch.

The paper (Sec. 3.3) replaces the second conv of a decoder block by a deformable conv whose offsets
come from an "offset generator", a 1x1 conv of the current features.

Offset channel layout (same as torchvision.ops.deform_conv2d): `offset` has 2*kh*kw channels,
`offset[:, 2*k] = dy_k` and `offset[:, 2*k + 1] = dx_k` for kernel tap k = i*kw + j (row-major).
Tap k of output pixel (y, x) reads the input at
    (y - padding + i*dilation + dy_k,  x - padding + j*dilation + dx_k)
with bilinear interpolation; every bilinear corner outside the image contributes zero.

Implementation: an im2col whose columns are bilinear samples, contracted with the weight in one matmul
per strip of output rows (no Python loop over taps or pixels; strips keep the samples in cache). Two
samplers fill the columns; they agree to float rounding (tests/test_layers.py):
  - gather, when no gradient is needed (inference): the four bilinear corners of every sample are rows
    of a zero-bordered channels-last copy of x, summed with their weights by ONE
    `F.embedding_bag(mode="sum", per_sample_weights=...)` per strip (fbgemm's weighted gather on CPU).
    Positions are used in pixels, never normalised, and the matmul writes the output directly in x's
    memory format (contiguous or channels_last). About 2x faster than grid_sample in forward.
  - grid_sample, when autograd needs a gradient (training): one F.grid_sample per strip. Its backward
    is about 2x faster than embedding_bag's (which sorts the indices), and gradients flow to input,
    offsets, mask, weight and bias.
Measured forward time / a plain nn.Conv2d of the same shape (32->32, 3x3, at 270x480 and 540x960, one
thread, on a 2-core machine shared with other jobs, so +-50%): gather 2.7-5x, grid_sample 4.4-7.6x
(+experiment=speed reports it for the machine it runs on).
Stride 1 and groups 1 only (all the networks here use "same"-size convs).
"""
import torch
import torch.nn as nn
import torch.nn.functional as F


# Output rows are processed in strips whose sampled block holds about this many values: a 4 MB strip
# stays in cache and reuses allocator memory, ~2x faster on CPU than one image-sized gather.
_STRIP_VALUES = 1 << 20


# ---- grid_sample sampler (differentiable) --------------------------------------------------------

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


def _deform_by_grid_sample(x, offset, weight, mask, padding, dilation, strip):
    """(B, O, H_out*W_out) without bias; columns sampled by F.grid_sample (see module docstring)."""
    b, c, in_h, in_w = x.shape
    out_ch, _, kh, kw = weight.shape
    taps, out_h, out_w = kh * kw, offset.shape[-2], offset.shape[-1]
    weight_matrix = weight.reshape(out_ch, c * taps)  # column c*K + k
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
    return torch.cat(outs, dim=2) if len(outs) > 1 else outs[0]


# ---- gather sampler (inference) ------------------------------------------------------------------

def _pixel_positions(offset, kh, kw, padding, dilation, row0):
    """Sampling positions in input pixels, (B, 2 (y, x), rows, W_out, K), for output rows
    row0..row0+rows-1 held by offset (B, 2*K, rows, W_out). At least float32: a bfloat16 position
    cannot address a pixel of a 1080p row."""
    b, _, rows, out_w = offset.shape
    taps = kh * kw
    dtype, device = torch.promote_types(offset.dtype, torch.float32), offset.device
    pos = offset.to(dtype).view(b, taps, 2, rows, out_w).permute(0, 2, 3, 4, 1).contiguous()
    tap_y = (torch.arange(kh, dtype=dtype, device=device) * dilation - padding).repeat_interleave(kw)
    tap_x = (torch.arange(kw, dtype=dtype, device=device) * dilation - padding).repeat(kh)
    pos[:, 0] += torch.arange(row0, row0 + rows, dtype=dtype, device=device).view(rows, 1, 1) + tap_y
    pos[:, 1] += torch.arange(out_w, dtype=dtype, device=device).view(out_w, 1) + tap_x
    return pos


def _padded_rows(x):
    """x (B, C, H, W) as the rows of a channels-last table with a zero border of 1 pixel before and 2
    after each axis, (B*(H+3)*(W+3), C): both corners of any position in [-1, H] x [-1, W] exist."""
    return F.pad(x.permute(0, 2, 3, 1), (0, 0, 1, 2, 1, 2)).reshape(-1, x.shape[1])


def _gather_bags(h, w, pos):
    """The four bilinear corners of every sample as rows of the _padded_rows table: flat int64 indices
    and weights, 4 per sample in pos's order, corners (dy, dx) row-major.

    A position outside [-1, H] x [-1, W] is clamped to that border: both of its corners then lie in
    the zero border (or the inner one has weight 0), so it reads 0, as bilinear sampling with zero
    padding does. A NaN position reads row 0 with NaN weights, so NaN propagates."""
    b = pos.shape[0]
    pos = pos.clone()
    pos[:, 0].clamp_(-1, h)
    pos[:, 1].clamp_(-1, w)
    corner = pos.floor()
    frac = (pos - corner).view(b, 2, -1)
    cell = corner.nan_to_num_(-1.0).view(b, 2, -1).long() + 1  # (row, column) in the padded table
    row_stride = w + 3
    top_left = cell[:, 0] * row_stride + cell[:, 1]
    if b > 1:
        top_left += torch.arange(b, device=pos.device).view(b, 1) * ((h + 3) * row_stride)
    top_left, fy, fx = top_left.view(-1), frac[:, 0].reshape(-1), frac[:, 1].reshape(-1)
    gy, gx = 1 - fy, 1 - fx
    # written column by column: a broadcast (S, 2, 1) x (S, 1, 2) product or a stack along the last
    # axis is 2-10x slower on CPU
    index = torch.empty(top_left.numel(), 4, dtype=torch.int64, device=pos.device)
    weight = torch.empty(top_left.numel(), 4, dtype=pos.dtype, device=pos.device)
    for column, (step, wy, wx) in enumerate(((0, gy, gx), (1, gy, fx), (row_stride, fy, gx),
                                            (row_stride + 1, fy, fx))):
        torch.add(top_left, step, out=index[:, column])
        torch.mul(wy, wx, out=weight[:, column])
    return index.view(-1), weight


def _deform_by_gather(x, offset, weight, mask, padding, dilation, strip, channels_last):
    """(B, O, H_out*W_out), or (B, H_out*W_out, O) when channels_last, without bias; columns gathered
    by embedding_bag (see module docstring). No autograd support needed (inference only)."""
    b, c, in_h, in_w = x.shape
    out_ch, _, kh, kw = weight.shape
    taps, out_h, out_w = kh * kw, offset.shape[-2], offset.shape[-1]
    table = _padded_rows(x)
    weight_matrix = weight.permute(0, 2, 3, 1).reshape(out_ch, taps * c)  # column k*C + c
    outs = []
    for r0 in range(0, out_h, strip):
        rows = min(strip, out_h - r0)
        pos = _pixel_positions(offset[:, :, r0:r0 + rows], kh, kw, padding, dilation, r0)
        index, corner_weight = _gather_bags(in_h, in_w, pos)
        if mask is not None:
            corner_weight = corner_weight * mask[:, :, r0:r0 + rows].permute(0, 2, 3, 1).reshape(-1, 1)
        # 1-D int64 indices with bag offsets: fbgemm's fast path (int32 or 2-D bags are 2-8x slower)
        bags = torch.arange(0, index.numel(), 4, device=x.device)
        samples = F.embedding_bag(index, table, bags, per_sample_weights=corner_weight.view(-1).to(table.dtype),
                                  mode="sum").view(b, rows * out_w, taps * c)
        outs.append(samples @ weight_matrix.t() if channels_last else weight_matrix @ samples.transpose(1, 2))
    return torch.cat(outs, dim=1 if channels_last else 2) if len(outs) > 1 else outs[0]


def deform_conv2d(x, offset, weight, bias=None, padding=1, dilation=1, mask=None):
    """Deformable 2D convolution, stride 1, groups 1.

    x: (B, C, H, W); offset: (B, 2*kh*kw, H_out, W_out) in the layout of the module docstring;
    weight: (O, C, kh, kw); bias: (O,) or None; mask: optional (B, kh*kw, H_out, W_out) modulation
    (DCNv2), multiplied onto each tap's sample. H_out = H + 2*padding - dilation*(kh-1), same for W.
    With zero offsets and no mask this equals F.conv2d(x, weight, bias, padding=padding, dilation=dilation).
    Without autograd the result is channels_last when x is (inference fast path), else contiguous.
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
    strip = max(1, _STRIP_VALUES // (b * c * taps * out_w))
    if x.is_meta:  # shape-only runs (MAC counting): no cache to fit, and meta ops cost per call
        strip = out_h
    needs_grad = torch.is_grad_enabled() and any(
        t is not None and t.requires_grad for t in (x, offset, weight, bias, mask))
    if needs_grad:
        out = _deform_by_grid_sample(x, offset, weight, mask, padding, dilation, strip)
    else:
        channels_last = not x.is_contiguous() and x.is_contiguous(memory_format=torch.channels_last)
        out = _deform_by_gather(x, offset, weight, mask, padding, dilation, strip, channels_last)
        if channels_last:
            out = out if bias is None else out + bias
            return out.view(b, out_h, out_w, out_ch).permute(0, 3, 1, 2)
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
