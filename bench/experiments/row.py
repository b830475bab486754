"""One table row: its model trained and evaluated for every seed (`evaluated`), the metrics averaged
over seeds, and what the row cost and how its learning curve ended, as recorded in the run store.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from bench import archived, runs
from bench.evaluate import SCORES
from bench.experiments.context import TRAINING_CODE, Context, code_of, model_config, with_training
from bench.experiments.evaluation import evaluated
from bench.tasks import get_task


def recorded_minutes(eval_hashes, runs_dir: str | Path, archives=()) -> dict[str, float | None]:
    """Recorded wall minutes of each distinct run behind these evaluations, keyed "eval/<hash>" and
    "train/<hash>": the evaluations and the trainings they scored (each stage of a Cascade). A run
    neither the store nor the archives hold maps to None; a missing evaluation hides its trainings."""
    minutes = {}
    for h in eval_hashes:
        record = runs.find_record("eval", h, runs_dir, archives)[1]
        if record is None:
            minutes[f"eval/{h}"] = None
            continue
        minutes[f"eval/{h}"] = (record.get("wall_time_s") or 0.0) / 60
        for t in runs.trainings_of(record):
            seconds = runs.recorded_wall_s("train", t, runs_dir, archives)
            minutes[f"train/{t}"] = None if seconds is None else seconds / 60
    return minutes


def last_fifth_gain(run_dir: Path, metric: str = "PSNR") -> float | None:
    """How much the validation `metric` rose over the last fifth of training `run_dir` (the final point
    minus the point at 80% of the steps, from its validation curve): near 0, the curve has flattened;
    None without a curve."""
    curve = archived.read_val_curve(run_dir)  # None: missing or damaged (the log names it)
    if curve is None or len(curve) < 2 or not {"step", metric} <= set(curve):
        return None
    last = curve.iloc[-1]
    before = curve[curve["step"] <= 0.8 * last["step"]].iloc[-1]
    return float(last[metric] - before[metric])


def row(ctx: Context, label: str, model: str, overrides: dict | None = None, task: str = "srd",
        split: str | None = None, train: dict | None = None, cascade: bool = False) -> dict:
    """One table row: metrics averaged over `ctx.seeds` (with std when there are several).
    `train` overrides the training recipe for this row; `cascade` trains the stages separately."""
    t = get_task(task)
    cfg = model_config(ctx, model, overrides)
    ctx = with_training(ctx, train, model)
    split = split or ctx.eval.split
    results = [evaluated(ctx, cfg, t, seed, split, label, cascade) for seed in ctx.seeds]
    out = {"method": label, "task": task}
    for metric in (*SCORES, "time_ms"):  # NaN: a seed's evaluation was recorded without it (LATER_SCORES)
        values = np.array([r.metrics.get(metric, np.nan) for r in results], dtype=float)
        out[metric] = float(values.mean())
        if len(values) > 1:
            out[f"{metric} std"] = float(values.std(ddof=1))
    for metric in SCORES:  # uncertainty over the split's sequences (a seed average for several seeds)
        out[f"{metric} se"] = float(np.mean([r.metrics.get(f"{metric} se", np.nan) for r in results]))
    out["params"] = results[0].metrics.get("params", 0)
    # what this row cost to compute, whenever it was computed (a reused run keeps its recorded time)
    out["train (min)"] = float(np.mean([sum(runs.recorded_wall_s("train", h, ctx.runs_dir, ctx.archives) or 0.0
                                            for h in runs.trainings_of(r.record)) for r in results])) / 60
    out["eval (min)"] = float(np.mean([r.record.get("wall_time_s") or 0.0 for r in results])) / 60
    gains = [last_fifth_gain(ctx.runs_dir / "train" / h) for r in results
             for h in runs.trainings_of(r.record)]
    gains = [g for g in gains if g is not None]
    out["last fifth (dB)"] = float(np.mean(gains)) if gains else None
    vgg = results[0].metrics.get("vgg")
    out["vgg"] = f"VGG16 {vgg['layer']} from {vgg['weights']}" if vgg else None
    out["renders"] = [r.metrics.get("render") for r in results]  # None: recorded before digests
    out["rounded"] = sum(bool(r.metrics.get("rounded_weights")) for r in results)
    trainings = [runs.read_record(ctx.runs_dir / "train" / h / runs.RECORD) for r in results
                 for h in runs.trainings_of(r.record)[:1]]  # a Cascade's stages: one recipe
    code = code_of(cfg, *TRAINING_CODE)
    out["stale"] = sum(bool(record and runs.code_changes(record, code)) for record in trainings)
    out["runs"] = " ".join(r.hash for r in results)
    out["train runs"] = [t for r in results for t in runs.trainings_of(r.record)]  # the curves figure reads them
    out["reused"] = all(r.reused for r in results)
    return out
