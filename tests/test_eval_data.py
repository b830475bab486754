"""eval.data_dir: recorded (archived) models scored on frames you bring, by the command line and real files.
Nothing is rendered, nothing is trained and the training data is not read: a training's identity takes
its data fingerprint from the data spec then, planned without rendering, and that must equal the rendered
manifest's (here at the smoke preset, and the cpu preset's committed trainings)."""
import json
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import yaml
from hydra import compose, initialize_config_dir

from bench import archived
from bench.cli import CONF_DIR, make_context
from bench.datagen import frame_paths, load_manifest
from bench.experiments.datasets import data_fingerprint, frame_records, split_fingerprint
from bench.train import CHECKPOINT
from conftest import bench_here

REPO = Path(__file__).resolve().parent.parent
# The smoke table (input bilinear, Ours) at the smoke preset, on frames small enough for seconds.
SMOKE = ["+experiment=smoke", "preset=smoke", "data.lr_width=8", "data.lr_height=6", "data.spp=1", "data.ref_spp=4",
         "data.seq_len=2", "data.max_depth=4", "data.splits.train.sequences=1", "data.splits.val.sequences=1",
         "~data.splits.generalization", "train.steps=2", "train.checkpoint_every=2", "train.crop=4",
         "train.seq_len=2", "train.batch_size=1", "train.val_sequences=1", "workers=1", "progress=false"]
SCORES = ["method", "relMSE", "PSNR", "SSIM"]


def smoke_table(*args):
    """`python -m bench` with SMOKE and `args`, in this process (conftest.bench_here)."""
    return bench_here(*SMOKE, *args)


def store(root, archive, data_dir, *more):
    return [f"runs_dir={root / 'runs'}", f"runs_archive={archive}", f"results_dir={root / 'results'}",
            f"data_dir={data_dir}", *more]


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    """The smoke table computed once, its runs archived (runs_archive, as the cpu preset keeps them)."""
    root = tmp_path_factory.mktemp("trained")
    out = smoke_table(*store(root, root / "archive", root / "data"))
    assert out.returncode == 0, out.stderr[-3000:]
    return root


def copy_of_split(data_dir: Path, split: str, dest: Path) -> Path:
    """A dataset of your own: one split's frames with only the documented files (each frame's _lr.exr,
    _hr.exr and record, and a manifest of those frames), copied without their mtimes."""
    manifest = load_manifest(data_dir)
    manifest["frames"] = [f for f in manifest["frames"] if f["split"] == split]
    for frame in manifest["frames"]:
        for source in frame_paths(data_dir, split, frame["sequence"], frame["frame"]):
            target = dest / Path(source).relative_to(data_dir)
            target.parent.mkdir(parents=True, exist_ok=True)
            shutil.copy(source, target)
    (dest / "manifest.json").write_text(json.dumps(manifest))
    return dest


def context(*overrides):
    with initialize_config_dir(config_dir=CONF_DIR, version_base=None):
        return make_context(compose("config", overrides=list(overrides)))


def test_the_split_fingerprint_planned_from_the_spec_is_the_rendered_manifests(trained, tmp_path):
    ctx = context(*SMOKE, f"data_dir={trained / 'data'}", f"eval.data_dir={tmp_path}")  # planned: nothing read
    for split in ("train", "val"):  # a training's, an evaluation's
        assert split_fingerprint(ctx, split) == data_fingerprint(ctx, split)
    records = [json.loads(p.read_text()) for p in (trained / "runs" / "train").glob("*/run.json")]
    assert [r["identity"]["data"] for r in records] == [split_fingerprint(ctx, "train")]


def test_the_cpu_presets_committed_trainings_are_found_from_its_spec_alone(tmp_path):
    """No cpu data here: every archived cpu training was trained on the data the cpu spec plans."""
    ctx = context("preset=cpu", f"data_dir={tmp_path / 'nowhere'}", f"eval.data_dir={tmp_path / 'mine'}")
    recorded = {json.loads(p.read_text())["identity"]["data"]
                for p in (REPO / "results" / "cpu" / "runs" / "train").glob("*/run.json")}
    assert recorded == {split_fingerprint(ctx, "train")}
    assert not (tmp_path / "nowhere").exists()


