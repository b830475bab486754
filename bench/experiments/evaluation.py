"""Evaluating a row: one recorded evaluation run per (training, split, data, domain, way of running),
reused when recorded, else the trained model scored by `bench.evaluate` (training it first if needed);
`eval.fast_path=auto` measures the fastest correct path first.
"""
from __future__ import annotations

import logging

from bench import archived, runs
from bench.errors import UserError
from bench.evaluate import LATER_SCORES, REQUIRED_SCORES, evaluate
from bench.experiments.context import EVALUATION_CODE, TRAINING_CODE, Context, code_of
from bench.experiments.datasets import dataset, evaluation_data, render_digest, split_fingerprint
from bench.experiments.training import RecordedTraining, cascade_model, reused_trainings, trained_model
from bench.exrio import write_exr
from bench.macs import count_params
from bench.measure import AUTO, choose_fast_path, fused_kernels_used
from bench.models.factory import build_model
from bench.score import unscored_frames
from bench.tasks import Task

log = logging.getLogger("bench")


def evaluated(ctx: Context, cfg: dict, task: Task, seed: int, split: str, label: str = "",
              cascade: bool = False) -> runs.Run:
    """Evaluation run of a row (training it first if needed)."""
    if cascade:  # the stages' runs name the evaluation; their weights load only where it is scored
        model, stage_runs = cascade_model(ctx, cfg, seed, label, load=False)
        train_run, trained = None, runs.join_trainings([r.hash for r in stage_runs])
    else:
        model, train_run = trained_model(ctx, cfg, task, seed, label, load=False)
        trained = train_run.hash if train_run else {"model": cfg, "task": task.name}
    hdr = ctx.train.hdr
    scoring_ctx = evaluation_data(ctx)
    fast_path = ctx.eval.fast_path
    if fast_path == AUTO:
        if model is None:  # the weights it will score, where at hand (loaded once: they are scored below)
            model = _trained_weights(ctx, cfg, task, seed, label, cascade, stage_runs if cascade else [train_run])
        fast_path = measured_fast_path(ctx, cfg, task, split, label, model)
    identity, code = _evaluation_key(ctx, scoring_ctx, cfg, trained, split, fast_path,
                                     learned=train_run is not None or cascade)
    run = runs.begin(ctx.runs_dir, "eval", identity, seed=seed, device=ctx.device, label=label,
                     force=ctx.force, code=code, reuse_stale=ctx.reuse_stale, archive=ctx.runs_archive)
    missing = missing_scores(ctx, run.metrics) if run.reused else []
    if missing:  # recorded before the evaluator scored these: evaluating again is cheap, training is not
        log.info("eval %s: re-evaluating run %s, recorded without %s", label, run.hash, ", ".join(missing))
        run = runs.begin(ctx.runs_dir, "eval", identity, seed=seed, device=ctx.device, label=label,
                         force=True, code=code)
    if run.reused:
        log.info("eval %s: reusing run %s", label, run.hash)
        return archive_evaluation(ctx, run)
    try:
        if model is None:  # recorded trainings whose weights were not read (or that lack them)
            if cascade:
                model, stage_runs = cascade_model(ctx, cfg, seed, label)
            else:
                model, train_run = trained_model(ctx, cfg, task, seed, label)
            run.restart_clock()  # a training done here for the weights is the training run's time, not this one's
        per_image, metrics = evaluate(model, dataset(scoring_ctx, split, task, training=False), task, hdr=hdr,
                                      device=ctx.device, out_dir=run.dir, save_exr=ctx.eval.save_exr,
                                      write_exr=write_exr, path=fast_path, tile=ctx.eval.tile)
        unscored = unscored_frames(per_image)
        if unscored:  # a mean would leave them out and the row would look better than the model is
            raise UserError(f"eval {label}: {len(unscored)} of {len(per_image)} frames score NaN ({', '.join(unscored[:3])}"
                            f"): the output or the reference is not finite there, and a table's means would leave "
                            f"them out (eval.fast_path={fast_path}); the evaluation is recorded failed")
    except BaseException as err:  # the record says so, never "running" forever
        runs.fail(run, f"{type(err).__name__}: {err}")
        raise
    metrics["params"] = count_params(model)
    metrics["train_run"] = trained if isinstance(trained, str) else None
    metrics["vgg"] = (train_run.record["identity"].get("vgg") if train_run else None)
    metrics["render"] = render_digest(scoring_ctx, split)
    metrics["fused_kernels"] = fused_kernels_used(ctx.device)
    trainings = stage_runs if cascade else [train_run] if train_run is not None else []
    metrics["rounded_weights"] = any(archived.rounded(r.dir) for r in trainings)  # the archive's float16 copy
    return archive_evaluation(ctx, runs.complete(run, metrics))


