"""`+experiment=adopt`: keep recorded runs through a code change that does not change their results.

Every run records the fingerprint of the code it ran (bench.runs.code_fingerprint); after a refactor of a
model, a layer or the trainer, the runs that ran the changed files are stale and would be recomputed: a
day of reruns at the cpu preset for a change that moves no number. This experiment checks, for each
group of stale trainings (one row of a table: the same identity but the seed), that the current code
reproduces the group's witness run (its lowest seed):

- weights: the recorded weights load into the model the current code builds (same names, shapes);
- training: the first `steps` steps, replayed by the current trainer from the same seed and data, give
  the recorded loss and gradient norm of the first step (same initial weights, batch, forward, backward)
  and the recorded loss of the later ones (to `rtol_later_steps`: floating-point summation order makes
  two runs of the same code drift apart slowly from the second step on, ~1e-5 by step 10 at smoke),
  and the current schedule gives the recorded learning rate at every step of the run;
- inference: the recorded weights, run by the current evaluator on the first sequence of an evaluation
  of the run on today's frames, give its recorded per-frame relMSE, PSNR and SSIM (a group whose
  evaluations all scored frames rendered again since has none to check: it is checked by training), to
  `rtol_rounded_weights` when the weights are the archive's float16-rounded ones (bench.archived);

each to a relative tolerance `rtol` unless said otherwise. A witness that did not train on this render of
its split (another host's, one from before a render change, or not recorded) cannot be held to its record,
since its numbers moved with the frames; it is checked against its recorded code instead: the code its
fingerprint names, rebuilt from git history (bench/experiments/recorded_code.py; what is replayed and
compared: bench/experiments/replay.py), replays the same first
steps and scores the same sequence of today's frames in a subprocess, and the current code must give the
same numbers (the differential check: the change moves no number, whatever the frames). The subprocess
fingerprints what it ran, which must be the recorded code. Where today's frames lack the split an
evaluation scored, both codes score val (or test) instead: any frames show whether the change moves a
number. Stale evaluations of models that are not trained (bilinear, OIDN) are checked the same way, on
their first sequence, against their record or their recorded code. A group that passes has its runs (every seed) and
their evaluations re-stamped with the current code fingerprint, the old one and the check kept in the record
(`code_adopted`), and archived again (`runs_archive`, complete runs only: else a fresh clone restores the
archive's stale copy); a group that fails is left stale, with the measured difference in the table. What
is not checked: training steps after the first `steps` (the same code paths run again, on other batches),
and evaluations run another way (a fast path, tiles), which stay stale.

A group none of whose seeds kept its weights (the archive leaves some out, docs/runs.md) is checked by its
training replay alone: the evaluator is then not checked for it.

Stopped trainings (interrupted, failed, or killed: a "running" record no process holds) with a checkpoint are adopted with their group, so they
resume instead of starting again; a group of only such runs has no evaluation to check.

The archive's runs (`runs_archive`) that the store lacks are restored into it first (with `dry_run`
too), and where anything is stale the frames the checks read are rendered where missing (the train split,
and val unless val or test is there: `render_what_the_checks_read`), so a fresh clone adopts the committed
runs. Runs recorded under an older identity version are not looked at: `+experiment=migrate` re-keys them first.

Writes `<results_dir>/adopt/table.{csv,md,tex}`: one row per group with the verdict and the differences.
"""
from __future__ import annotations

import logging
import time
from pathlib import Path

import pandas as pd

from bench import archived, runs
from bench.errors import UserError
from bench.experiments.context import (EVALUATION_CODE, FROZEN_SPLIT, TRAINING_CODE, TUNING_SPLIT, Context,
                                      code_of)
from bench.experiments.datasets import (data_fingerprint, ensure_data, evaluation_data, render_digest, split_fingerprint,
                                       splits_on_disk)
from bench.experiments.evaluation import archive_evaluation
from bench.experiments.replay import (COMPARED, check_against_recorded_code, check_inference, check_training,
                                      fingerprints_agree, scoring_of)
from bench.experiments.training import archive_training
from bench.infer import REFERENCE
from bench.table_writer import write_table
from bench.tasks import get_task
from bench.train import TrainingInterrupted

log = logging.getLogger("bench")

RESUMABLE = ("complete", "interrupted", "failed")  # a stopped training resumes from its checkpoint once adopted


