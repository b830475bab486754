"""Faults and bad input with real files and real processes: damaged frames are found and repaired (or
named), damaged run files are treated as missing, a full disk is one line, force computes each run once,
bad values stop a command before anything runs, nothing computed is lost. (Signals: tests/test_train.py;
bad train.* values: tests/test_cli.py; stale code and abandoned runs: tests/test_runs.py, and a real edit
to a model file: tests/test_cli.py.)"""
import dataclasses
import io
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from bench import datagen, exrio, runs
from bench.atomic import write_atomic
from bench.errors import UserError
from bench.experiments.datasets import RENDERING, ensure_data
from conftest import bench_here, python_process, smoke_context

SPEC = {"name": "tiny", "seed": 1, "lr_width": 8, "lr_height": 6, "scale": 2, "spp": 1, "ref_spp": 4,
        "seq_len": 2, "max_depth": 4, "splits": {"train": {"families": ["living_room"], "sequences": 1}}}
PASSES = {"lr_noisy", "lr_gbuf", "hr_ref"}


def _ctx(root, render_data=True):
    return smoke_context(preset="tiny", runs_dir=root / "runs", results_dir=root / "results", data_dir=root / "data",
                         data_spec=SPEC, render_data=render_data, progress=False)


@pytest.fixture
def rendered(tmp_path):
    ensure_data(_ctx(tmp_path), PASSES)
    hr = tmp_path / "data" / "train" / datagen.load_manifest(tmp_path / "data")["frames"][0]["sequence"] / "0001_hr.exr"
    return tmp_path, hr, exrio.read_exr(hr)


def test_a_render_of_one_split_counts_its_own_frames_not_the_splits_already_there(tmp_path, caplog):
    spec = {**SPEC, "splits": {**SPEC["splits"], "val": {"families": ["bathroom"], "sequences": 1}}}
    ctx = dataclasses.replace(_ctx(tmp_path), data_spec=spec)
    ensure_data(ctx, PASSES, {"train"})
    with caplog.at_level("INFO", logger="bench"):
        ensure_data(ctx, PASSES, {"val"})                    # the manifest lists train too
    assert "data: 2 frames of val rendered, 0 were already complete" in caplog.text
    record = next(json.loads(p.read_text()) for p in (tmp_path / "runs" / "data").glob("*/run.json")
                  if json.loads(p.read_text())["identity"]["splits"] == ["val"])
    assert record["metrics"]["frames"] == 2 and record["metrics"]["resumed_frames"] == 0


def test_a_truncated_frame_is_rendered_again_to_the_same_pixels(rendered):
    root, hr, original = rendered
    hr.write_bytes(hr.read_bytes()[:100])                         # cut in its header
    assert [p for p, _ in datagen.damaged_frames(root / "data", datagen.load_manifest(root / "data")["frames"],
                                                 sorted(PASSES))] == [str(hr)]
    ensure_data(_ctx(root), PASSES)
    repaired = exrio.read_exr(hr)
    np.testing.assert_array_equal(repaired["ref"], original["ref"])   # seeds are derived: same pixels


def _unstamp(root):
    """Drop the file stamps from the manifest and frame records: a dataset rendered before stamps."""
    import json
    manifest_path = root / "data" / "manifest.json"
    manifest = json.loads(manifest_path.read_text())
    for rec in manifest["frames"]:
        rec.pop("files")
    manifest_path.write_text(json.dumps(manifest))
    for rec_path in (root / "data").rglob("0*.json"):
        rec_path.write_text(json.dumps({k: v for k, v in json.loads(rec_path.read_text()).items() if k != "files"}))


def test_a_frame_cut_inside_its_pixels_is_found_by_its_stamp_or_by_decoding(rendered):
    root, hr, _ = rendered
    data = hr.read_bytes()
    hr.write_bytes(data[:int(len(data) * 0.9)])                   # the header survives
    frames = datagen.load_manifest(root / "data")["frames"]
    assert [p for p, _ in datagen.damaged_frames(root / "data", frames, sorted(PASSES))] == [str(hr)]
    _unstamp(root)                                                # rendered before stamps: decoding finds it
    frames = datagen.load_manifest(root / "data")["frames"]
    assert datagen.damaged_frames(root / "data", frames, sorted(PASSES)) == []
    assert datagen.damaged_frames(root / "data", frames, sorted(PASSES), decode=True) == [
        (str(hr), "does not decode (truncated or corrupt)")]


def test_the_data_experiment_with_verify_repairs_what_only_decoding_finds(rendered):
    from bench.experiments import data
    root, hr, original = rendered
    data_bytes = hr.read_bytes()
    hr.write_bytes(data_bytes[:int(len(data_bytes) * 0.9)])
    data.run(_ctx(root), passes=sorted(PASSES), examples=0, verify=True)
    np.testing.assert_array_equal(exrio.read_exr(hr)["ref"], original["ref"])


def test_your_own_damaged_frame_is_named_not_rendered(rendered):
    root, hr, _ = rendered
    hr.unlink()
    with pytest.raises(UserError, match=f"{hr}: missing.*yours to replace"):
        ensure_data(_ctx(root, render_data=False), PASSES)
    assert not hr.exists()


