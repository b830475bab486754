"""Fused GPU kernels (Triton): the deformable convolution, forward and backward, and the CFM affine.

Registered as torch.library custom ops (`torch.ops.srd_bench.deform_conv_fused`, its backward, and
`torch.ops.srd_bench.cfm_fused`), so autograd and torch.compile see one op each, as they see the CPU
kernels of bench.nn.native. Triton compiles them for the GPU; with TRITON_INTERPRET=1 its interpreter
runs them on CPU tensors, which is how CI tests them (fp32 only: the interpreter's bf16 dot is wrong,
and it runs one program at a time, so it cannot find races in the input gradient's scatter;
tests/test_cuda.py checks bf16 and repeatability on a GPU).

Deformable conv, forward (`_deform_forward`): one program per tile of BLOCK_P output pixels and
BLOCK_O output channels. For each tap it computes the tile's sample positions from the offsets (the
layout of bench.nn.deform: offset[:, 2k] = dy_k, offset[:, 2k + 1] = dx_k, in pixels), reads the four
bilinear corners of the channels-last input for BLOCK_C channels at a time, weights them (and the
DCNv2 mask) in float32, and multiplies the sampled (BLOCK_P, BLOCK_C) tile by the tap's (BLOCK_C,
BLOCK_O) weight tile (a tl.dot), accumulating the output in registers: no im2col column
reaches memory. Positions are clamped to [-1, H] x [-1, W], where every corner reads zero, so huge or
infinite offsets read zero (and get a zero offset gradient, as torch.clamp gives); a NaN offset makes
its pixel NaN.

Backward (`_deform_backward`): one program per (chunk of pixel tiles, tap), recomputing the samples
instead of storing columns. Per tile: the gradient of the tap's samples is grad_out (BLOCK_P, O) times
the tap's weight transposed (a tensor-core dot); it is scattered to the four corners of the input's
gradient (float32 atomics), reduced against the bilinear weights' derivatives (offset gradient) and the
unmodulated sample (mask gradient), both written without atomics (a (pixel, tap) belongs to one
program); the weight's gradient of the tap is the samples transposed times grad_out, summed over the
chunk's tiles in registers and written per chunk (summed by torch: deterministic, no atomics).

Operands of the dots are float32 (TF32 on the tensor cores where torch lets cuDNN's convs use it, its
default; else IEEE on the FMA units) or bfloat16 (the input's dtype, on the tensor cores); positions,
bilinear weights and accumulators are float32. Eight warps a program: four spill registers on sm_90.
Stride 1, groups 1, any kernel size, dilation and padding, O <= 128.
"""
from __future__ import annotations

from typing import Optional

import torch
import triton
import triton.language as tl

MAX_OUT_CHANNELS = 128  # the backward keeps a tile's whole grad_out row (O values) in registers


def _pow2(n: int, least: int = 16) -> int:
    return max(least, triton.next_power_of_2(n))


@triton.jit
def _tap_corners(off_ptr, os_b, os_k, os_y, os_x, b, oy, ox, live, k, KW: tl.constexpr, pad, dil, H, W):
    """Positions of tap k for a tile of pixels: the top-left corner (y0, x0), the fractions (fy, fx),
    and whether y or x was clamped (its offset gets no gradient)."""
    ki, kj = k // KW, k % KW
    at = b.to(tl.int64) * os_b + oy * os_y + ox * os_x
    dy = tl.load(off_ptr + at + (2 * k) * os_k, mask=live, other=0.0).to(tl.float32)
    dx = tl.load(off_ptr + at + (2 * k + 1) * os_k, mask=live, other=0.0).to(tl.float32)
    py = (oy - pad + ki * dil).to(tl.float32) + dy
    px = (ox - pad + kj * dil).to(tl.float32) + dx
    hf, wf = H * 1.0, W * 1.0  # (not .to(): Triton may pass a size of 1 as a constant)
    # comparisons with NaN are false: a NaN position stays NaN here and in its fractions
    clamped_y = (py < -1.0) | (py > hf)
    clamped_x = (px < -1.0) | (px > wf)
    py = tl.where(py < -1.0, -1.0, tl.where(py > hf, hf, py))
    px = tl.where(px < -1.0, -1.0, tl.where(px > wf, wf, px))
    nan = (py != py) | (px != px)
    y0f = tl.where(nan, -2.0, tl.floor(py))  # NaN: every corner outside (no read), its weights NaN
    x0f = tl.where(nan, -2.0, tl.floor(px))
    return y0f.to(tl.int32), x0f.to(tl.int32), py - y0f, px - x0f, clamped_y, clamped_x


