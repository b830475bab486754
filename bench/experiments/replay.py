"""What adopt compares (bench/experiments/adopt.py): a recorded training's first steps replayed, a model's
first sequence scored, and the differences to the record or to the same replay by the recorded code.

The differential check runs `replay` twice: here, by the current code, and in a subprocess,
`python -m bench.experiments.replay JOB OUT`, whose packages are the recorded code rebuilt from git
(bench/experiments/recorded_code.py); that subprocess also reports the fingerprint of what it ran.
"""
from __future__ import annotations

import dataclasses
import pickle
import sys
import tempfile
from pathlib import Path

import numpy as np
import pandas as pd
import torch

from bench import archived, runs
from bench.errors import UserError
from bench.evaluate import evaluate
from bench.experiments import recorded_code
from bench.experiments.context import EVALUATION_CODE, TRAINING_CODE, Context, recipe_from
from bench.experiments.datasets import dataset, evaluation_data
from bench.experiments.migrate import IMPLIED
from bench.experiments.training import cascade_net, perceptual_features
from bench.models.factory import build_model
from bench.models.srd import SRDStage
from bench.tasks import get_task
from bench.train import CHECKPOINT, Recipe, lr_at, train


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
    """Largest |a - b| / max(|b|, 1e-12) over paired values (0 for none); equal values count 0 (inf and inf
    included), any other non-finite pair inf: a NaN never passes for a match."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    if not a.size:
        return 0.0
    with np.errstate(invalid="ignore"):
        diff = np.abs(a - b) / np.maximum(np.abs(b), 1e-12)
    diff = np.where(a == b, 0.0, np.where(np.isfinite(diff), diff, np.inf))
    return float(np.max(diff))


def _model(cfg: dict, task, stage: str | None):
    return build_model(cfg, task.scale) if stage is None else SRDStage(cascade_net(cfg), stage)


BY_ORDER = False  # set by `main`: the rebuilt recorded code's subprocess


def _load_recorded(model, run_dir: Path):
    """`model` with the training's weights: by name, or, in the recorded code's replay (`BY_ORDER`), by
    order where every shape matches (its parameter names may predate a rename the archive's weights
    carry). Today's code loads by name only, as tables do."""
    state = archived.state_dict(run_dir)
    try:
        model.load_state_dict(state)
    except RuntimeError:
        if not BY_ORDER:
            raise
        own = model.state_dict()
        if [tuple(t.shape) for t in own.values()] != [tuple(t.shape) for t in state.values()]:
            raise
        model.load_state_dict(dict(zip(own, state.values())))
    return model


def replayed_curve(ctx: Context, record: dict, run_dir: Path, steps: int) -> pd.DataFrame:
    """The first `steps` steps of the recorded training, replayed by this code from the same seed on the
    frames of this store's data: the per-step curve (loss, grad_norm, lr) the trainer writes."""
    identity = record["identity"]
    cfg, task, seed, stage = identity["model"], get_task(identity["task"]), identity["seed"], identity.get("stage")
    recipe = recipe_of_this_code({**dataclasses.asdict(ctx.train), **identity["train"], "checkpoint_every": 1,
                                  "checkpoint_every_s": 1e9})
    if archived.has_weights(run_dir):  # the recorded weights fit the model built now: names, shapes
        _load_recorded(_model(cfg, task, stage), run_dir)
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


def recipe_of_this_code(train: dict) -> Recipe:
    """The recipe of `train` as this code's `Recipe` takes it: an option it lacks (the recorded code,
    rebuilt, predates it) is allowed only at the value the code before it implied (migrate.IMPLIED),
    and set as a plain attribute, for today's experiment code that reads it."""
    known = {f.name for f in dataclasses.fields(Recipe)}
    for option in set(train) - known:
        if option not in IMPLIED or train[option] != IMPLIED[option]:
            raise UserError(f"train.{option}={train[option]!r}: the code replayed has no such option")
    recipe = recipe_from({k: v for k, v in train.items() if k in known})
    for option in set(train) - known:
        object.__setattr__(recipe, option, train[option])  # older recipes were frozen dataclasses
    return recipe


def first_sequence_scores(ctx: Context, cfg: dict, task: str, weights: Path | None, split: str,
                          hdr: str, stage: str | None = None) -> pd.DataFrame:
    """The model `cfg` (with the weights of the training in directory `weights`; None: a model that is
    not trained; `stage`: one stage of a Cascade, on its own task) run by this code's evaluator on the
    first sequence of `split` as the frames are now: its per-frame scores."""
    task = get_task(task)
    model = _model(cfg, task, stage)
    if weights is not None:
        _load_recorded(model, weights)
    frames = dataset(evaluation_data(ctx), split, task, training=False)
    return evaluate(model, [frames[0]], task, hdr=hdr)[0]


