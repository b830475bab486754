"""A metrics table: one row per (model, overrides, task, training overrides), each a recorded run,
written with `bench.table_writer.write_table` to `<results_dir>/<name>/table.{csv,tex,md}`, with the paper's
numbers beside ours and a PNG of crops from a fixed validation frame.

A row of the experiment file:
  label: "rate {dilation}"     # shown in the table; `{key}` is filled from the row's sweep values
  model: edsr                  # a name in conf/model/
  overrides: {blocks: 4}       # model arguments
  task: sr                     # bench.tasks (default: the experiment's task, srd)
  train: {loss: {final: {perceptual: 0}}}   # training-recipe overrides for this row
  cascade: true                # train the SRDNet stages separately (paper Table 3 "Cascade")
  paper: "{dilation}"          # the paper's row label in bench/paper_values.csv
  sweep: {dilation: [1, 2, 3, 5], task: [sr, denoise]}   # one row per combination (task or model args)
"""
from __future__ import annotations

import contextlib
import copy
import dataclasses
import hashlib
import itertools
import json
import logging
import math
from pathlib import Path

import pandas as pd

from bench import archived, runs
from bench.errors import UserError
from bench.experiments.context import Context, model_config, row_setting, split_note, training_splits
from bench.experiments.datasets import ensure_data, evaluation_data, frame_records, splits_on_disk
from bench.experiments.evaluation import evaluation_recorded
from bench.experiments.figure import crop_figure, curve_figure
from bench.experiments.macs import frame_macs
from bench.experiments.row import row
from bench.experiments.training import scoring_only_error, training_records, untrained
from bench.measure import error_summary
from bench.exposure import NAMES
from bench.metrics import HIGHER_IS_BETTER, LOWER_IS_BETTER, RELMSE_FORMULA
from bench.models.factory import build_model
from bench.paper import TABLES, paper_values
from bench.table_writer import SCORED_ON, listed_evaluations, write_table
from bench.tasks import CASCADE_STAGES, TASKS, get_task

log = logging.getLogger("bench")

RENDERING_BECAUSE = " where missing, because: "  # in the log line that says why a table renders (scripts read it)
PAPER_TASK = {"srd": "SRD", "sr": "SR", "denoise": "Denoising"}  # our task name -> the paper's column
ROW_KEYS = {"label", "model", "overrides", "task", "train", "cascade", "paper", "split"}


def expand_rows(rows: list[dict], default_task: str = "srd") -> list[dict]:
    """Rows with `sweep` become one row per combination of the sweep's values (in the order written);
    `task` in a sweep sets the row's task, any other key a model argument. Labels and `paper` are
    format strings over the sweep values."""
    if not isinstance(rows, list) or not rows:
        raise ValueError(f"expected a non-empty list of rows, e.g. [{{label: A, model: bilinear}}], not {rows!r}")
    out = []
    for r in rows:
        if not isinstance(r, dict) or "label" not in r or "model" not in r:
            raise ValueError(f"row {r!r}: expected a mapping with at least label and model, "
                             "e.g. {label: A, model: bilinear}")
        unknown = set(r) - ROW_KEYS - {"sweep"}
        if unknown:
            raise ValueError(f"row {r.get('label')!r}: unknown keys {sorted(unknown)}; known: {sorted(ROW_KEYS)}")
        sweep = r.get("sweep") or {}
        for values in itertools.product(*sweep.values()):
            point = dict(zip(sweep, values))
            new = {k: copy.deepcopy(v) for k, v in r.items() if k != "sweep"}
            new["task"] = point.pop("task", r.get("task", default_task))
            if new["task"] not in TASKS:
                raise ValueError(f"row {r['label']!r}: unknown task {new['task']!r}; known tasks: {', '.join(TASKS)}")
            new["overrides"] = {**(r.get("overrides") or {}), **point}
            fmt = {**new["overrides"], "task": new["task"]}
            new["label"] = str(r["label"]).format(**fmt)
            if "paper" in r:
                new["paper"] = str(r["paper"]).format(**fmt)
            out.append(new)
    labels = [r["label"] for r in out]
    twice = sorted({label for label in labels if labels.count(label) > 1})
    if twice:  # a row's runs, figure panels and claims are found by its label
        raise ValueError(f"the label {twice[0]!r} names {labels.count(twice[0])} rows; give each row its own")
    return out


