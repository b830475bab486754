"""Deformable convolution (DCNv1, optionally DCNv2-modulated) in plain PyTorch.

The paper (Sec. 3.3) replaces the second conv of a decoder block by a deformable conv whose offsets
come from an "offset generator", a 1x1 conv of the current features.

Offset channel layout (same as torchvision.ops.deform_conv2d): `offset` has 2*kh*kw channels,
`offset[:, 2*k] = dy_k` and `offset[:, 2*k + 1] = dx_k` for kernel tap k = i*kw + j (row-major).
Tap k of output pixel (y, x) reads the input at
    (y - padding + i*dilation + dy_k,  x - padding + j*dilation + dx_k)
with bilinear interpolation; every bilinear corner outside the image contributes zero.

Implementation: five samplers, by device, dtype and whether autograd needs a gradient; they agree to
float rounding (tests/test_layers.py). None loops over taps or pixels in Python; all work in strips of
output rows.
  - columns, inference on CPU in float32/bfloat16 (the default there). Per strip of ~8k output pixels, a
    compiled kernel (cpu_kernels.cpp, built on first use by bench.nn.native) samples the im2col
    columns (pixels, K*C): positions and corner weights one vector of pixels at a time (16 with AVX-512, 8 with AVX2), each
    tap's 4-corner sum as a few vector FMAs, corners outside the image read as zero. One 1x1 conv
    (oneDNN, the 3x3 conv's MACs) turns them into the output while they are still in cache. Nothing
    per corner is written to memory. The kernel runs on torch's own OpenMP threads (a second pool
    fights torch's spinning workers for the cores: 1.5x slower).
  - gather, inference elsewhere (CUDA, float64, or no C++ compiler). Bilinear sampling is linear, so
    the weight goes first: a 1x1 conv turns the zero-padded input rows a strip's samples touch into a
    table of K*O values per pixel (tap k's weight times x there), and each output pixel is ONE bag of
    its K taps x 4 corners of that table, summed with the bilinear weights by
    `F.embedding_bag(mode="sum", per_sample_weights=...)`. The output comes out channels-last.
    Positions stay in pixels, at least float32. With small offsets a strip touches its own rows plus
    a few (about +10% of the table conv at 1080p); with offsets as large as the frame, every row.
  - compiled columns with a compiled backward, training on CPU in float32 (the default there,
    `_ColumnsTraining`): the columns kernel samples every output row's columns (kept for the weight's
    gradient), one matmul gives the output; the backward kernel (deform_columns_backward) scatters the
    columns' gradient to the input's bilinear corners and reduces it against the sample's y/x
    derivatives (offsets) and value (mask), one image per thread, one vector of channels at a time.
    Forward + backward on a 2-core AVX2 EPYC, 20 images: 1.2-2.5x faster than grid_sample at 32-64 px
    and 16-32 channels.
  - grid_sample, training elsewhere (CUDA, bf16 autocast, no compiler; `grid_sample_training()` forces
    it): an im2col whose columns are sampled by one F.grid_sample per strip, then one matmul. Its
    backward is about 2x faster than embedding_bag's (which sorts the indices), and gradients flow to
    input, offsets, mask, weight and bias. Positions are clamped like the other samplers' (huge or
    infinite offsets read zeros, with zero offset gradient).
  - fused, training and inference on CUDA, the entry points' default (bench.nn.fused decides;
    SRD_BENCH_FUSED_GPU=0 turns it off; tests/test_cuda.py passed with it on an H200): one Triton kernel per direction
    (bench/nn/triton_kernels.py) samples a tile's taps and multiplies them by the weight on the
    tensor cores without writing columns; its backward recomputes the samples, scatters the input's
    gradient with atomics and sums the weight's per chunk of tiles. float32 (TF32 where torch allows
    it) and bfloat16 under autocast. Its H200 times: results/gpu/speed/ and results/gpu/profile/.
Measured forward time / a plain nn.Conv2d of the same shape and layout (32->32, 3x3, 2 threads, glibc
keeping freed memory, see bench.infer.keep_freed_memory; results/*/speed/<machine>/ and runs of the
same day). AVX512-BF16 EPYC: columns with channels-last input 2.1-2.8x in fp32 and 2.6-3.0x in bf16
at 480x270 to 1920x1080; the eager gather 5.4-6.3x and 7.4-8.7x. AVX2-only EPYC: columns 2.7-2.9x
channels-last fp32 at 480x270 and 960x540 (5.8-6.8x before the kernels used 8-float vectors there),
the eager gather 5.6-6.1x. Contiguous (NCHW) fp32 input costs more (2.8-4.7x), since the sampler works
channels-last and converts the input and the output (the conv it is compared with does not). What is
left above the conv: the sampling (about 110 ms of a 1080p bf16 layer's 260 ms) and a 1x1 conv over
288 channels that oneDNN runs ~25% slower than the 3x3 conv. +experiment=speed reports the ratios for
the machine it runs on.
Stride 1 and groups 1 only (all the networks here use "same"-size convs).
"""
import contextlib