def test_a_frame_damaged_during_a_run_is_one_line_with_the_fix(rendered):
    root, hr, _ = rendered
    _unstamp(root)                                                # else the start check finds it first
    data = hr.read_bytes()
    hr.write_bytes(data[:int(len(data) * 0.9)])
    out = bench_here("+experiment=smoke", "preset=smoke", "render_data=false", f"data_dir={root / 'data'}",
                     f"runs_dir={root / 'runs'}", f"results_dir={root / 'results'}",
                     "experiment.rows=[{label:b,model:bilinear}]", "eval.split=train", "progress=false")
    assert out.returncode == 2 and "Traceback" not in out.stderr, out.stderr[-2000:]
    assert str(hr) in out.stderr and "yours to replace" in out.stderr and "verify=true" in out.stderr


def _write_nan(path):
    """Rewrite a frame file with one NaN and one Inf in each layer, as an external tool could."""
    layers = exrio.read_exr(path)
    for a in layers.values():
        a[0, 0, 0], a[-1, -1, -1] = np.nan, np.inf
    exrio.write_exr(path, layers, suffixes=datagen.SUFFIXES)


def _frames(root):
    return datagen.load_manifest(root / "data")["frames"]


def test_nan_written_into_a_rendered_frame_is_found_at_start_and_rendered_again(rendered):
    """The issue's case: NaN/Inf written into a rendered frame must not be trusted. The header check at
    every start sees the file changed since it was written; the frame is rendered again to the same
    pixels, so recorded runs stay valid (the data fingerprint is unchanged)."""
    from bench.experiments.datasets import data_fingerprint
    root, hr, original = rendered
    before = data_fingerprint(_ctx(root))
    _write_nan(hr)
    assert datagen.damaged_frames(root / "data", _frames(root), sorted(PASSES)) == [
        (str(hr), "changed since it was rendered (size or bytes differ from its record)")]
    ensure_data(_ctx(root), PASSES)
    repaired = exrio.read_exr(hr)
    assert set(repaired) == set(original)
    for name in original:
        np.testing.assert_array_equal(repaired[name], original[name])
    assert datagen.damaged_frames(root / "data", _frames(root), sorted(PASSES)) == []
    assert data_fingerprint(_ctx(root)) == before
    os.utime(hr, ns=(0, 0))                                       # a copy without -p: same bytes, other mtime
    assert datagen.damaged_frames(root / "data", _frames(root), sorted(PASSES)) == []


def test_a_frame_rendered_again_after_the_manifest_is_not_damaged(rendered):
    """A render stopped before it wrote the manifest leaves frames whose own records (beside them) are newer
    than the manifest's: their files match the own record's stamp, not the manifest's, and are not
    damaged. A file that matches neither still is."""
    root, hr, original = rendered
    rec_path = hr.with_name("0001.json")
    record = json.loads(rec_path.read_text())
    exrio.write_exr(hr, {name: a * 0.5 for name, a in original.items()}, suffixes=datagen.SUFFIXES)
    record["files"]["hr"] = datagen.file_stamp(hr)                 # what the render writes after the frame
    rec_path.write_text(json.dumps(record))
    assert datagen.damaged_frames(root / "data", _frames(root), sorted(PASSES)) == []
    exrio.write_exr(hr, original, suffixes=datagen.SUFFIXES)         # changed again, no record of it
    assert datagen.damaged_frames(root / "data", _frames(root), sorted(PASSES)) == [
        (str(hr), "changed since it was rendered (size or bytes differ from its record)")]
    record["settings_hash"] = "other settings"                     # a record of other settings does not vouch
    record["files"]["hr"] = datagen.file_stamp(hr)
    rec_path.write_text(json.dumps(record))
    assert [p for p, _ in datagen.damaged_frames(root / "data", _frames(root), sorted(PASSES))] == [str(hr)]


def test_verify_finds_nan_in_frames_without_stamps_repairs_and_stamps_them(rendered):
    """Frames rendered before stamps existed: only decoding finds NaN; `verify=true` renders them again
    and stamps every frame, so a later edit is found by the header check."""
    from bench.experiments import data
    root, hr, original = rendered
    _unstamp(root)
    _write_nan(hr)
    assert datagen.damaged_frames(root / "data", _frames(root), sorted(PASSES)) == []   # nothing to compare
    (why,) = [w for p, w in datagen.damaged_frames(root / "data", _frames(root), sorted(PASSES), decode=True)
              if p == str(hr)]
    assert why.startswith("non-finite pixel values (NaN/Inf)")
    data.run(_ctx(root), passes=sorted(PASSES), examples=0, verify=True)
    np.testing.assert_array_equal(exrio.read_exr(hr)["ref"], original["ref"])
    assert all(rec.get("files") for rec in _frames(root))
    lr = hr.with_name(hr.name.replace("_hr", "_lr"))
    _write_nan(lr)
    assert [p for p, _ in datagen.damaged_frames(root / "data", _frames(root), sorted(PASSES))] == [str(lr)]


def test_verify_lists_nan_in_your_own_data_and_changes_nothing(rendered):
    from bench.experiments import data
    root, hr, _ = rendered
    _unstamp(root)                                                # your own renders carry no stamps
    _write_nan(hr)
    manifest = (root / "data" / "manifest.json").read_bytes()
    with pytest.raises(UserError, match=f"{hr}: non-finite pixel values"):
        data.run(_ctx(root, render_data=False), passes=sorted(PASSES), examples=0, verify=True)
    assert (root / "data" / "manifest.json").read_bytes() == manifest


