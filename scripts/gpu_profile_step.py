"""Where Ours' training step spends its time: torch.profiler over a few steps of the trainer's step
(`bench.experiments.speed.training_step`: HDR encode, the loss without its perceptual term, backward, clip,
Adam, EMA, as the speed table times it) eager and under torch.compile, at the preset's recipe (the gpu
preset's batch 4 x 7 frames of 64x64 LR unless --batch, --frames, --crop say otherwise). Writes a markdown
table: wall ms per step, the GPU kernels' ms per step (the profiler's own per-kernel totals, device
time of kernels only, each kernel counted once), and the GPU busy share (kernels / wall). A busy share
far under 1 means the step is host-bound (launches, Python), not GPU-bound; the host column then says
where the host's time goes. `--reduce-overhead` adds torch.compile's CUDA-graph mode (the trainer's
train.compile=reduce-overhead). On a machine without CUDA it profiles the CPU and says so (no GPU columns).
    python scripts/gpu_profile_step.py --device cuda --out results/gpu/profile/<device>.md
    python scripts/gpu_profile_step.py --device cpu --batch 1 --frames 2 --crop 16 --channels 8 --out /tmp/p.md
"""
import argparse
import os
import sys
import time
from dataclasses import replace

import torch
from torch.profiler import ProfilerActivity, profile

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, os.path.join(ROOT, "scripts"))

from bench.experiments.speed import step_note, training_step  # noqa: E402
from bench.machine import device_tag  # noqa: E402
from bench.models.factory import build_model  # noqa: E402
from bench.train import Recipe  # noqa: E402
from gpu_step_concurrency import composed  # noqa: E402

MODES = {"eager": None, "torch.compile": "default", "reduce-overhead": "reduce-overhead"}  # path -> train.compile


def ours(cfg: dict, channels: int | None) -> torch.nn.Module:
    """Ours at the preset's width, or `channels`, at scale 2."""
    torch.manual_seed(0)
    return build_model({**cfg["models"]["srd"], **({"channels": channels} if channels else {})}, 2)


def make_step(model, recipe: Recipe, device: str, mode: str):
    """The trainer's step of `model` at `recipe`, compiled as `mode` says (Dynamo reset first: each mode
    compiles on its own)."""
    recipe = replace(recipe, compile=MODES[mode], precision="fp32", channels_last=False)
    if MODES[mode] is not None:
        torch._dynamo.reset()
    return training_step(model, recipe, device)


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
    averages = prof.key_averages()  # seconds per call over a step's tens of thousands of events: once
    if device == "cuda":
        # kernels only (device_type CUDA events): memcpy/memset and the CPU-side ops' "cuda time" (which
        # re-counts their kernels) are left out, so no kernel is counted twice
        kernel_us = sum(e.device_time_total for e in averages
                        if e.device_type == torch.autograd.DeviceType.CUDA)
        row["GPU kernels ms/step"] = kernel_us / 1e3 / steps
        row["GPU busy"] = row["GPU kernels ms/step"] / wall_ms
    def top(time_of):
        ranked = sorted(averages, key=lambda e: -time_of(e))[:5]
        return ", ".join(f"{e.key[:60]} {time_of(e) / 1e3 / steps:.2f}" for e in ranked)
    if device == "cuda":
        row["top ops (GPU self ms)"] = top(lambda e: e.self_device_time_total)
        row["launches/step"] = sum(e.count for e in averages
                                   if e.device_type == torch.autograd.DeviceType.CUDA) / steps
    row["top ops (host self ms)"] = top(lambda e: e.self_cpu_time_total)
    return row


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default="cuda")
    parser.add_argument("--preset", default="gpu", help="the recipe and Ours' width (conf/preset)")
    parser.add_argument("--batch", type=int, default=None, help="sequences a step (default: the preset's)")
    parser.add_argument("--frames", type=int, default=None, help="frames a sequence (default: the preset's)")
    parser.add_argument("--crop", type=int, default=None, help="LR crop (default: the preset's)")
    parser.add_argument("--channels", type=int, default=None, help="Ours' width (default: the preset's)")
    parser.add_argument("--warmup", type=int, default=3)
    parser.add_argument("--steps", type=int, default=5)
    parser.add_argument("--no-compile", action="store_true")
    parser.add_argument("--reduce-overhead", action="store_true", help="also torch.compile(mode='reduce-overhead')")
    parser.add_argument("--out", required=True)
    args = parser.parse_args()
    device = args.device if args.device != "cuda" or torch.cuda.is_available() else "cpu"
    cfg = composed(args.preset, [])
    recipe = Recipe.from_config(cfg["train"])
    recipe = replace(recipe, **{field: value for field, value in (("batch_size", args.batch), ("seq_len", args.frames),
                                                                   ("crop", args.crop)) if value is not None})
    rows = {}
    modes = ["eager"] + ([] if args.no_compile else ["torch.compile"]) + (["reduce-overhead"] if args.reduce_overhead else [])
    for mode in modes:
        try:
            rows[mode] = profile_step(make_step(ours(cfg, args.channels), recipe, device, mode), device,
                                      args.warmup, args.steps)
        except Exception as error:  # a mode that fails here is a finding, not the end of the profile
            rows[mode] = {"wall ms/step": f"failed: {str(error).splitlines()[0][:100]}"}
    columns = max(rows.values(), key=len)
    lines = [f"# Ours' training step under torch.profiler on {device_tag(device)}", "",
             f"`{' '.join(['python scripts/gpu_profile_step.py'] + [a for a in os.sys.argv[1:]])}`: batch "
             f"{recipe.batch_size} x {recipe.seq_len} frames of {recipe.crop}x{recipe.crop} LR at preset "
             f"{args.preset}, {step_note(recipe)}, fp32; mean of "
             f"{args.steps} steps after {args.warmup}; SRD_BENCH_FUSED_GPU={os.environ.get('SRD_BENCH_FUSED_GPU', '0')}; "
             f"torch {torch.__version__}." + ("" if device == "cuda" else " No CUDA here: CPU only, no GPU columns."), "",
             "| path | " + " | ".join(columns) + " |", "|---" * (len(columns) + 1) + "|"]
    for path, row in rows.items():
        lines.append(f"| {path} | " + " | ".join(f"{row[c]:.3g}" if isinstance(row.get(c), float) else str(row.get(c, ""))
                                                  for c in columns) + " |")
    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    with open(args.out, "w") as f:
        f.write("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