import torch
import torch.nn as nn
import torch.nn.functional as F

from . import fused, native
from .native import DTYPE_CODES, kernels_available


# Output rows are processed in strips whose sampled block holds about this many values: a 4 MB strip
# stays in cache and reuses allocator memory, ~2x faster on CPU than one image-sized gather.
_STRIP_VALUES = 1 << 20
# The gather sampler takes strips of about this many bilinear corners: each strip's table (the input
# rows it touches times K*O) is recomputed, so taller strips repeat fewer halo rows but index more.
_GATHER_INDICES = 1 << 21
# The compiled sampler's strips hold about this many output pixels: their columns (pixels x K*C values,
# 4.7 MB in bf16 at 32 channels) stay in cache for the conv that reads them.
_COLUMN_PIXELS = 1 << 13


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
    # Positions outside [-1, H] x [-1, W] are clamped to that border, where bilinear sampling reads 0 (as
    # the inference samplers do): an infinite offset would otherwise make grid_sample return NaN. NaN stays.
    y, x = y.clamp(-1, in_h), x.clamp(-1, in_w)
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

def _padded_input(x):
    """x zero-padded by 1 pixel before and 2 after each axis, channels-last: both bilinear corners of
    any position in [-1, H] x [-1, W] are cells of it (a position + 1 is its cell coordinate)."""
    return F.pad(x, (1, 2, 1, 2)).contiguous(memory_format=torch.channels_last)


def _pointwise(weight):
    """The (O, C, kh, kw) weight as a 1x1 conv weight (K*O, C, 1, 1), output channel k*O + o."""
    out_ch, in_ch, kh, kw = weight.shape
    return weight.permute(2, 3, 0, 1).reshape(kh * kw * out_ch, in_ch, 1, 1)


def _tap_products(padded, pointwise, out_ch, row0, row1):
    """The weight applied before sampling, on the padded rows row0..row1-1: the table
    Y[b, y, x, k, o] = sum_c weight[o, c, k] * padded[b, c, y, x] for every tap k, as rows
    (B*(row1-row0)*(W+3)*K, O), with pointwise = _pointwise(weight). One 1x1 conv (the 3x3 conv's
    MACs per row, run by oneDNN): a sample of Y at a position equals the tap's weight times x sampled
    there, since bilinear interpolation is linear. The border rows are zero: a corner outside the
    image contributes 0."""
    taps = F.conv2d(padded[:, :, row0:row1], pointwise)
    return taps.contiguous(memory_format=torch.channels_last).permute(0, 2, 3, 1).reshape(-1, out_ch)


