"""A metrics table: one row per (model, overrides, task), each a recorded run, written with
`bench.tables.write_table` to `<results_dir>/<name>/table.{csv,tex,md}`."""
from __future__ import annotations

import logging

import pandas as pd

from bench.experiments.pipeline import Context, ensure_data, model_config, row
from bench.metrics import HIGHER_IS_BETTER, LOWER_IS_BETTER, RELMSE_FORMULA
from bench.tables import write_table
from bench.tasks import get_task

log = logging.getLogger("bench")


def passes_for(rows: list[dict], default_task: str) -> set[str]:
    """The union of buffers the table's tasks read (training and evaluation)."""
    needed = set()
    for r in rows:
        needed.update(get_task(r.get("task", default_task)).buffers(with_mid=True))
    return needed


def run(ctx: Context, name: str, rows: list[dict], caption: str = "", task: str = "srd",
        split: str | None = None) -> pd.DataFrame:
    for r in rows:  # fail on a bad model name before any rendering or training
        model_config(ctx, r["model"], r.get("overrides"))
    ensure_data(ctx, passes_for(rows, task))
    table = pd.DataFrame([row(ctx, r["label"], r["model"], r.get("overrides"), r.get("task", task), split)
                          for r in rows])
    loss = ctx.train["loss"]["final"]
    notes = (f"{RELMSE_FORMULA}; PSNR/SSIM on images clamped to [0, 1]. Scale {ctx.scale}, "
             f"{ctx.train['steps']} training steps, loss g:t:s:p = {loss['edge']}:{loss['temporal']}:"
             f"{loss['spatial']}:{loss['perceptual']}, seeds {list(ctx.seeds)}.")
    vgg = sorted({v for v in table.pop("vgg") if v})
    if vgg:
        notes += f" Perceptual loss features: {'; '.join(vgg)}."
    write_table(table.drop(columns=["reused"]), ctx.results_dir / name,
                caption=f"{caption} {notes}".strip(),
                lower_is_better=LOWER_IS_BETTER, higher_is_better=HIGHER_IS_BETTER)
    reused = int(table["reused"].sum())
    log.info("%s: %d of %d rows reused from the run store; table in %s", name, reused, len(table),
             ctx.results_dir / name)
    return table
