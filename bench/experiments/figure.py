"""Qualitative figure of a table (as the paper's Figs. 8-11): crops of one fixed validation frame, the
input bilinear, each row's output and the reference, each crop titled with its relMSE.

The frame is the last frame of the split's first sequence (recurrent models have seen the whole
sequence); the crop is the window of the reference with the most gradient energy, so it shows edges
and texture rather than a flat wall.
"""
from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from bench import archived
from bench.evaluate import predict
from bench.experiments.context import Context, row_setting
from bench.experiments.datasets import dataset, evaluation_data
from bench.experiments.training import cascade_model, trained_model
from bench.metrics import relmse
from bench.nn.blocks import upsampled_input
from bench.tasks import get_task

log = logging.getLogger("bench")


def busiest_window(ref: torch.Tensor, size: int) -> tuple[int, int]:
    """Top-left corner of the size x size window of ref (3, H, W) with the largest gradient energy."""
    lum = ref.clamp(0, 1).mean(0)
    energy = (lum[1:, :-1] - lum[:-1, :-1]).abs() + (lum[:-1, 1:] - lum[:-1, :-1]).abs()
    sums = F.avg_pool2d(energy[None, None], size - 1, stride=1)[0, 0]
    flat = int(sums.argmax())
    return divmod(flat, sums.shape[1])


def tonemap(img: torch.Tensor) -> np.ndarray:
    """Linear radiance (3, h, w) -> displayable sRGB-ish (h, w, 3) in [0, 1] (clamp, gamma 2.2)."""
    return img.clamp(0, 1).pow(1 / 2.2).permute(1, 2, 0).cpu().numpy()


def _row_output(ctx: Context, r: dict, x, g, seed: int) -> torch.Tensor:
    rctx, cfg, task, cascade = row_setting(ctx, r)
    if cascade:
        model, _ = cascade_model(rctx, cfg, seed, r["label"])
    else:
        model, _ = trained_model(rctx, cfg, task, seed, r["label"])
    if hasattr(model, "eval"):
        model.to(ctx.device).eval()
    return predict(model, x.to(ctx.device), g.to(ctx.device), rctx.train.hdr)[0, -1].cpu()


def crop_figure(ctx: Context, rows: list[dict], path: Path, split: str = "val", size: int = 64) -> Path | None:
    """Write the crops PNG for `rows` (expanded table rows); rows of different tasks get their own input."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    seed = ctx.seeds[0]
    panels, ref = [], None
    for task_name in dict.fromkeys(r["task"] for r in rows):
        task = get_task(task_name)
        item = dataset(evaluation_data(ctx), split, task, training=False)[0]
        x, g, y = item[task.x][None], item[task.g][None], item[task.y][-1]
        if ref is None:
            ref = y
            size = min(size, y.shape[-2], y.shape[-1])
            top, left = busiest_window(y, size)
        if task.scale > 1:
            base = upsampled_input(x[0, -1:], task.scale)[0]
            panels.append((f"Input bilinear ({task_name})" if len(panels) else "Input bilinear", base))
        else:
            panels.append((f"Input ({task_name})", x[0, -1]))
        for r in (r for r in rows if r["task"] == task_name and r["model"] != "bilinear"):
            panels.append((r["label"], _row_output(ctx, r, x, g, seed)))
    panels.append(("Reference", ref))
    crop = (slice(None), slice(top, top + size), slice(left, left + size))
    cols = min(len(panels), 5)
    nrows = -(-len(panels) // cols)
    fig, axes = plt.subplots(nrows, cols, figsize=(2.4 * cols, 2.7 * nrows), squeeze=False)
    for ax in axes.flat:
        ax.axis("off")
    for ax, (label, img) in zip(axes.flat, panels):
        c = img[crop]
        ax.imshow(tonemap(c))
        title = label if label == "Reference" else f"{label}\nrelMSE {float(relmse(c, ref[crop])):.4f}"
        ax.set_title(title, fontsize=7)
    fig.suptitle(f"{path.parent.name}: {split} frame, crop {size}x{size} at ({top}, {left})", fontsize=8)
    return _save(fig, path, dpi=120)


def curve_figure(runs_dir: Path, curves: dict[str, list[str]], path: Path, metric: str = "PSNR") -> Path | None:
    """Learning curves of a table's rows: validation `metric` against training steps and against training
    wall time, one line per row (seeds of a row share its colour). `curves` maps a row label to the hashes
    of its training runs; runs without a recorded curve (cascade stages, non-learned rows) are left out."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (by_step, by_time) = plt.subplots(1, 2, figsize=(11, 4))
    drawn = 0
    for i, (label, hashes) in enumerate(curves.items()):
        for j, h in enumerate(hashes):
            curve = archived.read_val_curve(Path(runs_dir) / "train" / h)  # None: missing or damaged
            if curve is None or not {"step", "train_s", metric} <= set(curve):
                continue
            style = {"color": f"C{i % 10}", "label": label if j == 0 else None, "alpha": 1.0 if j == 0 else 0.5}
            by_step.plot(curve["step"], curve[metric], marker=".", **style)
            by_time.plot(curve["train_s"] / 60, curve[metric], marker=".", **style)
            drawn += 1
    if not drawn:
        plt.close(fig)
        return None
    by_step.set_xlabel("training step")
    by_time.set_xlabel("training wall time (min)")
    for ax in (by_step, by_time):
        ax.set_ylabel(f"val {metric} (curve subset)")
        ax.grid(alpha=0.3)
    by_step.legend(fontsize=7)
    fig.suptitle(f"{path.parent.name}: learning curves (EMA weights, validation subset; step 0 = the start)",
                 fontsize=9)
    return _save(fig, path, dpi=110)


def _save(fig, path: Path, dpi: int) -> Path:
    import matplotlib.pyplot as plt
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=dpi)
    plt.close(fig)
    log.info("figure: %s", path)
    return path
