"""Where Ours' training step spends its time: torch.profiler over a few steps (forward, L1 loss,
backward, Adam) eager and under torch.compile, at the gpu preset's training batch. Writes a markdown
table: wall ms per step, the GPU kernels' ms per step (the profiler's own per-kernel totals, device
time of kernels only, each kernel counted once), and the GPU busy share (kernels / wall). A busy share
far under 1 means the step is host-bound (launches, Python), not GPU-bound. On a machine without CUDA
it profiles the CPU and says so (no GPU columns).
    python scripts/gpu_profile_step.py --device cuda --out results/gpu/profile/<device>.md
    python scripts/gpu_profile_step.py --device cpu --batch 1 --frames 2 --crop 16 --channels 8 --out /tmp/p.md
"""
import argparse
import os
import time

import torch
import torch.nn.functional as F
import yaml
from torch.profiler import ProfilerActivity, profile

from bench.experiments.speed import device_tag, frame_inputs
from bench.models.factory import build_model

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def ours(channels: int | None) -> torch.nn.Module:
    """Ours (conf/model/srd.yaml) at scale 2, its width overridden by `channels`."""
    with open(os.path.join(ROOT, "conf/model/srd.yaml")) as f:
        cfg = yaml.safe_load(f)
    if channels:
        cfg["channels"] = channels
    torch.manual_seed(0)
    return build_model(cfg, 2)


def make_step(model, x, g, target, compiled: bool):
    optimizer = torch.optim.Adam(model.parameters(), lr=1e-4)
    forward = torch.compile(model) if compiled else model

    def step():
        optimizer.zero_grad(set_to_none=True)
        out = forward(x, g)
        loss = F.l1_loss(out["final"], target)
        if out.get("intermediate") is not None:
            loss = loss + F.l1_loss(out["intermediate"], target)
        loss.backward()
        optimizer.step()
    return step


def synchronize(device: str) -> None:
    if device == "cuda":
        torch.cuda.synchronize()


def profile_step(step, device: str, warmup: int, steps: int) -> dict:
    """Wall ms per step, and on CUDA the kernels' device ms per step from the profiler's totals."""
    for _ in range(warmup):
        step()
    synchronize(device)
    activities = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if device == "cuda" else [])
    with profile(activities=activities) as prof:
        start = time.perf_counter()
        for _ in range(steps):
            step()
        synchronize(device)
        wall_ms = (time.perf_counter() - start) * 1e3 / steps
    row = {"wall ms/step": wall_ms}
    if device == "cuda":
        # kernels only (device_type CUDA events): memcpy/memset and the CPU-side ops' "cuda time" (which
        # re-counts their kernels) are left out, so no kernel is counted twice
        kernel_us = sum(e.device_time_total for e in prof.key_averages()
                        if e.device_type == torch.autograd.DeviceType.CUDA)
        row["GPU kernels ms/step"] = kernel_us / 1e3 / steps
        row["GPU busy"] = row["GPU kernels ms/step"] / wall_ms
    row["top ops (self time)"] = ", ".join(
        f"{e.key} {(e.self_device_time_total if device == 'cuda' else e.self_cpu_time_total) / 1e3 / steps:.2f}"
        for e in sorted(prof.key_averages(), key=lambda e: -(e.self_device_time_total if device == "cuda"
                                                                else e.self_cpu_time_total))[:5])
    return row


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default="cuda")
    parser.add_argument("--batch", type=int, default=4)
    parser.add_argument("--frames", type=int, default=7)    # the gpu preset's seq_len
    parser.add_argument("--crop", type=int, default=64)     # the gpu preset's LR crop
    parser.add_argument("--channels", type=int, default=None, help="Ours' width (default conf/model/srd.yaml)")
    parser.add_argument("--warmup", type=int, default=3)
    parser.add_argument("--steps", type=int, default=5)
    parser.add_argument("--no-compile", action="store_true")
    parser.add_argument("--out", required=True)
    args = parser.parse_args()
    device = args.device if args.device != "cuda" or torch.cuda.is_available() else "cpu"
    x, g = frame_inputs(args.batch, args.frames, (args.crop, args.crop), device, seed=1)
    target = torch.rand(args.batch, args.frames, 3, 2 * args.crop, 2 * args.crop, device=device)
    rows = {}
    for compiled in (False,) if args.no_compile else (False, True):
        model = ours(args.channels).to(device).train()
        rows["torch.compile" if compiled else "eager"] = profile_step(make_step(model, x, g, target, compiled),
                                                                      device, args.warmup, args.steps)
    columns = list(next(iter(rows.values())))
    lines = [f"# Ours' training step under torch.profiler on {device_tag(device)}", "",
             f"`{' '.join(['python scripts/gpu_profile_step.py'] + [a for a in os.sys.argv[1:]])}`: batch "
             f"{args.batch} x {args.frames} frames of {args.crop}x{args.crop} LR, L1 loss, Adam; mean of "
             f"{args.steps} steps after {args.warmup}; SRD_BENCH_FUSED_GPU={os.environ.get('SRD_BENCH_FUSED_GPU', '0')}; "
             f"torch {torch.__version__}." + ("" if device == "cuda" else " No CUDA here: CPU only, no GPU columns."), "",
             "| path | " + " | ".join(columns) + " |", "|---" * (len(columns) + 1) + "|"]
    for path, row in rows.items():
        lines.append(f"| {path} | " + " | ".join(f"{v:.3g}" if isinstance(v, float) else str(v)
                                                  for v in row.values()) + " |")
    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    with open(args.out, "w") as f:
        f.write("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
