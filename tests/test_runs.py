import json
import logging
import os
import time

import pytest
import torch

from bench import runs


def test_hash_ignores_key_order_and_changes_with_values():
    assert runs.config_hash({"a": 1, "b": {"c": 2}}) == runs.config_hash({"b": {"c": 2}, "a": 1})
    assert runs.config_hash({"a": 1}) != runs.config_hash({"a": 2})


def test_begin_complete_reuse_and_force(tmp_path, monkeypatch):
    ident = {"model": "x", "steps": 3}
    run = runs.begin(tmp_path, "train", ident, seed=0, label="x")
    assert not run.reused and run.record["status"] == "running"
    assert runs.lookup(tmp_path, "train", ident) is None          # running is not reusable
    (run.dir / "artifact.txt").write_text("weights")
    runs.complete(run, {"relMSE": 0.5})
    again = runs.begin(tmp_path, "train", ident)
    assert again.reused and again.metrics["relMSE"] == 0.5
    assert runs.begin(tmp_path, "train", ident, force=True).reused   # computed since this command started
    monkeypatch.setattr(runs, "COMMAND_STARTED_S", time.time())      # a later command
    forced = runs.begin(tmp_path, "train", ident, force=True)
    assert not forced.reused and not (forced.dir / "artifact.txt").exists()


def test_interrupted_run_keeps_its_directory_for_resume(tmp_path):
    ident = {"model": "y"}
    run = runs.begin(tmp_path, "train", ident)
    (run.dir / "checkpoint.pt").write_text("partial")
    reopened = runs.begin(tmp_path, "train", ident)
    assert not reopened.reused and (reopened.dir / "checkpoint.pt").read_text() == "partial"


def test_record_has_provenance(tmp_path):
    run = runs.complete(runs.begin(tmp_path, "eval", {"m": 1}, seed=3, device="cpu"), {"PSNR": float("inf")})
    record = json.loads((run.dir / "run.json").read_text())
    for key in ("hash", "identity", "config", "git_commit", "git_dirty", "seed", "host", "device",
                "versions", "wall_time_s", "metrics", "status"):
        assert key in record, key
    assert record["versions"]["torch"].startswith("2.13")
    assert record["seed"] == 3


def test_load_is_one_tidy_frame(tmp_path):
    for i in range(3):
        runs.complete(runs.begin(tmp_path, "eval", {"m": i, "opt": {"d": i * 2}}, label=f"m{i}"),
                      {"relMSE": 0.1 * i})
    runs.begin(tmp_path, "train", {"m": 9})
    df = runs.load(tmp_path)
    assert len(df) == 4
    evals = runs.load(tmp_path, kind="eval").sort_values("label")
    assert list(evals["metric.relMSE"]) == pytest.approx([0.0, 0.1, 0.2])
    assert list(evals["cfg.opt.d"]) == [0, 2, 4]