def _weights_note(labels, rounded, stale, seeds: int) -> str:
    """Caption sentences naming the rows scored with the archive's float16-rounded weights and the rows
    whose trainings ran older code than this (reused with reuse_stale=true, not yet adopted)."""
    def named(counts) -> str:
        return ", ".join(f"{label}" + (f" ({n} of {seeds} seeds)" if n < seeds else "")
                         for label, n in zip(labels, counts) if n)
    notes = ""
    if any(rounded):
        notes += (f" Scored with the run archive's float16-rounded weights (bench/archived.py; "
                  f"scripts/fp16_weights_accuracy.py measures how far their metrics move): {named(rounded)}.")
    if any(stale):
        notes += (f" Trained by older code than this and reused as recorded (reuse_stale=true; "
                  f"+experiment=adopt checks and re-stamps them): {named(stale)}.")
    return notes


def _renders_note(renders) -> str:
    """A caption sentence when the rows' evaluations scored different renders of the split (another
    host's render of the same settings, e.g. runs restored from the archive), or when some did not
    record which (evaluated before render digests) beside some that did; empty when all scored one, or
    when none recorded it (a table older than digests: nothing to compare)."""
    known = {d for row in renders for d in row if d}
    unknown = sum(d is None for row in renders for d in row)
    if len(known) > 1:
        what = (f" The evaluations scored {len(known)} different renders of the split"
                + (f" ({unknown} recorded before render digests)" if unknown else ""))
    elif known and unknown:
        total = sum(len(row) for row in renders)
        what = (f" {unknown} of {total} evaluations {'has' if unknown == 1 else 'have'} no render digest "
                "(recorded before digests, or unstamped data), so whether they scored the same render of the "
                "split as the others is not known")
    else:
        return ""
    return what + (": hosts render the same settings with different noise of the same statistics, so rows "
                   "that scored different renders differ by that noise too.")


def shard_units(rows: list[dict], seeds: list, index: int, count: int) -> list[tuple[dict, int]]:
    """Shard `index` of `count`: every count-th (row, seed) pair, so that shards stay balanced when a
    table has fewer rows than shards or rows of unequal cost."""
    return [(r, seed) for r in rows for seed in seeds][index::count]


def unit_lock(lock_dir: Path, key: str, r: dict, seed) -> Path:
    """The lock file of one (row, seed) unit of the table and configuration `key`."""
    name = hashlib.sha256(json.dumps([key, r, seed], sort_keys=True, default=str).encode()).hexdigest()[:16]
    return Path(lock_dir) / f"{name}.lock"


def compute_shard(rows: list[dict], seeds: list, index: int, count: int, lock_dir: Path, key: str,
                  compute, take_others: bool = True) -> list[tuple[dict, int]]:
    """Shard `index` of `count` calls `compute(row, seed)` on its own (row, seed) units (`shard_units`)
    and then, with `take_others`, on the other shards' in turn, skipping any unit another process is
    computing (a lock per unit under `lock_dir`, named from `key`, the row and the seed). A shard that
    runs out of its own units so takes those a slower shard has not reached, and shards of unequal
    cost (3 seeds of rows that alternate cheap and dear, over 2 shards) finish together. `compute`
    reuses what is recorded, so a unit another process finished costs only its lookup. The skipped
    units are tried once more at the end (a holder may have died); one still held is left to its
    holder, and to the run without shard=, which computes whatever is missing, so a shard never idles
    on a cluster allocation. Returns the units it ran."""
    own = shard_units(rows, seeds, index, count)
    others = [u for i in range(1, count) for u in shard_units(rows, seeds, (index + i) % count, count)]

    def attempt(r, seed) -> bool:
        handle = runs.try_acquire(unit_lock(lock_dir, key, r, seed))
        if handle is None:
            return False
        with contextlib.closing(handle):
            compute(r, seed)
        return True

    units = own + (others if take_others else [])
    skipped = [u for u in units if not attempt(*u)]
    left = [u for u in skipped if not attempt(*u)]
    if left:
        log.info("shard %d/%d: left to the processes computing them: %s", index, count,
                 ", ".join(f"{r['label']} seed {seed}" for r, seed in left))
    return [u for u in units if u not in left]