def _sigint_as_a_terminal_gives_it():
    """In the child before exec: SIGINT's default disposition, so Python turns it into KeyboardInterrupt. A
    process started in the background by a non-interactive shell (`make test &`, a CI runner) ignores
    SIGINT, and a Python started from it keeps ignoring it: the command then rendered on to the end of its
    queue (the 106-275 s exits, and a failure, that this case once saw in full-suite runs)."""
    import signal
    signal.signal(signal.SIGINT, signal.SIG_DFL)


# SIGINT (Ctrl-C), SIGTERM (preemption)
@pytest.mark.parametrize("signum,exit_code", [(2, 130), (15, 143)])
def test_a_signal_while_rendering_is_one_line_and_the_data_run_is_recorded_failed(tmp_path, signum, exit_code):
    """SIGINT outside a training step (here: rendering in two worker processes) ends at once in one line and
    exit 130, not a traceback per worker, and the data run's record says what happened instead of staying
    "running"."""
    import json
    import subprocess
    import sys
    import time
    from pathlib import Path
    proc = subprocess.Popen([sys.executable, "-m", "bench", "+experiment=data", "preset=smoke", "workers=2",
                             f"data_dir={tmp_path / 'data'}", f"runs_dir={tmp_path / 'runs'}",
                             f"results_dir={tmp_path / 'results'}", "progress=false", "tracking=none"],
                            cwd=Path(__file__).parent.parent, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            text=True, preexec_fn=_sigint_as_a_terminal_gives_it)
    seen = []
    for line in proc.stdout:                                      # wait until rendering has begun
        seen.append(line)
        if RENDERING in line:
            break
    proc.send_signal(signum)
    t0 = time.perf_counter()
    rest, _ = proc.communicate(timeout=300)
    assert time.perf_counter() - t0 < 20                          # not after the rest of the render queue
    out = "".join(seen) + rest
    assert proc.returncode == exit_code, out[-3000:]
    assert "interrupted: runs recorded so far are kept" in out and "Traceback" not in out
    (record,) = [json.loads(p.read_text()) for p in (tmp_path / "runs" / "data").glob("*/run.json")]
    assert record["status"] == "failed" and record["error"].startswith(("KeyboardInterrupt", "Terminated"))


def test_the_callers_sigterm_handler_is_back_after_a_command(tmp_path):
    """main handles SIGTERM as Ctrl-C while it runs and gives the caller's handler back when it ends
    (else a SIGTERM while the interpreter shuts down, joining render workers, printed a traceback)."""
    code = ("import signal, sys\n"
            "from bench.cli import main\n"
            "def mine(signum, frame): pass\n"
            "signal.signal(signal.SIGTERM, mine)\n"
            f"sys.argv = ['bench', '+experiment=train', 'experiment.model=nosuch', 'preset=cpu', 'tracking=none',"
            f" 'runs_dir={tmp_path / 'runs'}', 'results_dir={tmp_path / 'results'}']\n"
            "try:\n    main()\nexcept SystemExit as end:\n    print('exit', end.code)\n"
            "print('handler', signal.getsignal(signal.SIGTERM) is mine)\n")
    out = python_process("-c", code, timeout=120)
    assert "exit 2" in out.stdout and "handler True" in out.stdout, out.stdout + out.stderr[-2000:]


def test_hr_files_of_the_wrong_size_under_a_copied_manifest_are_not_trusted(rendered):
    """The issue's case: another directory with the same manifest but HR files of another size must not
    reuse this one's results: the header check names each file, and rendering replaces it."""
    import shutil
    root, hr, original = rendered
    other = root / "other"
    shutil.copytree(root / "data", other / "data")
    _unstamp(other)                                               # not even stamps to compare: sizes decide
    wrong = other / hr.relative_to(root)
    exrio.write_exr(wrong, {name: np.zeros((3, 4, a.shape[-1]), np.float32) for name, a in original.items()},
                    suffixes=datagen.SUFFIXES)
    assert datagen.damaged_frames(other / "data", _frames(other), sorted(PASSES)) == [
        (str(wrong), "4x3 pixels; its record says 16x12")]
    ensure_data(_ctx(other), PASSES)
    np.testing.assert_array_equal(exrio.read_exr(wrong)["ref"], original["ref"])


def test_a_split_rendered_again_with_fewer_buffers_gets_the_rest_when_a_table_needs_them(tmp_path):
    """Giving val its own ref_spp re-renders its frames with the buffers the running table asks for; a
    later table needing another buffer must find it missing on those frames and render it."""
    import dataclasses
    val = {"families": ["gallery"], "sequences": 1}
    ctx = dataclasses.replace(_ctx(tmp_path), data_spec={**SPEC, "splits": {**SPEC["splits"], "val": val}})
    ensure_data(ctx, {"lr_noisy", "lr_ref", "hr_ref"})
    ctx = dataclasses.replace(ctx, data_spec={**SPEC, "splits": {**SPEC["splits"], "val": {**val, "ref_spp": 8}}})
    ensure_data(ctx, {"lr_noisy", "hr_ref"})
    val_frames = [f for f in _frames(tmp_path) if f["split"] == "val"]
    assert val_frames and all(set(f["buffers"]) == {"lr_noisy", "hr_ref"} for f in val_frames)
    ensure_data(ctx, {"lr_ref"})
    assert _frames(tmp_path)
    for f in _frames(tmp_path):
        assert "lr_ref" in f["buffers"]
        assert "ref" in exrio.exr_layers(tmp_path / "data" / f["split"] / f["sequence"] / f"{f['frame']:04d}_lr.exr")