def stale_groups(ctx: Context) -> dict[str, list[runs.Run]]:
    """Training runs with a checkpoint (complete, or stopped and resumable), or complete without one (an
    archive left its weights out: a witness only when no seed of its group has them, checked by its
    training alone), whose code changed since
    they were recorded and whose data is this data_dir's, grouped by identity without the seed (one
    table row): runs with weights first, then lowest seed first; complete runs first among equal seeds
    (their evaluations can be checked)."""
    data = split_fingerprint(ctx, "train")  # planned from the spec: found before the split is rendered
    groups: dict[str, list[runs.Run]] = {}
    for path in sorted((ctx.runs_dir / "train").glob(f"*/{runs.RECORD}")):
        record = runs.read_record(path) or {}  # a damaged record is missing
        identity = record.get("identity") or {}
        abandoned = record.get("status") == "running" and not runs.computing(path.parent)  # killed mid-run
        weightless = not archived.has_weights(path.parent)
        if (record.get("status") not in RESUMABLE and not abandoned) or identity.get("data") != data \
                or (weightless and record.get("status") != "complete") or "model" not in identity \
                or identity.get("version") != runs.IDENTITY_VERSION:  # an older identity: +experiment=migrate first
            continue
        code = code_of(identity["model"], *TRAINING_CODE)
        if not runs.code_changes(record, code):
            continue
        key = runs.config_hash({k: v for k, v in identity.items() if k != "seed"})
        groups.setdefault(key, []).append(runs.Run("train", record["hash"], path.parent, record))
    return {k: sorted(v, key=lambda r: (not archived.has_weights(r.dir), r.record["seed"] or 0,
                                        r.record["status"] != "complete")) for k, v in groups.items()}


def render_what_the_checks_read(ctx: Context, groups: dict[str, list[runs.Run]], untrained: list[runs.Run]) -> None:
    """Render, where missing, the frames the checks read and nothing else (rendered data only; your own
    is used as it is): the training split, for the groups' replays, and for the scoring the val or test
    frames on disk (`scoring_split` takes either), val where neither is, each with the stale tasks'
    buffers it lacks (a val rendered for other tasks lacked the sr task's LR reference, and every replay
    of an sr group failed on it). A fresh clone adopts after rendering two splits, not the whole dataset.
    `untrained`: the stale evaluations of untrained models."""
    if not (groups or untrained) or not ctx.render_data:
        return
    tasks = {g[0].record["identity"]["task"] for g in groups.values()}
    tasks |= {e.record["identity"]["trained"]["task"] for e in untrained}
    passes = set().union(*(get_task(t).buffers(with_mid=True) for t in tasks))
    splits = {"train"} if groups else set()
    if evaluation_data(ctx) is ctx:
        splits |= (splits_on_disk(ctx, as_specified=True) & {TUNING_SPLIT, FROZEN_SPLIT}) or {TUNING_SPLIT}
    if splits:
        log.info("adopt: rendering %s where missing, for the checks (%d groups, %d evaluations of untrained models)",
                 ", ".join(sorted(splits)), len(groups), len(untrained))
        ensure_data(ctx, passes, splits)


def restore_archive(ctx: Context) -> int:
    """Copy the archive's complete runs that the store has no record of into it; how many."""
    if ctx.runs_archive is None:
        return 0
    return sum(runs.restore(ctx.runs_dir, ctx.runs_archive, kind, path.parent.name)
               for kind in ("train", "eval")
               for path in sorted((Path(ctx.runs_archive) / kind).glob(f"*/{runs.RECORD}")))


def evaluations_of(runs_dir: Path, train_hashes: set[str]) -> list[runs.Run]:
    """Complete evaluation runs whose trainings are all among `train_hashes` (a Cascade's eval has two)."""
    out = []
    for path in sorted((runs_dir / "eval").glob(f"*/{runs.RECORD}")):
        record = runs.read_record(path) or {}
        trained = runs.trainings_of(record)
        if record.get("status") == "complete" and trained and set(trained) <= train_hashes \
                and record["identity"].get("version") == runs.IDENTITY_VERSION:
            out.append(runs.Run("eval", record["hash"], path.parent, record))
    return out


def evaluation_code(ctx: Context, evaluation: runs.Run) -> dict:
    """Today's code fingerprint of a learned row's evaluation: the evaluator's and its model's trainer's."""
    first = runs.trainings_of(evaluation.record)[0]
    model = runs.read_record(ctx.runs_dir / "train" / first / runs.RECORD)["identity"]["model"]
    return code_of(model, *EVALUATION_CODE, *TRAINING_CODE)


