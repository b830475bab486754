"""One model, trained and evaluated on its own (`+experiment=train`, conf/experiment/train.yaml):

    python -m bench +experiment=train experiment.model=srd preset=cpu [seeds=[0]]

It is a one-row table (bench.experiments.table) whose row is written as a table's rows are (model,
overrides, task, train, cascade), so its runs have that row's identity in any table: it reuses what a
table recorded (the sota table's Ours for `srd`) and a table reuses what it records. The log says, per
seed, which training and evaluation runs it reused and which it computed. Its table goes to
`<results_dir>/train/<label>/` (the label: the model's name unless `experiment.label` says otherwise).
"""
from __future__ import annotations

import logging
import time
from pathlib import Path

import pandas as pd

from bench import runs
from bench.errors import UserError
from bench.experiments.context import Context
from bench.experiments.table import run as run_table
from bench.table_writer import listed_evaluations

log = logging.getLogger("bench")


def one_row(model: str, overrides: dict | None = None, task: str = "srd", train: dict | None = None,
            cascade: bool = False, label: str | None = None) -> dict:
    """The table row of one model (the label is not part of any identity)."""
    return {"label": label or model, "model": model, "overrides": overrides or {}, "task": task,
            "train": train or {}, "cascade": cascade}


def run(ctx: Context, name: str, model: str, overrides: dict | None = None, task: str = "srd",
        train: dict | None = None, cascade: bool = False, label: str | None = None, split: str | None = None,
        figure: bool = True) -> pd.DataFrame:
    started = time.time()
    row = one_row(model, overrides, task, train, cascade, label)
    if Path(row["label"]).name != row["label"] or row["label"] in ("", ".", ".."):  # it names a folder
        raise UserError(f"experiment.label={row['label']!r}: the table's folder under {ctx.results_dir / name}, "
                        "one name without / or ..")
    table = run_table(ctx, f"{name}/{row['label']}", [row], caption=f"One model: {row['label']}.", task=task, split=split,
                      paper_table=None, figure=figure)
    if not table.empty:  # (a shard= run writes no table)
        for seed, eval_hash in zip(ctx.seeds, listed_evaluations(table["runs"].iloc[0])):
            log.info("%s seed %s: %s", row["label"], seed, reuse_summary(eval_hash, ctx.runs_dir, ctx.archives, started))
    return table


def reuse_summary(eval_hash: str, runs_dir, archives, started: float) -> str:
    """Which runs an evaluation and its trainings are, and whether each was computed before `started`
    (reused, with the label of the row that recorded it) or since."""
    said = []
    record = runs.find_record("eval", eval_hash, runs_dir, archives)[1] or {}
    trainings = runs.trainings_of(record)
    for kind, h, rec in [("train", t, runs.find_record("train", t, runs_dir, archives)[1] or {})
                         for t in trainings] + [("eval", eval_hash, record)]:
        what = "training" if kind == "train" else "evaluation"
        if rec.get("finished_s", 0.0) < started:
            said.append(f"reused {what} run {h} (recorded by the row {rec.get('label')!r})")
        else:
            said.append(f"computed {what} run {h}")
    return "; ".join(said)