def test_recorded_models_score_your_frames_on_a_fresh_clone_rendering_and_training_nothing(trained, tmp_path):
    """A fresh clone: no run store, no data_dir, only the archive; eval.data_dir is a copy of the val split.
    Every row is scored from the archived weights: no render job, no training, the same scores as the
    table that trained them (same frames)."""
    mine = copy_of_split(trained / "data", "val", tmp_path / "mine")
    archived_evaluations = sorted(p.name for p in (trained / "archive" / "eval").iterdir())
    out = smoke_table(*store(tmp_path, trained / "archive", tmp_path / "nowhere"), f"eval.data_dir={mine}")
    assert out.returncode == 0, out.stderr[-3000:]
    # the archive is read for the models; the scores of your frames stay out of it (it is committed)
    assert sorted(p.name for p in (trained / "archive" / "eval").iterdir()) == archived_evaluations
    log = out.stdout + out.stderr
    assert "smoke: 2 rows scored on" in log and "nothing was rendered or trained" in log
    assert "trained in" not in log and "rendering" not in log
    assert not (tmp_path / "nowhere").exists() and not (tmp_path / "runs" / "data").exists()
    restored = list((tmp_path / "runs" / "train").glob("*/run.json"))
    assert restored and all(p.read_bytes() == (trained / "archive" / "train" / p.parent.name / "run.json").read_bytes()
                            for p in restored)  # each training as archived, none recorded here
    scored = pd.read_csv(tmp_path / "results" / "smoke" / "table.csv")
    # the archive keeps float16-rounded weights: the tolerance adopt holds them to (docs/runs.md)
    rtol = yaml.safe_load((Path(CONF_DIR) / "experiment" / "adopt.yaml").read_text())["experiment"]["rtol_rounded_weights"]
    pd.testing.assert_frame_equal(scored[SCORES], pd.read_csv(trained / "results" / "smoke" / "table.csv")[SCORES],
                                  rtol=rtol)


def test_a_fresh_clone_regenerates_a_recorded_table_rendering_and_training_nothing(trained, tmp_path, caplog):
    """Every run of the table archived, and the archive's copy of the frame records: a fresh clone (no run
    store, no data) writes the same table, caption included (its reference check), without rendering or
    training; only the crops figure, which reads frames, is not redrawn (it says so)."""
    cards = list((trained / "archive" / "frames").glob("*.json.gz"))
    assert len(cards) == 1
    out = smoke_table(*store(tmp_path, trained / "archive", tmp_path / "nowhere"))
    assert out.returncode == 0, out.stderr[-3000:]
    log = out.stdout + out.stderr
    assert "every evaluation is recorded: nothing is rendered or trained" in log and "crops figure not redrawn" in log
    assert "trained in" not in log and "rendering" not in log and not (tmp_path / "nowhere").exists()
    table = (tmp_path / "results" / "smoke" / "table.md").read_text()
    assert table == (trained / "results" / "smoke" / "table.md").read_text() and "References" in table
    # a damaged copy of the frame records is treated as missing (the log names it): the table then
    # renders the scored split for them (table.render_what_runs)
    archive = tmp_path / "archive"
    shutil.copytree(trained / "archive" / "frames", archive / "frames")
    ctx = context(*SMOKE, f"data_dir={tmp_path / 'nowhere'}", f"runs_archive={archive}")
    assert [f["split"] for f in frame_records(ctx, "val")] == ["val"] * 2
    card = next((archive / "frames").iterdir())
    card.write_bytes(card.read_bytes()[:20])
    with caplog.at_level("WARNING", logger="bench"):
        assert frame_records(ctx, "val") == []
    assert "is damaged" in caplog.text


