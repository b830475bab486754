"""The steps every table shares: make the data, train a row's model, evaluate it; each step is a
recorded run that is reused when its identity is already in the run store.

A row is (model name, argument overrides, task, training overrides, cascade or not). Its identity hashes
only what determines its numbers, so two tables that ask for the same row (the paper reuses "ours" across
Tables 4, 5 and 7) share one run. A Cascade row (paper Table 3) is two runs, one per SRDNet stage, each
trained alone on its own task (bench.tasks.CASCADE_STAGES) and assembled for evaluation.

Identities hash configuration; each run also records the fingerprint of the code it ran (the model's
module, the trainer or evaluator, and what they import: `runs.code_fingerprint`). A recorded run whose
code has changed since is recomputed, and the log names the changed files; `reuse_stale=true` reuses it.
"""
from __future__ import annotations

import contextlib
import copy
import dataclasses
import functools
import hashlib
import json
import logging
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd
import torch
from hydra.utils import instantiate

from bench import distributed, runs
from bench.datagen import (build_dataset, damaged_frames, frame_paths, load_manifest, manifest_problems,
                           rebuild_manifest)
from bench.dataset import SequenceDataset
from bench.errors import UserError
from bench.evaluate import SCORES, evaluate
from bench.exrio import write_exr
from bench.infer import REFERENCE
from bench.macs import count_params
from bench.measure import AUTO, choose_fast_path
from bench.models.srd import SRDNet, SRDStage, load_stage
from bench.tasks import CASCADE_STAGES, Task, get_task
from bench.train import CHECKPOINT, Recipe, TrainingDiverged, TrainingInterrupted, load_weights, train

log = logging.getLogger("bench")

TORCH_HUB_VGG16 = Path.home() / ".cache/torch/hub/checkpoints/vgg16-397923af.pth"


@dataclass(frozen=True)
class EvalSpec:
    """How tables evaluate (conf/config.yaml `eval:`, where the defaults and their meaning are)."""
    split: str
    data_dir: Path | None        # another dataset to score (see evaluation_data); None: data_dir
    save_exr: bool
    fast_path: str
    tile: int | None


@dataclass(frozen=True)
class VggSpec:
    """The perceptual loss's features (conf/config.yaml `vgg:`)."""
    weights: str | None
    layer: str
    allow_random: bool


@dataclass
class Context:
    """Everything a table needs, as typed values built by the CLI from the Hydra config (`make_context`);
    the defaults live in conf/, not here. `data_spec` and `models` stay dicts: the data description and
    the model configs (`_target_` + arguments) are recorded and hashed as they are written."""
    preset: str                                     # the size preset's name (smoke, cpu, paper)
    runs_dir: Path
    results_dir: Path
    data_dir: Path
    data_spec: dict
    train: Recipe
    eval: EvalSpec
    vgg: VggSpec
    models: dict
    budget_gmac: float | None                       # the preset's MAC budget per 960x540 frame (GMac)
    seeds: list
    device: str
    workers: int
    force: bool
    progress: bool
    render_data: bool
    model_lr: dict                                  # model name -> peak learning rate (else train.lr)
    shard: tuple[int, int] | None                   # (i, n): a table computes its (row, seed) runs i, i+n, ... first
    reuse_stale: bool                               # reuse runs whose code changed since they were recorded
    runs_archive: Path | None = None                # finished trainings and evaluations kept with the results
                                                    # (bench.runs.archive); None: the run store only


# ---------------------------------------------------------------- models

def model_config(ctx: Context, name: str, overrides: dict | None = None) -> dict:
    if name not in ctx.models:
        raise UserError(f"unknown model {name!r}; known models: {', '.join(sorted(ctx.models))} "
                        f"(add one as conf/model/<name>.yaml, see README, 'Adding a model')")
    cfg = copy.deepcopy(ctx.models[name])
    cfg.update(overrides or {})
    return cfg


def build_model(cfg: dict, scale: int):
    return instantiate(cfg, scale=scale)