# ---------------------------------------------------------------- issue 44: the run store's files, force, values

REPO = Path(__file__).resolve().parent.parent
EDSR = {"label": "E", "model": "edsr"}
# the command line of a table of one tiny EDSR row on tiny renders (2 frames of 8x6), scored on train
TINY_CLI = ["+experiment=smoke", "preset=smoke", "data.lr_width=8", "data.lr_height=6", "data.spp=1", "data.ref_spp=4",
            "data.seq_len=2", "data.max_depth=4", "data.splits.train.sequences=1", "data.splits.train.families=[living_room]",
            "~data.splits.val", "~data.splits.generalization", "eval.split=train", "train.steps=2", "train.crop=4",
            "train.seq_len=2", "train.batch_size=1", "train.checkpoint_every=1", "train.val_sequences=1",
            "train.val_every=1", "models.edsr.channels=4", "models.edsr.blocks=1", "workers=1", "progress=false",
            "tracking=none", "experiment.rows=[{label:E,model:edsr}]"]


def _table_ctx(root, **changes):
    """`_ctx` with a tiny EDSR trained for 2 steps, scored on the train split (the tiny data has no other)."""
    from bench.experiments.context import recipe_from
    ctx = _ctx(root)
    train = {**dataclasses.asdict(ctx.train), "steps": 2, "crop": 4, "seq_len": 2, "batch_size": 1,
             "checkpoint_every": 1, "val_every": 1, "val_sequences": 1}
    return dataclasses.replace(ctx, device="cpu", train=recipe_from(train), eval=dataclasses.replace(ctx.eval, split="train"),
                               models={**ctx.models, "edsr": {**ctx.models["edsr"], "channels": 4, "blocks": 1}},
                               **changes)


def _table(ctx, figure=False):
    from bench.experiments import table
    return table.run(ctx, "t", rows=[dict(EDSR)], figure=figure)


@pytest.fixture(scope="module")
def tiny_store(tmp_path_factory):
    """A run store with one recorded tiny training and its evaluation, and the data it read."""
    root = tmp_path_factory.mktemp("store")
    _table(_table_ctx(root))
    return root


@pytest.fixture
def store(tiny_store, tmp_path):
    """A copy of `tiny_store` for one test to damage."""
    for part in ("runs", "data"):
        shutil.copytree(tiny_store / part, tmp_path / part)
    return tmp_path


def _run_dir(root, kind):
    (path,) = (root / "runs" / kind).glob(f"*/{'run.json'}")
    return path.parent


