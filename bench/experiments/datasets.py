"""The data a table reads: its fingerprint (what is on disk, hashed into training and evaluation
identities), rendering what a table needs and is missing (a recorded `data` run), checking your own
frames, and opening a split as a `SequenceDataset`.
"""
from __future__ import annotations

import contextlib
import dataclasses
import functools
import gzip
import json
import logging
import os
from pathlib import Path

from bench import runs
from bench.atomic import write_atomic
from bench.datagen import (MAX_NONFINITE, build_dataset, damaged_frames, frame_paths, load_manifest, manifest_problems,
                           planned_settings, rebuild_manifest)
from bench.dataset import SequenceDataset
from bench.device_frames import training_frames
from bench.errors import UserError
from bench.experiments.context import Context
from bench.tasks import Task

log = logging.getLogger("bench")
RENDERING = "rendering what is missing"  # in the log line of every render (scripts read it)


def _canonical(value) -> str:
    return json.dumps(value, sort_keys=True, default=str)


def _only_split(spec: dict, split: str) -> dict:
    """The spec with only `split`'s part: what decides that split's frames (its plan, its data
    fingerprint), whatever the other splits are."""
    if not isinstance(spec.get("splits"), dict):
        return spec
    return {**spec, "splits": {split: spec["splits"].get(split)}}


def _same_split_part(spec: dict, other: dict, split: str) -> bool:
    """Whether two data specs render `split`'s frames alike (their parts for it are the same)."""
    return _canonical(_only_split(spec, split)) == _canonical(_only_split(other, split))


def _identity_hash(spec: dict | None, frames: list, split: str | None, files: str | None = None) -> str:
    """The data fingerprint of a spec and its frames' (split, sequence, frame, settings hash): with
    `split`, only that split's part of the spec counts."""
    spec = spec or {}  # your own renders may have none
    identity = {"spec": spec if split is None else _only_split(spec, split), "frames": sorted(frames)}
    if files is not None:
        identity["files"] = files
    return runs.config_hash(identity)


@functools.lru_cache(maxsize=32)
def _fingerprint(manifest_path: str, mtime_ns: int, split: str | None, files: str | None = None) -> str:
    manifest = load_manifest(Path(manifest_path).parent)
    frames = [(f["split"], f["sequence"], f["frame"], f.get("settings_hash")) for f in manifest["frames"]
              if split is None or f["split"] == split]
    if not frames and split is not None:
        splits = sorted({f["split"] for f in manifest["frames"]})
        raise _no_split(f"{Path(manifest_path).parent}: no frames in split {split!r}", splits)
    return _identity_hash(manifest.get("spec"), frames, split, files)


def _no_split(what: str, splits: list[str]) -> UserError:
    example = ([s for s in splits if s != "train"] or ["NAME"])[0]
    return UserError(f"{what} (it has {splits}); tables score the split eval.split (e.g. eval.split={example}), "
                     "trainings read 'train'")


@functools.lru_cache(maxsize=8)
def _planned_fingerprint(spec_json: str, split: str) -> str:
    spec = json.loads(spec_json)
    if not (spec.get("splits") or {}).get(split):
        raise _no_split(f"data: the data spec {spec.get('name', '')!r} has no {split!r} split",
                        sorted(spec.get("splits") or {}))
    frames = [(split, job["sequence"], frame, digest) for job, digest in planned_settings(_only_split(spec, split))
              for frame in range(int(spec["seq_len"]))]
    return _identity_hash(spec, frames, split)


def split_fingerprint(ctx: Context, split: str) -> str:
    """The data fingerprint of `split` as run identities hold it (a training's of "train", an
    evaluation's of the split it scores). Rendered data's is planned from the data spec, without reading
    or rendering anything: its spec and settings determine the manifest datagen writes, so it equals the
    rendered manifest's (tests/test_eval_data.py), and a recorded run is found before its data exists (a
    table whose runs are all recorded renders nothing). Your own data (render_data=false) is read from
    its files."""
    if ctx.render_data:
        return _planned_fingerprint(_canonical(ctx.data_spec), split)
    return data_fingerprint(ctx, split)


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
    one machine (a frame rendered again on the CPU matches its file bit for bit; on a GPU, cuda_ad_rgb's
    layers differ by up to 6.2e-6 relative from one render to the next, docs/presets.md). Across hosts Mitsuba's LLVM
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
    return records_digest([rec for rec in load_manifest(ctx.data_dir)["frames"] if rec["split"] == split])


