"""`+experiment=lr_range`: a learning-rate range test (Smith 2017, "Cyclical Learning Rates") per model.

Each model trains `steps` steps with the scale's recipe, except that the learning rate rises
geometrically from lr_max * 1e-4 to lr_max (`train.schedule=range`); the loss per step is smoothed
(exponential moving average, `smoothing`) and the test reports where the smoothed loss falls fastest
(steepest descent per decade) and where it is lowest. The suggested peak rate for the cosine schedule is
the lowest-loss rate / 10, the usual rule: it leaves a margin below where the loss starts to blow up.
The runs are ordinary training runs, so a rerun reuses them. Writes `table.{csv,md,tex}` and
`lr_range.png` to `<results_dir>/lr_range/`; `conf/scale/<scale>.yaml`'s `model_lr` takes the suggestions.
"""
from __future__ import annotations

import logging

import numpy as np
import pandas as pd

from bench.experiments.pipeline import Context, model_config, trained_model, with_training, ensure_data
from bench.tables import write_table
from bench.tasks import get_task

log = logging.getLogger("bench")


def analyse(lr: np.ndarray, loss: np.ndarray, smoothing: float = 0.9, skip: float = 0.1) -> dict:
    """Steepest-descent and lowest-loss rates of one range test (the first `skip` fraction of steps is
    left out: the smoothed loss there still carries its bias towards the first value)."""
    smooth, avg = np.empty_like(loss), 0.0
    for i, value in enumerate(loss):  # bias-corrected EMA, as fast.ai's LR finder
        avg = smoothing * avg + (1 - smoothing) * value
        smooth[i] = avg / (1 - smoothing ** (i + 1))
    start = int(skip * len(lr))
    lowest = start + int(np.argmin(smooth[start:]))
    slope = np.gradient(smooth, np.log10(lr))
    steepest = start + int(np.argmin(slope[start:lowest + 1]))
    return {"lowest-loss lr": float(lr[lowest]), "steepest lr": float(lr[steepest]),
            "suggested lr": float(lr[lowest] / 10), "smoothed": smooth}


def run(ctx: Context, name: str = "lr_range", models: list[str] | None = None, steps: int = 200,
        lr_max: float = 0.1, smoothing: float = 0.9, task: str = "srd") -> pd.DataFrame:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t = get_task(task)
    ensure_data(ctx, set(t.buffers(with_mid=True)))
    test_ctx = with_training(ctx, {"schedule": "range", "lr": lr_max, "steps": steps, "ema": None,
                                   "val_sequences": 0})
    rows, fig = [], plt.figure(figsize=(6, 4))
    for model in models or []:
        _, run_ = trained_model(test_ctx, model_config(ctx, model), t, ctx.seeds[0], f"{model} (lr range)",
                                load=False)
        curve = pd.read_csv(run_.dir / "curve.csv")
        found = analyse(curve["lr"].to_numpy(float), curve["loss"].to_numpy(float), smoothing)
        plt.plot(curve["lr"], found.pop("smoothed"), label=model)
        rows.append({"model": model, **found, "steps": steps, "run": run_.hash})
    table = pd.DataFrame(rows)
    out = ctx.results_dir / name
    write_table(table, out, caption=(
        f"Learning-rate range test (Smith 2017), scale {ctx.scale}, task {task}: {steps} steps of the scale's "
        f"recipe with the lr rising geometrically from {lr_max:g}e-4 to {lr_max:g}; loss smoothed by an EMA "
        f"({smoothing}). suggested = lowest-loss lr / 10, the peak of the cosine schedule."))
    plt.xscale("log")
    plt.xlabel("learning rate")
    plt.ylabel("training loss (smoothed)")
    plt.legend(fontsize=7)
    plt.grid(alpha=0.3)
    plt.title(f"lr range test, scale {ctx.scale}", fontsize=9)
    plt.tight_layout()
    plt.savefig(out / "lr_range.png", dpi=110)
    plt.close(fig)
    log.info("%s: %s", name, out)
    return table
