"""Tile sizes of the fused deformable conv (bench/nn/triton_kernels.py) against nn.Conv2d of the same
shape, and what the DeformConv2d layer spends beside the kernel (its 1x1 offset conv): the
measurements for choosing `_blocks` and `NUM_WARPS`. Each (BLOCK_P, BLOCK_C, num_warps) is timed for the
forward alone and forward + backward (gradients of x, offsets and weight), without the DCNv2 mask as in
Ours' layers, channels-last, in
float32 (TF32 dots where torch's cuDNN flag allows them, its default) and bfloat16. Median of
calls after warm-up (bench.measure.time_call, synchronised). Writes a markdown table.
    python scripts/gpu_deform_sweep.py --out results/gpu/profile/<device>-deform-sweep.md
    TRITON_INTERPRET=1 python scripts/gpu_deform_sweep.py --device cpu --hw 6 7 --repeats 1 --out /tmp/s.md
"""
import argparse
import itertools
import os
from pathlib import Path

import torch

from bench.machine import device_tag
from bench.measure import time_call
from bench.table_writer import write_record
from bench.nn import fused
from bench.nn.deform import DeformConv2d


def timed(fn, device: str, repeats: int) -> float:
    """Median ms of `repeats` calls after two untimed ones (bench.measure.time_call, the suite's one loop)."""
    return time_call(fn, device, repeats=repeats, warmup=2)["ms"]


def inputs(hw, channels: int, dtype, device: str, seed: int = 0):
    """x (1, C, H, W) channels-last, offsets of a few pixels, no mask (Ours' layers are unmodulated)."""
    g = torch.Generator().manual_seed(seed)
    h, w = hw
    x = torch.randn(1, channels, h, w, generator=g).to(device, dtype).contiguous(memory_format=torch.channels_last)
    offset = (2 * torch.randn(1, 18, h, w, generator=g)).to(device, dtype).contiguous(memory_format=torch.channels_last)
    weight = (0.1 * torch.randn(channels, channels, 3, 3, generator=g)).to(device, dtype)
    bias = torch.zeros(channels, device=device, dtype=dtype)
    return x, offset, None, weight, bias


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default="cuda")
    parser.add_argument("--hw", type=int, nargs=2, default=[540, 960])
    parser.add_argument("--channels", type=int, default=32)
    parser.add_argument("--repeats", type=int, default=20)
    parser.add_argument("--block-p", type=int, nargs="+", default=[32, 64, 128])
    parser.add_argument("--block-c", type=int, nargs="+", default=[16, 32])
    parser.add_argument("--warps", type=int, nargs="+", default=[2, 4, 8])
    parser.add_argument("--out", required=True)
    args = parser.parse_args()
    device = args.device
    with fused.forced():
        kernels = fused.kernels()
    if kernels is None:
        raise SystemExit("gpu_deform_sweep: Triton is not installed")
    blocks, warps = kernels._blocks, kernels.NUM_WARPS
    lines = [f"# The fused deformable conv's tile sizes on {device_tag(device)}", "",
             f"`python scripts/gpu_deform_sweep.py {' '.join(os.sys.argv[1:])}`: 1 x {args.channels} -> "
             f"{args.channels} channels, 3x3, no mask, {args.hw[1]}x{args.hw[0]}, channels-last; median ms of "
             f"{args.repeats} calls; torch {torch.__version__}. fwd+bwd: the forward and the gradients of x, "
             f"offsets and weight. Today's choice: _blocks({args.channels}, {args.channels}) = "
             f"{blocks(args.channels, args.channels)}, "
             f"NUM_WARPS = {warps}.", ""]
    dtypes = (torch.float32, torch.bfloat16)
    for dtype in dtypes:
        name = "fp32 (TF32 dots)" if dtype == torch.float32 else "bf16"
        tensors = inputs(args.hw, args.channels, dtype, device)
        x = tensors[0]
        conv = torch.nn.Conv2d(args.channels, args.channels, 3, padding=1).to(device, dtype).to(
            memory_format=torch.channels_last)
        layer = DeformConv2d(args.channels, args.channels, 3, padding=1).to(device, dtype).to(
            memory_format=torch.channels_last)
        with torch.no_grad():
            conv_ms = timed(lambda: conv(x), device, args.repeats)
            offset_ms = timed(lambda: layer.offset_conv(x), device, args.repeats)
            with fused.forced():
                layer_ms = timed(lambda: layer(x), device, args.repeats)
        xg = x.detach().requires_grad_(True)
        conv_fb = timed(lambda: torch.autograd.grad(conv(xg).sum(), [xg, conv.weight]), device, args.repeats)
        lines += [f"## {name}", "",
                  f"nn.Conv2d {args.channels}->{args.channels} 3x3: forward {conv_ms:.3f} ms, fwd+bwd {conv_fb:.3f} ms. "
                  f"DeformConv2d layer forward (fused): {layer_ms:.3f} ms, of which its 1x1 offset conv "
                  f"{offset_ms:.3f} ms.", "",
                  "| BLOCK_P | BLOCK_C | warps | forward ms | / conv | fwd+bwd ms | / conv fwd+bwd |", "|---" * 7 + "|"]
        for block_p, block_c, nw in itertools.product(args.block_p, args.block_c, args.warps):
            kernels._blocks = lambda c, o, bp=block_p, bc=block_c: (bp, min(bc, kernels._pow2(c)), min(64, kernels._pow2(o)))
            kernels.NUM_WARPS = nw
            try:
                with torch.no_grad():
                    fwd = timed(lambda: kernels.deform_conv_fused(*tensors, 1, 1), device, args.repeats)
                xl, offl, wl = (t.detach().requires_grad_(True) for t in (tensors[0], tensors[1], tensors[3]))
                fb = timed(lambda: torch.autograd.grad(
                    kernels.deform_conv_fused(xl, offl, None, wl, tensors[4], 1, 1).sum(), [xl, offl, wl]),
                    device, args.repeats)
                lines.append(f"| {block_p} | {block_c} | {nw} | {fwd:.3f} | {fwd / conv_ms:.2f} | {fb:.3f} | "
                             f"{fb / conv_fb:.2f} |")
            except Exception as error:  # a tile that does not compile (registers, shared memory): say so
                lines.append(f"| {block_p} | {block_c} | {nw} | failed: {str(error).splitlines()[0][:80]} | | | |")
            print(lines[-1], flush=True)
        kernels._blocks, kernels.NUM_WARPS = blocks, warps
        lines.append("")
        # after each dtype: a call stopped at its limit keeps the first, marked PARTIAL until the last is in
        # (scripts/gpu_job.sh runs the sweep again then)
        write_record(Path(args.out), lines, None if dtype == dtypes[-1] else "stopped before bf16 was timed.")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