def _cut(path):
    path.write_bytes(path.read_bytes()[:len(path.read_bytes()) // 2])


def _edsr_training(ctx):
    from bench.experiments.context import model_config
    from bench.experiments.training import trained_model
    from bench.tasks import get_task
    return trained_model(ctx, model_config(ctx, "edsr"), get_task("srd"), 0, "E")


def test_a_damaged_run_record_is_named_and_its_run_computed_again(store, caplog):
    record = _run_dir(store, "eval") / "run.json"
    _cut(record)
    with caplog.at_level("INFO", logger="bench"):
        table = _table(_table_ctx(store))
    assert f"{record} is damaged" in caplog.text and "reusing run" in caplog.text   # the training is reused
    assert json.loads(record.read_text())["status"] == "complete" and table["PSNR"].notna().all()


def test_a_damaged_checkpoint_of_a_finished_training_is_trained_again_when_its_weights_are_read(store, caplog):
    import torch
    checkpoint = _run_dir(store, "train") / "checkpoint.pt"
    _cut(checkpoint)
    with caplog.at_level("INFO", logger="bench"):
        model, run = _edsr_training(_table_ctx(store))
    assert f"{checkpoint} is damaged" in caplog.text and "trained in" in caplog.text
    assert run.record["status"] == "complete" and torch.load(checkpoint, weights_only=False)["step"] == 2


def test_an_interrupted_training_whose_checkpoint_is_damaged_starts_over(store, caplog):
    run_dir = _run_dir(store, "train")
    record = json.loads((run_dir / "run.json").read_text())
    (run_dir / "run.json").write_text(json.dumps({**record, "status": "interrupted"}))
    (run_dir / "checkpoint.pt").write_bytes(b"PK\x03\x04 not a whole checkpoint")
    with caplog.at_level("INFO", logger="bench"):
        _, run = _edsr_training(_table_ctx(store))
    assert f"{run_dir / 'checkpoint.pt'} is damaged" in caplog.text
    assert run.record["status"] == "complete" and run.metrics["resumed_from_step"] == 0


def test_a_damaged_curve_is_treated_as_missing_and_named(store, caplog):
    from bench.experiments.figure import curve_figure
    from bench.experiments.row import last_fifth_gain
    run_dir = _run_dir(store, "train")
    (run_dir / "val_curve.csv").write_bytes(b"")                  # what a full disk leaves of a CSV
    with caplog.at_level("WARNING", logger="bench"):
        assert last_fifth_gain(run_dir) is None
        assert curve_figure(store / "runs", {"E": [run_dir.name]}, store / "curves.png") is None
    assert f"{run_dir / 'val_curve.csv'} is damaged" in caplog.text


def test_a_damaged_manifest_is_rebuilt_from_the_frame_records_without_rendering(rendered, caplog):
    root, _, _ = rendered
    manifest = root / "data" / "manifest.json"
    frames = json.loads(manifest.read_text())["frames"]
    written = {p: p.stat().st_mtime_ns for p in (root / "data").rglob("*.exr")}
    _cut(manifest)
    with caplog.at_level("INFO", logger="bench"):
        ensure_data(_ctx(root), PASSES)
    assert f"{manifest} is damaged" in caplog.text and "rebuilt" in caplog.text
    assert [f["sequence"] for f in json.loads(manifest.read_text())["frames"]] == [f["sequence"] for f in frames]
    assert {p: p.stat().st_mtime_ns for p in written} == written      # nothing rendered
    assert not list((root / "runs").glob("data/*/run.json"))[1:]     # no second render job


def test_your_own_damaged_manifest_is_one_line_naming_it_and_what_to_do(rendered):
    root, _, _ = rendered
    manifest = root / "data" / "manifest.json"
    _cut(manifest)
    with pytest.raises(UserError) as err:
        ensure_data(_ctx(root, render_data=False), PASSES)
    assert f"{manifest}: not JSON" in str(err.value) and "restore it" in str(err.value) and "\n" not in str(err.value)


def test_a_failed_write_leaves_no_temporary_file_and_a_killed_ones_is_removed_at_the_next_start(tmp_path):
    from bench import runs
    target = tmp_path / "run.json"

    def fails(tmp):
        tmp.write_text("half")
        raise OSError(28, "No space left on device")
    with pytest.raises(OSError):
        write_atomic(target, fails)
    assert list(tmp_path.iterdir()) == []
    run = runs.begin(tmp_path / "runs", "eval", {"a": 1})
    runs.fail(run, "killed")
    (run.dir / "checkpoint.pt.4242.tmp").write_bytes(b"half")        # what kill -9 mid-write leaves
    runs.begin(tmp_path / "runs", "eval", {"a": 1})
    assert not list(run.dir.glob("*.tmp"))


def _bench(root, *args, env=None):
    return subprocess.Popen([sys.executable, "-m", "bench", *TINY_CLI, f"runs_dir={root / 'runs'}",
                             f"results_dir={root / 'results'}", f"data_dir={root / 'data'}", *args], cwd=REPO,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                            env=dict(os.environ, HYDRA_FULL_ERROR="0", **(env or {})))


# A full disk under runs_dir from the first checkpoint on, as the child process sees it: torch's writer
# fails as it does on a full disk (a RuntimeError, after part of the file), Python's writes with ENOSPC.
FULL_DISK = '''
import builtins, errno, io, os
import torch
FULL, UNDER, real_open, real_save = [], os.environ["FULL_DISK_UNDER"], io.open, torch.save

def under(file):
    return isinstance(file, (str, os.PathLike)) and os.path.abspath(file).startswith(UNDER)

def save(obj, f, *args, **kwargs):
    if under(f):
        FULL.append(f)
        with real_open(f, "wb") as out:
            out.write(b"PK")
        raise RuntimeError("[enforce fail at inline_container.cc:672] . unexpected pos 704 vs 598")
    return real_save(obj, f, *args, **kwargs)

def open_(file, mode="r", *args, **kwargs):
    if FULL and under(file) and set(mode) & set("wx"):
        real_open(file, mode, *args, **kwargs).close()
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), os.fspath(file))
    return real_open(file, mode, *args, **kwargs)

torch.save, builtins.open, io.open = save, open_, open_
'''


def test_a_full_disk_is_one_line_and_leaves_no_running_record_and_no_temporary_file(tmp_path):
    (tmp_path / "inject").mkdir()
    (tmp_path / "inject" / "sitecustomize.py").write_text(FULL_DISK)
    out, _ = _bench(tmp_path, env={"FULL_DISK_UNDER": str(tmp_path / "runs"),
                                   "PYTHONPATH": os.pathsep.join([str(tmp_path / "inject"), str(REPO)])}).communicate(timeout=300)
    assert "No space left on device" in out and "Traceback" not in out, out[-3000:]
    (line,) = [x for x in out.splitlines() if x.startswith("error:")]
    assert "no space left on the device under runs_dir" in line
    records = [json.loads(p.read_text()) for p in (tmp_path / "runs").glob("*/*/run.json")]
    assert records and not [r for r in records if r["status"] == "running"]
    assert not list((tmp_path / "runs").rglob("*.tmp"))


def test_force_computes_each_run_once_per_command_the_crops_figure_included(store, caplog, monkeypatch):
    from bench import runs
    monkeypatch.setattr(runs, "COMMAND_STARTED_S", time.time())   # a new command, after the store was made
    with caplog.at_level("INFO", logger="bench"):
        table = _table(_table_ctx(store, force=True), figure=True)
    assert caplog.text.count("trained in") == 1 and "does not compute it twice" in caplog.text
    assert table.loc[0, "train (min)"] > 0 and table["last fifth (dB)"].notna().all()


def test_concurrent_forced_commands_compute_each_run_once_between_them(tmp_path):
    import pandas as pd
    procs = [_bench(tmp_path, "force=true", f"results_dir={tmp_path / name}") for name in ("a", "b")]
    outs = [p.communicate(timeout=300)[0] for p in procs]
    assert all(p.returncode == 0 for p in procs), outs[0][-2000:] + outs[1][-2000:]
    assert sum(out.count("trained in") for out in outs) == 1
    for name in ("a", "b"):
        table = pd.read_csv(tmp_path / name / "smoke" / "table.csv")
        assert table.loc[0, "train (min)"] > 0 and table["last fifth (dB)"].notna().all(), table.to_string()


@pytest.mark.parametrize("override,message", [
    ("models.srd.channels=0", "models.srd.channels=0: expected an integer >= 1"),
    ("models.srd.channels=-4", "models.srd.channels=-4: expected an integer >= 1"),
    ("train.crop=64", "train.crop=64: larger than the LR frame 32x24"),
    ("train.seq_len=9", "train.seq_len=9: longer than the dataset's sequences (3 frames"),
    ("experiment.rows=[{label:a,model:srd,train:{steps:abc}}]", "experiment.rows['a'].train.steps='abc': expected a positive"),
    ("experiment.rows=[{label:a,model:srd,train:{steps:-5}}]", "experiment.rows['a'].train.steps=-5: expected a positive"),
    ("experiment.rows=[{label:a,model:edsr,overrides:{blocks:0}}]", "experiment.rows['a'].overrides.blocks=0"),
    ("experiment.rows=[{label:a,model:srd,cascade:true}]",
     "experiment.rows['a'].cascade=true: its stages exchange RGB images only, so it needs channel_aug=false and skip=false"),
    ("experiment.rows=[{label:a,model:srd,cascade:true,overrides:{channel_aug:false}}]", "needs skip=false in its"),
    ("experiment.rows=[{label:a,model:edsr,cascade:true}]", "a Cascade trains the proposed model's stages apart"),
])
def test_a_bad_value_inside_a_model_or_a_row_is_one_line_before_anything_runs(tmp_path, override, message):
    from hydra import compose, initialize_config_dir
    from bench.cli import CONF_DIR, make_context
    with initialize_config_dir(config_dir=CONF_DIR, version_base=None):
        cfg = compose("config", overrides=["+experiment=smoke", "preset=smoke", override, f"runs_dir={tmp_path}/runs"])
    with pytest.raises(UserError) as err:
        make_context(cfg)
    assert message in str(err.value) and "\n" not in str(err.value)
    assert not (tmp_path / "runs").exists()


def test_a_cascade_row_of_an_unknown_model_gets_the_unknown_model_message_not_the_cascade_one(tmp_path):
    """The config check leaves a row's model to the table (table.selected_rows), which names the unknown
    model before anything runs, not the Cascade rule that a known model other than srd would break."""
    from hydra import compose, initialize_config_dir
    from omegaconf import OmegaConf
    from bench.cli import CONF_DIR
    from bench.config_checks import config_problems
    row = "experiment.rows=[{label:a,model:sdr,cascade:true}]"
    with initialize_config_dir(config_dir=CONF_DIR, version_base=None):
        cfg = compose("config", overrides=["+experiment=smoke", "preset=smoke", row])
    assert config_problems(OmegaConf.to_container(cfg, resolve=True)) == []
    done = bench_here(*TINY_CLI, f"runs_dir={tmp_path / 'runs'}", f"results_dir={tmp_path / 'results'}",
                      f"data_dir={tmp_path / 'data'}", row)
    out = done.stdout + done.stderr
    assert done.returncode == 2 and "Traceback" not in out, out[-2000:]
    assert "unknown model 'sdr'" in out and "Cascade" not in out, out[-2000:]
    assert not list((tmp_path / "runs").glob("*/*/run.json")) and not (tmp_path / "data").exists()


def test_a_bad_model_width_on_the_command_line_exits_2_with_one_line_and_no_record(tmp_path):
    done = bench_here(*TINY_CLI, f"runs_dir={tmp_path / 'runs'}", f"results_dir={tmp_path / 'results'}",
                      f"data_dir={tmp_path / 'data'}", "models.edsr.channels=-4")
    out = done.stdout + done.stderr
    assert done.returncode == 2 and "Traceback" not in out, out[-2000:]
    assert "error: bad config (nothing was run): models.edsr.channels=-4" in out, out[-2000:]
    assert not list((tmp_path / "runs").glob("*/*/run.json"))


def test_the_readmes_verify_command_is_one_hydra_accepts():
    import re
    from hydra import compose, initialize_config_dir
    from bench.cli import CONF_DIR
    commands = re.findall(r"`(\+experiment=data [^`]*verify=true)`", (REPO / "README.md").read_text())
    assert commands
    for command in commands:
        with initialize_config_dir(config_dir=CONF_DIR, version_base=None):
            assert compose("config", overrides=command.split()).experiment.verify is True


def _killed_after_a_checkpoint(runs_dir, sleep_s=0.0, force=False) -> None:
    """Another process begins run {'a': 1} (with `force`), writes a checkpoint after `sleep_s` and is
    killed (-9) there: what a kill leaves of a command."""
    child = subprocess.Popen([sys.executable, "-c", (
        "import time; from bench import runs\n"
        f"run = runs.begin({str(runs_dir)!r}, 'train', {{'a': 1}}, force={force})\n"
        f"time.sleep({sleep_s}); (run.dir / 'checkpoint.pt').write_bytes(b'step 1')\n"
        "print('checkpointed', flush=True); time.sleep(60)")], cwd=REPO, stdout=subprocess.PIPE, text=True)
    assert child.stdout.readline().strip() == "checkpointed"
    child.kill()
    child.wait()


def test_a_training_killed_and_resumed_records_the_wall_time_of_both_parts(tmp_path):
    """kill -9 leaves the record "running" with no time of its own: the resumed run counts the killed
    part from its start to its last write (its checkpoint), then its own."""
    _killed_after_a_checkpoint(tmp_path, sleep_s=1.5)
    run = runs.begin(tmp_path, "train", {"a": 1})
    assert 1.4 < run.record["resumed_wall_time_s"] < 5
    time.sleep(0.2)
    done = runs.complete(run, {})
    assert done.record["wall_time_s"] >= run.record["resumed_wall_time_s"] + 0.2


# ---------------------------------------------------------------- a run's files, checked on every read

def _cut_at_a_line_end(path):
    """Cut a CSV after half its lines: it still parses, as a file cut short by a full disk may."""
    lines = path.read_bytes().splitlines(keepends=True)
    path.write_bytes(b"".join(lines[:max(1, len(lines) // 2)]))


@pytest.mark.parametrize("name", ["curve.csv", "val_curve.csv"])
def test_a_cut_curve_that_still_parses_is_named_once_and_rebuilt_from_the_checkpoint(store, caplog, name):
    """The record lists every file with its size and digest: a curve cut at a line end (which parses) is
    named once, however many readers look at it, and written again from the sound checkpoint, byte for
    byte; the table's curve columns and the figure read the whole curve, and nothing is trained."""
    path = _run_dir(store, "train") / name
    whole = path.read_bytes()
    assert json.loads((path.parent / "run.json").read_text())["files"][name]["bytes"] == len(whole)
    _cut_at_a_line_end(path)
    with caplog.at_level("INFO", logger="bench"):
        table = _table(_table_ctx(store), figure=True)
    assert path.read_bytes() == whole and "trained in" not in caplog.text
    assert caplog.text.count(str(path)) == 1 and f"{path} was damaged (" in caplog.text and "is rebuilt" in caplog.text
    assert table["last fifth (dB)"].notna().all()


def test_a_cut_curve_beside_a_damaged_checkpoint_is_trained_again(store, caplog):
    run_dir = _run_dir(store, "train")
    _cut_at_a_line_end(run_dir / "val_curve.csv")
    _cut(run_dir / "checkpoint.pt")
    with caplog.at_level("INFO", logger="bench"):
        _table(_table_ctx(store))
    assert "trained in" in caplog.text
    record = json.loads((run_dir / "run.json").read_text())
    assert not runs.damaged_files(run_dir, record)                  # its files listed again as they are now


def test_a_cut_per_image_file_is_never_reused_its_evaluation_is_computed_again(store, caplog):
    """The issue's case: per_image.csv cut at a line end parsed, and `score --against` blamed the outputs.
    Readers now see no per-frame scores; a table computes the evaluation again, to the same bytes."""
    from bench import archived
    path = _run_dir(store, "eval") / "per_image.csv"
    whole = path.read_bytes()
    _cut_at_a_line_end(path)
    with caplog.at_level("INFO", logger="bench"):
        assert archived.read_per_image(path.parent) is None
        _table(_table_ctx(store))
    assert caplog.text.count(f"{path} is damaged") == 1 and "eval E: reusing" not in caplog.text
    assert pd.read_csv(path).drop(columns="time_ms").equals(pd.read_csv(io.BytesIO(whole)).drop(columns="time_ms"))


def test_the_verify_command_names_each_damaged_file_of_a_store_or_an_archive_and_exits_1(store, tmp_path):
    """`python -m bench.archived DIR --verify`: one line per damaged file, a summary, exit 1; a sound store
    exits 0. It changes nothing."""
    def verify(folder):
        return python_process("-m", "bench.archived", folder, "--verify", timeout=120)
    ctx = _table_ctx(store, runs_archive=tmp_path / "archive")
    _table(ctx)                                                      # archives the store's runs
    sound = verify(store / "runs")
    assert sound.returncode == 0 and "3 runs, 3 with listed files checked, 0 damaged" in sound.stdout, sound.stdout
    weights = next((tmp_path / "archive" / "train").glob("*/weights.fp16.pt"))
    weights.write_bytes(weights.read_bytes()[:-10] + b"0123456789")  # same size, other bytes
    before = sorted((p, p.read_bytes()) for p in (tmp_path / "archive").rglob("*") if p.is_file())
    out = verify(tmp_path / "archive")
    assert out.returncode == 1 and out.stdout.splitlines()[0] == f"{weights}: its digest differs from the recorded one"
    assert "1 damaged" in out.stdout.splitlines()[-1]
    assert sorted((p, p.read_bytes()) for p in (tmp_path / "archive").rglob("*") if p.is_file()) == before


def test_an_interrupted_forced_run_is_resumed_by_the_next_forced_command_and_says_so(tmp_path, caplog):
    """force=true computes a run once per command; a forced command killed mid-run leaves a checkpoint,
    which the next force=true command resumes (the log says so and how to start over), in a new process."""
    _killed_after_a_checkpoint(tmp_path, force=True)
    with caplog.at_level("INFO", logger="bench"):
        run = runs.begin(tmp_path, "train", {"a": 1}, force=True)
    assert (run.dir / "checkpoint.pt").read_bytes() == b"step 1" and run.record["forced"]
    assert "which an earlier force=true command started and left running" in caplog.text
    assert f"delete {run.dir} to start it over" in caplog.text
    runs.complete(run, {})
    again = runs.begin(tmp_path, "train", {"a": 1}, force=True)  # complete since this command started: once
    assert again.reused


def test_a_record_rebuilt_from_a_checkpoint_keeps_the_checkpoints_training_time(store, caplog):
    """A training's run.json cut in half: the finished checkpoint completes it again without a step; its
    recorded time is the checkpoint's optimisation seconds, not the rebuild's, and the record says so."""
    import torch
    run_dir = _run_dir(store, "train")
    elapsed = torch.load(run_dir / "checkpoint.pt", weights_only=False)["elapsed_s"]
    _cut(run_dir / "run.json")
    with caplog.at_level("INFO", logger="bench"):
        _edsr_training(_table_ctx(store))
    record = json.loads((run_dir / "run.json").read_text())
    assert record["status"] == "complete" and record["metrics"]["resumed_from_step"] == 2
    assert record["resumed_wall_time_s"] == elapsed and record["wall_time_s"] >= elapsed
    assert record["earlier_wall_time"].startswith("lost with its record")
    assert caplog.text.count(f"{run_dir / 'run.json'} is damaged") == 1


def test_rendered_frames_take_the_umasks_mode_as_their_records_do(rendered):
    root, hr, _ = rendered
    umask = os.umask(0)
    os.umask(umask)
    modes = {p.suffix: p.stat().st_mode & 0o777 for p in (root / "data").rglob("*") if p.suffix in (".exr", ".json")}
    assert modes == {".exr": 0o666 & ~umask, ".json": 0o666 & ~umask}


def test_a_full_disk_under_data_dir_names_data_dir(tmp_path):
    """ENOSPC while writing a frame: the line names data_dir (not runs_dir) and the advice sets data_dir."""
    inject = tmp_path / "inject"
    inject.mkdir()
    (inject / "sitecustomize.py").write_text(
        "import errno, os\nfrom bench import exrio\n"
        "def full(path, *a, **k):\n    raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), os.fspath(path))\n"
        "exrio.write_exr = full\n")
    out, _ = _bench(tmp_path, env={"PYTHONPATH": os.pathsep.join([str(inject), str(REPO)])}).communicate(timeout=300)
    (line,) = [x for x in out.splitlines() if x.startswith("error:")]
    assert f"no space left on the device under data_dir={tmp_path / 'data'}" in line and "set data_dir=..." in line


def test_a_row_whose_model_does_not_import_here_is_left_out_only_when_asked_and_the_caption_says_why(tmp_path, monkeypatch):
    """OIDN needs pyoidn, which the GPU machine lacks (its wheel does not fit a call): with
    experiment.leave_out_unavailable its rows are left out and named with the import's message (the GPU
    job's sota step asks for it; tests/test_gpu_job.py checks the caption); without, the missing package
    is an error before anything runs."""
    import sys
    from hydra import compose, initialize_config_dir
    from omegaconf import OmegaConf
    from bench.cli import CONF_DIR, make_context
    from bench.experiments.table import selected_rows
    import baselines
    monkeypatch.setitem(sys.modules, "pyoidn", None)            # `import pyoidn` raises ModuleNotFoundError
    monkeypatch.delitem(sys.modules, "baselines.oidn", raising=False)   # imported again, without pyoidn
    monkeypatch.delattr(baselines, "oidn", raising=False)               # Hydra looks for the attribute first
    with initialize_config_dir(config_dir=CONF_DIR, version_base=None):
        cfg = compose("config", overrides=["+experiment=sota", "preset=smoke", f"runs_dir={tmp_path}/runs"])
    ctx = make_context(cfg)
    rows = OmegaConf.to_container(cfg.experiment.rows)
    with pytest.raises(UserError, match="baselines.oidn.OIDN"):
        selected_rows(ctx, rows, "srd", None)
    kept, unavailable = selected_rows(ctx, rows, "srd", ["EDSR"], leave_out_unavailable=True)
    assert [r["label"] for r in kept] == ["Input bilinear", "RAE", "KPCN", "CFM", "Ours", "Input bicubic"]
    assert list(unavailable) == ["OIDN at LR then bilinear", "OIDN at HR after bilinear"]
    assert all(why.startswith("ModuleNotFoundError: ") and "pyoidn" in why and "\n" not in why  # as on a machine without it
               for why in unavailable.values())
    for target in ("baselines.oidnn.OIDN", "torch.nn.NoSuchLayer"):   # typos, not a machine's lack: errors still
        typo = [{"label": "typo", "model": "bilinear", "overrides": {"_target_": target}}]
        with pytest.raises(UserError, match=target):
            selected_rows(ctx, typo, "srd", None, leave_out_unavailable=True)
