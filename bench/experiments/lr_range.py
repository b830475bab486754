"""`+experiment=lr_range`: a learning-rate range test (Smith 2017, "Cyclical Learning Rates") per model.

Each model trains `steps` steps with the preset's recipe (at cpu, the 1000-step recipe without the SSIM
term it was run at: conf/pin/studies.yaml), except that the learning rate rises
geometrically from lr_max * 1e-4 to lr_max (`train.schedule=range`); the loss per step is smoothed
(exponential moving average, `smoothing`) and the test reports where the smoothed loss is lowest and
where training diverges: the first rate whose smoothed loss exceeds `blowup` x its minimum so far. The
suggested peak rate for the cosine schedule is the divergence rate / 10. The textbook rule (lowest-loss
rate / 10) is not used: at the cpu preset one batch's loss varies 2-4x with its crops, so over a few
hundred steps the lowest point of the smoothed loss is mostly noise, while the divergence is sharp.
The runs are ordinary training runs, so a rerun reuses them. Writes `table.{csv,md,tex}` and
`lr_range.png` to `<results_dir>/lr_range/`; `conf/preset/<preset>.yaml`'s `model_lr` takes the suggestions
(at cpu, those of `+study=lr_range_ssim`: this test with the SSIM term, not pinned).
"""
from __future__ import annotations

import logging

import numpy as np
import pandas as pd

from bench import archived
from bench.errors import UserError
from bench.experiments.context import Context, model_config, training_splits, with_training
from bench.experiments.datasets import ensure_data
from bench.experiments.training import trained_model
from bench.table_writer import write_table
from bench.tasks import get_task
from bench.train import lr_at

log = logging.getLogger("bench")


BLOWUP = 4.0  # diverged: the smoothed loss above this many times its minimum so far


def analyse(lr: np.ndarray, loss: np.ndarray, smoothing: float = 0.9, blowup: float = BLOWUP) -> dict:
    """Lowest-loss and divergence rates of one range test, and the suggested peak rate."""
    smooth, avg = np.empty_like(loss), 0.0
    for i, value in enumerate(loss):  # bias-corrected EMA, as fast.ai's LR finder
        avg = smoothing * avg + (1 - smoothing) * value
        smooth[i] = avg / (1 - smoothing ** (i + 1))
    lowest_so_far = np.minimum.accumulate(smooth)
    diverged = np.flatnonzero(~(smooth <= blowup * lowest_so_far))  # NaN counts as diverged
    diverge = int(diverged[0]) if len(diverged) else len(lr) - 1
    lowest = int(np.nanargmin(smooth[:diverge + 1]))
    return {"lowest-loss lr": float(lr[lowest]), "divergence lr": float(lr[diverge]),
            "diverged": bool(len(diverged)), "suggested lr": float(lr[diverge] / 10), "smoothed": smooth}


def run(ctx: Context, name: str, models: list[str], steps: int, lr_max: float, smoothing: float = 0.9,
        task: str = "srd") -> pd.DataFrame:
    """conf/experiment/lr_range.yaml says what each argument is (smoothing and task: the analysis' EMA and
    the task trained, which no table has needed to change)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t = get_task(task)
    ensure_data(ctx, set(t.buffers(with_mid=True)), training_splits(ctx))
    test_ctx = with_training(ctx, {"schedule": "range", "lr": lr_max, "steps": steps, "ema": None,
                                   "val_sequences": 0})
    rows, fig = [], plt.figure(figsize=(6, 4))
    for model in models:
        _, run_ = trained_model(test_ctx, model_config(ctx, model), t, ctx.seeds[0], f"{model} (lr range)",
                                load=False, divergence_ends=True)
        curve = archived.read_curve(run_.dir)  # a range test's is archived whole
        if curve is None:
            raise UserError(f"{run_.dir} has no per-step curve that reads: train it again with force=true")
        found = analyse(curve["lr"].to_numpy(float), curve["loss"].to_numpy(float), smoothing)
        found["diverged"] = found["diverged"] or "diverged_at_step" in run_.metrics  # a non-finite step ended it
        plt.plot(curve["lr"], found.pop("smoothed"), label=model)
        plt.axvline(found["suggested lr"], color=plt.gca().lines[-1].get_color(), ls=":", lw=1)
        rows.append({"model": model, **found, "steps": len(curve), "run": run_.hash})
    table = pd.DataFrame(rows)
    out = ctx.results_dir / name
    lowest_lr = lr_at(0, test_ctx.train)  # the range schedule's own start (bench.train.lr_at)
    write_table(table, out, caption=(
        f"Learning-rate range test (Smith 2017), preset {ctx.preset}, task {task}: {steps} steps of the preset's "
        f"recipe with the lr rising geometrically from {lowest_lr:g} to {lr_max:g}; loss smoothed by an EMA "
        f"({smoothing}). divergence: the first lr whose smoothed loss exceeds {BLOWUP:g}x its minimum so far (diverged "
        f"false: it never did, the test's top lr is shown); suggested = divergence lr / 10, the peak of the cosine "
        f"schedule (conf/preset/<preset>.yaml model_lr)."))
    plt.xscale("log")
    plt.yscale("log")
    plt.xlabel("learning rate")
    plt.ylabel("training loss (smoothed)")
    plt.legend(fontsize=7)
    plt.grid(alpha=0.3)
    plt.title(f"lr range test, preset {ctx.preset}", fontsize=9)
    plt.tight_layout()
    plt.savefig(out / "lr_range.png", dpi=110)
    plt.close(fig)
    log.info("%s: %s", name, out)
    return table
