"""`+experiment=references`: which sequences' references need more samples, read from the recorded tables.

A scored frame's reference passes when its estimated error (two half-sample renders) is below a tenth of
the best row's relMSE on it (`table.reference_shortfall`). For every table in `results_dir` and in its split
folders (results/cpu/val/...) that scored a split with two-half references, each frame's
shortfall against that table's best row; a frame's worst over the tables decides. More samples shrink
the reference's error as 1/spp, and the best row's relMSE with it (the reference's error is part of it),
so a sequence whose worst frame falls short by a factor f gets its ref spp times the power of two at or
above f (1 - m/10) / (m (1 - f/10)), the factor that brings f to `margin` m (at most `max_ref_spp`; f >= 10
cannot be brought below 1 by samples: the estimate says the reference errs more than the row). That count
goes into the data spec, `data.splits.<split>.sequence_ref_spp` (datagen.render_settings), which adds samples to
those sequences' references; every table of the split then scores again (evaluations only).

Writes `<results_dir>/references/table.{csv,md,tex}` (per sequence: frames, frames passing, worst
shortfall and the table it comes from, spp now and proposed, the recorded reference render seconds and
the seconds the proposal adds: more samples are added to a reference, not started over) and `sequence_ref_spp.yaml`: every sequence of a split whose count differs from the
split's `ref_spp`, those already given more samples included, to replace the split's `sequence_ref_spp`.
Renders and trains nothing: the frames' records (reference spp, error estimate, render seconds) are data_dir's
manifest's, or for a split it does not hold, the run archive's copy (`datasets.frame_records`), so a clean
clone writes this table. A table of a split neither holds, or that scored it rendered with
other settings (before its references got more samples), is left out; one whose evaluations scored another
render of the split (same settings, other noise) is included as an estimate: its rows' per-frame errors
with today's reference error estimates. The caption names both.
"""
from __future__ import annotations

import logging
import math
import re

import pandas as pd
import yaml

from bench.errors import UserError
from bench.experiments.context import Context
from bench.experiments.datasets import frame_records, records_digest, split_fingerprint
from bench.experiments.table import (REFERENCE_SHARE, evaluation_records, per_image_of, reference_errors,
                                    reference_shortfall)
from bench.table_writer import SCORED_ON_PATTERN, listed_evaluations, read_caption, read_table, write_table
from bench.tasks import get_task

log = logging.getLogger("bench")


# A table scored on another render of the split (same settings, other noise; e.g. rendered again after
# session 28's change to multi-light scenes) still says how close its best row comes to the references:
# its per-frame errors are taken with today's reference error estimates, and the caption names it.
OTHER_RENDER = "estimated: it scored another render of the split, of the same settings"


def table_shortfalls(ctx: Context, frames: list[dict]) -> tuple[pd.DataFrame, dict[str, list[str]]]:
    """One row per (table, scored frame): the frame's reference shortfall against that table's best row;
    and the tables left out or taken as estimates, by why ({why: [table, ...]}, each also logged)."""
    held = {f["split"] for f in frames}
    out, notes, other_render = [], {}, []

    def leave_out(name: str, why: str) -> None:
        log.info("references: %s left out: %s", name, why)
        notes.setdefault(why, []).append(name)
    for path in sorted([*ctx.results_dir.glob("*/table.csv"), *ctx.results_dir.glob("*/*/table.csv")]):
        caption = read_caption(path.with_suffix(".md"))
        match = re.search(SCORED_ON_PATTERN, caption)
        table = read_table(path)
        if not match or "References (" not in caption or not {"relMSE", "runs"} <= set(table) \
                or table["relMSE"].isna().all():
            continue  # not a metrics table, or its references are not estimated (no two halves)
        split, name = match.group(2), path.parent.relative_to(ctx.results_dir).as_posix()
        if split not in held:
            leave_out(name, f"neither {ctx.data_dir} nor the run archive holds the frame records of split {split}")
            continue
        best = table.loc[table["relMSE"].idxmin()]
        try:
            evaluations = evaluation_records(listed_evaluations(best["runs"]), ctx.runs_dir, ctx.archives)
        except UserError as err:  # a table of another run store (or of your frames, never archived)
            leave_out(name, str(err))
            continue
        if {(record or {}).get("identity", {}).get("data") for _, record in evaluations} \
                != {split_fingerprint(ctx, split)}:  # e.g. scored before its sequences got more samples
            leave_out(name, f"it scored split {split} rendered with other settings")
            continue
        if {(record or {}).get("metrics", {}).get("render") for _, record in evaluations} \
                != {records_digest([f for f in frames if f["split"] == split])}:  # same settings, other
            # noise: an estimate, said in the caption
            log.info("references: %s scored another render of split %s: its rows' errors are taken with "
                     "today's reference errors", name, split)
            other_render.append(name)
        task = best["task"] if "task" in table else re.search(r"Task (\w+)", caption).group(1)
        errors = reference_errors([f for f in frames if f["split"] == split], get_task(task).y[:2])
        shortfall = reference_shortfall(errors, per_image_of(evaluations))
        out += [{"split": split, "sequence": seq, "frame": frame, "table": name, "best row": best["method"],
                 "shortfall": value} for (seq, frame), value in shortfall.items()]
    if other_render:
        notes[OTHER_RENDER] = other_render
    return pd.DataFrame(out, columns=["split", "sequence", "frame", "table", "best row", "shortfall"]), notes