def evaluations_to_restamp(ctx: Context, adopted: set[str]) -> list[runs.Run]:
    """The stale evaluations, run the default way, of trainings this call adopted, once every training
    they scored runs today's code (a Cascade's stages may be adopted in different calls): the adopted
    group's check scored its witness with this evaluator. An evaluation whose trainings were all current
    before this call is not one of them: nothing here checked its evaluator."""
    def current(h: str) -> bool:
        record = runs.read_record(ctx.runs_dir / "train" / h / runs.RECORD) or {}
        identity = record.get("identity") or {}
        return "model" in identity and not runs.code_changes(record, code_of(identity["model"], *TRAINING_CODE))
    out = []
    trainings = {p.parent.name for p in (ctx.runs_dir / "train").glob(f"*/{runs.RECORD}")}
    for evaluation in evaluations_of(ctx.runs_dir, trainings):
        trained = runs.trainings_of(evaluation.record)
        if set(trained) & adopted and all(map(current, trained)) \
                and ran_the_default_way(evaluation.record["identity"]) \
                and runs.code_changes(evaluation.record, evaluation_code(ctx, evaluation)):
            out.append(evaluation)
    return out


def scored_here(ctx: Context, evaluation: runs.Run) -> bool:
    """Whether `evaluation` ran the default way on frames as they are now: only then can the current code
    be held to its numbers. An evaluation against references rendered again since says nothing about the
    code: other render settings (the data fingerprint), or the same settings rendered on another host
    (its render digest, where it recorded one: the noise differs in the last bits and beyond)."""
    identity, scoring_ctx = evaluation.record["identity"], evaluation_data(ctx)
    recorded = evaluation.record.get("metrics", {}).get("render")
    return (same_settings_here(scoring_ctx, identity)
            and recorded in (None, render_digest(scoring_ctx, identity["split"])))


def same_settings_here(scoring_ctx: Context, identity: dict) -> bool:
    """Whether an evaluation (its identity) ran the default way on a split that `scoring_ctx` has, rendered
    with the same settings (any render of them)."""
    split = identity["split"]
    return (ran_the_default_way(identity) and split in splits_on_disk(scoring_ctx)
            and identity.get("data") == data_fingerprint(scoring_ctx, split))


def ran_the_default_way(identity: dict) -> bool:
    """Whether an evaluation ran the model the reference way (fp32, whole frames), as adopt's check does."""
    return identity["fast_path"] == REFERENCE and not identity["tile"]


def trained_here(ctx: Context, training: runs.Run) -> bool:
    """Whether `training` recorded that it trained on this render of the split (same settings, same
    host's noise): only then can its replay be held to its record. Trainings recorded before 2026-11-25
    record no render."""
    return training.record.get("metrics", {}).get("render") == render_digest(ctx, "train")


def differential_evaluation(ctx: Context, training: runs.Run) -> runs.Run | None:
    """An evaluation of `training` run the default way, preferably on a split today's frames have with
    its settings: the differential check scores the model as it did, by both codes."""
    scoring_ctx = evaluation_data(ctx)
    default = [e for e in evaluations_of(ctx.runs_dir, {training.hash})
               if ran_the_default_way(e.record["identity"])]
    here = [e for e in default if same_settings_here(scoring_ctx, e.record["identity"])]
    return (here or default or [None])[0]


def differential_scoring(ctx: Context, evaluation: runs.Run, weights: Path | None) -> dict:
    """`scoring_of(evaluation, weights)` on a split of today's frames: its own where they have it, else
    val or test. Both codes score the same frames, so any frames show whether the change moves a number."""
    scoring = scoring_of(evaluation, weights)
    return {**scoring, "split": scoring_split(ctx, scoring["split"])}


def training_scoring(ctx: Context, training: runs.Run) -> dict:
    """The scoring of a training no evaluation ran the default way: its weights on val (or test), in the
    network domain it trained in."""
    identity = training.record["identity"]
    return {"cfg": identity["model"], "task": identity["task"], "weights": training.dir,
            "split": scoring_split(ctx, TUNING_SPLIT), "hdr": identity["train"]["hdr"],
            "stage": identity.get("stage")}


def scoring_split(ctx: Context, split: str) -> str:
    """`split` where today's frames have it, else val or test."""
    here = splits_on_disk(evaluation_data(ctx))
    splits = [s for s in (split, TUNING_SPLIT, FROZEN_SPLIT) if s in here]
    if not splits:
        raise UserError(f"no frames of split {split}, {TUNING_SPLIT} or {FROZEN_SPLIT} to score")
    return splits[0]