def _tap_grid(kh, kw, padding, dilation, rows, out_w, device):
    """(rows, W_out, K, 2): position (y, x) + 1 of every tap of output pixel (row, column), rows from 0
    (+1: the coordinates of the padded input's cells)."""
    tap_y = (torch.arange(kh, device=device) * dilation - padding + 1).repeat_interleave(kw)
    tap_x = (torch.arange(kw, device=device) * dilation - padding + 1).repeat(kh)
    ys = torch.arange(rows, device=device).view(rows, 1, 1) + tap_y
    xs = torch.arange(out_w, device=device).view(1, out_w, 1) + tap_x
    return torch.stack(torch.broadcast_tensors(ys, xs), dim=-1).float()


def _bags(offset, grid, row0, in_h, in_w):
    """The bilinear samples of output rows row0..row0+rows-1, whose offsets are offset
    (B, 2*K, rows, W_out), grid = _tap_grid(..., rows, ...): (index, weight, first, last) where
    first..last are the padded-input rows the samples touch, and index, weight give 4*K rows of the
    _tap_products table of those rows per output pixel (4 bilinear corners x K taps), as flat int64
    indices and weights ordered (b, row, column, corner, tap) (a bag's order does not matter to its sum).

    A position outside [-1, H] x [-1, W] is clamped to that border: both of its corners then lie in
    the zero border (or the inner one has weight 0), so it reads 0, as bilinear sampling with zero
    padding does. A NaN position reads cell (0, 0) with NaN weights, so NaN propagates to its pixel."""
    b, _, rows, out_w = offset.shape
    taps = grid.shape[-2]
    device = offset.device
    # positions + 1 (cells of the padded input, never negative: truncation is floor), at least float32:
    # a bfloat16 position cannot address a pixel of a 1080p row. A view of offset when it is channels_last.
    pos = offset.permute(0, 2, 3, 1).reshape(b, rows, out_w, taps, 2).to(torch.promote_types(offset.dtype, torch.float32))
    pos = pos + grid
    pos[..., 0] += row0
    pos[..., 0].clamp_(0, in_h + 1)
    pos[..., 1].clamp_(0, in_w + 1)
    frac = torch.frac(pos)
    cell = pos.nan_to_num_(0.0).long()
    first, last = int(cell[..., 0].min()), int(cell[..., 0].max()) + 1  # + 1: the lower corners
    row_stride = in_w + 3
    # the table row of the tap at the top-left corner: (cell row * row_stride + cell column) * K + tap
    top_left = torch.add(cell[..., 1], cell[..., 0] - first, alpha=row_stride).mul_(taps)
    top_left += torch.arange(taps, device=device)
    if b > 1:
        top_left += (torch.arange(b, device=device) * ((last + 1 - first) * row_stride * taps)).view(b, 1, 1, 1)
    fy, fx = frac.unbind(-1)
    gy, gx = 1 - fy, 1 - fx
    index = torch.empty(b, rows, out_w, 4, taps, dtype=torch.int64, device=device)
    weight = torch.empty(b, rows, out_w, 4, taps, dtype=frac.dtype, device=device)
    for corner, (step, wy, wx) in enumerate(((0, gy, gx), (1, gy, fx), (row_stride, fy, gx),
                                            (row_stride + 1, fy, fx))):
        torch.add(top_left, step * taps, out=index[:, :, :, corner])
        torch.mul(wy, wx, out=weight[:, :, :, corner])
    return index.view(-1), weight.view(-1), first, last