def deep_merge(base: dict, overrides: dict | None) -> dict:
    """A copy of `base` with `overrides` merged in, nested dicts key by key."""
    out = copy.deepcopy(base)
    for key, value in (overrides or {}).items():
        out[key] = deep_merge(out[key], value) if isinstance(value, dict) and isinstance(out.get(key), dict) \
            else copy.deepcopy(value)
    return out


def with_training(ctx: Context, overrides: dict | None, model: str | None = None) -> Context:
    """`ctx` with the recipe a row trains with: the model's own learning rate (`model_lr`, from the
    range test), then the row's training overrides (e.g. the perceptual weight) merged in."""
    if model in ctx.model_lr:
        overrides = deep_merge({"lr": ctx.model_lr[model]}, overrides)
    return dataclasses.replace(ctx, train=recipe_from(deep_merge(dataclasses.asdict(ctx.train), overrides))) \
        if overrides else ctx


def recipe_from(config: dict) -> Recipe:
    """The training recipe of a `train:` dict, a bad key or value as a UserError."""
    try:
        return Recipe.from_config(config)
    except (TypeError, ValueError) as err:
        raise UserError(f"train: {err}") from err


TRAINING_CODE = ("bench.train", "bench.dataset")
EVALUATION_CODE = ("bench.evaluate", "bench.dataset")


def code_of(cfg: dict, *modules: str) -> dict:
    """Code fingerprint of a run of the model `cfg` that also runs `modules`."""
    return runs.code_fingerprint([cfg["_target_"], *modules])


def is_learned(model) -> bool:
    return count_params(model) > 0


# ---------------------------------------------------------------- data

def _canonical(value) -> str:
    return json.dumps(value, sort_keys=True, default=str)


@functools.lru_cache(maxsize=32)
def _fingerprint(manifest_path: str, mtime_ns: int, split: str | None, files: str | None = None) -> str:
    manifest = load_manifest(Path(manifest_path).parent)
    spec = copy.deepcopy(manifest.get("spec") or {})  # your own renders may have none
    if split is not None and isinstance(spec.get("splits"), dict):
        spec["splits"] = {split: spec["splits"].get(split)}
    frames = sorted((f["split"], f["sequence"], f["frame"], f.get("settings_hash")) for f in manifest["frames"]
                    if split is None or f["split"] == split)
    if not frames and split is not None:
        splits = sorted({f["split"] for f in manifest["frames"]})
        raise UserError(f"{Path(manifest_path).parent}: no frames in split {split!r} (it has {splits}); tables "
                        f"score the split eval.split (e.g. eval.split={([s for s in splits if s != 'train'] or ['NAME'])[0]}), "
                        "trainings read 'train'")
    identity = {"spec": spec, "frames": frames}
    if files is not None:
        identity["files"] = files
    return runs.config_hash(identity)


def data_fingerprint(ctx: Context, split: str | None = None) -> str:
    """Hash of what is on disk (the manifest's spec and every frame's render settings), not of the path:
    runs trained on it are reused exactly while the data they saw is unchanged. With `split`, only that
    split's part of the spec and its frames count: re-rendering the validation references does not make
    the training runs stale."""
    path = ctx.data_dir / "manifest.json"
    if not path.exists():
        raise UserError(f"data directory {ctx.data_dir} has no manifest.json; render it with "
                        f"`python -m bench +experiment=data preset={ctx.preset}` or point data_dir=... at a "
                        f"dataset in the documented layout (docs/data.md)")
    files = None if ctx.render_data else _file_stats(ctx.data_dir, split)
    return _fingerprint(str(path.resolve()), path.stat().st_mtime_ns, split, files)