def proposed_spp(ref_spp: int, shortfall: float, margin: float, max_ref_spp: int) -> int:
    """The reference spp that brings a frame `shortfall` times over the criterion to `margin` of it, in
    doublings of `ref_spp`, never fewer than `ref_spp` nor (for more) over `max_ref_spp`."""
    if shortfall < margin:
        return ref_spp
    share = REFERENCE_SHARE
    cap = ref_spp * 2 ** max(0, math.floor(math.log2(max_ref_spp / ref_spp)))  # doublings of ref_spp only
    if shortfall * share >= 1:  # the estimate exceeds the row's error: no finite count is enough
        return cap
    factor = shortfall * (1 - share * margin) / (margin * (1 - share * shortfall))
    return max(ref_spp, min(cap, ref_spp * 2 ** math.ceil(math.log2(factor))))


def run(ctx: Context, name: str, margin: float, max_ref_spp: int) -> pd.DataFrame:
    # the frames' estimated reference errors and render times: data_dir's, else the archive's records
    frames = [f for split in (ctx.data_spec.get("splits") or {}) for f in frame_records(ctx, split)]
    if not frames:
        raise UserError(f"references: neither {ctx.data_dir} nor the run archive holds the frame records of the "
                        f"{ctx.preset} preset's data (their estimated reference errors); `python -m bench "
                        f"+experiment=data preset={ctx.preset}` renders it")
    shortfalls, notes = table_shortfalls(ctx, frames)
    unknown = shortfalls["shortfall"].isna()
    if unknown.any():
        log.info("references: %d frame scores are not numbers (NaN relMSE), left out", int(unknown.sum()))
        shortfalls = shortfalls[~unknown]
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
        seconds = sum(r["time_s"].get(f"{res}_ref_s", 0.0) for r in recs for res in ("lr", "hr")) \
            if all(r.get("time_s") for r in recs) else math.nan  # records archived before they kept times
        rows.append({"split": split, "sequence": sequence, "frames": len(part),
                     "frames passing": int((part["shortfall"] < 1).sum()),
                     "worst shortfall": float(top["shortfall"]), "worst in": f"{top['table']} ({top['best row']})",
                     "ref spp": now, "proposed ref spp": new, "ref render s": seconds,
                     "ref render s added": seconds * (new / now - 1)})
    table = pd.DataFrame(rows).sort_values(["split", "worst shortfall"], ascending=[True, False])
    proposal = {}
    for split, part in table.groupby("split"):
        spec = ctx.data_spec["splits"].get(split) or {}
        spp = {**(spec.get("sequence_ref_spp") or {}), **dict(zip(part["sequence"], part["proposed ref spp"]))}
        proposal[split] = {seq: int(n) for seq, n in sorted(spp.items()) if int(n) != int(spec.get("ref_spp", 0))}
    out_dir = ctx.results_dir / name
    caption = (f"References that fall short, preset {ctx.preset}: per sequence of each scored split, its frames' "
               f"worst shortfall over the recorded tables (estimated reference relMSE over a tenth of the table's "
               f"best row's relMSE on the frame; below 1 passes) and the reference spp that brings it to "
               f"{margin:g} of the criterion (the reference's error falls as 1/spp, and the row's relMSE with it; "
               f"at most {max_ref_spp}). Passing now: "
               + ", ".join(f"{split} {int(p['frames passing'].sum())} of {int(p['frames'].sum())} frames"
                           for split, p in table.groupby("split"))
               + ". Frames passing per table (its best row against today's references): "
               + ", ".join(f"{t} {int((p['shortfall'] < 1).sum())} of {len(p)}" for t, p in shortfalls.groupby("table"))
               + ". ref render s: the recorded seconds of the sequence's reference renders (both resolutions; "
               "- (empty in the csv) where a frame's record holds none, as the archive's records made before "
               "they kept times); "
               "ref render s added: what the proposal adds to them (its samples are added to the references, "
               "datagen.refine_reference). sequence_ref_spp.yaml beside this table holds, per split, the "
               "sequence_ref_spp to put in conf/data/<preset>.yaml."
               + "".join(f" {'Included' if why == OTHER_RENDER else 'Left out'} ({why}): {', '.join(names)}."
                         for why, names in notes.items()))
    write_table(table, out_dir, caption=caption)
    (out_dir / "sequence_ref_spp.yaml").write_text(yaml.safe_dump(
        {split: {"sequence_ref_spp": spp} for split, spp in proposal.items() if spp}, sort_keys=True))
    for split, spp in proposal.items():
        log.info("references: split %s: %d sequences with more samples than %s's ref_spp (%s)", split, len(spp),
                 split, ", ".join(f"{s} {n}" for s, n in spp.items()) or "none")
    return table