def restamp(run: runs.Run, code: dict, check: dict) -> None:
    """Record that `run` is what the current code computes: its fingerprint replaced, the old kept."""
    run.record["code_adopted"] = {"from": runs.config_hash(run.record.get("code") or {}),
                                  "changed": runs.code_changes(run.record, code), "check": check,
                                  "date": time.strftime("%Y-%m-%dT%H:%M:%S%z"), **runs.provenance()}
    run.record["code"] = code
    run.save()


def check_group(ctx: Context, group: list[runs.Run], steps: int, rtol: float, rtol_later_steps: float,
                rtol_rounded_weights: float) -> dict:
    """The table row of one group of stale trainings (a table row, every seed): its witness replayed
    against its record, or against its recorded code (trained on other frames), and the verdict."""
    witness = group[0]
    code = code_of(witness.record["identity"]["model"], *TRAINING_CODE)
    row = {"label": witness.record.get("label"), "runs in group": len(group), "witness": witness.hash,
           "changed": ", ".join(runs.code_changes(witness.record, code))}
    try:
        weights = row["weights"] = archived.has_weights(witness.dir)  # False: no seed's archive kept
        # them, and the group is checked by its training alone
        if trained_here(ctx, witness):  # its record can judge the code
            row |= against_record(ctx, witness, steps, weights)
            eval_rtol = rtol_rounded_weights if archived.rounded(witness.dir) else rtol
        else:  # trained on other frames: the recorded code, rebuilt, replays on today's
            row |= against_recorded_code(ctx, witness, steps, weights)
            eval_rtol = rtol  # the same weights on both sides
        row["eval rtol"] = eval_rtol
        row["verdict"] = verdict(row, rtol, eval_rtol, rtol_later_steps)
    except TrainingInterrupted:  # Ctrl-C / SIGTERM during a replay stops the command, not one group
        raise
    except Exception as err:  # noqa: BLE001 - a group that cannot be checked stays stale, with why
        row["verdict"] = f"not checked: {type(err).__name__}: {err}"
    log.info("adopt %s (%d runs): %s", row["label"], len(group), row["verdict"])
    return row


def adopt_group(ctx: Context, group: list[runs.Run], row: dict, rtol: float, rtol_later_steps: float) -> None:
    """Re-stamp an adopted group's trainings with today's code and what the check found; archive them."""
    code = code_of(group[0].record["identity"]["model"], *TRAINING_CODE)
    check = {k: v for k, v in row.items() if k.startswith(("train ", "eval ", "check", "scored", "weights"))} | {
        "rtol": rtol, "rtol_later_steps": rtol_later_steps}
    for r in group:
        restamp(r, code, check)
        archive_training(ctx, r)


def untrained_rows(ctx: Context, untrained: list[runs.Run], rtol: float, dry_run: bool) -> list[dict]:
    """Rows for the stale evaluations of models that are not trained (bilinear, OIDN: their evaluator
    changed), each checked on its first sequence and re-stamped when adopted."""
    rows = []
    for evaluation in untrained:
        row = check_untrained(ctx, evaluation, rtol)
        log.info("adopt %s (evaluation %s): %s", row["label"], evaluation.hash, row["verdict"])
        if row["verdict"] == "adopted" and not dry_run:
            restamp(evaluation, code_of(evaluation.record["identity"]["trained"]["model"], *EVALUATION_CODE),
                    {k: v for k, v in row.items() if k.startswith(("eval ", "check", "scored"))} | {"rtol": rtol})
            archive_evaluation(ctx, evaluation)
        rows.append(row)
    return rows


def caption(steps: int, rtol_rounded_weights: float) -> str:
    return (
        f"Stale training runs checked against the current code (bench/experiments/adopt.py): per group (a "
        f"table row, every seed), the witness run's first {steps} training steps replayed, its whole "
        f"learning-rate schedule, and its weights through the evaluator on one sequence, as relative "
        f"differences to the recorded values; adopted when the first step (loss, gradient norm: the same "
        f"initial weights, batch, forward and backward) and the schedule are within rtol, the evaluation "
        f"within eval rtol (rtol, or {rtol_rounded_weights:g} for the archive's float16-rounded weights), "
        f"and the later steps' loss within rtol later steps (summation order makes two runs of the same "
        f"code drift apart slowly from the second step on). Check: 'record' compares with the witness's "
        f"recorded values (it trained on this render); 'recorded code' compares with the same replay by the "
        f"code the witness recorded, rebuilt from git (it trained on another render), on today's frames "
        f"(scored split: the frames both codes scored). weights false: no seed of the group kept its weights, "
        f"so only its training was checked. Rows whose witness is an evaluation (runs in group 1, no step "
        f"columns) are of models that are not trained (bilinear, OIDN) whose evaluator changed, checked on "
        f"their first sequence. One row per witness, its latest check: groups that earlier calls adopted are "
        f"no longer stale and keep their row.")