def passes_for(rows: list[dict], default_task: str) -> set[str]:
    """The union of buffers the table's tasks read (training and evaluation, Cascade stages included)."""
    needed = set()
    for r in rows:
        tasks = [r.get("task", default_task)]
        if r.get("cascade"):
            tasks += [t for _, t in CASCADE_STAGES[(r.get("overrides") or {}).get("stage_order", "sr_dn")]]
        for t in tasks:
            needed.update(get_task(t).buffers(with_mid=True))
    return needed


def gmac(ctx: Context, r: dict, input_hw=(540, 960)) -> float | None:
    """Analytic GMac of a row's model per 960x540 LR frame (None for non-learned rows)."""
    layers = frame_macs(model_config(ctx, r["model"], r.get("overrides")), input_hw, get_task(r["task"]).scale)
    return None if layers is None else float(layers["macs"].sum()) / 1e9


def with_paper(table: pd.DataFrame, rows: list[dict], paper_table: str | None) -> pd.DataFrame:
    """Add the paper's relMSE/PSNR/SSIM for rows that name their paper row."""
    if not paper_table:
        return table
    published = paper_values(paper_table).set_index(["row", "task"])
    for metric in ("relMSE", "PSNR", "SSIM"):
        values = []
        for r in rows:
            key = (r.get("paper"), PAPER_TASK.get(r["task"], r["task"]))
            values.append(published.loc[key, metric] if r.get("paper") and key in published.index else None)
        table[f"paper {metric}"] = values
    return table


def paper_agreement(table: pd.DataFrame) -> dict[str, tuple[int, int]]:
    """Per metric, (pairs of rows ordered as in the paper, pairs compared): every two rows of the same
    task that both have our value and the paper's; pairs the paper ties are left out."""
    out = {}
    groups = table.groupby("task") if "task" in table else [(None, table)]
    for metric in ("relMSE", "PSNR", "SSIM"):
        if f"paper {metric}" not in table:
            continue
        agree = total = 0
        for _, group in groups:
            known = group.dropna(subset=[metric, f"paper {metric}"])
            ours, paper = known[metric].to_numpy(float), known[f"paper {metric}"].to_numpy(float)
            for i in range(len(known)):
                for j in range(i + 1, len(known)):
                    if paper[i] == paper[j]:
                        continue
                    total += 1
                    agree += (ours[i] - ours[j]) * (paper[i] - paper[j]) > 0
        if total:
            out[metric] = (int(agree), total)
    return out


REFERENCE_SHARE = 0.1  # a reference passes when its estimated error is below this share of the best row's


def reference_errors(frames: list[dict], res: str = "hr") -> dict:
    """(sequence, frame) -> the estimated relMSE of its `res` reference (two half-sample renders,
    bench.metrics.reference_error), for the frames that have one."""
    return {(str(f["sequence"]), f["frame"]): f["ref_error"][res] for f in frames if res in (f.get("ref_error") or {})}


def reference_shortfall(errors: dict, per_image: pd.DataFrame) -> pd.Series:
    """Per scored frame ((sequence, frame) index): its estimated reference relMSE (`errors`, from
    `reference_errors` of the scored split's manifest records at the resolution of the task's target) over
    REFERENCE_SHARE of the best row's relMSE on that frame (`per_image`: that row's per-frame values,
    averaged over seeds); below 1 the frame passes (issue #17's criterion), inf where the row's relMSE is
    0. Frames without an estimate are left out."""
    per_frame = per_image.assign(sequence=per_image["sequence"].astype(str)).groupby(["sequence", "frame"])["relMSE"].mean()
    return pd.Series({key: errors[key] / (REFERENCE_SHARE * rel) if rel > 0 else math.inf
                      for key, rel in per_frame.items() if key in errors}, dtype=float)