def records_digest(frames: list[dict]) -> str | None:
    """`render_digest` of these frame records (a manifest's or the archive's: both keep the stamps)."""
    crcs = []
    for rec in frames:
        files = rec.get("files") or {}
        if not (files.get("lr") and files.get("hr")):
            return None
        crcs.append((rec["sequence"], rec["frame"], files["lr"]["crc32"], files["hr"]["crc32"]))
    return runs.config_hash({"render": sorted(crcs)})[:8]


def ensure_data(ctx: Context, passes: set[str], splits: set[str] | None = None, scoring: bool = False) -> str:
    """Make sure `data_dir` holds the preset's dataset (its `splits`; None: all) with at least `passes`,
    rendering only what is missing; returns the data fingerprint. With render_data=false the directory is
    used as it is. `scoring`: `ctx` is `evaluation_data`'s (eval.data_dir, frames scored as they are):
    every frame is decoded first, so one that does not decode or is mostly NaN/Inf stops the command
    before anything runs or is recorded."""
    if not ctx.render_data:
        problems = manifest_problems(ctx.data_dir)
        if problems:  # one problem (a damaged manifest) on one line
            listed = problems[0] if len(problems) == 1 else "\n  " + "\n  ".join(problems)
            raise UserError(f"data: {ctx.data_dir} is not a dataset in the documented layout (docs/data.md): "
                            f"{listed}")
        fingerprint = data_fingerprint(ctx)
        manifest = load_manifest(ctx.data_dir)
        damaged = damaged_frames(ctx.data_dir, manifest["frames"], manifest.get("passes", []), stamps=False,
                                 decode=scoring, max_nonfinite=MAX_NONFINITE)
        if damaged:
            setting = "eval.data_dir" if scoring else "data_dir"
            raise UserError(f"data: {len(damaged)} damaged frame files in {setting}={ctx.data_dir} ({_listed(damaged)}); "
                            f"they are yours to replace (or drop their records from {ctx.data_dir / 'manifest.json'}); "
                            f"`python -m bench +experiment=data render_data=false data_dir={ctx.data_dir} "
                            "experiment.verify=true` lists every damaged one")
        return fingerprint
    ctx.data_dir.mkdir(parents=True, exist_ok=True)
    # one process checks and renders a dataset at a time: two tables needing other buffers would
    # otherwise render the same frames at once, and each take the other's files for damaged ones
    with contextlib.closing(runs.acquire(ctx.data_dir / ".render.lock", f"rendering {ctx.data_dir}")):
        return _render_missing(ctx, passes, sorted(splits or ctx.data_spec["splits"]))


def _render_missing(ctx: Context, passes: set[str], splits: list[str]) -> str:
    unknown = sorted(set(splits) - set(ctx.data_spec["splits"]))
    if unknown:
        raise UserError(f"data: the data spec {ctx.data_spec.get('name', '')!r} has no split {unknown[0]!r} "
                        f"(it has {sorted(ctx.data_spec['splits'])})")
    manifest = _manifest_or_rebuilt(ctx)
    if manifest is not None:
        if _canonical(manifest.get("spec")) == _canonical(ctx.data_spec):
            frames = [f for f in manifest["frames"] if f["split"] in splits]
            # per frame: a split re-rendered for another table (new settings) may hold fewer buffers
            lacking = [f for f in frames if not passes <= set(f.get("buffers", []))]
            absent = {s for s in splits if not any(f["split"] == s for f in frames)}  # a manifest holds whole splits
            damaged = damaged_frames(ctx.data_dir, frames, manifest["passes"])
            if not damaged and not lacking and not absent:
                log.info("data: %s already holds %s of %s", ctx.data_dir, ", ".join(sorted(passes)), ", ".join(splits))
                archive_frame_records(ctx, manifest)
                return data_fingerprint(ctx)
            if damaged:
                log.warning("data: %d damaged frame files (%s); rendering them again", len(damaged), _listed(damaged))
    identity = {"spec": ctx.data_spec, "passes": sorted(passes), "splits": splits}
    run = runs.begin(ctx.runs_dir, "data", identity, seed=ctx.data_spec.get("seed"), device=ctx.device,
                     label=f"data {ctx.preset}", force=True, every_call=True)  # a data run records one render job
    try:
        log.info("data: making sure %s holds %s (%s)", ctx.data_dir, ", ".join(sorted(passes)), RENDERING)
        manifest = build_dataset(ctx.data_dir, ctx.data_spec, sorted(passes), workers=ctx.workers,
                                 progress=ctx.progress, variant="cuda_ad_rgb" if ctx.device == "cuda" else None,
                                 splits=splits)
    except BaseException as err:  # the record says so, never "running" forever; rendered frames are kept
        runs.fail(run, f"{type(err).__name__}: {err}")
        raise
    job = manifest[manifest["split"].isin(splits)]  # the manifest also lists the other splits already there
    timing_cols = [c for c in job.columns if c.startswith("time_s.")]
    complete = int(job["resumed"].sum())
    repaired = int(job["nonfinite_repaired"].sum()) if "nonfinite_repaired" in job else 0
    runs.complete(run, {"frames": int(len(job)), "resumed_frames": complete, "nonfinite_repaired": repaired,
                        "render_time_s": float(job[timing_cols].fillna(0).to_numpy().sum())})
    log.info("data: %d frames of %s rendered, %d were already complete (%.1f min)", len(job) - complete,
             ", ".join(splits), complete, run.record["wall_time_s"] / 60)
    archive_frame_records(ctx, load_manifest(ctx.data_dir))
    return data_fingerprint(ctx)


