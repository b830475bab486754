"""Training a row's model, once: the training run's identity, reusing a recorded run (from the run store
or its archive), else training it with the one training loop (`bench.train.train`), the learning
curve's validation and the perceptual loss's features; the Cascade's stages (paper Table 3), each
trained alone on its own task and assembled; the torchrun ranks that join rank 0's trainings.
"""
from __future__ import annotations

import dataclasses
import functools
import hashlib
import logging
from pathlib import Path

import torch

from bench import archived, distributed, runs
from bench.errors import UserError
from bench.evaluate import evaluate
from bench.experiments.context import TRAINING_CODE, Context, code_of, working_split
from bench.experiments.datasets import check_training_frames, dataset, render_digest, split_fingerprint
from bench.measure import fused_kernels_used
from bench.models.factory import build_model, is_learned
from bench.models.srd import SRDNet, SRDStage, load_stage
from bench.tasks import CASCADE_STAGES, Task, get_task
# _State and _write_curves: the trainer's own writer of a checkpoint's curves, to rebuild them byte for byte
# (public once bench/train.py changes anyway: an edit there makes every recorded training stale)
from bench.train import CHECKPOINT, TrainingDiverged, TrainingInterrupted, _State, _write_curves, train

log = logging.getLogger("bench")

TORCH_HUB_VGG16 = Path.home() / ".cache/torch/hub/checkpoints/vgg16-397923af.pth"
CURVE_SCORES = ("relMSE", "PSNR", "SSIM")  # the learning curve's (FLIP would cost more than these three)

def validation(ctx: Context, task: Task, sequences: int):
    """The learning curve's scorer: `validate(model) -> {relMSE, PSNR, SSIM}` on whole frames of
    `sequences` validation sequences spread over the split (None when there are none to score)."""
    if sequences <= 0:
        return None
    split = working_split(ctx)
    try:
        full = dataset(ctx, split, task, training=False)
    except ValueError:  # no such split in this dataset: no curve, the final table still scores it
        log.warning("no %r split for the learning curve; training without one", split)
        return None
    n = min(sequences, len(full))  # spread over the split; all of it when it has no more than asked
    chosen = sorted({round(i * (len(full) - 1) / max(1, n - 1)) for i in range(n)})
    subset = torch.utils.data.Subset(full, chosen)
    hdr = ctx.train.hdr

    def validate(model) -> dict:
        _, metrics = evaluate(model, subset, task, hdr=hdr, device=ctx.device, scores=CURVE_SCORES)
        return {k: metrics[k] for k in CURVE_SCORES}
    return validate


def perceptual_features(ctx: Context):
    """(features module or None, identity dict saying which weights and layer are used)."""
    from bench.nn.vgg import load_vgg16_features, random_vgg16_features
    layer = ctx.vgg.layer
    path = ctx.vgg.weights or (str(TORCH_HUB_VGG16) if TORCH_HUB_VGG16.exists() else None)
    if path:
        if not Path(path).exists():
            raise UserError(f"VGG16 weights file {path} (vgg.weights / SRD_VGG16_WEIGHTS) does not exist")
        try:
            features = load_vgg16_features(path, layer)
        except (ValueError, KeyError, RuntimeError, EOFError) as err:  # not VGG16 weights, or cut short
            raise UserError(f"vgg.weights={path}: not VGG16 weights in torchvision's format up to {layer} "
                            f"({str(err).splitlines()[0][:300]})") from err
        return (features.to(ctx.device),
                {"weights": Path(path).name, "sha256": _file_sha256(str(Path(path).resolve())), "layer": layer})
    if ctx.vgg.allow_random:
        log.warning("perceptual loss uses a fixed-seed RANDOM VGG16 (no weights found); tables will say so")
        return random_vgg16_features(layer, seed=0).to(ctx.device), {"weights": "random(seed=0)", "layer": layer}
    raise UserError("the perceptual loss needs ImageNet VGG16 weights in torchvision's format: set "
                    "vgg.weights=/path/to/vgg16-397923af.pth (or SRD_VGG16_WEIGHTS), or put the file at "
                    f"{TORCH_HUB_VGG16}; or allow a fixed-seed random VGG with vgg.allow_random=true; "
                    "or turn the term off with train.loss.final.perceptual=0")