def reference_check(frames: list[dict], per_image: pd.DataFrame, best: str, res: str = "hr") -> str:
    """How converged the references of the scored frames are: `reference_shortfall` below 1 on how many
    of them."""
    spp = sorted({int(f["ref_spp"]) for f in frames if "ref_spp" in f})
    spp_text = "/".join(map(str, spp)) or "?"
    errors = reference_errors(frames, res)
    if not errors:
        return (f" References: one render of {spp_text} spp per frame; their error is not estimated (frames "
                "rendered with their split's own ref_spp, as two halves, have it).")
    shortfall = reference_shortfall(errors, per_image)
    values = pd.Series([errors[key] for key in shortfall.index] or list(errors.values()))
    return (f" References ({spp_text} spp as two independent halves): estimated relMSE median {values.median():.2g}, "
            f"max {values.max():.2g}; below a tenth of the best row's ({best}) relMSE on {int((shortfall < 1).sum())} "
            f"of {len(shortfall)} scored frames.")


def evaluation_records(eval_hashes, runs_dir, archives=()) -> list[tuple[Path, dict]]:
    """Where each evaluation run is (the run store, else the first archive that has it) and its record."""
    found = []
    for h in eval_hashes:
        path, record = runs.find_record("eval", h, runs_dir, archives)
        if path is None:
            raise UserError(f"evaluation run {h} is recorded neither in {runs_dir} nor in the archive")
        found.append((path.parent, record))
    return found


def per_image_of(evaluations: list[tuple[Path, dict]]) -> pd.DataFrame:
    """The per-frame scores of evaluation runs (`evaluation_records`: all seeds of a row), stacked."""
    parts = []
    for run_dir, _ in evaluations:
        scores = archived.read_per_image(run_dir)
        if scores is None:
            raise UserError(f"evaluation run {run_dir.name} has no per-frame scores in {run_dir.parent}")
        parts.append(scores)
    return pd.concat(parts)


def _reference_note(ctx: Context, scoring_ctx: Context, table: pd.DataFrame, rows: list[dict], split: str | None) -> str:
    """The reference check against the row with the lowest relMSE (none when no row has one)."""
    if table["relMSE"].isna().all():
        return ""
    best_index = int(table["relMSE"].idxmin())
    best, row_def = table.loc[best_index], rows[best_index]
    target = get_task(row_def["task"]).y
    if target not in ("hr_ref", "lr_ref"):  # a noisy target (sr_noisy) is no converged reference
        return ""
    scored = row_def.get("split", split) or ctx.eval.split
    return reference_check(frame_records(scoring_ctx, scored),
                           per_image_of(evaluation_records(listed_evaluations(best["runs"]), ctx.runs_dir)), best["method"], target[:2])


def unrecorded_rows(ctx: Context, rows: list[dict], split: str | None, trainings: dict) -> list[dict]:
    """The rows with an evaluation that is not recorded (scoring it reads its split's frames, and its
    training's weights), decided from records alone (`evaluation_recorded`; `trainings`: (label, seed) ->
    its `training_records`)."""
    def recorded(r: dict, seed: int) -> bool:
        rctx, cfg, task, cascade = row_setting(ctx, r)
        return evaluation_recorded(rctx, cfg, task, seed, r.get("split", split) or ctx.eval.split,
                                   trainings[r["label"], seed], cascade)
    return [r for r in rows if ctx.force or not all(recorded(r, seed) for seed in ctx.seeds)]