FRAME_RECORD_KEYS = ("split", "sequence", "frame", "ref_spp", "ref_error", "time_s")  # what tables read of a frame


def _frame_records_path(ctx: Context) -> Path:
    """Where the archive keeps the frame records of `ctx.data_spec`'s renders."""
    name = f"{ctx.data_spec.get('name', 'data')}-{runs.config_hash({'spec': ctx.data_spec})[:12]}.json.gz"
    return Path(ctx.runs_archive) / "frames" / name


def _read_gzipped_json(path: Path) -> dict:
    return json.loads(gzip.decompress(Path(path).read_bytes()))


def _records_of_unchanged_splits(ctx: Context, path: Path) -> list[dict]:
    """Frame records that the archive keeps under earlier specs, of the splits whose part of the spec is
    still `ctx.data_spec`'s (e.g. val's and train's when only test's references got more samples): the
    same frames, so a data_dir holding only the changed split does not lose the others' records."""
    found = {}
    for other in sorted(path.parent.glob("*.json.gz")):
        card = runs.read_or_none(other, read=_read_gzipped_json) if other != path else None
        for split in {f["split"] for f in (card or {}).get("frames", [])} - set(found):
            if _same_split_part(card.get("spec") or {}, ctx.data_spec, split):
                found[split] = [f for f in card["frames"] if f["split"] == split]
    return [f for frames in found.values() for f in frames]


def archive_frame_records(ctx: Context, manifest: dict) -> None:
    """Keep in the archive, beside the runs, what tables read of the rendered frames (each frame's
    reference spp, estimated reference error and render seconds), with its files' CRC-32 stamps (which render they
    describe): a table whose evaluations are all recorded is then written on a machine that has not
    rendered its split. Merged per split: a data_dir holding some splits replaces only theirs. The last
    host to find the data writes it: another host's render of the same settings differs in its noise."""
    if ctx.runs_archive is None or not ctx.render_data or _canonical(manifest.get("spec")) != _canonical(ctx.data_spec):
        return
    path = _frame_records_path(ctx)
    ours = {f["split"] for f in manifest["frames"]}
    frames = [{**{k: f[k] for k in FRAME_RECORD_KEYS if k in f},
               "files": {res: {"crc32": v["crc32"]} for res, v in (f.get("files") or {}).items()}}
              for f in manifest["frames"]]

    def merged(kept: dict | None) -> dict:
        others = list((kept or {}).get("frames", []))
        held = ours | {f["split"] for f in others}
        others += [f for f in _records_of_unchanged_splits(ctx, path) if f["split"] not in held]
        every = frames + [f for f in others if f["split"] not in ours]
        return {"spec": ctx.data_spec,
                "frames": sorted(every, key=lambda f: (f["split"], str(f["sequence"]), f["frame"]))}
    kept = runs.read_or_none(path, read=_read_gzipped_json)
    if merged(kept) == kept:
        return  # as recorded: nothing to write (an archive you may only read stays as it is)
    # read again, merge and write under the archive's lock: two commands merging other splits keep both
    lock = Path(ctx.runs_archive) / runs.PARTIAL / f"frames.{path.name}.lock"
    with contextlib.closing(runs.acquire(lock, f"writing the frame records {path.name}")):
        card = merged(runs.read_or_none(path, read=_read_gzipped_json))
        path.parent.mkdir(parents=True, exist_ok=True)
        data = gzip.compress(json.dumps(card, sort_keys=True).encode(), mtime=0)
        write_atomic(path, lambda tmp: tmp.write_bytes(data))