def _deform_by_gather(x, offset, weight, mask, padding, dilation, strip):
    """(B, H_out, W_out, O) (channels-last order) without bias. Per strip of output rows: the bilinear
    corners of its samples (_bags), the weight applied to the input rows they touch (_tap_products:
    the strip's rows plus a few for small offsets, every row in the worst case), then each output
    pixel is ONE bag of its K taps x 4 corners of that table, summed by
    `F.embedding_bag(mode="sum", per_sample_weights=...)` (fbgemm's weighted gather on CPU). No
    autograd support needed (inference only)."""
    b, c, in_h, in_w = x.shape
    out_ch, _, kh, kw = weight.shape
    taps, out_h, out_w = kh * kw, offset.shape[-2], offset.shape[-1]
    padded, pointwise = _padded_input(x), _pointwise(weight)
    out = None
    grid = _tap_grid(kh, kw, padding, dilation, min(strip, out_h), out_w, x.device)
    for r0 in range(0, out_h, strip):
        rows = min(strip, out_h - r0)
        index, corner_weight, first, last = _bags(offset[:, :, r0:r0 + rows], grid[:rows], r0, in_h, in_w)
        table = _tap_products(padded, pointwise, out_ch, first, last + 1)
        if out is None:
            out = torch.empty(b, out_h, out_w, out_ch, dtype=table.dtype, device=x.device)
        if mask is not None:
            corner_weight = (corner_weight.view(b, rows, out_w, 4, taps)
                             * mask[:, :, r0:r0 + rows].permute(0, 2, 3, 1).unsqueeze(3)).view(-1)
        # 1-D int64 indices with bag offsets: fbgemm's fast path (int32 or 2-D bags are 2-8x slower)
        bags = torch.arange(0, index.numel(), 4 * taps, device=x.device)
        out[:, r0:r0 + rows] = F.embedding_bag(index, table, bags, mode="sum",
                                               per_sample_weights=corner_weight.to(table.dtype)
                                               ).view(b, rows, out_w, out_ch)
    return out


_use_columns_kernel = True  # False inside eager_gather()
_use_training_kernel = True  # False inside grid_sample_training()


@contextlib.contextmanager
def grid_sample_training():
    """Training takes the grid_sample sampler even where the compiled one applies (to compare them)."""
    global _use_training_kernel
    previous, _use_training_kernel = _use_training_kernel, False
    try:
        yield
    finally:
        _use_training_kernel = previous


def _deform_fused(x, offset, weight, bias, mask, padding, dilation):
    """The fused Triton kernels (bench.nn.triton_kernels); offsets and mask are read in float32."""
    dtype = fused.compute_dtype(x)
    with torch.autocast(x.device.type, enabled=False):
        out = fused.kernels().deform_conv_fused(x.to(dtype), offset, mask, weight.to(dtype),
                                                None if bias is None else bias.to(dtype), padding, dilation)
    return fused.same_layout(out, x)


@contextlib.contextmanager
def eager_gather():
    """Inference takes the eager gather sampler even where the compiled one applies (to compare them)."""
    global _use_columns_kernel
    previous, _use_columns_kernel = _use_columns_kernel, False
    try:
        yield
    finally:
        _use_columns_kernel = previous


def _columns_kernel_applies(*tensors):
    """The compiled columns kernel applies: CPU tensors (None allowed) of float32/bfloat16, and the kernel
    built (and not inside eager_gather())."""
    return (_use_columns_kernel
            and all(t is None or (t.device.type == "cpu" and t.dtype in DTYPE_CODES) for t in tensors)
            and kernels_available())


def inference_sampler(x, weight=None) -> str:
    """The sampler deform_conv2d takes for input x (without autograd): "fused", "columns" or "gather"."""
    if fused.applies(x, weight.shape[0] if weight is not None else 1):
        return "fused"
    return "columns" if _columns_kernel_applies(x) else "gather"