@functools.lru_cache(maxsize=4)
def _file_sha256(path: str) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            digest.update(chunk)
    return digest.hexdigest()[:16]


def _train_identity(ctx: Context, cfg: dict, task: Task, seed: int, vgg_id: dict | None,
                    stage: str | None = None) -> dict:
    identity = {"version": runs.IDENTITY_VERSION, "model": cfg, "task": task.name, "train": ctx.train.identity(),
                "data": split_fingerprint(ctx, "train"), "seed": seed, "vgg": vgg_id}
    if stage is not None:
        identity["stage"] = stage
    return identity


def _trainings(ctx: Context, cfg: dict, task: Task, seed: int, cascade: bool):
    """(stage label or None, identity) of each training that scoring (cfg, task, seed) uses: a
    Cascade's stages in order, none for a model that learns nothing."""
    stages = CASCADE_STAGES[cfg.get("stage_order", "sr_dn")] if cascade else [(None, task.name)]
    for stage, task_name in stages:
        stage_task = get_task(task_name)
        if is_learned(_initial_model(cfg, stage_task, seed, stage)):
            yield stage, _train_identity(ctx, cfg, stage_task, seed, _loss_features(ctx)[1], stage)


def planned_trainings(ctx: Context, cfg: dict, task: Task, seed: int, cascade: bool = False) -> list[str]:
    """The run hashes of the trainings that scoring (cfg, task, seed) uses, from the configuration alone
    (the data fingerprint is planned from the spec): reads no record and needs no rendered frame."""
    return [runs.config_hash(identity) for _, identity in _trainings(ctx, cfg, task, seed, cascade)]


@dataclasses.dataclass(frozen=True)
class RecordedTraining:
    """A training that scoring a row uses, as the records say (`training_records`)."""
    hash: str
    stage: str | None   # a Cascade's stage ("sr", "dn"), else None
    why: str | None     # why it would run (not recorded, or recorded with other code); None: reused
    weights: bool       # recorded with its weights


def training_records(ctx: Context, cfg: dict, task: Task, seed: int, cascade: bool = False) -> list[RecordedTraining]:
    """The trainings that scoring (cfg, task, seed) uses (a Cascade's stages in order; none for a model
    that learns nothing), each as `runs.begin` would find it. Reads records and restores archived runs;
    never renders, trains or records a run."""
    code = code_of(cfg, *TRAINING_CODE)
    return [_recorded(ctx, identity, code, stage) for stage, identity in _trainings(ctx, cfg, task, seed, cascade)]


def untrained(trainings: list[RecordedTraining]) -> list[str]:
    """Why each of `trainings` would run before its weights load ("[sr stage] ..." for a Cascade's
    stages); empty when every one is recorded with weights this code reuses."""
    whys = [(t.stage, t.why or (None if t.weights else _weightless(t.hash))) for t in trainings]
    return [f"[{stage} stage] {why}" if stage else why for stage, why in whys if why]


def reused_trainings(trainings: list[RecordedTraining]) -> list[str] | None:
    """The run hashes of `trainings` when all are reused as recorded ([] for a model that learns
    nothing), else None. Their weights are not asked for: a recorded evaluation needs none (a training
    without them, left out of the archive, is trained again only where its weights are loaded)."""
    if any(t.why for t in trainings):
        return None
    return [t.hash for t in trainings]


def _recorded(ctx: Context, identity: dict, code: dict, stage: str | None = None) -> RecordedTraining:
    """The training of `identity` as `runs.begin` would find it: not recorded in the store or
    `ctx.runs_archive`, recorded with other code, or reused (with or without its weights)."""
    h = runs.config_hash(identity)
    run = runs.lookup(ctx.runs_dir, "train", identity, ctx.runs_archive)
    if run is None:
        where = f"{ctx.runs_dir}" + (f" or {ctx.runs_archive}" if ctx.runs_archive else "")
        return RecordedTraining(h, stage, f"no complete training recorded in {where}", False)
    stale = runs.code_changes(run.record, code) and not ctx.reuse_stale
    kept = runs.lookup(ctx.runs_archive, "train", identity) if stale and ctx.runs_archive else None
    if kept is not None and not runs.code_changes(kept.record, code):
        run, stale = kept, False  # begin restores the archive's run of this code over the store's
    why = f"its training {h} was recorded with other code (reuse_stale=true loads it anyway)" if stale else None
    return RecordedTraining(h, stage, why, archived.has_weights(run.dir))


