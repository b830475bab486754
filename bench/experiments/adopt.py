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
fingerprint names, rebuilt from git history (bench/experiments/recorded_code.py), replays the same first
steps and scores the same sequence of today's frames in a subprocess, and the current code must give the
same numbers (the differential check: the change moves no number, whatever the frames). A group that passes has its runs (every seed) and
their evaluations re-stamped with the current code fingerprint, the old one and the check kept in the record
(`code_adopted`), and archived again (`runs_archive`, complete runs only: else a fresh clone restores the
archive's stale copy); a group that fails is left stale, with the measured difference in the table. What
is not checked: training steps after the first `steps` (the same code paths run again, on other batches),
and evaluations run another way (a fast path, tiles), which stay stale.

A group none of whose seeds kept its weights (the archive leaves some out, docs/runs.md) is checked by its
training replay alone: the evaluator is then not checked for it.

Stopped trainings (interrupted, failed, or killed: a "running" record no process holds) with a checkpoint are adopted with their group, so they
resume instead of starting again; a group of only such runs has no evaluation to check.

The archive's runs (`runs_archive`) that the store lacks are restored into it first, so a fresh clone
adopts the committed runs. Runs recorded under an older identity version are not looked at: `+experiment=migrate` re-keys them first.

Writes `<results_dir>/adopt/table.{csv,md,tex}`: one row per group with the verdict and the differences.
"""
from __future__ import annotations

import dataclasses
import logging
import pickle
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import pandas as pd
import torch

from bench import archived, runs
from bench.datagen import load_manifest
from bench.errors import UserError
from bench.evaluate import evaluate
from bench.experiments import recorded_code
from bench.experiments.context import EVALUATION_CODE, TRAINING_CODE, Context, code_of, recipe_from
from bench.experiments.datasets import data_fingerprint, dataset, evaluation_data, render_digest
from bench.experiments.evaluation import archive_evaluation
from bench.experiments.training import archive_training, cascade_net, perceptual_features
from bench.infer import REFERENCE
from bench.models.factory import build_model
from bench.models.srd import SRDStage
from bench.table_writer import write_table
from bench.tasks import get_task
from bench.train import CHECKPOINT, TrainingInterrupted, lr_at, train

log = logging.getLogger("bench")

COMPARED = ("relMSE", "PSNR", "SSIM")


class _Replayed(Exception):
    """Raised by `_FirstSteps` once the trainer asks for a batch past the replayed steps."""


class _FirstSteps:
    """The training dataset, stopping the trainer when it draws the first batch of step `steps`."""

    def __init__(self, data, steps: int, batch_size: int):
        self.data, self.last_draw = data, steps * batch_size

    def __len__(self):
        return len(self.data)

    def item(self, index: int, draw: int):
        if draw >= self.last_draw:
            raise _Replayed
        return self.data.item(index, draw)


def relative_difference(a, b) -> float:
    """Largest |a - b| / max(|b|, 1e-12) over paired values (0 for none)."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    if not a.size:
        return 0.0
    return float(np.max(np.abs(a - b) / np.maximum(np.abs(b), 1e-12)))


def _model(cfg: dict, task, stage: str | None):
    return build_model(cfg, task.scale) if stage is None else SRDStage(cascade_net(cfg), stage)


def replayed_curve(ctx: Context, record: dict, run_dir: Path, steps: int) -> pd.DataFrame:
    """The first `steps` steps of the recorded training, replayed by this code from the same seed on the
    frames of this store's data: the per-step curve (loss, grad_norm, lr) the trainer writes."""
    identity = record["identity"]
    cfg, task, seed, stage = identity["model"], get_task(identity["task"]), identity["seed"], identity.get("stage")
    recipe = recipe_from({**dataclasses.asdict(ctx.train), **identity["train"], "checkpoint_every": 1,
                          "checkpoint_every_s": 1e9})
    if archived.has_weights(run_dir):  # the recorded weights fit the model built now: names, shapes
        archived.load_weights(_model(cfg, task, stage), run_dir)
    torch.manual_seed(seed)  # as trained_model builds it: the initial weights come from this seed
    model = _model(cfg, task, stage)
    features = perceptual_features(ctx)[0] if identity.get("vgg") else None
    ctx = dataclasses.replace(ctx, train=recipe)  # the recorded recipe's crops and sequence length
    data = _FirstSteps(dataset(ctx, "train", task, training=True, seed=seed), steps, recipe.batch_size)
    with tempfile.TemporaryDirectory() as tmp:
        try:
            train(model, data, task, tmp, recipe, features=features, seed=seed, progress=False)
        except _Replayed:
            pass
        return pd.DataFrame(torch.load(Path(tmp) / CHECKPOINT, weights_only=False)["curve"])


def first_sequence_scores(ctx: Context, train_record: dict, train_dir: Path, split: str, hdr: str) -> pd.DataFrame:
    """The recorded weights run by this code's evaluator on the first sequence of `split` as the frames
    are now: its per-frame scores."""
    identity = train_record["identity"]
    task = get_task(identity["task"])
    model = archived.load_weights(build_model(identity["model"], task.scale), train_dir)
    frames = dataset(evaluation_data(ctx), split, task, training=False)
    return evaluate(model, [frames[0]], task, hdr=hdr)[0]


def replay(ctx: Context, record: dict, run_dir: Path, steps: int, evaluation: dict | None) -> dict:
    """What the differential check computes twice, by the recorded code and by this code: the replayed
    curve and, given an evaluation identity, the first sequence's scores."""
    return {"curve": replayed_curve(ctx, record, run_dir, steps),
            "scores": None if evaluation is None else
            first_sequence_scores(ctx, record, run_dir, evaluation["split"], evaluation["hdr"])}


def curve_differences(replayed: pd.DataFrame, reference: pd.DataFrame, steps: int) -> dict:
    n = min(steps, len(reference), len(replayed))
    return {"step 1 loss": relative_difference(replayed["loss"][:1], reference["loss"][:1]),
            "step 1 grad_norm": relative_difference(replayed["grad_norm"][:1], reference["grad_norm"][:1]),
            "later loss": relative_difference(replayed["loss"][1:n], reference["loss"][1:n]), "steps": n}


def score_differences(scores: pd.DataFrame, reference: pd.DataFrame) -> dict:
    reference = reference[reference["sequence"].astype(str) == str(scores["sequence"].iloc[0])]
    merged = scores.merge(reference, on="frame", suffixes=("", " reference"))
    return {m: relative_difference(merged[m], merged[f"{m} reference"]) for m in COMPARED} | {"frames": len(merged)}


def schedule_difference(record: dict, run_dir: Path, ctx: Context) -> dict:
    """The current schedule's learning rate at every recorded step against the recorded one."""
    recorded = archived.read_curve(run_dir)  # the trainer's curve (an archive's keeps the first steps whole)
    if recorded is None:
        raise UserError(f"{run_dir} has no per-step curve that reads")
    recipe = recipe_from({**dataclasses.asdict(ctx.train), **record["identity"]["train"]})
    return {"lr": relative_difference([lr_at(int(s) - 1, recipe) for s in recorded["step"]], recorded["lr"])}


def check_training(ctx: Context, record: dict, run_dir: Path, steps: int) -> dict:
    """Replay the witness training's first steps and its schedule; {what: relative difference} to its record."""
    out = schedule_difference(record, run_dir, ctx)
    return out | curve_differences(replayed_curve(ctx, record, run_dir, steps), archived.read_curve(run_dir), steps)


def check_inference(ctx: Context, train_record: dict, train_dir: Path, evaluation: runs.Run) -> dict:
    """Run the recorded weights through the current evaluator on the first sequence of `evaluation`;
    {metric: relative difference to its recorded per-frame values}."""
    identity = evaluation.record["identity"]
    scores = first_sequence_scores(ctx, train_record, train_dir, identity["split"], identity["hdr"])
    recorded = archived.read_per_image(evaluation.dir)
    if recorded is None:
        raise UserError(f"adopt: evaluation run {evaluation.hash} has no per-frame scores to compare with")
    return score_differences(scores, recorded)


def check_against_recorded_code(ctx: Context, witness: runs.Run, steps: int, evaluation: runs.Run | None) -> dict:
    """The differential check (bench/experiments/recorded_code.py): the replay by the code the witness
    (and `evaluation`) recorded, rebuilt from git, against the same replay by this code, on today's
    frames; {what: relative difference}, keyed as the other checks' ("train ...", "eval ...")."""
    identity = witness.record["identity"]
    recorded = {**(evaluation.record.get("code") or {} if evaluation else {}), **(witness.record.get("code") or {})}
    current = code_of(identity["model"], *EVALUATION_CODE, *TRAINING_CODE)
    job = {"ctx": ctx, "record": witness.record, "run_dir": witness.dir, "steps": steps,
           "evaluation": evaluation and {k: evaluation.record["identity"][k] for k in ("split", "hdr")}}
    with tempfile.TemporaryDirectory(prefix="srd-recorded-code-") as tmp:
        then = recorded_code.replay_there(recorded_code.rebuild(recorded, current, Path(tmp)), job)
    now = replay(**job)
    out = {f"train {k}": v for k, v in (schedule_difference(witness.record, witness.dir, ctx)
                                         | curve_differences(now["curve"], then["curve"], steps)).items()}
    if evaluation is not None:
        out |= {f"eval {k}": v for k, v in score_differences(now["scores"], then["scores"]).items()}
    return out


RESUMABLE = ("complete", "interrupted", "failed")  # a stopped training resumes from its checkpoint once adopted


def stale_groups(ctx: Context) -> dict[str, list[runs.Run]]:
    """Training runs with a checkpoint (complete, or stopped and resumable), or complete without one (an
    archive left its weights out: a witness only when no seed of its group has them, checked by its
    training alone), whose code changed since
    they were recorded and whose data is this data_dir's, grouped by identity without the seed (one
    table row): runs with weights first, then lowest seed first; complete runs first among equal seeds
    (their evaluations can be checked)."""
    data = data_fingerprint(ctx, "train")
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
        trained = record.get("metrics", {}).get("train_run") or ""
        if record.get("status") == "complete" and trained and set(trained.split("+")) <= train_hashes \
                and record["identity"].get("version") == runs.IDENTITY_VERSION:
            out.append(runs.Run("eval", record["hash"], path.parent, record))
    return out


def scored_here(ctx: Context, evaluation: runs.Run) -> bool:
    """Whether `evaluation` ran the default way on frames as they are now: only then can the current code
    be held to its numbers. An evaluation against references rendered again since says nothing about the
    code: other render settings (the data fingerprint), or the same settings rendered on another host
    (its render digest, where it recorded one: the noise differs in the last bits and beyond)."""
    identity, frames = evaluation.record["identity"], evaluation_data(ctx)
    recorded = evaluation.record.get("metrics", {}).get("render")
    return (ran_the_default_way(identity) and identity.get("data") == data_fingerprint(frames, identity["split"])
            and recorded in (None, render_digest(frames, identity["split"])))


def ran_the_default_way(identity: dict) -> bool:
    """Whether an evaluation ran the model the reference way (fp32, whole frames), as adopt's check does."""
    return identity["fast_path"] == REFERENCE and not identity["tile"]


def trained_here(ctx: Context, training: runs.Run) -> bool:
    """Whether `training` recorded that it trained on this render of the split (same settings, same
    host's noise): only then can its replay be held to its record. Trainings recorded before 2026-11-25
    record no render."""
    return training.record.get("metrics", {}).get("render") == render_digest(ctx, "train")


def differential_evaluation(ctx: Context, training: runs.Run) -> runs.Run | None:
    """An evaluation of `training` run the default way on a split whose settings today's frames have (any
    render of it): the differential check scores its first sequence by both codes."""
    frames = evaluation_data(ctx)
    on_disk = {frame["split"] for frame in load_manifest(frames.data_dir)["frames"]}
    for evaluation in evaluations_of(ctx.runs_dir, {training.hash}):
        identity = evaluation.record["identity"]
        if ran_the_default_way(identity) and identity["split"] in on_disk \
                and identity.get("data") == data_fingerprint(frames, identity["split"]):
            return evaluation
    return None


def restamp(run: runs.Run, code: dict, check: dict) -> None:
    """Record that `run` is what the current code computes: its fingerprint replaced, the old kept."""
    run.record["code_adopted"] = {"from": runs.config_hash(run.record.get("code") or {}),
                                  "changed": runs.code_changes(run.record, code), "check": check,
                                  "date": time.strftime("%Y-%m-%dT%H:%M:%S%z"), **runs.provenance()}
    run.record["code"] = code
    run.save()


def run(ctx: Context, name: str, steps: int, rtol: float, rtol_later_steps: float, rtol_rounded_weights: float,
        dry_run: bool) -> pd.DataFrame:
    """conf/experiment/adopt.yaml says what each argument is."""
    log.info("adopt: %d archived runs restored into the store", restore_archive(ctx))
    groups = stale_groups(ctx)
    log.info("adopt: %d groups of stale training runs (%d runs)", len(groups), sum(map(len, groups.values())))
    rows, adopted = [], set()
    for group in groups.values():
        witness = group[0]
        identity = witness.record["identity"]
        code = code_of(identity["model"], *TRAINING_CODE)
        row = {"label": witness.record.get("label"), "runs": len(group), "witness": witness.hash,
               "changed": ", ".join(runs.code_changes(witness.record, code))}
        try:
            weights = archived.has_weights(witness.dir)  # none: no seed's archive kept them; training is checked
            if trained_here(ctx, witness):  # its record can judge the code
                row["check"] = "record"
                row |= {f"train {k}": v for k, v in check_training(ctx, witness.record, witness.dir, steps).items()}
                evals = [e for e in evaluations_of(ctx.runs_dir, {witness.hash}) if scored_here(ctx, e)]
                if evals and weights:
                    row |= {f"eval {k}": v for k, v in check_inference(ctx, witness.record, witness.dir, evals[0]).items()}
                eval_rtol = rtol_rounded_weights if archived.rounded(witness.dir) else rtol
            else:  # trained on other frames: the recorded code, rebuilt, replays on today's
                row["check"] = "recorded code"
                row |= check_against_recorded_code(ctx, witness, steps,
                                                   differential_evaluation(ctx, witness) if weights else None)
                eval_rtol = rtol  # the same weights on both sides
            limits = {k: eval_rtol if k.startswith("eval ") else rtol for k in row
                      if k.startswith(("train step 1", "train lr", "eval ")) and k != "eval frames"}
            over = {k: row[k] for k, limit in limits.items() if row[k] > limit}
            later = row["train later loss"]
            row["eval rtol"] = eval_rtol
            worst = max(over, key=lambda k: row[k] / limits[k]) if over else None
            row["verdict"] = ("adopted" if not over and later <= rtol_later_steps else
                              f"differs ({worst} {row[worst]:.2g} > {limits[worst]:g})" if over else
                              f"differs (later loss {later:.2g} > {rtol_later_steps:g})")
        except TrainingInterrupted:  # Ctrl-C / SIGTERM during a replay stops the command, not one group
            raise
        except Exception as err:  # noqa: BLE001 - a group that cannot be checked stays stale, with why
            row["verdict"] = f"not checked: {type(err).__name__}: {err}"
        log.info("adopt %s (%d runs): %s", row["label"], len(group), row["verdict"])
        if row["verdict"] == "adopted" and not dry_run:
            check = {k: v for k, v in row.items() if k.startswith(("train ", "eval "))} | {
                "rtol": rtol, "rtol_later_steps": rtol_later_steps}
            for r in group:
                restamp(r, code, check)
                archive_training(ctx, r)
            adopted |= {r.hash for r in group}
        rows.append(row)
    for evaluation in evaluations_of(ctx.runs_dir, adopted):  # their evaluations, run the default way
        identity, trained = evaluation.record["identity"], evaluation.record["metrics"]["train_run"]
        model_cfg = runs.read_record(ctx.runs_dir / "train" / trained.split("+")[0] / runs.RECORD)["identity"]["model"]
        code = code_of(model_cfg, *EVALUATION_CODE, *TRAINING_CODE)
        if ran_the_default_way(identity) and runs.code_changes(evaluation.record, code):
            restamp(evaluation, code, {"trainings": trained, "rtol": rtol})
            archive_evaluation(ctx, evaluation)
    checked = time.strftime("%Y-%m-%dT%H:%M:%S%z")
    table = pd.DataFrame([{**row, "checked": checked, "rtol": rtol, "rtol later steps": rtol_later_steps,
                           "dry run": dry_run} for row in rows])
    table = with_earlier_verdicts(table, ctx.results_dir / name / "table.csv")
    write_table(table, ctx.results_dir / name, caption=(
        f"Stale training runs checked against the current code (bench/experiments/adopt.py): per group (a "
        f"table row, every seed), the witness run's first {steps} training steps replayed, its whole "
        f"learning-rate schedule, and its weights through the evaluator on one sequence, as relative "
        f"differences to the recorded values; adopted when the first step (loss, gradient norm: the same "
        f"initial weights, batch, forward and backward) and the schedule are within rtol, the evaluation "
        f"within eval rtol (rtol, or {rtol_rounded_weights:g} for the archive's float16-rounded weights), "
        f"and the later steps' loss within rtol later steps (summation order makes two runs of the same "
        f"code drift apart slowly from the second step on). Check: 'record' compares with the witness's "
        f"recorded values (it trained on this render); 'recorded code' compares with the same replay by the "
        f"code the witness recorded, rebuilt from git (it trained on another render), on today's frames. "
        f"One row per witness, its latest check: groups "
        f"that earlier calls adopted are no longer stale and keep their row."))
    log.info("adopt: %d of %d groups adopted%s; table in %s", sum(r["verdict"] == "adopted" for r in rows),
             len(rows), " (dry run)" if dry_run else "", ctx.results_dir / name)
    return table


def with_earlier_verdicts(table: pd.DataFrame, previous_csv: Path) -> pd.DataFrame:
    """`table` after the rows of the previous call's table whose witness this call did not check (an
    adopted group is no longer stale, so a later call would otherwise drop the record of its check)."""
    if not previous_csv.exists():
        return table
    earlier = pd.read_csv(previous_csv)
    if "witness" not in earlier:
        return table
    earlier = earlier[~earlier["witness"].isin(table["witness"] if "witness" in table else [])]
    return pd.concat([earlier, table], ignore_index=True)


def main(argv=None) -> int:
    """The differential check's subprocess (recorded_code.replay_there): `replay` of a pickled job, run by
    the code this module was imported from (the recorded code, rebuilt)."""
    job_file, out_file = (argv or sys.argv[1:])[:2]
    job = pickle.loads(Path(job_file).read_bytes())
    Path(out_file).write_bytes(pickle.dumps(replay(**job)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