def render_what_runs(ctx: Context, name: str, rows: list[dict], task: str, split: str | None, figure: bool,
                     trainings: dict) -> bool:
    """Render the data this table computes from, and nothing else: the splits of the evaluations not
    recorded (`unrecorded_rows`); the training and working splits when a training must run for them or
    for the figure (`trainings`: (label, seed) -> its `training_records`); the scored split when the
    crops figure is redrawn (where that split is rendered as the preset specifies it); and each row's
    scored split whose frame records, which the caption's reference check reads for the best row, are
    neither there nor archived. Returns whether the figure is redrawn."""
    pending = unrecorded_rows(ctx, rows, split, trainings)
    needed = {r.get("split", split) or ctx.eval.split for r in pending}
    shown = split or ctx.eval.split
    scored = {r.get("split", split) or ctx.eval.split for r in rows}
    splits_without_frame_records = {s for s in scored if not frame_records(ctx, s)}
    needed |= splits_without_frame_records
    if figure and shown in splits_on_disk(ctx, as_specified=True):
        needed.add(shown)
    drawn = figure and shown in needed
    loading = {(r["label"], seed) for r in pending for seed in ctx.seeds} | (
        {(r["label"], ctx.seeds[0]) for r in rows} if drawn else set())  # the figure shows the first seed
    to_train = [] if ctx.force else [f"{label} seed {seed}: {why}" for label, seed in sorted(loading)
                                     for why in untrained(trainings[label, seed])]
    if ctx.force or to_train:
        needed |= training_splits(ctx)
    if needed:
        # why, before the render: a table a user expected from the archive says what is missing
        whys = ["force=true"] if ctx.force else (  # every run computes again: the one reason
            ([f"not recorded: the evaluation of {', '.join(r['label'] for r in pending)}"] if pending else [])
            + [f"no frame records of {s} (the caption's reference check)" for s in sorted(splits_without_frame_records)]
            + [f"to train: {why}" for why in to_train])
        log.info("%s: rendering %s%s%s", name, ", ".join(sorted(needed)), RENDERING_BECAUSE,
                 "; ".join(whys) or f"the crops figure reads {shown}")
        ensure_data(ctx, passes_for(rows, task), needed)
    else:
        log.info("%s: every evaluation is recorded: nothing is rendered or trained", name)
    return drawn


def selected_rows(ctx: Context, rows: list[dict], task: str, leave_out: list[str] | None,
                  leave_out_unavailable: bool = False) -> tuple[list[dict], dict[str, str]]:
    """The table's rows, expanded, less those left out, and {label: why} of the rows left out because
    their model does not import on this machine (`leave_out_unavailable`; else that is an error like any
    other); a bad model, model argument or task name fails here, before any rendering or training."""
    rows = expand_rows(rows, task)
    unknown = sorted(set(leave_out or []) - {r["label"] for r in rows})
    if unknown:
        raise UserError(f"experiment.leave_out: no row {unknown[0]!r} in this table "
                        f"(its rows: {', '.join(r['label'] for r in rows)})")
    kept, unavailable = [], {}
    for r in (r for r in rows if r["label"] not in (leave_out or [])):
        try:
            build_model(model_config(ctx, r["model"], r.get("overrides")), get_task(r["task"]).scale)
        except UserError as err:
            missing = missing_package(err)
            if not (leave_out_unavailable and missing):
                raise
            unavailable[r["label"]] = error_summary(missing)
            log.warning("%s: left out, its model does not import here (%s)", r["label"], unavailable[r["label"]])
            continue
        kept.append(r)
    return kept, unavailable


def missing_package(err: BaseException) -> ModuleNotFoundError | None:
    """The package this machine lacks behind a model that could not be built: the deepest ImportError of
    the chain (Hydra wraps the first in one of its own), if it is a ModuleNotFoundError of a whole package
    outside this project (a misspelt `_target_` or a broken import in bench or baselines is an error)."""
    seen, deepest = set(), None
    while err is not None and id(err) not in seen:   # a chain that loops (raise e from e) ends
        seen.add(id(err))
        if isinstance(err, ImportError):
            deepest = err
        err = err.__cause__ or err.__context__
    # a package: a top-level name (a dotted one is a module missing from a package that is there, a typo)
    name = (deepest.name or "") if isinstance(deepest, ModuleNotFoundError) else ""
    return deepest if name and "." not in name and name not in ("bench", "baselines") else None


def ready_data(ctx: Context, scoring_ctx: Context, name: str, rows: list[dict], task: str, split: str | None,
               figure: bool) -> bool:
    """Render what the table's runs need (on the suite's data), or check the frames and the recorded
    trainings it scores (another dataset: nothing is rendered or trained). Returns whether the crops
    figure can be drawn."""
    # per (row, seed): the trainings its scoring uses, as recorded (force=true: every one runs)
    settings = {r["label"]: row_setting(ctx, r) for r in rows}
    trainings = {} if ctx.force else {(label, seed): training_records(s.ctx, s.cfg, s.task, seed, s.cascade)
                                      for label, s in settings.items() for seed in ctx.seeds}
    if scoring_ctx is ctx:
        return render_what_runs(ctx, name, rows, task, split, figure, trainings)
    ensure_data(scoring_ctx, set(), scoring=True)
    whys = [f"{label} seed {seed}: {why}" for (label, seed), recorded in trainings.items()
            for why in untrained(recorded)]
    if whys:  # before anything is scored, every training that would be missing
        raise scoring_only_error(whys)
    return figure