def _weightless(h: str) -> str:
    return (f"its training {h} is recorded without weights (an archive leaves files over "
            f"{runs.ARCHIVED_FILE_MAX_BYTES / 2**20:.0f} MiB out)")


def scoring_only_error(whys: list[str]) -> UserError:
    """What eval.data_dir says instead of training: which trainings it lacks, and what to do."""
    return UserError("eval.data_dir scores recorded trainings only (it renders and trains nothing); not recorded "
                     "with weights: " + "; ".join(whys) + ". Train them first (the same command without "
                     "eval.data_dir renders data_dir and trains what is missing), then score your frames again")


def trained_model(ctx: Context, cfg: dict, task: Task, seed: int, label: str = "", load: bool = True,
                  stage: str | None = None, divergence_ends: bool = False):
    """The model of `cfg` trained on `task`, from the run store when recorded. Returns (model, run or None).

    With load=False a recorded run's weights are not read (the caller may not need them; see
    `evaluated`) and the model returned is None: call again with load=True when needed. A recorded run
    restored from the archive without its weights (runs.ARCHIVED_FILE_MAX_BYTES) is trained again then,
    into the store only: the archive keeps the record its evaluations scored.
    With `stage` ("sr" or "dn") only that stage of an SRDNet (built at the SRD scale, 2) is trained on
    `task`, through SRDStage. With `divergence_ends` (a learning-rate range test) a diverging training is
    recorded complete with the step it diverged at, instead of failing.
    With `eval.data_dir` set nothing is trained (nor forced): a training not recorded with what is
    needed is a UserError saying which (`untrained` lists them all before a table runs)."""
    model = _initial_model(cfg, task, seed, stage)
    if not is_learned(model):
        return model, None
    features, vgg_id = _loss_features(ctx)
    identity = _train_identity(ctx, cfg, task, seed, vgg_id, stage)
    code = code_of(cfg, *TRAINING_CODE)
    scoring_only = bool(ctx.eval.data_dir)  # recorded models scored on other frames: never a training
    if scoring_only:
        recorded = _recorded(ctx, identity, code)
        why = recorded.why or (load and not recorded.weights and _weightless(recorded.hash))
        if why:
            raise scoring_only_error([f"{label or cfg['_target_']} seed {seed}: {why}"])
    if not ctx.render_data:  # your own data: a frame the trainer cannot crop is named before a run is recorded
        check_training_frames(ctx)
    force = ctx.force and not scoring_only  # force=true recomputes the evaluations on your frames only
    run = runs.begin(ctx.runs_dir, "train", identity, seed=seed, device=ctx.device, label=label,
                     force=force, code=code, reuse_stale=ctx.reuse_stale, archive=ctx.runs_archive,
                     needs=((CHECKPOINT, archived.WEIGHTS),) if load else (), rebuild=curves_from_checkpoint)
    # a run trained again for the weights its archive left out: the archive keeps the run it scored
    weights_only = None if force else archived_without_weights(ctx, run, code)
    if run.reused:
        log.info("train %s: reusing run %s", label or cfg["_target_"], run.hash)
        if not weights_only:
            archive_training(ctx, run)
        return (archived.load_weights(model, run.dir, ctx.device) if load else None), run
    recipe = ctx.train
    _drop_damaged_checkpoint(run.dir / CHECKPOINT)
    if run.record.get("earlier_wall_time") and (saved := _checkpoint(run.dir / CHECKPOINT)) is not None:
        run.record["resumed_wall_time_s"] = float(saved.get("elapsed_s", 0.0))
        run.record["earlier_wall_time"] = ("lost with its record; its checkpoint's optimisation seconds "
                                           "(validation excluded) stand in")
        log.info("train %s: run %s resumes from a checkpoint whose record was lost; its training time is the "
                 "checkpoint's %.1f s of optimisation", label or cfg["_target_"], run.hash, saved.get("elapsed_s", 0.0))
    if distributed.rank_and_size()[1] > 1:  # the other torchrun ranks (serve_trainings) join this training
        distributed.share((ctx, cfg, task.name, seed, stage, str(run.dir)))
    validate = None
    try:
        if stage is None:
            validate = validation(ctx, task, recipe.val_sequences)
        summary = train(model, dataset(ctx, "train", task, training=True, seed=seed), task, run.dir, recipe,
                        features=features, seed=seed, device=ctx.device, progress=ctx.progress,
                        validate=validate, distributed_ranks=True)
    except TrainingDiverged as err:
        if divergence_ends:  # a learning-rate range test: divergence is its result, recorded as such
            archive_training(ctx, runs.complete(run, {"diverged_at_step": err.step, "divergence": str(err)}))
            log.info("train %s: diverged at step %d (expected in a range test)", label, err.step)
            return model, run
        runs.fail(run, str(err))
        raise UserError(f"training {label or cfg['_target_']} (run {run.dir}) diverged: {err}") from err
    except TrainingInterrupted as err:  # stopped on request with a checkpoint: resumable, not failed
        runs.fail(run, str(err), status="interrupted")
        raise TrainingInterrupted(f"training {label or cfg['_target_']} stopped by {err}", err.exit_code - 128) \
            from None
    except BaseException as err:  # interrupted or crashed: the record says so; the checkpoint stays
        runs.fail(run, f"{type(err).__name__}: {err}")
        raise
    summary["render"] = render_digest(ctx, "train")  # which render it trained on (adopt compares it)
    if validate is not None:  # and which its curve scored: curves on two renders of val differ
        summary["val_render"] = render_digest(ctx, working_split(ctx))
    summary["fused_kernels"] = fused_kernels_used(ctx.device)
    runs.complete(run, summary)
    if weights_only:
        log.warning("train %s: run %s trained again for its weights, which its archive left out; they match "
                    "the archived run's bit for bit only on the same CPU and threads (archived final val PSNR "
                    "%s, now %s)", label or cfg["_target_"], run.hash, _final_val_psnr(weights_only),
                    _final_val_psnr(run.record))
    else:
        archive_training(ctx, run)
    log.info("train %s: trained in %.1f min (run %s)", label or cfg["_target_"], run.record["wall_time_s"] / 60,
             run.hash)
    return model, run