@triton.jit
def _corner(x_ptr, base, yy, xx, c, live, cm, H, W, C):
    """The (BLOCK_P, BLOCK_C) input values at integer positions (yy, xx), zero outside the image."""
    inside = live & (yy >= 0) & (yy < H) & (xx >= 0) & (xx < W)
    at = base + (yy * W + xx).to(tl.int64) * C
    return tl.load(x_ptr + at[:, None] + c[None, :], mask=inside[:, None] & cm[None, :], other=0.0).to(tl.float32)


@triton.jit
def _deform_forward(x_ptr, off_ptr, mask_ptr, w_ptr, bias_ptr, out_ptr,
                    P, H, W, C, HO, WO, O, pad, dil,
                    os_b, os_k, os_y, os_x, ms_b, ms_k, ms_y, ms_x,
                    HAS_MASK: tl.constexpr, HAS_BIAS: tl.constexpr, KH: tl.constexpr, KW: tl.constexpr,
                    BLOCK_P: tl.constexpr, BLOCK_C: tl.constexpr, BLOCK_O: tl.constexpr,
                    PRECISION: tl.constexpr):
    pid_p, pid_o = tl.program_id(0), tl.program_id(1)
    p = pid_p * BLOCK_P + tl.arange(0, BLOCK_P)
    live = p < P
    b, rest = p // (HO * WO), p % (HO * WO)
    oy, ox = rest // WO, rest % WO
    o = pid_o * BLOCK_O + tl.arange(0, BLOCK_O)
    om = o < O
    base = b.to(tl.int64) * H * W * C
    acc = tl.zeros((BLOCK_P, BLOCK_O), dtype=tl.float32)
    for k in range(KH * KW):  # not unrolled: nine unrolled taps spill registers and compile 18x slower
        y0, x0, fy, fx, _, _ = _tap_corners(off_ptr, os_b, os_k, os_y, os_x, b, oy, ox, live, k, KW, pad, dil, H, W)
        w00, w01, w10, w11 = (1 - fy) * (1 - fx), (1 - fy) * fx, fy * (1 - fx), fy * fx
        if HAS_MASK:
            m = tl.load(mask_ptr + b.to(tl.int64) * ms_b + k * ms_k + oy * ms_y + ox * ms_x,
                        mask=live, other=0.0).to(tl.float32)
            w00, w01, w10, w11 = w00 * m, w01 * m, w10 * m, w11 * m
        for c0 in range(0, C, BLOCK_C):
            c = c0 + tl.arange(0, BLOCK_C)
            cm = c < C
            sample = (w00[:, None] * _corner(x_ptr, base, y0, x0, c, live, cm, H, W, C)
                      + w01[:, None] * _corner(x_ptr, base, y0, x0 + 1, c, live, cm, H, W, C)
                      + w10[:, None] * _corner(x_ptr, base, y0 + 1, x0, c, live, cm, H, W, C)
                      + w11[:, None] * _corner(x_ptr, base, y0 + 1, x0 + 1, c, live, cm, H, W, C))
            wk = tl.load(w_ptr + (k * C + c)[:, None] * O + o[None, :], mask=cm[:, None] & om[None, :], other=0.0)
            acc += tl.dot(sample.to(wk.dtype), wk, input_precision=PRECISION)
    if HAS_BIAS:
        acc += tl.load(bias_ptr + o, mask=om, other=0.0).to(tl.float32)[None, :]
    at = p.to(tl.int64)[:, None] * O + o[None, :]
    tl.store(out_ptr + at, acc.to(out_ptr.dtype.element_ty), mask=live[:, None] & om[None, :])


@triton.jit
def _scatter(gx_ptr, base, yy, xx, c, live, cm, H, W, C, value):
    inside = live & (yy >= 0) & (yy < H) & (xx >= 0) & (xx < W)
    at = base + (yy * W + xx).to(tl.int64) * C
    # relaxed: a fire-and-forget reduction (red.global), no fence per add
    tl.atomic_add(gx_ptr + at[:, None] + c[None, :], value, mask=inside[:, None] & cm[None, :], sem="relaxed")