def _file_stats(root: Path, split: str | None) -> str:
    """Your own renders (render_data=false) are fingerprinted by content too: each frame file's size
    and modification time. Not its bytes: hashing gigabytes at every command would cost more than
    the check is worth, and editing a frame, re-rendering it or copying a dataset (without `cp -p`)
    changes its mtime. Rendered data needs none of this: its spec and settings determine the pixels on
    one machine (a frame rendered again matches its file bit for bit). Across hosts Mitsuba's LLVM
    backend compiles for the CPU, paths diverge on last-bit differences, and the noise differs with the
    same statistics (the cpu val split's input bilinear: 31.68-31.70 dB over three hosts' renders)."""
    stats = []
    for frame in load_manifest(root)["frames"]:
        if split is not None and frame["split"] != split:
            continue
        for name in frame_paths(root, frame["split"], frame["sequence"], frame["frame"])[:2]:
            st = os.stat(name) if os.path.exists(name) else None
            stats.append((name, st.st_size, st.st_mtime_ns) if st else (name, None, None))
    return runs.config_hash({"files": stats})


def render_digest(ctx: Context, split: str) -> str | None:
    """Which render of `split` this is: a hash of its frame files' CRC-32 stamps in the manifest, or
    None when a frame has none (your own data before `verify=true`). Not part of any identity: renders
    of the same settings on other hosts share the data fingerprint but differ in their noise, and
    tables use this to say when their rows were scored on different ones."""
    crcs = []
    for rec in load_manifest(ctx.data_dir)["frames"]:
        if rec["split"] == split:
            files = rec.get("files") or {}
            if not (files.get("lr") and files.get("hr")):
                return None
            crcs.append((rec["sequence"], rec["frame"], files["lr"]["crc32"], files["hr"]["crc32"]))
    return runs.config_hash({"render": sorted(crcs)})[:8]


def ensure_data(ctx: Context, passes: set[str]) -> str:
    """Make sure `data_dir` holds the preset's dataset with at least `passes`, rendering only what is
    missing; returns the data fingerprint. With render_data=false the directory is used as it is."""
    if not ctx.render_data:
        problems = manifest_problems(ctx.data_dir)
        if problems:  # one problem (a damaged manifest) on one line
            listed = problems[0] if len(problems) == 1 else "\n  " + "\n  ".join(problems)
            raise UserError(f"data: {ctx.data_dir} is not a dataset in the documented layout (docs/data.md): "
                            f"{listed}")
        fingerprint = data_fingerprint(ctx)
        manifest = load_manifest(ctx.data_dir)
        damaged = damaged_frames(ctx.data_dir, manifest["frames"], manifest.get("passes", []), stamps=False)
        if damaged:
            raise UserError(f"data: {len(damaged)} damaged frame files in {ctx.data_dir} ({_listed(damaged)}); "
                            "with render_data=false they are yours to replace (or drop their records from "
                            "manifest.json)")
        return fingerprint
    ctx.data_dir.mkdir(parents=True, exist_ok=True)
    # one process checks and renders a dataset at a time: two tables needing other buffers would
    # otherwise render the same frames at once, and each take the other's files for damaged ones
    with contextlib.closing(runs.acquire(ctx.data_dir / ".render.lock", f"rendering {ctx.data_dir}")):
        return _render_missing(ctx, passes)


def _render_missing(ctx: Context, passes: set[str]) -> str:
    manifest = _manifest_or_rebuilt(ctx)
    if manifest is not None:
        if _canonical(manifest.get("spec")) == _canonical(ctx.data_spec):
            # per frame: a split re-rendered for another table (new settings) may hold fewer buffers
            lacking = [f for f in manifest["frames"] if not passes <= set(f.get("buffers", []))]
            damaged = damaged_frames(ctx.data_dir, manifest["frames"], manifest["passes"])
            if not damaged and not lacking:
                log.info("data: %s already holds %s", ctx.data_dir, ", ".join(sorted(passes)))
                return data_fingerprint(ctx)
            if damaged:
                log.warning("data: %d damaged frame files (%s); rendering them again", len(damaged), _listed(damaged))
    identity = {"spec": ctx.data_spec, "passes": sorted(passes)}
    run = runs.begin(ctx.runs_dir, "data", identity, seed=ctx.data_spec.get("seed"), device=ctx.device,
                     label=f"data {ctx.preset}", force=True, every_call=True)  # a data run records one render job
    try:
        log.info("data: making sure %s holds %s (rendering what is missing)", ctx.data_dir, ", ".join(sorted(passes)))
        manifest = build_dataset(ctx.data_dir, ctx.data_spec, sorted(passes), workers=ctx.workers,
                                 progress=ctx.progress, variant="cuda_ad_rgb" if ctx.device == "cuda" else None)
    except BaseException as err:  # the record says so, never "running" forever; rendered frames are kept
        runs.fail(run, f"{type(err).__name__}: {err}")
        raise
    timing_cols = [c for c in manifest.columns if c.startswith("time_s.")]
    complete = int(manifest["resumed"].sum())
    runs.complete(run, {"frames": int(len(manifest)), "resumed_frames": complete,
                        "render_time_s": float(manifest[timing_cols].fillna(0).to_numpy().sum()),
                        "nonfinite_repaired": int(manifest.get("nonfinite_repaired", 0).sum())})
    log.info("data: %d frames rendered, %d were already complete (%.1f min)", len(manifest) - complete, complete,
             run.record["wall_time_s"] / 60)
    return data_fingerprint(ctx)