def scoring_of(evaluation: runs.Run, weights: Path | None) -> dict:
    """`first_sequence_scores`' arguments (past ctx) for the model an evaluation scored."""
    identity = evaluation.record["identity"]
    trained = identity["trained"]
    stage = None
    if weights is not None:  # a training's weights (a Cascade stage's: that stage, on its own task)
        record = runs.read_record(Path(weights) / runs.RECORD)["identity"]
        cfg, task, stage = record["model"], record["task"], record.get("stage")
    else:
        cfg, task = trained["model"], trained["task"]
    return {"cfg": cfg, "task": task, "weights": weights, "split": identity["split"], "hdr": identity["hdr"],
            "stage": stage}


def replay(ctx: Context, steps: int, training: tuple | None, scoring: dict | None) -> dict:
    """What the differential check computes twice, by the recorded code and by this code: the first
    `steps` steps of `training` (record, directory) replayed, and `scoring` (first_sequence_scores)."""
    return {"curve": None if training is None else replayed_curve(ctx, *training, steps),
            "scores": None if scoring is None else first_sequence_scores(ctx, **scoring)}


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


def check_inference(ctx: Context, evaluation: runs.Run, weights: Path | None) -> dict:
    """Run the model `evaluation` scored (with the weights in directory `weights`, or none) through the
    current evaluator on its first sequence; {metric: relative difference to its recorded per-frame values}."""
    scores = first_sequence_scores(ctx, **scoring_of(evaluation, weights))
    recorded = archived.read_per_image(evaluation.dir)
    if recorded is None:
        raise UserError(f"adopt: evaluation run {evaluation.hash} has no per-frame scores to compare with")
    return score_differences(scores, recorded)


def check_against_recorded_code(ctx: Context, recorded: dict, modules: list, steps: int,
                                training: runs.Run | None, scoring: dict | None, commit: str | None = None) -> dict:
    """The differential check (bench/experiments/recorded_code.py): the replay of `training`'s first steps
    and of `scoring` by the `recorded` code (the fingerprint of `modules` a run recorded), rebuilt from
    git (`commit`: the git commit the run recorded), against the same by this code, on today's frames;
    {what: relative difference}, keyed "train ..." and "eval ...". The subprocess fingerprints what it
    ran: a file that is not the recorded one is an error."""
    job = {"ctx": ctx, "steps": steps, "scoring": scoring,
           "training": None if training is None else (training.record, training.dir)}
    with tempfile.TemporaryDirectory(prefix="srd-recorded-code-") as tmp:
        # the harness imports the trainer and the evaluator whatever `modules` names (an untrained row's
        # evaluation names no trainer): rebuild takes what the recorded fingerprint lacks at `commit`
        harness = runs.code_fingerprint([*modules, *TRAINING_CODE, *EVALUATION_CODE])
        tree = recorded_code.rebuild(recorded, harness, Path(tmp), commit)
        then = recorded_code.replay_there(tree, {"replay": job, "modules": modules})
    other = sorted(p for p in recorded if then["code"].get(p) != recorded[p])
    if other:
        raise UserError(f"the rebuilt code is not the recorded one: {', '.join(other)}")
    now = replay(**job)
    out = {}
    if training is not None:
        out |= {f"train {k}": v for k, v in (schedule_difference(training.record, training.dir, ctx)
                                             | curve_differences(now["curve"], then["curve"], steps)).items()}
    if scoring is not None:
        out |= {f"eval {k}": v for k, v in score_differences(now["scores"], then["scores"]).items()}
        out["scored split"] = scoring["split"]
    return out


def fingerprints_agree(a: dict, b: dict) -> bool:
    """Whether two recorded fingerprints name the same version of every file both name."""
    return all(a[path] == b[path] for path in set(a) & set(b))


def main(argv=None) -> int:
    """The differential check's subprocess (recorded_code.replay_there): `replay` of a pickled job, run by
    the code this module was imported from (the recorded code, rebuilt)."""
    global BY_ORDER
    BY_ORDER = True
    job_file, out_file = (argv or sys.argv[1:])[:2]
    job = pickle.loads(Path(job_file).read_bytes())
    out = replay(**job["replay"]) | {"code": runs.code_fingerprint(job["modules"])}  # what ran: the rebuilt files
    Path(out_file).write_bytes(pickle.dumps(out))
    return 0


if __name__ == "__main__":
    sys.exit(main())