def run(ctx: Context, name: str, steps: int, rtol: float, rtol_later_steps: float, rtol_rounded_weights: float,
        dry_run: bool) -> pd.DataFrame:
    """conf/experiment/adopt.yaml says what each argument is."""
    log.info("adopt: %d archived runs restored into the store", restore_archive(ctx))
    groups = stale_groups(ctx)
    log.info("adopt: %d groups of stale training runs (%d runs)", len(groups), sum(map(len, groups.values())))
    untrained = stale_untrained_evaluations(ctx)
    render_what_the_checks_read(ctx, groups, untrained)
    rows, adopted = [], set()
    for group in groups.values():
        row = check_group(ctx, group, steps, rtol, rtol_later_steps, rtol_rounded_weights)
        if row["verdict"] == "adopted" and not dry_run:
            adopt_group(ctx, group, row, rtol, rtol_later_steps)
            adopted |= {r.hash for r in group}
        rows.append(row)
    for evaluation in [] if dry_run else evaluations_to_restamp(ctx, adopted):
        restamp(evaluation, evaluation_code(ctx, evaluation),
                {"trainings": evaluation.record["metrics"]["train_run"], "rtol": rtol})
        archive_evaluation(ctx, evaluation)
    rows += untrained_rows(ctx, untrained, rtol, dry_run)
    checked = time.strftime("%Y-%m-%dT%H:%M:%S%z")
    table = pd.DataFrame([{**row, "checked": checked, "rtol": rtol, "rtol later steps": rtol_later_steps,
                           "dry run": dry_run} for row in rows])
    table = with_earlier_verdicts(table, ctx.results_dir / name / "table.csv")
    write_table(table, ctx.results_dir / name, caption=caption(steps, rtol_rounded_weights))
    log.info("adopt: %d of %d groups adopted%s; table in %s", sum(r["verdict"] == "adopted" for r in rows),
             len(rows), " (dry run)" if dry_run else "", ctx.results_dir / name)
    return table


def against_record(ctx: Context, witness: runs.Run, steps: int, weights: bool) -> dict:
    """A group's check against the witness's record: its first steps replayed, its weights scored on the
    first sequence of an evaluation of today's frames (where there is one)."""
    row = {"check": "record"}
    row |= {f"train {k}": v for k, v in check_training(ctx, witness.record, witness.dir, steps).items()}
    evals = [e for e in evaluations_of(ctx.runs_dir, {witness.hash}) if scored_here(ctx, e)]
    if evals and weights:
        row |= {f"eval {k}": v for k, v in check_inference(ctx, evals[0], witness.dir).items()}
    return row


def against_recorded_code(ctx: Context, witness: runs.Run, steps: int, weights: bool) -> dict:
    """A group's check against its recorded code (the differential check): the same first steps, and its
    weights scored as an evaluation scored them (or on val in its training's network domain)."""
    evaluation = differential_evaluation(ctx, witness) if weights else None
    scoring = None
    if weights:
        scoring = (differential_scoring(ctx, evaluation, witness.dir) if evaluation is not None
                   else training_scoring(ctx, witness))
    modules = [witness.record["identity"]["model"]["_target_"], *EVALUATION_CODE, *TRAINING_CODE]
    trained_with = witness.record["code"]
    scored_with = (evaluation.record.get("code") or {}) if evaluation is not None else {}
    row = {"check": "recorded code"}
    trained_at = fingerprinted_at(witness.record)
    if fingerprints_agree(trained_with, scored_with):  # one rebuilt tree ran both
        return row | check_against_recorded_code(ctx, {**scored_with, **trained_with}, modules, steps, witness,
                                                 scoring, trained_at)
    # the evaluation ran later code than the training: each is replayed by its own
    return (row | check_against_recorded_code(ctx, trained_with, modules, steps, witness, None, trained_at)
            | check_against_recorded_code(ctx, scored_with, modules, 0, None, scoring,
                                          fingerprinted_at(evaluation.record)))