def _manifest_or_rebuilt(ctx: Context) -> dict | None:
    """The rendered dataset's manifest; a damaged one is rebuilt from the frame records beside it, without
    rendering. None when there is none (or a frame lacks its record): rendering makes it."""
    path = ctx.data_dir / "manifest.json"
    manifest = runs.read_json_or_none(path)  # damaged: the log names it
    if manifest is None and path.exists():
        manifest = rebuild_manifest(ctx.data_dir, ctx.data_spec)
        if manifest is not None:
            log.info("data: rebuilt %s from its %d frame records (nothing rendered)", path, len(manifest["frames"]))
    return manifest


def _listed(problems: list, shown: int = 3) -> str:
    """'path: problem; ...' for (path, problem) pairs, the first `shown` of them."""
    text = "; ".join(f"{path}: {why}" for path, why in problems[:shown])
    return text + (f"; and {len(problems) - shown} more" if len(problems) > shown else "")


def evaluation_data(ctx: Context) -> Context:
    """The context evaluations read their frames from: `eval.data_dir` when set (another dataset, e.g.
    your own renders, used as it is), else `data_dir`. Trainings always read `data_dir`, so evaluating
    recorded models on other data retrains nothing."""
    other = ctx.eval.data_dir
    return dataclasses.replace(ctx, data_dir=Path(other), render_data=False) if other else ctx


def dataset(ctx: Context, split: str, task: Task, training: bool, seed: int = 0):
    data_fingerprint(ctx)  # a clear error when the directory is not a dataset
    buffers = task.buffers(with_mid=training)
    if not training:
        return SequenceDataset(ctx.data_dir, split, buffers)
    recipe = ctx.train
    manifest = load_manifest(ctx.data_dir)
    frames = (manifest.get("spec") or {}).get("seq_len")
    if frames is not None and recipe.seq_len > frames:
        raise UserError(f"train.seq_len={recipe.seq_len} but the dataset's sequences have {frames} frames")
    check_training_frames(ctx, split, manifest)
    return SequenceDataset(ctx.data_dir, split, buffers, seq_len=recipe.seq_len, crop=recipe.crop,
                           augment=True, seed=seed, max_sequences=recipe.train_sequences,
                           permute_colours=recipe.colour_permute)


def check_training_frames(ctx: Context, split: str = "train", manifest: dict | None = None) -> None:
    """Training crops are drawn inside each frame's `lr_size`, optional for evaluation (whole frames):
    a frame without it is named before a training run is recorded."""
    manifest = manifest or load_manifest(ctx.data_dir)
    unsized = [f"{r['sequence']}/{r['frame']}" for r in manifest["frames"] if r["split"] == split and "lr_size" not in r]
    if unsized:
        raise UserError(f"{ctx.data_dir}/manifest.json: training crops need each {split!r} frame's \"lr_size\" "
                        f"([width, height] of its LR frame); missing on {len(unsized)} frames ({', '.join(unsized[:3])}"
                        f"{', ...' if len(unsized) > 3 else ''})")