def test_a_training_without_recorded_weights_is_one_line_before_anything_is_scored(trained, tmp_path):
    """An archive that left a training's weights out (RAE's at the cpu preset): eval.data_dir names the row
    and seed and what to do, exit 2, instead of rendering the training data and training it again."""
    archive = tmp_path / "archive"
    shutil.copytree(trained / "archive", archive)
    for weights in [*archive.glob(f"train/*/{CHECKPOINT}"), *archive.glob(f"train/*/{archived.WEIGHTS}")]:
        weights.unlink()
    mine = copy_of_split(trained / "data", "val", tmp_path / "mine")
    out = smoke_table(*store(tmp_path, archive, tmp_path / "nowhere"), f"eval.data_dir={mine}")
    assert out.returncode == 2 and "Traceback" not in out.stderr, out.stderr[-3000:]
    message = [line for line in out.stderr.splitlines() if "eval.data_dir" in line]
    assert len(message) == 1 and "Ours seed 0: its training" in message[0] and "without weights" in message[0]
    assert "without eval.data_dir" in message[0]
    assert not (tmp_path / "nowhere").exists() and not (tmp_path / "runs" / "eval").exists()
    records = list((tmp_path / "runs").glob("*/*/run.json"))
    assert records and all(json.loads(p.read_text())["status"] == "complete" for p in records)


def test_a_fresh_clone_scores_the_frozen_test_split_rendering_only_it(trained, tmp_path):
    """The archive holds every training of the table, so a table on a new (frozen) test split renders that
    split alone, not the training data, and reports it as the split nothing was chosen on."""
    test_split = "+data.splits.test={families:[bathroom],sequences:1}"
    out = smoke_table(*store(tmp_path, trained / "archive", tmp_path / "data"), test_split)
    assert out.returncode == 0, out.stderr[-3000:]
    assert sorted(p.name for p in (tmp_path / "data").iterdir() if p.is_dir()) == ["test"]
    assert {f["split"] for f in load_manifest(tmp_path / "data")["frames"]} == {"test"}
    assert "trained in" not in out.stdout + out.stderr
    caption = (tmp_path / "results" / "smoke" / "table.md").read_text().split("\n\n")[0]
    assert "split test" in caption and "frozen" in caption
    evaluations = [json.loads(p.read_text()) for p in (tmp_path / "runs" / "eval").glob("*/run.json")]
    assert evaluations and {e["identity"]["split"] for e in evaluations} == {"test"}


def test_a_table_that_must_train_renders_the_training_and_working_splits_not_the_others(tmp_path):
    """A training to run needs the train split and the split its learning curve reads (val), besides the
    scored one; a split no one reads (here an extra one, as generalization is to the sota table) stays
    unrendered."""
    extra = "+data.splits.extra={families:[bathroom],sequences:1}"
    out = smoke_table(*store(tmp_path, tmp_path / "archive", tmp_path / "data"), extra)
    assert out.returncode == 0, out.stderr[-3000:]
    assert sorted(p.name for p in (tmp_path / "data").iterdir() if p.is_dir()) == ["train", "val"]
    assert "trained in" in out.stdout + out.stderr
    # before it renders, the log says why: what is not recorded, and each training to run (row, seed, why)
    said = re.search(r": rendering (.+) where missing, because: (.+)", out.stdout + out.stderr)
    assert said and said.group(1) == "train, val", (out.stdout + out.stderr)[-3000:]
    assert said.group(2).startswith("not recorded: the evaluation of ")
    assert re.search(r"; to train: \S.* seed 0: no complete training recorded in ", said.group(2)), said.group(2)


def test_frame_records_merge_splits_under_the_archives_lock(tmp_path):
    """Each command merges its splits' frame records into the archive's copy: another split's stay. The
    read-merge-write happens under the archive's lock: a split another process writes while it holds the
    lock is read, not overwritten (read before the lock, it would be lost)."""
    import gzip
    import types
    from bench import runs
    from bench.experiments.datasets import _frame_records_path, archive_frame_records
    spec = {"name": "tiny", "splits": {"val": {}, "test": {}, "generalization": {}}}
    ctx = types.SimpleNamespace(runs_archive=tmp_path / "archive", render_data=True, data_spec=spec,
                                data_dir=tmp_path / "no data")  # no manifest: records come from the archive

    def frame(split):
        return {"split": split, "sequence": "s", "frame": 0, "ref_spp": 4, "ref_error": 0.1,
                "files": {"hr": {"crc32": 1}}}
    archive_frame_records(ctx, {"spec": spec, "frames": [frame("val")]})
    path = _frame_records_path(ctx)
    lock = ctx.runs_archive / runs.PARTIAL / f"frames.{path.name}.lock"
    lock.parent.mkdir(parents=True, exist_ok=True)
    card = {"spec": spec, "frames": [frame("generalization"), frame("val")]}
    holder = subprocess.Popen(  # holds the lock, then writes a third split and lets go
        [sys.executable, "-c", f"import fcntl, gzip, json, time\nh = open({str(lock)!r}, 'a')\n"
         "fcntl.flock(h, fcntl.LOCK_EX)\nprint('held', flush=True)\ntime.sleep(1)\n"
         f"open({str(path)!r}, 'wb').write(gzip.compress(json.dumps({card!r}).encode()))"],
        stdout=subprocess.PIPE, text=True)
    assert holder.stdout.readline().strip() == "held"
    archive_frame_records(ctx, {"spec": spec, "frames": [frame("test")]})
    assert holder.wait(timeout=10) == 0
    kept = json.loads(gzip.decompress(path.read_bytes()))
    assert sorted(f["split"] for f in kept["frames"]) == ["generalization", "test", "val"]
    assert frame_records(ctx, "test") == [frame("test")]