def fingerprinted_at(record: dict) -> str | None:
    """The git commit whose code a run's fingerprint names: its last adoption's (adopt re-stamps the
    fingerprint with the code of that commit), else the commit it ran at. The recorded code's other
    model definitions are taken there (recorded_code.rebuild), so that they import what it defined."""
    return (record.get("code_adopted") or {}).get("git_commit") or record.get("git_commit")


def verdict(row: dict, rtol: float, eval_rtol: float, rtol_later_steps: float) -> str:
    """"adopted", or "differs (<what> <difference> > <limit>)" for the largest difference over its limit;
    "not checked" when a replay compared nothing (no step, no frame: a difference of 0 would be vacuous)."""
    limits = {k: eval_rtol if k.startswith("eval ") else rtol for k in row
              if k.startswith(("train step 1", "train lr")) or k.removeprefix("eval ") in COMPARED}
    empty = [k for k in ("train steps", "eval frames") if k in row and not row[k]]
    if empty or not limits:
        return f"not checked: nothing compared ({', '.join(empty) or 'no replay'})"
    over = {k: row[k] for k, limit in limits.items() if not row[k] <= limit}  # NaN: over
    later = row.get("train later loss", 0.0)
    worst = max(over, key=lambda k: row[k] / limits[k]) if over else None
    return ("adopted" if not over and later <= rtol_later_steps else
            f"differs ({worst} {row[worst]:.2g} > {limits[worst]:g})" if over else
            f"differs (later loss {later:.2g} > {rtol_later_steps:g})")


def stale_untrained_evaluations(ctx: Context) -> list[runs.Run]:
    """Complete evaluations of a model that is not trained (bilinear, OIDN: the identity names its config),
    run the default way, whose code changed since they were recorded."""
    out = []
    for path in sorted((ctx.runs_dir / "eval").glob(f"*/{runs.RECORD}")):
        record = runs.read_record(path) or {}
        identity = record.get("identity") or {}
        trained = identity.get("trained")
        if record.get("status") == "complete" and isinstance(trained, dict) \
                and identity.get("version") == runs.IDENTITY_VERSION and ran_the_default_way(identity) \
                and runs.code_changes(record, code_of(trained["model"], *EVALUATION_CODE)):
            out.append(runs.Run("eval", record["hash"], path.parent, record))
    return out


def check_untrained(ctx: Context, evaluation: runs.Run, rtol: float) -> dict:
    """The table row of a stale evaluation of a model that is not trained: its first sequence scored by
    the current code against its record (scored on today's render) or against its recorded code (on
    another render of the same settings)."""
    identity = evaluation.record["identity"]
    code = code_of(identity["trained"]["model"], *EVALUATION_CODE)
    row = {"label": evaluation.record.get("label"), "runs in group": 1, "witness": evaluation.hash,
           "changed": ", ".join(runs.code_changes(evaluation.record, code))}
    try:
        if scored_here(ctx, evaluation):
            row["check"] = "record"
            row |= {f"eval {k}": v for k, v in check_inference(ctx, evaluation, None).items()}
        else:
            row["check"] = "recorded code"
            row |= check_against_recorded_code(ctx, evaluation.record["code"],
                                               [identity["trained"]["model"]["_target_"], *EVALUATION_CODE], 0,
                                               None, differential_scoring(ctx, evaluation, None),
                                               fingerprinted_at(evaluation.record))
        row["eval rtol"] = rtol
        row["verdict"] = verdict(row, rtol, rtol, 0.0)
    except TrainingInterrupted:
        raise
    except Exception as err:  # noqa: BLE001 - an evaluation that cannot be checked stays stale, with why
        row["verdict"] = f"not checked: {type(err).__name__}: {err}"
    return row


def with_earlier_verdicts(table: pd.DataFrame, previous_csv: Path) -> pd.DataFrame:
    """`table` after the rows of the previous call's table whose witness this call did not check (an
    adopted group is no longer stale, so a later call would otherwise drop the record of its check)."""
    if not previous_csv.exists() or not previous_csv.stat().st_size > 1:  # a call with nothing stale wrote none
        return table
    earlier = pd.read_csv(previous_csv).rename(columns={"runs": "runs in group"})  # its name until session 37
    if "witness" not in earlier:
        return table
    earlier = earlier[~earlier["witness"].isin(table["witness"] if "witness" in table else [])]
    return pd.concat([earlier, table], ignore_index=True)