def validation(ctx: Context, task: Task, sequences: int):
    """The learning curve's scorer: `validate(model) -> {relMSE, PSNR, SSIM}` on whole frames of
    `sequences` validation sequences spread over the split (None when there are none to score)."""
    if sequences <= 0:
        return None
    split = ctx.eval.split
    try:
        full = dataset(ctx, split, task, training=False)
    except ValueError:  # no such split in this dataset: no curve, the final table still scores it
        log.warning("no %r split for the learning curve; training without one", split)
        return None
    chosen = sorted({round(i * (len(full) - 1) / max(1, sequences - 1)) for i in range(min(sequences, len(full)))})
    subset = torch.utils.data.Subset(full, chosen)
    hdr = ctx.train.hdr

    def validate(model) -> dict:
        _, metrics = evaluate(model, subset, task, hdr=hdr, device=ctx.device)
        return {k: metrics[k] for k in ("relMSE", "PSNR", "SSIM")}
    return validate


# ---------------------------------------------------------------- perceptual features

def perceptual_features(ctx: Context):
    """(features module or None, identity dict saying which weights and layer are used)."""
    from bench.nn.vgg import load_vgg16_features, random_vgg16_features
    layer = ctx.vgg.layer
    path = ctx.vgg.weights or (str(TORCH_HUB_VGG16) if TORCH_HUB_VGG16.exists() else None)
    if path:
        if not Path(path).exists():
            raise UserError(f"VGG16 weights file {path} (vgg.weights / SRD_VGG16_WEIGHTS) does not exist")
        return (load_vgg16_features(path, layer).to(ctx.device),
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


# ---------------------------------------------------------------- train + evaluate

def _train_identity(ctx: Context, cfg: dict, task: Task, seed: int, vgg_id: dict | None,
                    stage: str | None = None) -> dict:
    identity = {"model": cfg, "task": task.name, "train": ctx.train.identity(),
                "data": data_fingerprint(ctx, "train"), "seed": seed, "vgg": vgg_id}
    if stage is not None:
        identity["stage"] = stage
    return identity


def recorded_training(ctx: Context, cfg: dict, task: Task, seed: int) -> runs.Run | None:
    """The complete training run of (cfg, task, seed) in this context, or None; never trains."""
    try:
        vgg_id = _loss_features(ctx)[1]
    except UserError:  # no VGG weights: nothing can have been trained with them here either
        return None
    return runs.lookup(ctx.runs_dir, "train", _train_identity(ctx, cfg, task, seed, vgg_id, None), ctx.runs_archive)


def trained_model(ctx: Context, cfg: dict, task: Task, seed: int, label: str = "", load: bool = True,
                  stage: str | None = None, divergence_ends: bool = False):
    """The model of `cfg` trained on `task`, from the run store when recorded. Returns (model, run or None).

    With load=False a recorded run's weights are not read (the caller may not need them; see
    `evaluated`) and the model returned is None: call again with load=True when needed. A recorded run
    restored from the archive without its weights (runs.ARCHIVED_FILE_MAX_BYTES) is trained again then,
    into the store only: the archive keeps the record its evaluations scored.
    With `stage` ("sr" or "dn") only that stage of an SRDNet (built at the SRD scale, 2) is trained on
    `task`, through SRDStage. With `divergence_ends` (a learning-rate range test) a diverging training is
    recorded complete with the step it diverged at, instead of failing."""
    model = _initial_model(cfg, task, seed, stage)
    if not is_learned(model):
        return model, None
    features, vgg_id = _loss_features(ctx)
    identity = _train_identity(ctx, cfg, task, seed, vgg_id, stage)
    if not ctx.render_data:  # your own data: a frame the trainer cannot crop is named before a run is recorded
        check_training_frames(ctx)
    code = code_of(cfg, *TRAINING_CODE)
    run = runs.begin(ctx.runs_dir, "train", identity, seed=seed, device=ctx.device, label=label,
                     force=ctx.force, code=code, reuse_stale=ctx.reuse_stale, archive=ctx.runs_archive,
                     needs=(CHECKPOINT,) if load else ())
    # a run trained again for the weights its archive left out: the archive keeps the run it scored
    weights_only = None if ctx.force else archived_without_weights(ctx, run, code)
    if run.reused:
        log.info("train %s: reusing run %s", label or cfg["_target_"], run.hash)
        if not weights_only:
            archive_training(ctx, run)
        return (load_weights(model, run.dir, ctx.device) if load else None), run
    recipe = ctx.train
    _drop_damaged_checkpoint(run.dir / CHECKPOINT)
    if distributed.rank_and_size()[1] > 1:  # the other torchrun ranks (serve_trainings) join this training
        distributed.share((ctx, cfg, task.name, seed, stage, str(run.dir)))
    try:
        summary = train(model, dataset(ctx, "train", task, training=True, seed=seed), task, run.dir, recipe,
                        features=features, seed=seed, device=ctx.device, progress=ctx.progress,
                        validate=validation(ctx, task, recipe.val_sequences) if stage is None else None,
                        distributed_ranks=True)
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


def _drop_damaged_checkpoint(path: Path) -> None:
    """A checkpoint that does not read (cut short, overwritten) is no checkpoint: removed, so the
    training starts over instead of failing to resume (the log names it, `runs.read_or_none`)."""
    if path.exists() and runs.read_or_none(path) is None:
        path.unlink()


def archived_without_weights(ctx: Context, run: runs.Run, code: dict) -> dict | None:
    """The record `ctx.runs_archive` holds of this training, complete, of this code and without its
    weights (over the archive's file limit), else None."""
    archived = ctx.runs_archive / "train" / run.hash if ctx.runs_archive is not None else None
    if archived is None or (archived / CHECKPOINT).exists():
        return None
    record = runs.read_record(archived / runs.RECORD) or {}
    return record if record.get("status") == "complete" and not runs.code_changes(record, code) else None


def _final_val_psnr(record: dict) -> str:
    psnr = record.get("metrics", {}).get("val", {}).get("PSNR")
    return f"{psnr:.3f} dB" if psnr is not None else "not recorded"


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


def cascade_model(ctx: Context, cfg: dict, seed: int, label: str = ""):
    """A Cascade (paper Table 3): each SRDNet stage trained alone on its own task, assembled into one
    net. Returns (net, list of the stages' training runs)."""
    net, stage_runs = cascade_net(cfg), []
    for stage, task_name in CASCADE_STAGES[cfg.get("stage_order", "sr_dn")]:
        stage_model, run = trained_model(ctx, cfg, get_task(task_name), seed, f"{label} [{stage} stage]",
                                         stage=stage)
        load_stage(net, stage, stage_model.state_dict())
        stage_runs.append(run)
    return net, stage_runs


def evaluated(ctx: Context, cfg: dict, task: Task, seed: int, split: str, label: str = "",
              cascade: bool = False) -> runs.Run:
    """Evaluation run of a row (training it first if needed)."""
    if cascade:
        model, stage_runs = cascade_model(ctx, cfg, seed, label)
        train_run, trained = None, "+".join(r.hash for r in stage_runs)
    else:
        model, train_run = trained_model(ctx, cfg, task, seed, label, load=False)
        trained = train_run.hash if train_run else {"model": cfg, "task": task.name}
    hdr = ctx.train.hdr
    frames = evaluation_data(ctx)
    identity = {"trained": trained, "split": split, "data": data_fingerprint(frames, split), "hdr": hdr}
    if ctx.eval.save_exr:
        identity["frames"] = True  # output frames are an artifact of their own run
    fast_path, tile = ctx.eval.fast_path, ctx.eval.tile
    if fast_path == AUTO:
        fast_path = measured_fast_path(ctx, cfg, task, split, label)
    if fast_path != REFERENCE or tile:  # only a non-default way of running changes the identity
        identity.update(path=fast_path, tile=tile)  # ("path": the identity key from before the rename)
    # a learned row's numbers also depend on the trainer: retraining it makes its evaluation stale too
    code = code_of(cfg, *EVALUATION_CODE, *(TRAINING_CODE if train_run is not None or cascade else ()))
    run = runs.begin(ctx.runs_dir, "eval", identity, seed=seed, device=ctx.device, label=label,
                     force=ctx.force, code=code, reuse_stale=ctx.reuse_stale, archive=ctx.runs_archive)
    missing = [m for m in SCORES if f"{m} se" not in run.metrics] if run.reused else []
    if missing:  # recorded before the evaluator scored these: evaluating again is cheap, training is not
        log.info("eval %s: re-evaluating run %s, recorded without %s", label, run.hash, ", ".join(missing))
        run = runs.begin(ctx.runs_dir, "eval", identity, seed=seed, device=ctx.device, label=label,
                         force=True, code=code)
    if run.reused:
        log.info("eval %s: reusing run %s", label, run.hash)
        return archive_evaluation(ctx, run)
    if model is None:  # a recorded training whose weights trained_model did not read (or that lacks them)
        model, train_run = trained_model(ctx, cfg, task, seed, label)
    try:
        _, metrics = evaluate(model, dataset(frames, split, task, training=False), task, hdr=hdr,
                              device=ctx.device, out_dir=run.dir, save_exr=ctx.eval.save_exr,
                              write_exr=write_exr, path=fast_path, tile=tile)
    except BaseException as err:  # the record says so, never "running" forever
        runs.fail(run, f"{type(err).__name__}: {err}")
        raise
    metrics["params"] = count_params(model)
    metrics["train_run"] = trained if isinstance(trained, str) else None
    metrics["vgg"] = (train_run.record["identity"].get("vgg") if train_run else None)
    metrics["render"] = render_digest(frames, split)
    return archive_evaluation(ctx, runs.complete(run, metrics))


def archive_training(ctx: Context, run: runs.Run) -> runs.Run:
    """Keep a finished training in `ctx.runs_archive`: its record, curves and the weights evaluation
    loads (EMA, else raw), without the optimizer state a finished run never resumes from, nor the
    per-step curve, which curve.csv holds (a third of the file at 1000 steps)."""
    def slim_checkpoint(directory: Path) -> None:
        if not (run.dir / CHECKPOINT).exists():  # a range test that diverged before its first checkpoint
            return
        state = torch.load(run.dir / CHECKPOINT, map_location="cpu", weights_only=False)
        weights = {"ema": state["ema"], "model": None} if state.get("ema") else {"model": state["model"], "ema": None}
        kept = {key: state.get(key) for key in ("step", "val_curve", "elapsed_s")}
        torch.save({**weights, **kept}, directory / CHECKPOINT)  # what load_weights and adopt read

    if ctx.runs_archive is not None:
        runs.archive(run, ctx.runs_archive, ("curve.csv", "val_curve.csv"), write=slim_checkpoint)
    return run


def archive_evaluation(ctx: Context, run: runs.Run) -> runs.Run:
    """Keep a finished evaluation in `ctx.runs_archive`: its record and per-frame scores (claims pair
    them), not its output frames (`eval.save_exr`), which stay in the run store."""
    if ctx.runs_archive is not None and not run.record["identity"].get("frames"):
        runs.archive(run, ctx.runs_archive, ("per_image.csv",))
    return run


def recorded_minutes(eval_hashes, runs_dir: str | Path, archives=()) -> dict[str, float | None]:
    """Recorded wall minutes of each distinct run behind these evaluations, keyed "eval/<hash>" and
    "train/<hash>": the evaluations and the trainings they scored (each stage of a Cascade). A run
    neither the store nor the archives hold maps to None; a missing evaluation hides its trainings."""
    minutes = {}
    for h in eval_hashes:
        record = runs.find_record("eval", h, runs_dir, archives)[1]
        if record is None:
            minutes[f"eval/{h}"] = None
            continue
        minutes[f"eval/{h}"] = (record.get("wall_time_s") or 0.0) / 60
        for t in filter(None, (record.get("metrics", {}).get("train_run") or "").split("+")):
            seconds = runs.recorded_wall_s("train", t, runs_dir, archives)
            minutes[f"train/{t}"] = None if seconds is None else seconds / 60
    return minutes


def measured_fast_path(ctx: Context, cfg: dict, task: Task, split: str, label: str) -> str:
    """eval.fast_path=auto: the fastest correct path for this model on this machine (bench.measure),
    timed on an untrained copy (speed does not depend on the weights) and one sequence of the split,
    cached in <runs_dir>/fast_paths.json. The evaluation's identity records the path chosen."""
    item = dataset(evaluation_data(ctx), split, task, training=False)[0]
    model = build_model(cfg, task.scale).to(ctx.device).eval()
    x, g = item[task.x][None].to(ctx.device), item[task.g][None].to(ctx.device)
    chosen, times = choose_fast_path(model, x, g, ctx.device, ctx.runs_dir / "fast_paths.json",
                                     {"model": cfg, "task": task.name})
    if times:
        log.info("eval %s: fast_path=auto chose %s (%s)", label, chosen,
                 ", ".join(f"{k} {v:.0f} ms" if isinstance(v, float) else f"{k} {v}" for k, v in times.items()))
    return chosen


def last_fifth_gain(curve_csv: Path, metric: str = "PSNR") -> float | None:
    """How much the validation `metric` rose over the last fifth of a training (the final point minus
    the point at 80% of the steps, from val_curve.csv): near 0, the curve has flattened; None without
    a curve."""
    curve = runs.read_or_none(curve_csv)  # None: missing or damaged (the log names it)
    if curve is None or len(curve) < 2 or not {"step", metric} <= set(curve):
        return None
    last = curve.iloc[-1]
    before = curve[curve["step"] <= 0.8 * last["step"]].iloc[-1]
    return float(last[metric] - before[metric])


def row(ctx: Context, label: str, model: str, overrides: dict | None = None, task: str = "srd",
        split: str | None = None, train: dict | None = None, cascade: bool = False) -> dict:
    """One table row: metrics averaged over `ctx.seeds` (with std when there are several).
    `train` overrides the training recipe for this row; `cascade` trains the stages separately."""
    t = get_task(task)
    cfg = model_config(ctx, model, overrides)
    ctx = with_training(ctx, train, model)
    split = split or ctx.eval.split
    results = [evaluated(ctx, cfg, t, seed, split, label, cascade) for seed in ctx.seeds]
    out = {"method": label, "task": task}
    for metric in (*SCORES, "time_ms"):
        values = np.array([r.metrics[metric] for r in results], dtype=float)
        out[metric] = float(values.mean())
        if len(values) > 1:
            out[f"{metric} std"] = float(values.std(ddof=1))
    for metric in SCORES:  # uncertainty over the split's sequences (a seed average for several seeds)
        out[f"{metric} se"] = float(np.mean([r.metrics[f"{metric} se"] for r in results]))
    out["params"] = results[0].metrics.get("params", 0)
    # what this row cost to compute, whenever it was computed (a reused run keeps its recorded time)
    out["train (min)"] = float(np.mean([runs.wall_time_s(ctx.runs_dir, "train", r.metrics.get("train_run"))
                                        for r in results])) / 60
    out["eval (min)"] = float(np.mean([r.record.get("wall_time_s") or 0.0 for r in results])) / 60
    gains = [last_fifth_gain(ctx.runs_dir / "train" / h / "val_curve.csv") for r in results
             for h in (r.metrics.get("train_run") or "").split("+") if h]
    gains = [g for g in gains if g is not None]
    out["last fifth (dB)"] = float(np.mean(gains)) if gains else None
    vgg = results[0].metrics.get("vgg")
    out["vgg"] = f"VGG16 {vgg['layer']} from {vgg['weights']}" if vgg else None
    out["renders"] = [r.metrics.get("render") for r in results]  # None: recorded before digests
    out["runs"] = " ".join(r.hash for r in results)
    out["train runs"] = " ".join(t for r in results if r.metrics.get("train_run")
                                 for t in r.metrics["train_run"].split("+"))
    out["reused"] = all(r.reused for r in results)
    return out