def evaluation_recorded(ctx: Context, cfg: dict, task: Task, seed: int, split: str,
                        trainings: list[RecordedTraining], cascade: bool = False) -> bool:
    """Whether scoring (cfg, task, seed) on `split` reuses a recorded evaluation, and so reads no frame:
    decided from records alone (its `trainings`, `training_records`), before any data is rendered. False
    when force=true or eval.fast_path=auto (its choice is measured on the frames)."""
    if ctx.force or ctx.eval.fast_path == AUTO:
        return False
    hashes = reused_trainings(trainings)
    if hashes is None:
        return False
    trained = runs.join_trainings(hashes) if cascade else hashes[0] if hashes else {"model": cfg, "task": task.name}
    identity, code = _evaluation_key(ctx, evaluation_data(ctx), cfg, trained, split, ctx.eval.fast_path,
                                     learned=bool(hashes))
    run = runs.reusable(ctx.runs_dir, "eval", identity, code, ctx.reuse_stale, ctx.runs_archive)
    return run is not None and not missing_scores(ctx, run.metrics)


def missing_scores(ctx: Context, metrics: dict) -> list[str]:
    """The scores a recorded evaluation's `metrics` lack but must hold to be reused: those added since it
    was recorded (FLIP) only when eval.rescore_missing asks."""
    required = REQUIRED_SCORES + (LATER_SCORES if ctx.eval.rescore_missing else ())
    return [m for m in required if f"{m} se" not in metrics]


def _evaluation_key(ctx: Context, scoring_ctx: Context, cfg: dict, trained, split: str, fast_path: str,
                    learned: bool) -> tuple[dict, dict]:
    """(identity, code fingerprint) of the evaluation of `trained` on `split` of `scoring_ctx`'s data
    (`evaluation_data`);
    a learned row's numbers also depend on the trainer: retraining it makes its evaluation stale too."""
    identity = evaluation_identity(trained, split, split_fingerprint(scoring_ctx, split), ctx.train.hdr,
                                   fast_path, ctx.eval.tile, ctx.eval.save_exr)
    return identity, code_of(cfg, *EVALUATION_CODE, *(TRAINING_CODE if learned else ()))


def evaluation_identity(trained, split: str, data: str, hdr: str, fast_path: str, tile: int | None,
                        saves_frames: bool) -> dict:
    """What an evaluation's numbers depend on: the training (its run hash, Cascade stages' joined by "+",
    or the config of a model that is not trained), the frames scored, the network domain and the way the
    model runs (the fast path, tiles); `saves_frames`: the output frames are saved (`eval.save_exr`), an
    artifact of their own run (identity key "frames", hashed as it is named)."""
    identity = {"version": runs.IDENTITY_VERSION, "trained": trained, "split": split, "data": data, "hdr": hdr,
                "fast_path": fast_path, "tile": tile}
    if saves_frames:
        identity["frames"] = True
    return identity


def archive_evaluation(ctx: Context, run: runs.Run) -> runs.Run:
    """Keep a finished evaluation in `ctx.runs_archive`: its record and per-frame scores (claims pair
    them), not its output frames (`eval.save_exr`), which stay in the run store. Scores of your frames
    (`eval.data_dir`) stay out too: the archive is committed with the preset's tables, and there it is
    only read, for the recorded models."""
    if ctx.runs_archive is not None and ctx.eval.data_dir is None and not run.record["identity"].get("frames"):
        runs.archive(run, ctx.runs_archive, write=lambda directory: archived.write_evaluation(run.dir, directory))
    return run


def _trained_weights(ctx: Context, cfg: dict, task: Task, seed: int, label: str, cascade: bool, trainings):
    """The row's model with the weights it scores, where they are at hand (in the store or the archive),
    else None: a training the archive keeps without weights is not trained again only to choose a path."""
    if not all(archived.has_weights(r.dir) for r in trainings):
        return None
    return (cascade_model(ctx, cfg, seed, label) if cascade else trained_model(ctx, cfg, task, seed, label))[0]


def measured_fast_path(ctx: Context, cfg: dict, task: Task, split: str, label: str, model=None) -> str:
    """eval.fast_path=auto: the fastest correct path on this machine and one sequence of the split, for
    `model` with the weights it scores (a path's accuracy depends on them, bench.measure), or for an
    untrained copy when they are not at hand (`_trained_weights`); cached in <runs_dir>/fast_paths.json
    under the weights' digest. The evaluation's identity records the path."""
    item = dataset(evaluation_data(ctx), split, task, training=False)[0]
    if model is None:
        log.info("eval %s: fast_path=auto is measured on an untrained copy: the training's weights are not kept",
                 label)
        model = build_model(cfg, task.scale)
    model = model.to(ctx.device).eval()
    x, g = item[task.x][None].to(ctx.device), item[task.g][None].to(ctx.device)
    chosen, times = choose_fast_path(model, x, g, ctx.device, ctx.runs_dir / "fast_paths.json",
                                     {"model": cfg, "task": task.name})
    if times:
        log.info("eval %s: fast_path=auto chose %s (%s)", label, chosen,
                 ", ".join(f"{k} {v:.0f} ms" if isinstance(v, float) else f"{k} {v}" for k, v in times.items()))
    return chosen