def test_unwritable_runs_dir_gives_clear_error(tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("not a directory")
    with pytest.raises(PermissionError, match="not writable"):
        runs.begin(blocker / "sub", "train", {"m": 1})


def _probe_often(path, times):
    for _ in range(times):
        runs.ensure_writable(path)


def test_processes_started_together_all_find_the_store_writable(tmp_path):
    """Each process proves the store writable with a probe of its own: with one shared probe name, one
    process deleted another's and that one reported a writable store as unwritable (seen 2026-11-25, three
    table shards started at once)."""
    import multiprocessing
    ctx = multiprocessing.get_context("fork")
    procs = [ctx.Process(target=_probe_often, args=(tmp_path, 300)) for _ in range(4)]
    for proc in procs:
        proc.start()
    for proc in procs:
        proc.join(60)
    assert [proc.exitcode for proc in procs] == [0] * 4
    assert not list(tmp_path.iterdir())                              # no probe left behind


def _compute_in_child(runs_dir, started, release):
    run = runs.begin(runs_dir, "train", {"a": 1})
    started.set()
    release.wait(30)
    runs.complete(run, {"loss": 0.5, "by": "child"})


def test_second_process_waits_for_a_run_in_progress_then_reuses_it(tmp_path):
    import multiprocessing as mp
    import threading

    ctx = mp.get_context("spawn")
    started, release = ctx.Event(), ctx.Event()
    child = ctx.Process(target=_compute_in_child, args=(str(tmp_path), started, release))
    child.start()
    assert started.wait(60)
    result = {}
    waiter = threading.Thread(target=lambda: result.update(run=runs.begin(tmp_path, "train", {"a": 1})))
    waiter.start()
    waiter.join(1.0)
    assert waiter.is_alive(), "begin() must wait while another process computes the same run"
    release.set()
    waiter.join(30)
    child.join(30)
    assert result["run"].reused and result["run"].metrics["by"] == "child"


def test_a_run_begun_again_in_the_same_process_does_not_deadlock(tmp_path):
    first = runs.begin(tmp_path, "train", {"a": 1})
    runs.fail(first, "boom")
    again = runs.begin(tmp_path, "train", {"a": 1})
    assert not again.reused
    third = runs.begin(tmp_path, "train", {"a": 1})  # the earlier one never released (e.g. an exception)
    runs.complete(third, {"loss": 1.0})
    assert runs.begin(tmp_path, "train", {"a": 1}).reused


def test_code_fingerprint_follows_imports_not_the_whole_project():
    srd = runs.code_fingerprint(["bench.models.srd.SRDNet", "bench.train"])
    assert {"bench/models/srd.py", "bench/train.py", "bench/nn/deform.py", "bench/losses.py"} <= set(srd)
    assert "baselines/kpcn.py" not in srd and "bench/experiments/pipeline.py" not in srd
    kpcn = runs.code_fingerprint(["baselines.kpcn.KPCN"])
    assert "baselines/kpcn.py" in kpcn and "bench/models/srd.py" not in kpcn


def test_source_hash_ignores_comments_and_docstrings_not_code(tmp_path):
    def source_hash(text, name):
        path = tmp_path / name
        path.write_text(text)
        return runs.source_hash(path)
    base = source_hash('"""Doc."""\ndef f(x):\n    """What f does."""\n    return x + 1\n', "a.py")
    assert source_hash('# a comment\ndef f(x):\n\n    return x + 1  # why\n', "b.py") == base
    assert source_hash('def f(x):\n    return x + 2\n', "c.py") != base


def test_a_run_of_changed_code_is_recomputed_unless_reuse_stale(tmp_path):
    ident = {"model": "z"}
    old = {"bench/models/srd.py": "aaaa", "bench/train.py": "bbbb"}
    new = {"bench/models/srd.py": "cccc", "bench/train.py": "bbbb"}
    run = runs.begin(tmp_path, "train", ident, code=old)
    (run.dir / "weights.pt").write_text("old code's weights")
    runs.complete(run, {"PSNR": 30.0})
    assert runs.begin(tmp_path, "train", ident, code=old).reused
    kept = runs.begin(tmp_path, "train", ident, code=new, reuse_stale=True)
    assert kept.reused and kept.stale == ["bench/models/srd.py"]
    redo = runs.begin(tmp_path, "train", ident, code=new)
    assert not redo.reused and not (redo.dir / "weights.pt").exists()
    assert redo.record["code"] == new


def test_an_interrupted_run_of_other_code_does_not_resume_its_checkpoint(tmp_path):
    ident = {"model": "w"}
    run = runs.begin(tmp_path, "train", ident, code={"bench/train.py": "old"})
    (run.dir / "checkpoint.pt").write_text("partial, old code")
    run.release()
    same = runs.begin(tmp_path, "train", ident, code={"bench/train.py": "old"})
    assert (same.dir / "checkpoint.pt").exists()
    same.release()
    changed = runs.begin(tmp_path, "train", ident, code={"bench/train.py": "new"})
    assert not (changed.dir / "checkpoint.pt").exists()


def test_runs_recorded_before_code_fingerprints_are_trusted(tmp_path):
    ident = {"model": "v"}
    runs.complete(runs.begin(tmp_path, "train", ident), {"PSNR": 1.0})
    assert runs.begin(tmp_path, "train", ident, code={"bench/train.py": "x"}).reused


def test_a_run_left_running_by_a_dead_process_shows_as_abandoned_and_is_taken_over(tmp_path, caplog):
    import subprocess
    import sys
    from pathlib import Path
    code = (f"import sys; sys.path.insert(0, {str(Path(runs.__file__).parent.parent)!r}); from bench import runs; "
            f"runs.begin({str(tmp_path)!r}, 'train', {{'model': 'killed'}}); import os; os._exit(0)")
    subprocess.run([sys.executable, "-c", code], check=True)   # exits without completing or failing
    live = runs.begin(tmp_path, "train", {"model": "live"})
    status = runs.load(tmp_path).set_index("cfg.model")["status"]
    assert status["killed"] == "abandoned" and status["live"] == "running"
    live.release()
    with caplog.at_level(logging.INFO, logger="bench"):
        taken = runs.begin(tmp_path, "train", {"model": "killed"})   # the next request says so and takes it over
    assert "which is gone (abandoned); taking it over" in caplog.text and taken.record["pid"] == os.getpid()
    taken.release()


def test_archive_keeps_a_finished_run_that_a_lost_store_gets_back(tmp_path):
    store, archive = tmp_path / "runs", tmp_path / "archive"
    ident = {"model": "z", "seed": 0}
    run = runs.begin(store, "train", ident, label="z")
    (run.dir / "curve.csv").write_text("step,loss\n1,0.5\n")
    (run.dir / "checkpoint.pt").write_text("weights and optimizer")
    assert runs.archive(run, archive, ("curve.csv",)) is None           # running: nothing to keep yet
    runs.complete(run, {"relMSE": 0.25})
    kept = runs.archive(run, archive, ("curve.csv", "absent.csv"), write=lambda d: (d / "slim.pt").write_text("w"))
    assert sorted(p.name for p in kept.iterdir()) == ["curve.csv", runs.RECORD, "slim.pt"]
    assert not [p for p in (archive / runs.PARTIAL).iterdir() if p.is_dir()]  # no half-written copy left
    stamp = (kept / runs.RECORD).stat().st_mtime_ns
    assert runs.archive(run, archive, ("curve.csv",)) == kept and (kept / runs.RECORD).stat().st_mtime_ns == stamp

    lost = tmp_path / "fresh"                                            # a new clone: no run store
    assert runs.lookup(lost, "train", ident) is None
    back = runs.begin(lost, "train", ident, archive=archive)
    assert back.reused and back.metrics["relMSE"] == 0.25 and (back.dir / "curve.csv").read_text().startswith("step")
    assert not runs.restore(lost, archive, "train", back.hash)           # already there: left alone


def test_find_record_looks_in_the_store_then_in_each_archive_in_turn(tmp_path):
    store, first, second = tmp_path / "runs", tmp_path / "a", tmp_path / "b"
    run = runs.complete(runs.begin(store, "eval", {"row": 1}), {})
    assert runs.find_record("eval", run.hash, store, [first, second])[0] == run.dir / runs.RECORD
    runs.archive(run, second, ())
    lost = tmp_path / "lost"
    assert runs.find_record("eval", run.hash, lost, [first, second])[0] == second / "eval" / run.hash / runs.RECORD
    runs.archive(run, first, ())
    assert runs.find_record("eval", run.hash, lost, [first, second])[0].is_relative_to(first)
    assert runs.find_record("train", run.hash, store, [first, second])[0] is None
    assert not lost.exists()                                             # read where it is, not restored


def test_a_file_over_the_archive_limit_stays_out_and_the_run_restores_without_it(tmp_path, monkeypatch, caplog):
    store, archive = tmp_path / "runs", tmp_path / "archive"
    monkeypatch.setattr(runs, "ARCHIVED_FILE_MAX_BYTES", 100)
    run = runs.begin(store, "train", {"model": "big"})
    (run.dir / "curve.csv").write_text("step,loss\n1,0.5\n")
    runs.complete(run, {"relMSE": 0.2})
    with caplog.at_level(logging.INFO, logger="bench"):
        kept = runs.archive(run, archive, ("curve.csv",), write=lambda d: (d / "checkpoint.pt").write_bytes(bytes(101)))
    assert sorted(p.name for p in kept.iterdir()) == ["curve.csv", runs.RECORD]
    assert "without checkpoint.pt" in caplog.text
    back = runs.begin(tmp_path / "fresh", "train", {"model": "big"}, archive=archive)
    assert back.reused and back.metrics["relMSE"] == 0.2 and not (back.dir / "checkpoint.pt").exists()


def test_a_complete_run_without_a_file_its_caller_needs_is_computed_again_from_scratch(tmp_path, caplog):
    """begin(needs=...): the weights an archive left out are computed again, under the run's lock (a
    second process waiting on it then reuses the result) and from scratch (no earlier time, no files)."""
    ident = {"model": "big"}
    done = runs.complete(runs.begin(tmp_path, "train", ident), {"relMSE": 0.2, "wall_time_s": 60.0})
    (done.dir / "curve.csv").write_text("step,loss\n1,0.5\n")
    assert runs.begin(tmp_path, "train", ident).reused                  # no needs: reused as it is
    with caplog.at_level(logging.INFO, logger="bench"):
        again = runs.begin(tmp_path, "train", ident, needs=("checkpoint.pt",))
    assert not again.reused and "has no checkpoint.pt" in caplog.text
    assert list(again.dir.iterdir()) == [again.dir / runs.RECORD] and "resumed_wall_time_s" not in again.record
    torch.save({"model": {}}, again.dir / "checkpoint.pt")        # a checkpoint that reads
    runs.complete(again, {"relMSE": 0.2})
    assert runs.begin(tmp_path, "train", ident, needs=("checkpoint.pt",)).reused


def test_an_interrupted_run_in_the_store_resumes_rather_than_being_replaced_from_the_archive(tmp_path):
    store, archive, other = tmp_path / "runs", tmp_path / "archive", tmp_path / "other"
    ident = {"model": "w"}
    done = runs.begin(other, "train", ident)
    runs.archive(runs.complete(done, {"relMSE": 0.1}), archive)
    partial = runs.begin(store, "train", ident)
    (partial.dir / "checkpoint.pt").write_text("partial")
    partial.release()
    again = runs.begin(store, "train", ident, archive=archive)
    assert not again.reused and (again.dir / "checkpoint.pt").read_text() == "partial"


def test_a_stale_run_in_the_store_gives_way_to_an_archived_run_of_current_code(tmp_path):
    """Another machine recomputed the run after a code change and archived it: this store's older run
    is replaced by it, not trained again; an archived run as stale as the store's changes nothing."""
    store, archive = tmp_path / "runs", tmp_path / "archive"
    ident, old, new = {"model": "t"}, {"bench/m.py": "1"}, {"bench/m.py": "2"}
    runs.complete(runs.begin(store, "train", ident, code=old), {"PSNR": 30.0})
    stale_archive = tmp_path / "stale_archive"
    runs.archive(runs.complete(runs.begin(tmp_path / "b", "train", ident, code=old), {"PSNR": 29.0}), stale_archive)
    again = runs.begin(store, "train", ident, code=new, archive=stale_archive)
    assert not again.reused                                              # both stale: recomputed
    again.release()
    runs.complete(runs.begin(store, "train", ident, code=old, force=True), {"PSNR": 30.0})
    runs.archive(runs.complete(runs.begin(tmp_path / "c", "train", ident, code=new), {"PSNR": 31.0}), archive)
    current = runs.begin(store, "train", ident, code=new, archive=archive)
    assert current.reused and current.metrics["PSNR"] == 31.0 and not current.stale


def test_the_archive_keeps_only_what_current_code_computed_and_partial_copies_are_never_runs(tmp_path):
    store, archive = tmp_path / "runs", tmp_path / "archive"
    run = runs.complete(runs.begin(store, "eval", {"model": "v"}), {"relMSE": 0.3})
    run.stale = ["bench/evaluate.py"]                                    # reused with reuse_stale=true
    assert runs.archive(run, archive) is None and not (archive / "eval").exists()
    leftover = store / runs.PARTIAL / f"eval.{run.hash}.123"             # a restore killed halfway
    leftover.mkdir(parents=True)
    (leftover / runs.RECORD).write_text((run.dir / runs.RECORD).read_text())
    assert list(runs.load(store)["hash"]) == [run.hash]


def test_a_run_directory_made_empty_before_the_lock_is_filled_from_the_archive(tmp_path):
    """begin makes the run's directory before it waits for the lock; a restore must still fill it."""
    store, archive = tmp_path / "runs", tmp_path / "archive"
    ident = {"model": "u"}
    runs.archive(runs.complete(runs.begin(tmp_path / "elsewhere", "train", ident), {"PSNR": 30.0}), archive)
    (store / "train" / runs.config_hash(ident)).mkdir(parents=True)
    assert runs.begin(store, "train", ident, archive=archive).reused


def test_an_evaluations_trainings_read_back_in_stage_order():
    assert runs.split_trainings(runs.join_trainings(["stage1", "stage2"])) == ["stage1", "stage2"]
    assert runs.trainings_of({"metrics": {"train_run": "a+b"}}) == ["a", "b"]
    assert runs.trainings_of({"metrics": {"train_run": None}}) == runs.trainings_of({}) == []


def test_a_path_fault_is_said_in_one_line_naming_the_path(tmp_path):
    (tmp_path / "afile").write_text("")
    for make in (lambda: (tmp_path / "afile").mkdir(parents=True, exist_ok=True),
                 lambda: (tmp_path / "afile" / "sub").mkdir(parents=True)):
        with pytest.raises(runs.PATH_ERRORS) as err:
            make()
        line = runs.error_line(err.value)
        assert line.startswith(str(tmp_path / "afile")) and "a file stands where a folder" in line
    with pytest.raises(IsADirectoryError) as err:
        tmp_path.joinpath().open("w")
    assert runs.error_line(err.value) == f"{tmp_path}: a folder stands where a file is needed (Is a directory)"