def row_of(ctx: Context, r: dict, split: str | None) -> dict:
    """Table row `r` computed or reused (bench.experiments.row) with `ctx`'s seeds."""
    return row(ctx, r["label"], r["model"], r.get("overrides"), r["task"], r.get("split", split), r.get("train"),
               r.get("cascade", False))


def domain_note(default: str, rows: list[dict]) -> str:
    """The caption's network domain: the default's, and where rows set their own (a domain study), which."""
    note = f"network domain {NAMES[default]} (train.hdr={default}, bench/exposure.py)"
    own = sorted({r["train"]["hdr"] for r in rows if "hdr" in (r.get("train") or {})})
    return note + (f" where a row does not set its own (rows here set {', '.join(own)})" if own else "")


def caption_notes(ctx: Context, scoring_ctx: Context, table: pd.DataFrame, rows: list[dict], split: str | None,
                  leave_out: list[str] | None, gmac_column: bool, paper_table: str | None,
                  unavailable: dict[str, str] | None = None) -> str:
    """What the caption says after the experiment's own caption: task, metrics, data, recipe and seeds,
    the paper's ordering, the references' check, renders, weights, VGG features, time columns. Takes the
    columns it reports on (renders, rounded, stale, vgg) out of `table`."""
    loss = ctx.train.loss["final"]
    paper_terms = ("edge", "temporal", "spatial", "perceptual")
    extra = "".join(f" + {term} {w:g}" for term, w in loss.items() if term not in paper_terms and w)
    tasks = ", ".join(dict.fromkeys(r["task"] for r in rows))
    scored_on = SCORED_ON.format(preset=ctx.preset, split=split or ctx.eval.split)
    notes = (f"Task {tasks}. {RELMSE_FORMULA}; robust relMSE leaves out the 0.1% of pixels with the highest "
             f"error; temporal relMSE scores the frame-to-frame change against the reference's; PSNR/SSIM on "
             f"images clamped to [0, 1]; LDR-FLIP of those images, HDR-FLIP of the linear radiance (NVIDIA FLIP, "
             f"flip-evaluator; '-': evaluated before the suite scored FLIP); (se ...): standard error over the "
             f"split's sequences. "
             f"{scored_on[0].upper()}{scored_on[1:]}, {ctx.train.steps} training steps, loss g:t:s:p = "
             f"{loss['edge']}:{loss['temporal']}:{loss['spatial']}:{loss['perceptual']}{extra} (unless a row says "
             f"otherwise), {domain_note(ctx.train.hdr, rows)}, "
             f"seeds {list(ctx.seeds)} (mean +- std over seeds when several); time_ms: "
             f"inference per frame on {ctx.device}.")
    notes += split_note(ctx, split or ctx.eval.split)
    if leave_out:
        notes += f" Left out of this call (experiment.leave_out): {', '.join(leave_out)}."
    if unavailable:
        notes += (" Left out because their model does not import on the machine that wrote this table "
                  f"(experiment.leave_out_unavailable): {'; '.join(f'{k} ({v})' for k, v in unavailable.items())}.")
    if gmac_column:
        notes += f" GMac: multiply-accumulates per 960x540 input frame at this preset's widths (budget {ctx.budget_gmac:g})."
    if paper_table:
        notes += " 'paper' columns: the published values (Wei et al., same metrics, their data and scale)."
        agreement = paper_agreement(table)
        if agreement:
            notes += " Pairs of rows ordered as in the paper: " + ", ".join(
                f"{m} {a}/{n}" for m, (a, n) in agreement.items()) + "."
    notes += _reference_note(ctx, scoring_ctx, table, rows, split)
    notes += _renders_note(table.pop("renders"))
    notes += _weights_note(table["method"], table.pop("rounded"), table.pop("stale"), len(ctx.seeds))
    vgg = sorted({v for v in table.pop("vgg") if isinstance(v, str)})
    if vgg:
        notes += f" Perceptual loss features: {'; '.join(vgg)}."
    notes += (" train/eval (min): wall time of each row's runs as recorded in the run store (a run shared "
              "with another table was computed once; a seed average for several seeds). last fifth (dB): "
              "what the validation PSNR (learning curve subset) gained over the last fifth of training, a "
              "seed average; near 0: the curve has flattened.")
    return notes