def frame_records(ctx: Context, split: str) -> list[dict]:
    """The records of `split`'s frames (`load_manifest`'s, or the `FRAME_RECORD_KEYS` of them): from
    data_dir's manifest when it holds the split as `ctx` specifies it (the split's part of the spec: a
    change to another split's does not touch its frames), else from the archive's copy
    (`archive_frame_records`, or an earlier spec's whose part for the split is the same); [] when
    neither has them."""
    manifest = _manifest_here(ctx, as_specified=False)
    if manifest is not None and (not ctx.render_data or _same_split_part(manifest.get("spec") or {}, ctx.data_spec, split)):
        frames = [f for f in manifest["frames"] if f["split"] == split]
        if frames or not ctx.render_data:
            return frames
    if ctx.runs_archive is None or not ctx.render_data:
        return []
    path = _frame_records_path(ctx)
    kept = runs.read_or_none(path, read=_read_gzipped_json)
    return [f for f in (kept or {}).get("frames", []) if f["split"] == split] \
        or [f for f in _records_of_unchanged_splits(ctx, path) if f["split"] == split]


def splits_on_disk(ctx: Context, as_specified: bool = False) -> set[str]:
    """The splits data_dir's manifest holds (none without one that reads); `as_specified`: only if it
    was rendered from `ctx`'s data spec (a table would render the others again)."""
    manifest = _manifest_here(ctx, as_specified)
    return {f["split"] for f in manifest["frames"]} if manifest else set()


def _manifest_here(ctx: Context, as_specified: bool) -> dict | None:
    """data_dir's manifest, read only (None when there is none or it does not read); `as_specified`:
    only if it was rendered from `ctx`'s data spec (your own frames, render_data=false, always are)."""
    path = ctx.data_dir / "manifest.json"
    manifest = runs.read_json_or_none(path) if path.exists() else None
    if manifest is None or (as_specified and ctx.render_data
                            and _canonical(manifest.get("spec")) != _canonical(ctx.data_spec)):
        return None
    return manifest


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
    your own renders, used as it is), else `data_dir`. With `eval.data_dir` the recorded trainings of
    `data_dir` are scored and none is trained (`training.trained_model`); rendered training data is
    then neither rendered nor read (`split_fingerprint`)."""
    other = ctx.eval.data_dir
    return dataclasses.replace(ctx, data_dir=Path(other), render_data=False) if other else ctx


def dataset(ctx: Context, split: str, task: Task, training: bool, seed: int = 0):
    data_fingerprint(ctx)  # a clear error when the directory is not a dataset
    buffers = task.buffers(with_mid=training)
    if not training:
        return SequenceDataset(ctx.data_dir, split, buffers)
    recipe = ctx.train
    manifest = load_manifest(ctx.data_dir)
    seq_len = (manifest.get("spec") or {}).get("seq_len")
    if seq_len is not None and recipe.seq_len > seq_len:
        raise UserError(f"train.seq_len={recipe.seq_len} but the dataset's sequences have {seq_len} frames")
    check_training_frames(ctx, split, manifest)
    # an option added later is passed only when set: adopt's replay runs dataset code that predates it
    later = {"permute_colours": True} if recipe.colour_permute else {}
    # on a GPU the split is held in its memory where it fits (the same items, bit for bit)
    return training_frames(ctx.data_dir, split, buffers, device=ctx.device, seq_len=recipe.seq_len, crop=recipe.crop,
                           augment=True, seed=seed, **later)


def check_training_frames(ctx: Context, split: str = "train", manifest: dict | None = None) -> None:
    """Training crops are drawn inside each frame's `lr_size`, optional for evaluation (whole frames):
    a frame without it is named before a training run is recorded."""
    manifest = manifest or load_manifest(ctx.data_dir)
    unsized = [f"{r['sequence']}/{r['frame']}" for r in manifest["frames"] if r["split"] == split and "lr_size" not in r]
    if unsized:
        raise UserError(f"{ctx.data_dir}/manifest.json: training crops need each {split!r} frame's \"lr_size\" "
                        f"([width, height] of its LR frame); missing on {len(unsized)} frames ({', '.join(unsized[:3])}"
                        f"{', ...' if len(unsized) > 3 else ''})")