@triton.jit
def _deform_backward(x_ptr, off_ptr, mask_ptr, w_ptr, gout_ptr, gx_ptr, goff_ptr, gmask_ptr, gw_ptr,
                     P, H, W, C, HO, WO, O, pad, dil, TILES,
                     os_b, os_k, os_y, os_x, ms_b, ms_k, ms_y, ms_x,
                     HAS_MASK: tl.constexpr, NEED_GX: tl.constexpr, KH: tl.constexpr, KW: tl.constexpr,
                     BLOCK_P: tl.constexpr, BLOCK_C: tl.constexpr, BLOCK_O: tl.constexpr,
                     PRECISION: tl.constexpr):
    chunk, k = tl.program_id(0), tl.program_id(1)
    chunks = tl.num_programs(0)
    o = tl.arange(0, BLOCK_O)
    om = o < O
    for c0 in range(0, C, BLOCK_C):
        c = c0 + tl.arange(0, BLOCK_C)
        cm = c < C
        wk = tl.load(w_ptr + (k * C + c)[:, None] * O + o[None, :], mask=cm[:, None] & om[None, :], other=0.0)
        grad_wk = tl.zeros((BLOCK_C, BLOCK_O), dtype=tl.float32)
        for tile in range(chunk, TILES, chunks):
            p = tile * BLOCK_P + tl.arange(0, BLOCK_P)
            live = p < P
            b, rest = p // (HO * WO), p % (HO * WO)
            oy, ox = rest // WO, rest % WO
            base = b.to(tl.int64) * H * W * C
            y0, x0, fy, fx, clamped_y, clamped_x = _tap_corners(off_ptr, os_b, os_k, os_y, os_x, b, oy, ox, live, k,
                                                                KW, pad, dil, H, W)
            if HAS_MASK:
                at_mask = b.to(tl.int64) * ms_b + k * ms_k + oy * ms_y + ox * ms_x
                m = tl.load(mask_ptr + at_mask, mask=live, other=0.0).to(tl.float32)
            else:
                m = tl.full((BLOCK_P,), 1.0, tl.float32)
            v00 = _corner(x_ptr, base, y0, x0, c, live, cm, H, W, C)
            v01 = _corner(x_ptr, base, y0, x0 + 1, c, live, cm, H, W, C)
            v10 = _corner(x_ptr, base, y0 + 1, x0, c, live, cm, H, W, C)
            v11 = _corner(x_ptr, base, y0 + 1, x0 + 1, c, live, cm, H, W, C)
            gy, gx = 1 - fy, 1 - fx
            raw = (gy * gx)[:, None] * v00 + (gy * fx)[:, None] * v01 + (fy * gx)[:, None] * v10 + (fy * fx)[:, None] * v11
            gout = tl.load(gout_ptr + p.to(tl.int64)[:, None] * O + o[None, :], mask=live[:, None] & om[None, :],
                           other=0.0)
            # d loss / d (modulated sample) of the tile's BLOCK_C channels
            grad_sample = tl.dot(gout, tl.trans(wk), input_precision=PRECISION)
            grad_wk += tl.dot(tl.trans((raw * m[:, None]).to(gout.dtype)), gout, input_precision=PRECISION)
            grad_raw = grad_sample * m[:, None]
            if NEED_GX:
                _scatter(gx_ptr, base, y0, x0, c, live, cm, H, W, C, grad_raw * (gy * gx)[:, None])
                _scatter(gx_ptr, base, y0, x0 + 1, c, live, cm, H, W, C, grad_raw * (gy * fx)[:, None])
                _scatter(gx_ptr, base, y0 + 1, x0, c, live, cm, H, W, C, grad_raw * (fy * gx)[:, None])
                _scatter(gx_ptr, base, y0 + 1, x0 + 1, c, live, cm, H, W, C, grad_raw * (fy * fx)[:, None])
            # offsets: the sample's derivative along y and x, summed over channels; a clamped axis gets 0
            d_y = tl.sum(grad_raw * (gx[:, None] * (v10 - v00) + fx[:, None] * (v11 - v01)), axis=1)
            d_x = tl.sum(grad_raw * (gy[:, None] * (v01 - v00) + fy[:, None] * (v11 - v10)), axis=1)
            d_y = tl.where(clamped_y, 0.0, d_y)
            d_x = tl.where(clamped_x, 0.0, d_x)
            # goff is (B, 2K, HO, WO) contiguous float32; this (pixel, tap) belongs to this program only
            plane = HO.to(tl.int64) * WO  # int64: 2K planes of an 8K frame pass 2^31
            at_g = b.to(tl.int64) * (2 * KH * KW) * plane + oy * WO + ox
            gy_at = goff_ptr + at_g + (2 * k) * plane
            gx_at = goff_ptr + at_g + (2 * k + 1) * plane
            tl.store(gy_at, tl.load(gy_at, mask=live, other=0.0) + d_y, mask=live)
            tl.store(gx_at, tl.load(gx_at, mask=live, other=0.0) + d_x, mask=live)
            if HAS_MASK:
                d_m = tl.sum(grad_sample * raw, axis=1)
                gm_at = gmask_ptr + b.to(tl.int64) * (KH * KW) * plane + k * plane + oy * WO + ox
                tl.store(gm_at, tl.load(gm_at, mask=live, other=0.0) + d_m, mask=live)
        at_w = ((chunk * KH * KW + k) * C + c).to(tl.int64)[:, None] * O + o[None, :]
        tl.store(gw_ptr + at_w, grad_wk, mask=cm[:, None] & om[None, :])