def run(ctx: Context, name: str, rows: list[dict], caption: str = "", task: str = "srd",
        split: str | None = None, paper_table: str | None = "auto", gmac_column: bool = False,
        figure: bool = True, leave_out: list[str] | None = None,
        leave_out_unavailable: bool = False) -> pd.DataFrame:
    """`paper_table`: the published table whose values go beside the rows that name a paper row
    (bench/paper_values.csv); "auto": the experiment's own, where the paper has one. `leave_out`: labels
    of rows this call does not compute, named in the caption (e.g. rows whose trainings cannot be loaded
    or run here); the table has the others. `leave_out_unavailable`: rows whose model does not import
    here (OIDN on a machine without pyoidn) are left out too, each named in the caption with why."""
    if paper_table not in ("auto", None, *TABLES):
        raise UserError(f"experiment.paper_table={paper_table!r}: expected auto, null or one of {', '.join(TABLES)}")
    rows, unavailable = selected_rows(ctx, rows, task, leave_out, leave_out_unavailable)
    scoring_ctx = evaluation_data(ctx)
    drawn = ready_data(ctx, scoring_ctx, name, rows, task, split, figure)
    if ctx.shard:  # compute this shard's runs only; a run without a shard assembles the table from them
        index, count = ctx.shard
        # a unit's lock is this table under this whole configuration, whichever process runs it
        key = f"{name} {dataclasses.replace(ctx, shard=None, progress=False, workers=0)!r}"
        units = compute_shard(rows, ctx.seeds, index, count, ctx.runs_dir / "units", key,
                              take_others=not ctx.force,  # force recomputes: each shard its own units, once
                              compute=lambda r, seed: row_of(dataclasses.replace(ctx, seeds=[seed]), r, split))
        log.info("%s: shard %d/%d computed or found %d of %d (row, seed) runs (the rest: left to other "
                 "processes); run without shard= to write the table", name, index, count, len(units),
                 len(rows) * len(ctx.seeds))
        return pd.DataFrame()
    table = pd.DataFrame([row_of(ctx, r, split) for r in rows])
    if table["task"].nunique() == 1:  # a single task goes in the caption, not a column
        table = table.drop(columns=["task"])
    if gmac_column:
        after = "SSIM std" if "SSIM std" in table else "SSIM"
        table.insert(table.columns.get_loc(after) + 1, "GMac", [gmac(ctx, r) for r in rows])
    published = (name if name in TABLES else None) if paper_table == "auto" else paper_table
    table = with_paper(table, rows, published)
    notes = caption_notes(ctx, scoring_ctx, table, rows, split, leave_out, gmac_column, published, unavailable)
    out_dir = ctx.results_dir / name
    curves = {label: hashes for label, hashes in zip(table["method"], table.pop("train runs")) if hashes}
    write_table(table.drop(columns=["reused"]), out_dir, caption=f"{caption} {notes}".strip(),
                lower_is_better=LOWER_IS_BETTER, higher_is_better=HIGHER_IS_BETTER)
    if drawn:
        crop_figure(ctx, rows, out_dir / "crops.png", split=split or ctx.eval.split)
    elif figure:
        log.info("%s: crops figure not redrawn: split %s is not rendered in %s and no evaluation needed it "
                 "(`python -m bench +experiment=data preset=%s` renders it)", name, split or ctx.eval.split,
                 ctx.data_dir, ctx.preset)
    if figure:
        curve_figure(ctx.runs_dir, curves, out_dir / "curves.png")
    reused = int(table["reused"].sum())
    log.info("%s: %d of %d rows reused from the run store; table in %s", name, reused, len(table), out_dir)
    if scoring_ctx is not ctx:
        log.info("%s: %d rows scored on %s with recorded trainings: nothing was rendered or trained", name,
                 len(table), scoring_ctx.data_dir)
    return table
