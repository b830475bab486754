"""The one evaluator: full frames of a split, per-image metrics, aggregates and inference time.

Metrics (bench.metrics): relMSE, robust relMSE, temporal relMSE and HDR-FLIP on linear HDR radiance,
PSNR/SSIM and LDR-FLIP on images clamped to [0, 1]; each with its standard error over sequences.
Methods with `linear_hdr = True` (OIDN, bilinear, bicubic) take and return linear radiance; every other model works in the
network domain of `hdr` (bench.exposure) and its output is mapped back to linear before scoring.
"""
from __future__ import annotations

import math
import time
from pathlib import Path

import numpy as np
import pandas as pd
import torch

from bench.atomic import write_atomic
from bench.exposure import decode, encode, frame_exposure, pass_highlights
from bench.infer import REFERENCE, prepare, tiled_predict
from bench.metrics import METRICS, SEQUENCE_METRICS, all_metrics
from bench.sanitize import sanitize_inputs
from bench.tasks import Task


@torch.no_grad()
def predict(model, x_lin: torch.Tensor, g: torch.Tensor, hdr: str, sanitize: bool = True,
            forward=None) -> torch.Tensor:
    """Linear-radiance prediction for one batch of sequences (B, T, C, h, w), on sanitized inputs
    (bench.sanitize; `sanitize=False` only to show what happens without it). `forward(x, g)` runs the
    model another way (a fast path or tiles, see `runner`); by default `model` itself."""
    if sanitize:
        x_lin, g = sanitize_inputs(x_lin, g)
    forward = forward or model
    if getattr(model, "linear_hdr", False):
        return forward(x_lin, g)["final"]
    exposure = frame_exposure(x_lin, hdr)
    x_net = encode(x_lin, hdr, exposure)
    y = forward(x_net, g)["final"]
    return decode(pass_highlights(y, x_lin, x_net, hdr, exposure), hdr, exposure)


def runner(model, path: str = REFERENCE, tile: int | None = None):
    """The forward function `predict` uses: `model` itself (fp32, untiled), or a fast path of
    bench.infer (e.g. "bf16", "channels_last+bf16") and/or tiled inference with `tile` LR pixels per
    tile. External methods (OIDN, which takes linear radiance) always run their own way."""
    if getattr(model, "linear_hdr", False) or not isinstance(model, torch.nn.Module):
        return None
    if tile:
        overlap = min(128, tile)
        return lambda x, g: {"final": tiled_predict(model, x, g, tile=tile, overlap=overlap, path=path)}
    return None if path == REFERENCE else prepare(model, path)


def sync(device: str) -> None:
    """CUDA kernels run asynchronously: wait for them before reading the clock."""
    if str(device).startswith("cuda"):
        torch.cuda.synchronize()


@torch.no_grad()
def evaluate(model, dataset, task: Task, *, hdr: str = "clamp", device: str = "cpu",
             out_dir: str | Path | None = None, save_exr: bool = False,
             write_exr=None, path: str = REFERENCE, tile: int | None = None,
             scores: tuple[str, ...] | None = None) -> tuple[pd.DataFrame, dict]:
    """Score `model` on every frame of `dataset` (items: full-frame sequences).

    Returns (per-image rows, aggregate metrics). With `save_exr`, `write_exr(path, {name: HxWxC array})`
    writes each output frame beside the metrics in `out_dir/frames/`. `path` and `tile` choose how the
    model runs (see `runner`): fp32 untiled is the reference every table uses unless told otherwise.
    `scores`: the metrics computed (None: every one, SCORES); a learning curve needs three, not FLIP's cost.
    """
    if hasattr(model, "eval"):
        model.to(device).eval()
    forward = runner(model, path, tile)
    rows = []
    for index in range(len(dataset)):
        item = dataset[index]
        x, g, y = (item[k].unsqueeze(0).to(device) for k in (task.x, task.g, task.y))
        # warm-up: first-call allocation is not inference time
        predict(model, x[:, :1], g[:, :1], hdr, forward=forward)
        sync(device)
        t0 = time.perf_counter()
        if getattr(model, "recurrent", False):
            pred = predict(model, x, g, hdr, forward=forward)
        else:  # frame by frame: bounded memory (KPCN's kernels at 1080p), same result
            pred = torch.cat([predict(model, x[:, t:t + 1], g[:, t:t + 1], hdr, forward=forward)
                              for t in range(x.shape[1])], 1)
        sync(device)
        per_frame_ms = 1000 * (time.perf_counter() - t0) / x.shape[1]
        scored = all_metrics(pred[0].cpu(), y[0].cpu(), scores)
        meta = item.get("meta", {})
        frames = meta.get("frames", list(range(x.shape[1])))
        for t in range(x.shape[1]):
            rows.append({"scene": meta.get("scene", index), "sequence": meta.get("sequence", index),
                         "frame": frames[t], "time_ms": per_frame_ms,
                         **{k: float(v[t]) for k, v in scored.items()}})
            if save_exr and out_dir is not None and write_exr is not None:
                frame_dir = Path(out_dir) / "frames"
                frame_dir.mkdir(parents=True, exist_ok=True)
                write_exr(frame_dir / f"{rows[-1]['scene']}_{rows[-1]['frame']:04d}.exr",
                          {"output": pred[0, t].permute(1, 2, 0).cpu().numpy().astype(np.float32)})
    per_image = pd.DataFrame(rows)
    if out_dir is not None:
        Path(out_dir).mkdir(parents=True, exist_ok=True)
        write_atomic(Path(out_dir) / "per_image.csv", lambda tmp: per_image.to_csv(tmp, index=False))
    return per_image, aggregate(per_image)


SCORES = (*METRICS, *SEQUENCE_METRICS)
# scored since evaluations were first recorded: one recorded without them is still reused (its table
# shows "-"; re-evaluating every recorded run would need every split rendered); force=true adds them
LATER_SCORES = ("LDR-FLIP", "HDR-FLIP")
REQUIRED_SCORES = tuple(s for s in SCORES if s not in LATER_SCORES)


def aggregate(per_image: pd.DataFrame) -> dict:
    """Mean of each metric over images (a PSNR of +inf, identical images, stays +inf; the temporal
    relMSE over the frames that have one), and "<metric> se": its standard error over sequences (the
    frames of one sequence are not independent samples: their per-sequence means are)."""
    out = {"images": int(len(per_image))}
    for col in (*SCORES, "time_ms"):
        if col in per_image:
            out[col] = float(per_image[col].mean())
    if "sequence" in per_image and len(per_image):
        by_sequence = per_image.groupby("sequence")
        out["sequences"] = int(by_sequence.ngroups)
        for col in SCORES:
            if col in per_image:
                means = by_sequence[col].mean().replace([np.inf, -np.inf], np.nan).dropna()
                out[f"{col} se"] = float(means.std(ddof=1) / np.sqrt(len(means))) if len(means) > 1 else math.nan
    return out