def _deform_by_columns(x, offset, weight, bias, mask, padding, dilation, strip):
    """(B, H_out, W_out, O) (channels-last order) WITH bias: per strip of output rows, the im2col columns
    (B*rows*W_out, K*C) sampled by the compiled kernel (cpu_kernels.cpp: positions, corner weights
    and 4-corner sums in registers; corners outside the image read zero), then one 1x1 conv of them
    (oneDNN; the weight reordered to columns k*C + c). The strip's columns stay in cache between the two."""
    b, c = x.shape[:2]
    out_ch, _, kh, kw = weight.shape
    taps, out_h, out_w = kh * kw, offset.shape[-2], offset.shape[-1]
    cols_dtype = torch.get_autocast_dtype("cpu") if torch.is_autocast_enabled("cpu") else x.dtype
    image = x.permute(0, 2, 3, 1).contiguous()  # (B, H, W, C): no copy when x is channels_last
    # cast once here, not by autocast in every strip's conv
    matrix = weight.permute(0, 2, 3, 1).reshape(out_ch, taps * c, 1, 1).to(cols_dtype)
    bias = None if bias is None else bias.to(cols_dtype)
    tap_y, tap_x = _tap_positions(kh, kw, padding, dilation)
    cols = torch.empty(b * min(strip, out_h) * out_w, taps * c, dtype=cols_dtype, device=x.device)
    out = None
    for r0 in range(0, out_h, strip):
        rows = min(strip, out_h - r0)
        n = b * rows * out_w
        native.deform_columns(image, offset, mask, cols, r0, rows, tap_y, tap_x)  # on meta: nothing
        # the strip's columns as a channels-last (1, K*C, 1, n) image: the conv reads them in place
        strip_out = F.conv2d(cols[:n].view(1, 1, n, taps * c).permute(0, 3, 1, 2), matrix, bias)
        if out is None:  # its dtype is the conv's, which autocast decides
            out = torch.empty(b, out_h, out_w, out_ch, dtype=strip_out.dtype, device=x.device)
        out[:, r0:r0 + rows] = strip_out.permute(0, 2, 3, 1).reshape(b, rows, out_w, out_ch)
    return out


def _tap_positions(kh, kw, padding, dilation):
    """Row and column offsets (int64, one per tap k = i*kw + j) of the taps from the output pixel."""
    return (torch.arange(kh) * dilation - padding).repeat_interleave(kw), (torch.arange(kw) * dilation - padding).repeat(kh)


class _ColumnsTraining(torch.autograd.Function):
    """The training sampler on CPU in float32: the compiled columns kernel forward (all rows at once;
    the columns are kept for the weight's gradient) and its compiled backward (cpu_kernels.cpp,
    deform_columns_backward) for the input, offsets and mask; the weight's and the bias's gradients
    are matrix products with the columns. Agrees with the grid_sample sampler to float rounding."""

    @staticmethod
    def forward(ctx, x, offset, mask, weight, bias, padding, dilation):
        b, c, in_h, in_w = x.shape
        out_ch, _, kh, kw = weight.shape
        taps, out_h, out_w = kh * kw, offset.shape[-2], offset.shape[-1]
        image = x.detach().permute(0, 2, 3, 1).contiguous()
        offset = offset.detach().contiguous()
        mask = None if mask is None else mask.detach().contiguous()
        tap_y, tap_x = _tap_positions(kh, kw, padding, dilation)
        cols = torch.empty(b * out_h * out_w, taps * c)
        native.deform_columns(image, offset, mask, cols, 0, out_h, tap_y, tap_x)
        matrix = weight.detach().permute(0, 2, 3, 1).reshape(out_ch, taps * c)  # column k*C + c
        out = cols @ matrix.t()
        if bias is not None:
            out += bias.detach()
        ctx.save_for_backward(image, offset, mask, cols, matrix, tap_y, tap_x)
        ctx.shape, ctx.has_bias = (b, c, in_h, in_w, out_ch, kh, kw, out_h, out_w), bias is not None
        return out.view(b, out_h, out_w, out_ch).permute(0, 3, 1, 2).contiguous()

    @staticmethod
    def backward(ctx, grad_out):
        image, offset, mask, cols, matrix, tap_y, tap_x = ctx.saved_tensors
        b, c, in_h, in_w, out_ch, kh, kw, out_h, out_w = ctx.shape
        grad = grad_out.permute(0, 2, 3, 1).reshape(-1, out_ch)
        grad_weight = (grad.t() @ cols).view(out_ch, kh, kw, c).permute(0, 3, 1, 2)
        grad_bias = grad.sum(0) if ctx.has_bias else None
        grad_cols = (grad @ matrix).contiguous()
        grad_image = torch.zeros_like(image)
        grad_offset = torch.empty_like(offset)
        grad_mask = None if mask is None else torch.empty_like(mask)
        native.deform_columns_backward(image, offset, mask, grad_cols, tap_y, tap_x, grad_image, grad_offset,
                                       grad_mask)
        return grad_image.permute(0, 3, 1, 2), grad_offset, grad_mask, grad_weight, grad_bias, None, None