def test_a_spec_changed_in_one_split_keeps_the_other_splits_frame_records(tmp_path):
    """test's references got more samples (a new spec, so a new records file) on a machine holding only
    test: val's records, of an unchanged part of the spec, come over from the earlier file; a split whose
    part changed does not."""
    import types
    from bench.experiments.datasets import _frame_records_path, archive_frame_records

    def frame(split, spp=4):
        return {"split": split, "sequence": "s", "frame": 0, "ref_spp": spp, "ref_error": 0.1,
                "files": {"hr": {"crc32": 1}}}
    before = {"name": "tiny", "seq_len": 2, "splits": {"val": {"ref_spp": 4}, "test": {"ref_spp": 4}, "train": {"ref_spp": 4}}}
    after = {**before, "splits": {**before["splits"], "test": {"ref_spp": 4, "sequence_ref_spp": {"s": 8}}}}
    ctx = types.SimpleNamespace(runs_archive=tmp_path / "archive", render_data=True, data_spec=before,
                                data_dir=tmp_path / "no data")
    archive_frame_records(ctx, {"spec": before, "frames": [frame("val"), frame("test"), frame("train")]})
    elsewhere = {**after, "splits": {**after["splits"], "train": {"ref_spp": 16}}}   # train changed too
    ctx.data_spec = elsewhere
    archive_frame_records(ctx, {"spec": elsewhere, "frames": [frame("test", 8)]})
    assert _frame_records_path(ctx).exists()
    assert frame_records(ctx, "test") == [frame("test", 8)] and frame_records(ctx, "val") == [frame("val")]
    assert frame_records(ctx, "train") == []


def test_a_split_whose_part_of_the_spec_is_unchanged_keeps_its_records_before_anything_renders(tmp_path):
    """test's proposal is put in the spec but not rendered yet: val's records still come from data_dir's
    manifest (of the earlier spec), or without it from the archive's earlier file; test's from neither."""
    import types
    from bench.experiments.datasets import archive_frame_records

    def frame(split, crc=1):
        return {"split": split, "sequence": "s", "frame": 0, "ref_spp": 4, "ref_error": 0.1,
                "files": {"hr": {"crc32": crc}}}
    before = {"name": "tiny", "seq_len": 2, "splits": {"val": {"ref_spp": 4}, "test": {"ref_spp": 4}}}
    after = {**before, "splits": {**before["splits"], "test": {"ref_spp": 4, "sequence_ref_spp": {"s": 8}}}}
    ctx = types.SimpleNamespace(runs_archive=tmp_path / "archive", render_data=True, data_spec=before,
                                data_dir=tmp_path / "data")
    archive_frame_records(ctx, {"spec": before, "frames": [frame("val"), frame("test")]})
    ctx.data_spec = after
    assert frame_records(ctx, "val") == [frame("val")] and frame_records(ctx, "test") == []
    ctx.data_dir.mkdir()
    (ctx.data_dir / "manifest.json").write_text(json.dumps({"spec": before, "frames": [frame("val", 2), frame("test", 2)]}))
    assert frame_records(ctx, "val") == [frame("val", 2)]  # the frames on disk, not another render's
    assert frame_records(ctx, "test") == []


def _eval_records(root: Path) -> list:
    return list((root / "runs" / "eval").glob("*/run.json")) if (root / "runs" / "eval").exists() else []