def _checkpoint(path: Path) -> dict | None:
    """A training's checkpoint as saved (weights, optimizer, step, curves, optimisation seconds), or None
    when it is missing or damaged."""
    if runs.read_or_none(path) is None:
        return None
    return torch.load(path, map_location="cpu", weights_only=False)


def curves_from_checkpoint(run_dir: Path, names: list[str]) -> bool:
    """`runs.begin`'s rebuild of a complete training: its curves (curve.csv, val_curve.csv) written again
    from its checkpoint, which holds them whole; False where anything else is damaged or the checkpoint
    is missing (an archived run keeps none) or damaged. The run store checks the result against the
    recorded digests."""
    if not set(names) <= {archived.CURVE, archived.VAL_CURVE} or (saved := _checkpoint(run_dir / CHECKPOINT)) is None:
        return False
    _write_curves(Path(run_dir), _State(saved["step"], saved["curve"], saved.get("val_curve", []),
                                        saved.get("elapsed_s", 0.0)))
    return True


def _drop_damaged_checkpoint(path: Path) -> None:
    """A checkpoint that does not read (cut short, overwritten) is no checkpoint: removed, so the
    training starts over instead of failing to resume (the log names it, `runs.read_or_none`)."""
    if path.exists() and runs.read_or_none(path) is None:
        path.unlink()