# ---- launch --------------------------------------------------------------------------------------

def _precision(dtype: torch.dtype) -> str:
    """TF32 dots for float32 where torch lets cuDNN's convs use TF32 (its default: the op replaces a
    conv), IEEE fp32 (FMA, no tensor cores) where it does not; bf16 operands are exact products."""
    if dtype != torch.float32:
        return "ieee"
    try:
        allowed = torch.backends.cudnn.allow_tf32
    except RuntimeError:  # torch refuses the legacy flag once the new fp32_precision API was used
        allowed = torch.backends.cudnn.conv.fp32_precision == "tf32"
    return "tf32" if allowed else "ieee"


NUM_WARPS = 8  # 4 spill registers in the backward and the forward on sm_90 (ptxas -v)


def _blocks(c: int, o: int) -> tuple[int, int, int]:
    """(BLOCK_P, BLOCK_C, BLOCK_O) of the forward; the backward takes the whole O (<= 128) and, with more
    than 64 outputs, 32 channels at a time (64 spill)."""
    return 64, min(32 if o > 64 else 64, _pow2(c)), min(64, _pow2(o))


def _chunks(tiles: int, taps: int, device: torch.device) -> int:
    """Backward programs per tap: about four per multiprocessor in all, so the per-chunk weight
    gradients (chunks x K x C x O floats) stay a few MB."""
    units = torch.cuda.get_device_properties(device).multi_processor_count if device.type == "cuda" else 4
    return max(1, min(tiles, -(-4 * units // taps)))


def _check(x, offset, mask, weight, bias, padding, dilation):
    if x.dtype not in (torch.float32, torch.bfloat16) or weight.dtype != x.dtype:
        raise ValueError(f"deform_conv_fused: float32 or bfloat16 x and weight of one dtype expected, "
                         f"got {x.dtype} and {weight.dtype}")
    b, c, h, w = x.shape
    o, c_w, kh, kw = weight.shape
    out_h, out_w = h + 2 * padding - dilation * (kh - 1), w + 2 * padding - dilation * (kw - 1)
    if c_w != c or o > MAX_OUT_CHANNELS:
        raise ValueError(f"deform_conv_fused: weight (O <= {MAX_OUT_CHANNELS}, {c}, kh, kw) expected, got {tuple(weight.shape)}")
    if offset.shape != (b, 2 * kh * kw, out_h, out_w):
        raise ValueError(f"deform_conv_fused: offset {(b, 2 * kh * kw, out_h, out_w)} expected, got {tuple(offset.shape)}")
    if mask is not None and mask.shape != (b, kh * kw, out_h, out_w):
        raise ValueError(f"deform_conv_fused: mask {(b, kh * kw, out_h, out_w)} expected, got {tuple(mask.shape)}")
    if bias is not None and bias.shape != (o,):
        raise ValueError(f"deform_conv_fused: bias ({o},) expected, got {tuple(bias.shape)}")
    devices = {t.device for t in (x, offset, mask, weight, bias) if t is not None}
    if len(devices) != 1:
        raise ValueError(f"deform_conv_fused: tensors on one device expected, got {sorted(map(str, devices))}")
    return b, c, h, w, o, kh, kw, out_h, out_w


def _nhwc(x: torch.Tensor) -> torch.Tensor:
    """x (B, C, H, W) as a contiguous (B, H, W, C) tensor: no copy when x is channels_last."""
    return x.permute(0, 2, 3, 1).contiguous()


def _tap_matrix(weight: torch.Tensor) -> torch.Tensor:
    """The (O, C, kh, kw) weight as the (K, C, O) contiguous matrix the kernels read, tap k = i*kw + j."""
    o, c, kh, kw = weight.shape
    return weight.permute(2, 3, 1, 0).reshape(kh * kw, c, o).contiguous()


@torch.library.custom_op("srd_bench::deform_conv_fused", mutates_args=())
def deform_conv_fused(x: torch.Tensor, offset: torch.Tensor, mask: Optional[torch.Tensor], weight: torch.Tensor,
                      bias: Optional[torch.Tensor], padding: int, dilation: int) -> torch.Tensor:
    """Deformable conv (bench.nn.deform.deform_conv2d's contract) by the fused kernel: x (B, C, H, W) of
    float32 or bfloat16, weight of x's dtype; returns (B, O, H_out, W_out) in x's dtype, channels_last."""
    b, c, h, w, o, kh, kw, out_h, out_w = _check(x, offset, mask, weight, bias, padding, dilation)
    out = torch.empty((b, out_h, out_w, o), dtype=x.dtype, device=x.device)
    pixels = b * out_h * out_w
    if pixels and c:
        block_p, block_c, block_o = _blocks(c, o)
        m = mask if mask is not None else offset  # a placeholder pointer, never read
        grid = (triton.cdiv(pixels, block_p), triton.cdiv(o, block_o))
        _deform_forward[grid](_nhwc(x), offset, m, _tap_matrix(weight), bias.contiguous() if bias is not None else weight, out,
                              pixels, h, w, c, out_h, out_w, o, padding, dilation,
                              *offset.stride(), *m.stride(), HAS_MASK=mask is not None, HAS_BIAS=bias is not None,
                              KH=kh, KW=kw, BLOCK_P=block_p, BLOCK_C=block_c, BLOCK_O=block_o,
                              PRECISION=_precision(x.dtype), num_warps=NUM_WARPS)
    elif bias is not None:
        out[:] = bias
    else:
        out.zero_()
    return out.permute(0, 3, 1, 2)


@deform_conv_fused.register_fake
def _(x, offset, mask, weight, bias, padding, dilation):
    b, c, h, w, o, kh, kw, out_h, out_w = _check(x, offset, mask, weight, bias, padding, dilation)
    return x.new_empty((b, out_h, out_w, o)).permute(0, 3, 1, 2)


@torch.library.custom_op("srd_bench::deform_conv_fused_backward", mutates_args=())
def deform_conv_fused_backward(grad_out: torch.Tensor, x: torch.Tensor, offset: torch.Tensor,
                               mask: Optional[torch.Tensor], weight: torch.Tensor, padding: int, dilation: int,
                               need_input_grad: bool) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Gradients of deform_conv_fused's output (without bias) for x (channels-last; an empty tensor
    unless need_input_grad: its scatter is the costliest part), offset and mask (contiguous; an empty
    tensor when mask is None) and weight (contiguous), each in its input's dtype."""
    b, c, h, w, o, kh, kw, out_h, out_w = _check(x, offset, mask, weight, None, padding, dilation)
    taps, pixels = kh * kw, b * out_h * out_w
    block_p, block_c, _ = _blocks(c, o)
    block_o = _pow2(o)  # the whole grad_out row of a pixel
    tiles = triton.cdiv(pixels, block_p)
    chunks = _chunks(tiles, taps, x.device)
    grad_x = torch.zeros((b, h, w, c) if need_input_grad else (0,), dtype=torch.float32, device=x.device)
    grad_offset = torch.zeros((b, 2 * taps, out_h, out_w), dtype=torch.float32, device=x.device)
    grad_mask = torch.zeros((b, taps, out_h, out_w) if mask is not None else (0,), dtype=torch.float32,
                            device=x.device)
    grad_w = torch.zeros((chunks, taps, c, o), dtype=torch.float32, device=x.device)
    if pixels and c:
        m = mask if mask is not None else offset
        _deform_backward[(chunks, taps)](
            _nhwc(x), offset, m, _tap_matrix(weight), _nhwc(grad_out.to(x.dtype)),
            grad_x if need_input_grad else grad_offset, grad_offset, grad_mask if mask is not None else grad_offset,
            grad_w, pixels, h, w, c, out_h, out_w, o, padding, dilation, tiles,
            *offset.stride(), *m.stride(), HAS_MASK=mask is not None, NEED_GX=need_input_grad, KH=kh, KW=kw,
            BLOCK_P=block_p, BLOCK_C=block_c, BLOCK_O=block_o, PRECISION=_precision(x.dtype), num_warps=NUM_WARPS)
    grad_weight = grad_w.sum(0).permute(2, 1, 0).reshape(o, c, kh, kw).contiguous()
    return ((grad_x.permute(0, 3, 1, 2) if need_input_grad else grad_x).to(x.dtype), grad_offset.to(offset.dtype),
            grad_mask.to(mask.dtype if mask is not None else torch.float32), grad_weight.to(weight.dtype))


@deform_conv_fused_backward.register_fake
def _(grad_out, x, offset, mask, weight, padding, dilation, need_input_grad):
    b, c, h, w, o, kh, kw, out_h, out_w = _check(x, offset, mask, weight, None, padding, dilation)
    grad_x = x.new_empty((b, h, w, c)).permute(0, 3, 1, 2) if need_input_grad else x.new_empty((0,))
    return (grad_x, offset.new_empty(offset.shape),
            mask.new_empty(mask.shape) if mask is not None else x.new_empty((0,), dtype=torch.float32),
            weight.new_empty(weight.shape))


def _setup_context(ctx, inputs, output):
    x, offset, mask, weight, bias, padding, dilation = inputs
    ctx.save_for_backward(x, offset, mask, weight)
    ctx.padding, ctx.dilation, ctx.has_bias = padding, dilation, bias is not None


def _backward(ctx, grad_out):
    x, offset, mask, weight = ctx.saved_tensors
    need_input_grad = ctx.needs_input_grad[0]
    grad_x, grad_offset, grad_mask, grad_weight = deform_conv_fused_backward(
        grad_out.contiguous(memory_format=torch.channels_last), x, offset, mask, weight, ctx.padding, ctx.dilation,
        need_input_grad)
    grad_bias = grad_out.sum((0, 2, 3)) if ctx.has_bias else None
    return (grad_x if need_input_grad else None, grad_offset, (grad_mask if mask is not None else None), grad_weight,
            grad_bias, None, None)


deform_conv_fused.register_autograd(_backward, setup_context=_setup_context)


# ---- CFM: x * (1 + gamma) + beta, then ReLU, with gamma | beta a 1x1 conv of cond, in one pass ------

@triton.jit
def _cfm_forward(x_ptr, cond_ptr, w_ptr, bias_ptr, out_ptr, P, C, G,
                 RELU: tl.constexpr, BLOCK_P: tl.constexpr, BLOCK_C: tl.constexpr, BLOCK_G: tl.constexpr,
                 PRECISION: tl.constexpr):
    """A tile of BLOCK_P pixels: gamma and beta as two (BLOCK_P, G) x (G, C) dots of the conditioning
    features, the affine and the ReLU in registers; x, cond and out are channels-last rows."""
    p = tl.program_id(0) * BLOCK_P + tl.arange(0, BLOCK_P)
    live = p < P
    c = tl.arange(0, BLOCK_C)
    g = tl.arange(0, BLOCK_G)
    cm, gm = c < C, g < G
    cond = tl.load(cond_ptr + p.to(tl.int64)[:, None] * G + g[None, :], mask=live[:, None] & gm[None, :], other=0.0)
    w_at = g[:, None] * (2 * C) + c[None, :]  # weight (G, 2C): gamma's columns, then beta's
    w_mask = gm[:, None] & cm[None, :]
    w_gamma = tl.load(w_ptr + w_at, mask=w_mask, other=0.0).to(cond.dtype)
    w_beta = tl.load(w_ptr + w_at + C, mask=w_mask, other=0.0).to(cond.dtype)
    gamma = tl.dot(cond, w_gamma, input_precision=PRECISION) + tl.load(bias_ptr + c, mask=cm, other=0.0)[None, :]
    beta = tl.dot(cond, w_beta, input_precision=PRECISION) + tl.load(bias_ptr + C + c, mask=cm, other=0.0)[None, :]
    at = p.to(tl.int64)[:, None] * C + c[None, :]
    both = live[:, None] & cm[None, :]
    x = tl.load(x_ptr + at, mask=both, other=0.0).to(tl.float32)
    y = x * (1.0 + gamma) + beta
    if RELU:
        y = tl.maximum(y, 0.0)
    tl.store(out_ptr + at, y.to(out_ptr.dtype.element_ty), mask=both)


def _check_cfm(x, cond, weight, bias):
    b, c, h, w = x.shape
    g = cond.shape[1]
    if (x.dtype not in (torch.float32, torch.bfloat16) or cond.dtype != x.dtype or cond.shape != (b, g, h, w)
            or weight.shape != (2 * c, g, 1, 1) or bias.shape != (2 * c,) or max(c, g) > MAX_OUT_CHANNELS):
        raise ValueError(f"cfm_fused: x (B, C, H, W) and cond (B, G, H, W) of one float32/bfloat16 dtype, "
                         f"weight (2C, G, 1, 1), bias (2C,), C and G <= {MAX_OUT_CHANNELS} expected, got "
                         f"{tuple(x.shape)} {x.dtype}, {tuple(cond.shape)} {cond.dtype}, {tuple(weight.shape)}, "
                         f"{tuple(bias.shape)}")
    return b, c, h, w, g


@torch.library.custom_op("srd_bench::cfm_fused", mutates_args=())
def cfm_fused(x: torch.Tensor, cond: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor,
              relu: bool) -> torch.Tensor:
    """x * (1 + gamma) + beta (then ReLU when relu), gamma | beta = conv1x1(cond, weight, bias) (gamma's
    C channels first): x and cond (B, C, H, W) and (B, G, H, W) of one dtype; out channels_last, x's
    dtype. Sums in float32."""
    b, c, h, w, g = _check_cfm(x, cond, weight, bias)
    out = torch.empty((b, h, w, c), dtype=x.dtype, device=x.device)
    pixels = b * h * w
    if pixels:
        block_p = 64
        _cfm_forward[(triton.cdiv(pixels, block_p),)](
            _nhwc(x), _nhwc(cond), weight.reshape(2 * c, g).t().float().contiguous(), bias.float().contiguous(), out,
            pixels, c, g, RELU=relu, BLOCK_P=block_p, BLOCK_C=_pow2(c), BLOCK_G=_pow2(g),
            PRECISION=_precision(x.dtype), num_warps=NUM_WARPS)
    return out.permute(0, 3, 1, 2)


@cfm_fused.register_fake
def _(x, cond, weight, bias, relu):
    b, c, h, w, g = _check_cfm(x, cond, weight, bias)
    return x.new_empty((b, h, w, c)).permute(0, 3, 1, 2)


def _cfm_setup_context(ctx, inputs, output):
    x, cond, weight, bias, relu = inputs
    ctx.save_for_backward(x, cond, weight, bias, output if relu else None)


def _cfm_backward(ctx, grad_out):
    """The eager gradients, gamma and beta recomputed (one 1x1 conv) rather than kept from the forward."""
    x, cond, weight, bias, out = ctx.saved_tensors
    gamma, beta = torch.nn.functional.conv2d(cond, weight, bias).chunk(2, dim=1)
    grad = grad_out if out is None else grad_out * (out > 0)
    grad_gamma_beta = torch.cat((grad * x, grad), dim=1)
    grad_cond = torch.nn.functional.conv2d(grad_gamma_beta, weight.transpose(0, 1))
    grad_weight = torch.einsum("bohw,bghw->og", grad_gamma_beta, cond).view_as(weight)
    return grad * (1 + gamma), grad_cond, grad_weight, grad_gamma_beta.sum((0, 2, 3)), None


cfm_fused.register_autograd(_cfm_backward, setup_context=_cfm_setup_context)