def training_sampler(x, weight=None) -> str:
    """The sampler deform_conv2d takes for input x when autograd needs a gradient: "fused", "columns"
    or "grid_sample"."""
    if fused.applies(x, weight.shape[0] if weight is not None else 1):
        return "fused"
    return "columns" if _use_training_kernel and _columns_training_applies(x) else "grid_sample"


def _columns_training_applies(*tensors):
    """The compiled training sampler applies: float32 CPU tensors (None allowed), no autocast, kernels built."""
    return (_use_columns_kernel and not torch.is_autocast_enabled("cpu")
            and all(t is None or (t.device.type == "cpu" and t.dtype == torch.float32) for t in tensors)
            and kernels_available())


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
    if 0 in (b, in_h, in_w, out_h, out_w):  # no pixels: what nn.Conv2d does (empty output or its error)
        return F.conv2d(x, weight, bias, padding=padding, dilation=dilation)
    if fused.applies(x, out_ch):
        return _deform_fused(x, offset, weight, bias, mask, padding, dilation)
    needs_grad = torch.is_grad_enabled() and any(
        t is not None and t.requires_grad for t in (x, offset, weight, bias, mask))
    if needs_grad and not x.is_meta and _use_training_kernel and _columns_training_applies(x, offset, weight, bias, mask):
        return _ColumnsTraining.apply(x, offset, mask, weight, bias, padding, dilation)
    if needs_grad:
        strip = out_h if x.is_meta else max(1, _STRIP_VALUES // (b * c * taps * out_w))
        out = _deform_by_grid_sample(x, offset, weight, mask, padding, dilation, strip)
    else:
        # shape-only runs (MAC counting) take the columns path, whether or not the kernel builds, so the
        # counted MACs are the default CPU path's (DeformConv2d.macs), in one strip (meta ops cost per call)
        if x.is_meta or _columns_kernel_applies(x, offset, weight, bias, mask):
            strip = out_h if x.is_meta else max(1, _COLUMN_PIXELS // (b * out_w))
            out = _deform_by_columns(x, offset, weight, bias, mask, padding, dilation, strip)
        else:
            strip = max(1, _GATHER_INDICES // (b * 4 * taps * out_w))
            out = _deform_by_gather(x, offset, weight, mask, padding, dilation, strip)
            if bias is not None:
                out += bias.to(out.dtype)
        out = out.permute(0, 3, 1, 2)
        channels_last = not x.is_contiguous() and x.is_contiguous(memory_format=torch.channels_last)
        return out if channels_last else out.contiguous()
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

    def macs(self, inputs, output):
        """MACs of the weight product (bench.macs protocol): the conv's count, output pixels x O x C*K,
        which the default CPU sampler runs as its 1x1 conv over the columns (and shape-only runs take
        that path). The eager gather sampler (CUDA, float64) applies the weight on the zero-padded
        input and its strips' halo rows instead (+0.4% and about +10% at 1080p): time, not MACs."""
        out_ch, in_ch, kh, kw = self.weight.shape
        return output.shape[0] * output.shape[2] * output.shape[3] * kh * kw * out_ch * in_ch

    def extra_macs(self, inputs, output):
        """MACs of the bilinear sampling (4 per sampled value), which MAC counters that see only
        conv/matmul miss; the weight product itself is the usual conv count (out_elements * C * k*k)."""
        taps = self.weight.shape[2] * self.weight.shape[3]
        return 4 * (output.numel() // output.shape[1]) * inputs[0].shape[1] * taps

    def forward(self, x):
        offset = self.offset_conv(x)
        mask = 2 * torch.sigmoid(self.mask_conv(x)) if self.mask_conv is not None else None
        return deform_conv2d(x, offset, self.weight, self.bias, self.padding, self.dilation, mask)