@pytest.mark.parametrize("damage", ["lr_all_nan", "hr_cut"])
def test_your_damaged_frame_is_one_line_naming_it_and_eval_data_dir_before_anything_is_recorded(trained, tmp_path,
                                                                                                 damage):
    """eval.data_dir decodes every frame first: an LR frame that is all NaN (the evaluator would repair it
    silently into another image) and an HR reference cut inside its pixels (OpenEXR would print its own
    lines mid-evaluation) each end in one line naming the frame, the data_dir it is in and the fix, with
    no evaluation recorded (a frame with at most 1% of its pixels NaN/Inf is scored: the evaluator repairs those)."""
    from bench import datagen, exrio
    mine = copy_of_split(trained / "data", "val", tmp_path / "mine")
    frame = load_manifest(mine)["frames"][0]
    lr, hr, _ = frame_paths(mine, "val", frame["sequence"], frame["frame"])
    if damage == "lr_all_nan":
        layers = exrio.read_exr(lr)
        layers["noisy"][:] = np.nan
        exrio.write_exr(lr, layers, suffixes=datagen.SUFFIXES)
        bad = lr
    else:
        Path(hr).write_bytes(Path(hr).read_bytes()[:os.path.getsize(hr) * 2 // 3])  # header whole, pixels cut
        bad = hr
    out = smoke_table(*store(tmp_path, trained / "archive", tmp_path / "nowhere"), f"eval.data_dir={mine}")
    assert out.returncode == 2, out.stderr[-3000:]
    lines = [x for x in out.stderr.splitlines() if x.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: data: 1 damaged frame files in eval.data_dir="), out.stderr
    assert str(bad) in lines[0] and "experiment.verify=true" in lines[0] and f"data_dir={mine}" in lines[0]
    assert "Traceback" not in out.stdout + out.stderr and not _eval_records(tmp_path)



def test_an_output_that_is_not_finite_on_a_frame_stops_the_table_instead_of_leaving_the_frame_out(
        trained, tmp_path, monkeypatch):
    """A NaN output gives NaN scores, which a mean skips: the row would be scored on the other frames and
    look better than the model is. The evaluation is recorded failed and the table stops with one line
    naming the frame."""
    import bench.evaluate
    real = bench.evaluate.predict

    def nan_on_the_second_frame(model, x, g, hdr, forward=None):
        out = real(model, x, g, hdr, forward=forward)
        if getattr(model, "recurrent", False) and out.shape[1] > 1:   # Ours, not the bilinear input row
            out[:, 1] = float("nan")
        return out
    monkeypatch.setattr(bench.evaluate, "predict", nan_on_the_second_frame)
    out = smoke_table(*store(tmp_path, "null", trained / "data"))      # no archive: trained and scored here
    assert out.returncode == 2 and "Traceback" not in out.stderr, out.stderr[-3000:]
    (line,) = [line for line in out.stderr.splitlines() if "score NaN" in line]
    assert "eval Ours: 1 of 2 frames score NaN (" in line and "frame 1): the output or the reference" in line
    failed = [json.loads(p.read_text()) for p in (tmp_path / "runs" / "eval").glob("*/run.json")]
    assert [r["status"] for r in failed if r["label"] == "Ours"] == ["failed"]


def test_fast_path_auto_does_not_train_again_only_to_choose_a_path(tmp_path, monkeypatch):
    """A training the archive keeps without weights: auto measures an untrained copy instead of training
    it again (the evaluation may be recorded already); with weights at hand it takes them."""
    from bench import runs
    from bench.experiments import evaluation
    monkeypatch.setattr(evaluation, "trained_model", lambda *a, **k: ("trained model", None))
    weightless = runs.Run("train", "0" * 16, tmp_path / "weightless", {})
    (tmp_path / "weightless").mkdir()
    assert evaluation._trained_weights(None, {}, None, 0, "x", False, [weightless]) is None
    kept = runs.Run("train", "1" * 16, tmp_path / "kept", {})
    (tmp_path / "kept").mkdir()
    (tmp_path / "kept" / CHECKPOINT).write_bytes(b"weights")
    assert evaluation._trained_weights(None, {}, None, 0, "x", False, [kept]) == "trained model"
    assert evaluation._trained_weights(None, {}, None, 0, "x", False, [kept, weightless]) is None
