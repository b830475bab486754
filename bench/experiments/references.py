"""`+experiment=references`: which sequences' references need more samples, read from the recorded tables.

A scored frame's reference passes when its estimated error (two half-sample renders) is below a tenth of
the best row's relMSE on it (`table.reference_shortfall`). For every table of `results_dir` and of the
split folders beside it (results/cpu/val/...) that scored a split with two-half references, each frame's
shortfall against that table's best row; a frame's worst over the tables decides. A reference's error
falls as 1/spp, so a sequence whose worst frame falls short by a factor f gets
ref_spp x 2^ceil(log2(f / margin)) samples (at most `max_ref_spp`), and that count goes into the data spec:
`data.splits.<split>.sequence_ref_spp` (datagen.render_settings), which re-renders those sequences'
frames; every table of the split is then scored again (evaluations only).

Writes `<results_dir>/references/table.{csv,md,tex}` (per sequence: frames, worst shortfall, the table it
comes from, spp now and proposed, the recorded reference render seconds and the estimate at the proposed
spp) and `sequence_ref_spp.yaml`, the lines for conf/data/<preset>.yaml. It renders and trains nothing. A
table whose evaluations scored another render of the split than `data_dir` holds is left out (the log says so).
"""
from __future__ import annotations

import logging
import math
import re

import pandas as pd
import yaml

from bench import runs
from bench.datagen import load_manifest
from bench.errors import UserError
from bench.experiments.context import SCORED_ON_PATTERN, Context
from bench.experiments.datasets import render_digest
from bench.experiments.table import reference_shortfall
from bench.table_writer import write_table
from bench.tasks import get_task

log = logging.getLogger("bench")


def _caption(table_md) -> str:
    return table_md.read_text().split("\n\n")[0] if table_md.exists() else ""


def table_shortfalls(ctx: Context, frames: list[dict]) -> pd.DataFrame:
    """One row per (table, scored frame): the frame's reference shortfall against that table's best row,
    for the tables of results_dir and its split folders whose runs the store or archive holds."""
    archives = [ctx.runs_archive] if ctx.runs_archive else []
    out = []
    for path in sorted([*ctx.results_dir.glob("*/table.csv"), *ctx.results_dir.glob("*/*/table.csv")]):
        caption = _caption(path.with_suffix(".md"))
        match = re.search(SCORED_ON_PATTERN, caption)
        table = pd.read_csv(path)
        if not match or "References (" not in caption or not {"relMSE", "runs"} <= set(table):
            continue  # not a metrics table, or its references are not estimated (no two halves)
        split = match.group(2)
        best = table.loc[table["relMSE"].idxmin()]
        task = best["task"] if "task" in table else re.search(r"Task (\w+)", caption).group(1)
        per_image, scored = [], set()
        for h in str(best["runs"]).split():
            record_path, record = runs.find_record("eval", h, ctx.runs_dir, archives)
            per_image_csv = record_path.parent / "per_image.csv" if record_path else None
            if per_image_csv is None or not per_image_csv.exists():
                raise UserError(f"references: {path}: evaluation {h} of its best row ({best['method']}) is in "
                                "neither the run store nor the archive; regenerate the table first")
            per_image.append(pd.read_csv(per_image_csv, dtype={"sequence": str}))
            scored.add(record.get("metrics", {}).get("render"))
        if scored != {render_digest(ctx, split)}:  # the estimates describe this render's references, not those
            log.info("references: %s left out: it scored another render of split %s", path, split)
            continue
        shortfall = reference_shortfall([f for f in frames if f["split"] == split], pd.concat(per_image),
                                        get_task(task).y[:2])
        name = path.parent.relative_to(ctx.results_dir).as_posix()
        out += [{"split": split, "sequence": seq, "frame": frame, "table": name, "best row": best["method"],
                 "shortfall": value} for (seq, frame), value in shortfall.items()]
    return pd.DataFrame(out, columns=["split", "sequence", "frame", "table", "best row", "shortfall"])


def proposed_spp(ref_spp: int, shortfall: float, margin: float, max_ref_spp: int) -> int:
    """The reference spp that brings a frame `shortfall` times over the criterion to `margin` of it
    (error ~ 1/spp), in powers of two of `ref_spp`, at most `max_ref_spp`; `ref_spp` when it passes."""
    if shortfall < margin:
        return ref_spp
    return min(max_ref_spp, ref_spp * 2 ** math.ceil(math.log2(shortfall / margin)))


def run(ctx: Context, name: str = "references", margin: float = 0.8, max_ref_spp: int = 8192) -> pd.DataFrame:
    frames = load_manifest(ctx.data_dir)["frames"]  # the frames' estimated reference errors
    shortfalls = table_shortfalls(ctx, frames)
    if shortfalls.empty:
        raise UserError(f"references: no table in {ctx.results_dir} scored frames of {ctx.data_dir} whose references "
                        "have an error estimate (splits with their own ref_spp render two halves)")
    worst = shortfalls.loc[shortfalls.groupby(["split", "sequence", "frame"])["shortfall"].idxmax()]
    records = {(f["split"], f["sequence"], f["frame"]): f for f in frames}
    rows = []
    for (split, sequence), part in worst.groupby(["split", "sequence"]):
        top = part.loc[part["shortfall"].idxmax()]
        recs = [records[(split, sequence, frame)] for frame in part["frame"]]
        now = int(recs[0]["ref_spp"])
        new = proposed_spp(now, float(top["shortfall"]), margin, max_ref_spp)
        seconds = sum(r["time_s"].get("hr_ref_s", 0) + r["time_s"].get("lr_ref_s", 0) for r in recs)
        rows.append({"split": split, "sequence": sequence, "frames": len(part),
                     "frames passing": int((part["shortfall"] < 1).sum()),
                     "worst shortfall": float(top["shortfall"]), "worst in": f"{top['table']} ({top['best row']})",
                     "ref spp": now, "proposed ref spp": new, "ref render s": seconds,
                     "ref render s at proposed": seconds * new / now})
    table = pd.DataFrame(rows).sort_values(["split", "worst shortfall"], ascending=[True, False])
    proposal = {split: {r["sequence"]: int(r["proposed ref spp"]) for _, r in part.iterrows()
                        if r["proposed ref spp"] != r["ref spp"]} for split, part in table.groupby("split")}
    out_dir = ctx.results_dir / name
    caption = (f"References that fall short, preset {ctx.preset}: per sequence of each scored split, its frames' "
               f"worst shortfall over the recorded tables (estimated reference relMSE over a tenth of the table's "
               f"best row's relMSE on the frame; below 1 passes) and the reference spp that brings it to "
               f"{margin:g} of the criterion, assuming error ~ 1/spp (at most {max_ref_spp}). Passing now: "
               + ", ".join(f"{split} {int(p['frames passing'].sum())} of {int(p['frames'].sum())} frames"
                           for split, p in table.groupby("split"))
               + ". ref render s: the recorded seconds of the sequence's reference renders (both resolutions), "
               "and scaled to the proposed spp. The proposal, for conf/data/<preset>.yaml under each split "
               "(data.splits.<split>.sequence_ref_spp), is in sequence_ref_spp.yaml beside this table.")
    write_table(table, out_dir, caption=caption)
    (out_dir / "sequence_ref_spp.yaml").write_text(yaml.safe_dump(
        {split: {"sequence_ref_spp": spp} for split, spp in proposal.items() if spp}, sort_keys=True))
    for split, spp in proposal.items():
        log.info("references: split %s: %d sequences need more samples (%s)", split, len(spp),
                 ", ".join(f"{s} {n}" for s, n in spp.items()) or "none")
    return table