def archived_without_weights(ctx: Context, run: runs.Run, code: dict) -> dict | None:
    """The record `ctx.runs_archive` holds of this training, complete, of this code and without its
    weights (over the archive's file limit), else None."""
    kept = ctx.runs_archive / "train" / run.hash if ctx.runs_archive is not None else None
    if kept is None or archived.has_weights(kept):
        return None
    record = runs.read_record(kept / runs.RECORD) or {}
    return record if record.get("status") == "complete" and not runs.code_changes(record, code) else None


def _final_val_psnr(record: dict) -> str:
    """The learning curve's last PSNR, with the render of val it scored: a run trained again on the same
    frames ends near its archived curve only when both scored the same render."""
    metrics = record.get("metrics", {})
    psnr = metrics.get("val", {}).get("PSNR")
    if psnr is None:
        return "not recorded"
    return f"{psnr:.3f} dB on val render {metrics.get('val_render') or '(not recorded)'}"


def _initial_model(cfg: dict, task: Task, seed: int, stage: str | None):
    """The model of `cfg` as its training starts (seeded), or one stage of it (SRDStage)."""
    torch.manual_seed(seed)
    return build_model(cfg, task.scale) if stage is None else SRDStage(cascade_net(cfg), stage)


def _loss_features(ctx: Context):
    """(VGG16 features, their identity) when the recipe has a perceptual term, else (None, None)."""
    uses_vgg = any(w.get("perceptual", 0) > 0 for w in ctx.train.loss.values())
    return perceptual_features(ctx) if uses_vgg else (None, None)


def serve_trainings() -> None:
    """A torchrun rank other than 0: join each training that rank 0 starts (`trained_model` shares what
    it trains), until rank 0 says there is none left. Rank 0 records the runs; this process writes nothing."""
    while (job := distributed.share()) is not None:
        ctx, cfg, task_name, seed, stage, run_dir = job
        task = get_task(task_name)
        model = _initial_model(cfg, task, seed, stage)
        try:
            train(model, dataset(ctx, "train", task, training=True, seed=seed), task, run_dir, ctx.train,
                  features=_loss_features(ctx)[0], seed=seed, device=ctx.device, progress=False,
                  distributed_ranks=True)
        except TrainingDiverged:  # rank 0 diverged at the same step and records it (a range test goes on)
            continue


def cascade_net(cfg: dict) -> SRDNet:
    net = build_model(cfg, get_task("srd").scale)
    if not isinstance(net, SRDNet):
        raise UserError(f"a Cascade row needs the proposed model (SRDNet), got {cfg['_target_']}")
    return net


def cascade_model(ctx: Context, cfg: dict, seed: int, label: str = "", load: bool = True):
    """A Cascade (paper Table 3): each SRDNet stage trained alone on its own task, assembled into one
    net. Returns (net, list of the stages' training runs); load=False: (None, the runs), each stage
    trained first only if it is not recorded, as `trained_model(load=False)` does for one training."""
    net, stage_runs = cascade_net(cfg) if load else None, []
    for stage, task_name in CASCADE_STAGES[cfg.get("stage_order", "sr_dn")]:
        stage_model, run = trained_model(ctx, cfg, get_task(task_name), seed, f"{label} [{stage} stage]",
                                         stage=stage, load=load)
        if load:
            load_stage(net, stage, stage_model.state_dict())
        stage_runs.append(run)
    return net, stage_runs


def archive_training(ctx: Context, run: runs.Run) -> runs.Run:
    """Keep a finished training in `ctx.runs_archive`, in the archive's compact form (bench.archived):
    its record, the weights evaluation loads in float16, its curves. A training the archive already keeps
    without its weights (left out on purpose, docs/runs.md) stays without them when it is archived again
    (adopt re-stamps it from a store that has them)."""
    if ctx.runs_archive is not None:
        copy = Path(ctx.runs_archive) / run.kind / run.hash
        weightless = (copy / runs.RECORD).exists() and not archived.has_weights(copy)

        def write(directory):
            archived.write(run.dir, directory, run.record)
            if weightless:
                (directory / archived.WEIGHTS).unlink(missing_ok=True)
        runs.archive(run, ctx.runs_archive, write=write)
    return run
