"""Reuse through code changes: a real edit makes runs stale and a comment does not; `+experiment=adopt`
re-stamps the runs a change moves no number of, and holds a training of another render to its recorded
code rebuilt from git (bench/experiments/adopt.py, replay.py, recorded_code.py)."""
import json
import subprocess
import sys
from pathlib import Path

import pandas as pd
import pytest
import torch

from bench.errors import UserError
from conftest import bench, copy_of_project_and_store, smoke_context


def test_a_real_edit_to_a_model_file_makes_its_trainings_stale_and_a_comment_does_not(smoke_dirs, tmp_path):
    """Code identity on real source files: a copy of the project, its model file edited, run against a
    copy of the smoke run store. A comment keeps the recorded training; a statement makes it recompute
    (the log names the file) unless reuse_stale=true."""
    project, copied = copy_of_project_and_store(smoke_dirs, tmp_path)
    model_file = project / "bench" / "models" / "srd.py"

    def run(*extra):
        return bench("+experiment=smoke", *copied, *extra, cwd=project)

    model_file.write_text(model_file.read_text() + "\n# a comment changes no result\n")
    out = run()
    assert out.returncode == 0 and "train Ours: reusing run" in out.stdout + out.stderr, out.stderr[-2000:]
    model_file.write_text(model_file.read_text() + "EDITED = True\n")
    out = run("reuse_stale=true")
    assert out.returncode == 0, out.stderr[-2000:]
    assert "although its code changed since (bench/models/srd.py), as reuse_stale=true asks" in out.stdout + out.stderr
    proc = subprocess.Popen([sys.executable, "-m", "bench", "+experiment=smoke", *copied], cwd=project,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    seen = ""
    for line in proc.stdout:                      # stop as soon as it says it recomputes: no need to train
        seen += line
        if "its code changed since it was recorded" in line:
            break
    proc.kill()
    proc.communicate()
    assert "recomputing run" in seen and "(bench/models/srd.py)" in seen, seen[-2000:]


def test_adopt_holds_the_code_only_to_evaluations_of_todays_frames(monkeypatch):
    """An evaluation scored against references rendered again since (other settings: another data
    fingerprint; the same settings on another host: another render digest) cannot witness for the code:
    its numbers moved with the data. Nor can a training's record, unless it trained on this render of its
    split: the recorded code, rebuilt, is replayed against the current instead."""
    import types
    from bench import runs
    from bench.experiments import adopt
    monkeypatch.setattr(adopt, "evaluation_data", lambda ctx: types.SimpleNamespace(data_dir=Path(".")))
    monkeypatch.setattr(adopt, "splits_on_disk", lambda frames: {"val"})
    monkeypatch.setattr(adopt, "data_fingerprint", lambda ctx, split: f"today-{split}")
    monkeypatch.setattr(adopt, "render_digest", lambda ctx, split: f"host-a-{split}")

    def evaluation(render=None, **identity):
        identity = {"split": "val", "fast_path": "fp32", "tile": None, **identity}
        return runs.Run("eval", "0" * 16, Path("."), {"identity": identity,
                                                      "metrics": {"render": render}})
    assert adopt.scored_here(None, evaluation(data="today-val"))
    assert adopt.scored_here(None, evaluation(data="today-val", render="host-a-val"))
    assert not adopt.scored_here(None, evaluation(data="today-val", render="host-b-val"))
    assert not adopt.scored_here(None, evaluation(data="before-val"))
    assert not adopt.scored_here(None, evaluation(data="today-val", fast_path="bf16"))
    assert not adopt.scored_here(None, evaluation(data="today-test", split="test"))  # not on disk

    def training(render):
        return runs.Run("train", "0" * 16, Path("."), {"metrics": {"render": render}})
    assert not adopt.trained_here(None, training(None))                  # recorded before digests
    assert adopt.trained_here(None, training("host-a-train"))
    assert not adopt.trained_here(None, training("host-b-train"))


def test_adopt_stops_on_ctrl_c_or_sigterm_during_a_replay(monkeypatch, tmp_path):
    """A signal in a replayed training stops the command (exit 130/143), not just that group's check."""
    from bench import runs
    from bench.experiments import adopt
    from bench.train import TrainingInterrupted
    witness = runs.Run("train", "0" * 16, tmp_path, {"identity": {"model": {"_target_": "x"}}, "label": "row"})
    (tmp_path / "checkpoint.pt").write_text("weights")                   # a witness has them
    monkeypatch.setattr(adopt, "stale_groups", lambda ctx: {"g": [witness]})
    monkeypatch.setattr(adopt, "restore_archive", lambda ctx: 0)
    monkeypatch.setattr(adopt, "render_what_the_checks_read", lambda *a: None)  # no frames here
    monkeypatch.setattr(adopt, "stale_untrained_evaluations", lambda ctx: [])   # no store here
    monkeypatch.setattr(adopt, "code_of", lambda *a: {})
    monkeypatch.setattr(runs, "code_changes", lambda *a: [])

    def interrupted(*args):
        raise TrainingInterrupted("SIGTERM at step 3 of 10", 15)
    monkeypatch.setattr(adopt, "check_training", interrupted)
    monkeypatch.setattr(adopt, "trained_here", lambda *a: True)
    with pytest.raises(TrainingInterrupted):
        adopt.run(None, "adopt", 10, 1e-5, 1e-3, 1e-3, dry_run=True)


def test_adopt_renders_the_training_split_and_val_where_missing_and_nothing_else(monkeypatch, tmp_path):
    """A fresh clone adopts after rendering what the checks read: the training split for the replays and
    val for the scoring (with the buffers of the stale groups' tasks), not the whole dataset; nothing
    when nothing is stale, the scoring's buffers in the test frames when today's frames have test and not
    val, and never your own data."""
    import dataclasses
    from bench import runs
    from bench.experiments import adopt
    rendered = []
    monkeypatch.setattr(adopt, "ensure_data", lambda ctx, passes, splits: rendered.append((passes, splits)))
    ctx = smoke_context(runs_dir=tmp_path / "runs", data_dir=tmp_path / "no data")
    group = {"g": [runs.Run("train", "0" * 16, tmp_path, {"identity": {"task": "srd"}})]}
    adopt.render_what_the_checks_read(ctx, group, [])
    assert rendered == [({"lr_noisy", "lr_gbuf", "hr_noisy", "hr_ref"}, {"train", "val"})]
    adopt.render_what_the_checks_read(ctx, {}, [])
    assert len(rendered) == 1                                         # nothing stale: nothing rendered
    monkeypatch.setattr(adopt, "splits_on_disk", lambda ctx, as_specified: {"test"})
    adopt.render_what_the_checks_read(ctx, group, [])
    assert rendered[-1][1] == {"train", "test"}                       # test scores as well as val: its buffers
    monkeypatch.setattr(adopt, "splits_on_disk", lambda ctx, as_specified: {"val"})
    adopt.render_what_the_checks_read(ctx, group, [])                 # a val rendered for other tasks gets
    assert rendered[-1] == ({"lr_noisy", "lr_gbuf", "hr_noisy", "hr_ref"}, {"train", "val"})  # the srd task's
    adopt.render_what_the_checks_read(dataclasses.replace(ctx, render_data=False), group, [])
    assert len(rendered) == 3                                         # your own frames: as they are
    untrained = runs.Run("eval", "1" * 16, tmp_path, {"identity": {"trained": {"task": "denoise"}}})
    monkeypatch.setattr(adopt, "splits_on_disk", lambda ctx, as_specified: set())
    adopt.render_what_the_checks_read(ctx, {}, [untrained])
    assert rendered[-1][1] == {"val"}                                 # an untrained model's evaluation: val only


def _archived_stale_training(tmp_path, name):
    """A complete training recorded by older code (label "row"), with its checkpoint in the store, archived
    as a table archives it (bench.experiments.training.archive_training); (run, its archived copy)."""
    import torch
    from bench import archived, runs
    run_dir = tmp_path / "runs" / "train" / name
    run_dir.mkdir(parents=True)
    run = runs.Run("train", name, run_dir, {"identity": {"model": {"_target_": "x"}}, "label": "row",
                                            "status": "complete", "code": {"bench/x.py": "old"}})
    run.save()
    torch.save({"model": {"w": torch.zeros(1)}, "ema": None, "optimizer": {}, "step": 3}, run_dir / "checkpoint.pt")
    return run, runs.archive(run, tmp_path / "archive", write=lambda d: archived.write(run_dir, d, run.record))


def test_adopt_archives_what_it_restamps_over_the_stale_copy(monkeypatch, tmp_path):
    """An adopted run's archived copy is replaced by the re-stamped one: a fresh clone restores from the
    archive, and the stale copy there would be trained again."""
    import types
    import torch
    from bench import archived, runs
    from bench.experiments import adopt
    witness, _ = _archived_stale_training(tmp_path, "0" * 16)
    archive = tmp_path / "archive"
    monkeypatch.setattr(adopt, "stale_groups", lambda ctx: {"g": [witness]})
    monkeypatch.setattr(adopt, "code_of", lambda *a: {"bench/x.py": "new"})
    monkeypatch.setattr(adopt, "evaluations_of", lambda *a: [])
    monkeypatch.setattr(adopt, "check_training", lambda *a: {"step 1 loss": 0.0, "later loss": 0.0})
    monkeypatch.setattr(adopt, "trained_here", lambda *a: True)
    monkeypatch.setattr(adopt, "restore_archive", lambda ctx: 0)
    monkeypatch.setattr(adopt, "render_what_the_checks_read", lambda *a: None)  # no frames here
    ctx = types.SimpleNamespace(runs_dir=tmp_path / "runs", runs_archive=archive, results_dir=tmp_path / "results")
    table = adopt.run(ctx, "adopt", 10, 1e-5, 1e-3, 1e-3, dry_run=False)
    assert list(table["verdict"]) == ["adopted"]
    record = runs.read_record(archive / "train" / witness.hash / runs.RECORD)
    assert record["code"] == {"bench/x.py": "new"} and "code_adopted" in record
    assert torch.equal(archived.state_dict(archive / "train" / witness.hash)["w"], torch.zeros(1))  # compact form
    other = runs.Run("train", "1" * 16, tmp_path / "runs" / "train" / ("1" * 16),
                     {"identity": {"model": {"_target_": "y"}}, "label": "next", "status": "interrupted"})
    monkeypatch.setattr(adopt, "stale_groups", lambda ctx: {"h": [other]})       # a later call, another group
    adopt.run(ctx, "adopt", 10, 1e-5, 5e-3, 1e-3, dry_run=True)
    table = pd.read_csv(tmp_path / "results" / "adopt" / "table.csv")
    assert list(table["label"]) == ["row", "next"] and list(table["rtol later steps"]) == [1e-3, 5e-3]


def test_adopt_keeps_runs_through_a_change_that_moves_no_number_and_not_through_one_that_does(smoke_dirs,
                                                                                              tmp_path):
    """+experiment=adopt on a copy of the smoke store: a refactor-like edit (a new function) leaves the
    training stale until adopt replays it, finds the recorded values and re-stamps it, after which the
    table reuses it; an edit that changes the model's output is measured and left stale."""
    project, copied = copy_of_project_and_store(smoke_dirs, tmp_path)
    model_file = project / "bench" / "models" / "srd.py"
    source = model_file.read_text()

    model_file.write_text(source + "\n\ndef _a_helper_nothing_calls_yet():\n    return None\n")
    (record_path,) = [p for p in (tmp_path / "runs" / "train").glob("*/run.json")  # as if killed near its end:
                      if json.loads(p.read_text())["label"] == "Ours"]                # adopted, it resumes
    record = json.loads(record_path.read_text())
    assert len(record["metrics"]["render"]) == 8                    # the render it trained on (adopt compares it)
    record_path.write_text(json.dumps({**record, "status": "interrupted"}))
    out = bench("+experiment=adopt", *copied, cwd=project)
    assert out.returncode == 0, out.stderr[-3000:]
    table = pd.read_csv(tmp_path / "results" / "adopt" / "table.csv")
    assert list(table["verdict"]) == ["adopted"], table.to_string()
    assert table.loc[0, "train steps"] == 10 and table.loc[0, "train step 1 loss"] <= 1e-5 and table.loc[0, "eval frames"] > 0
    out = bench("+experiment=smoke", *copied, cwd=project)
    text = out.stdout + out.stderr
    assert out.returncode == 0 and "resuming from step 12 of 12" in text and "eval Ours: reusing run" in text, \
        text[-3000:]
    out = bench("+experiment=smoke", *copied, cwd=project)
    assert "train Ours: reusing run" in out.stdout + out.stderr

    model_file.write_text(source + "\n\n_forward = SRDNet.forward\nSRDNet.forward = lambda self, *a, **k: "
                          "{n: 1.01 * v for n, v in _forward(self, *a, **k).items()}\n")
    out = bench("+experiment=adopt", *copied, cwd=project)
    assert out.returncode == 0, out.stderr[-3000:]
    table = pd.read_csv(tmp_path / "results" / "adopt" / "table.csv")
    assert table.loc[0, "verdict"].startswith("differs") and table.loc[0, "train step 1 loss"] > 1e-3, table.to_string()


def test_adopt_holds_a_training_of_another_render_to_its_recorded_code_rebuilt_from_git(smoke_dirs, tmp_path):
    """A training whose record names another render of its split cannot witness for the code; adopt
    rebuilds the code it recorded from git history and replays both on today's frames: a refactor is
    adopted (the same numbers, exactly), an edit that scales the output is not."""
    project, copied = copy_of_project_and_store(smoke_dirs, tmp_path)
    git = ["git", "-C", str(project), "-c", "user.name=t", "-c", "user.email=t@t", "-c", "commit.gpgsign=false"]

    def commit():
        subprocess.run([*git, "add", "-A"], check=True, capture_output=True)
        subprocess.run([*git, "commit", "-qm", "code"], check=True, capture_output=True)
    subprocess.run([*git, "init", "-q"], check=True, capture_output=True)
    commit()                                                     # the code the smoke store recorded
    (record_path,) = [p for p in (tmp_path / "runs" / "train").glob("*/run.json")
                      if json.loads(p.read_text())["label"] == "Ours"]
    record = json.loads(record_path.read_text())
    record["metrics"]["render"] = "0badf00d"                      # trained on frames no longer here
    record_path.write_text(json.dumps(record))
    model_file = project / "bench" / "models" / "srd.py"
    model_file.write_text(model_file.read_text() + "\n\ndef _a_helper_nothing_calls_yet():\n    return None\n")
    out = bench("+experiment=adopt", "experiment.steps=3", *copied, cwd=project)
    assert out.returncode == 0, out.stderr[-3000:]
    table = pd.read_csv(tmp_path / "results" / "adopt" / "table.csv").iloc[-1]
    assert table["verdict"] == "adopted" and table["check"] == "recorded code", table.to_string()
    assert table["train step 1 loss"] == 0 and table["train later loss"] == 0 and table["train steps"] == 3
    assert table["eval frames"] > 0 and table["eval PSNR"] == 0, table.to_string()

    commit()                                                     # the adopted code, as a later session finds it
    model_file.write_text(model_file.read_text() + "\n_forward = SRDNet.forward\nSRDNet.forward = lambda self, *a, "
                          "**k: {n: 1.01 * v for n, v in _forward(self, *a, **k).items()}\n")
    out = bench("+experiment=adopt", "experiment.steps=3", *copied, cwd=project)
    assert out.returncode == 0, out.stderr[-3000:]
    table = pd.read_csv(tmp_path / "results" / "adopt" / "table.csv").iloc[-1]
    assert table["verdict"].startswith("differs") and table["check"] == "recorded code", table.to_string()
    assert table["train step 1 loss"] > 1e-3 and table["eval PSNR"] > 1e-4, table.to_string()


def test_adopt_keeps_out_of_the_archive_the_weights_it_left_out(monkeypatch, tmp_path):
    """A training whose archived copy was left without its weights on purpose (docs/runs.md) is archived
    again by adopt from a store that has them: the re-stamped copy stays without them."""
    import types
    from bench import archived, runs
    from bench.experiments import adopt
    run, copy = _archived_stale_training(tmp_path, "2" * 16)
    archive = tmp_path / "archive"
    (copy / archived.WEIGHTS).unlink()                            # left out on purpose, the record relisted
    record = runs.read_record(copy / runs.RECORD)
    record["files"].pop(archived.WEIGHTS)
    (copy / runs.RECORD).write_text(json.dumps(record))
    for name, value in (("stale_groups", lambda ctx: {"g": [run]}), ("code_of", lambda *a: {"bench/x.py": "new"}),
                        ("evaluations_of", lambda *a: []), ("trained_here", lambda *a: True),
                        ("check_training", lambda *a: {"step 1 loss": 0.0, "later loss": 0.0}),
                        ("restore_archive", lambda ctx: 0), ("render_what_the_checks_read", lambda *a: None)):
        monkeypatch.setattr(adopt, name, value)
    ctx = types.SimpleNamespace(runs_dir=tmp_path / "runs", runs_archive=archive, results_dir=tmp_path / "results")
    assert list(adopt.run(ctx, "adopt", 10, 1e-5, 1e-3, 1e-3, dry_run=False)["verdict"]) == ["adopted"]
    record = runs.read_record(copy / runs.RECORD)
    assert record["code"] == {"bench/x.py": "new"} and "code_adopted" in record
    assert not archived.has_weights(copy) and archived.WEIGHTS not in record["files"]


def test_adopt_restamps_a_run_its_archive_kept_without_weights_beside_a_witness_that_has_them(monkeypatch,
                                                                                              tmp_path):
    """An archive leaves big weights out (runs.ARCHIVED_FILE_MAX_BYTES): such a complete run joins its
    group after the runs with weights and is restamped with them; a group with none is checked by its
    training alone, and the table says it had no weights."""
    import types
    import torch
    from bench import runs
    from bench.experiments import adopt
    ident = {"version": runs.IDENTITY_VERSION, "model": {"_target_": "x"}, "data": "d", "seed": 0}
    made = {}
    for seed, weights in ((0, False), (1, True)):
        run = runs.complete(runs.begin(tmp_path / "runs", "train", {**ident, "seed": seed}, seed=seed,
                                       code={"bench/x.py": "old"}), {})
        if weights:
            torch.save({"model": {"w": torch.zeros(1)}, "ema": None}, run.dir / "checkpoint.pt")
        made[weights] = run
    lone = runs.complete(runs.begin(tmp_path / "runs", "train", {**ident, "model": {"_target_": "y"}}, seed=0,
                                    code={"bench/x.py": "old"}), {})
    monkeypatch.setattr(adopt, "split_fingerprint", lambda *a: "d")
    monkeypatch.setattr(adopt, "code_of", lambda *a: {"bench/x.py": "new"})
    groups = sorted(adopt.stale_groups(types.SimpleNamespace(runs_dir=tmp_path / "runs")).values(), key=len)
    assert [[r.hash for r in g] for g in groups] == [[lone.hash], [made[True].hash, made[False].hash]]
    monkeypatch.setattr(adopt, "evaluations_of", lambda *a: [])
    monkeypatch.setattr(adopt, "check_training", lambda *a: {"step 1 loss": 0.0, "later loss": 0.0})
    monkeypatch.setattr(adopt, "trained_here", lambda *a: True)
    monkeypatch.setattr(adopt, "restore_archive", lambda ctx: 0)
    monkeypatch.setattr(adopt, "render_what_the_checks_read", lambda *a: None)  # no frames here
    ctx = types.SimpleNamespace(runs_dir=tmp_path / "runs", runs_archive=None, results_dir=tmp_path / "results")
    table = adopt.run(ctx, "adopt", 10, 1e-5, 1e-3, 1e-3, dry_run=False).set_index("witness")
    assert table.loc[made[True].hash, "verdict"] == "adopted" and table.loc[made[True].hash, "weights"]
    assert table.loc[lone.hash, "verdict"] == "adopted" and not table.loc[lone.hash, "weights"]
    assert runs.read_record(made[False].dir / runs.RECORD)["code"] == {"bench/x.py": "new"}
    assert runs.read_record(lone.dir / runs.RECORD)["code"] == {"bench/x.py": "new"}


def test_adopt_never_adopts_on_a_comparison_of_nothing():
    """A replay that compared no step or no frame has differences of 0 that prove nothing."""
    from bench.experiments.adopt import verdict
    train = {"train step 1 loss": 0.0, "train step 1 grad_norm": 0.0, "train later loss": 0.0, "train steps": 10}
    assert verdict(train, 1e-5, 1e-5, 1e-3) == "adopted"
    assert verdict({**train, "eval PSNR": 0.0, "eval frames": 7}, 1e-5, 1e-5, 1e-3) == "adopted"
    assert verdict({**train, "eval PSNR": 0.0, "eval frames": 0}, 1e-5, 1e-5, 1e-3).startswith("not checked")
    assert verdict({**train, "train steps": 0}, 1e-5, 1e-5, 1e-3).startswith("not checked")
    assert verdict({}, 1e-5, 1e-5, 1e-3).startswith("not checked")
    assert verdict({**train, "train step 1 loss": 2e-5}, 1e-5, 1e-5, 1e-3).startswith("differs (train step 1 loss")
    assert verdict({**train, "train later loss": 2e-3}, 1e-5, 1e-5, 1e-3).startswith("differs (later loss")


def test_adopt_never_takes_a_nan_for_a_match():
    from bench.experiments.adopt import verdict
    from bench.experiments.replay import relative_difference
    nan, inf = float("nan"), float("inf")
    assert relative_difference([nan], [nan]) == inf and relative_difference([1.0], [nan]) == inf
    assert relative_difference([inf], [inf]) == 0.0 and relative_difference([inf], [1.0]) == inf
    assert relative_difference([1.0, 2.0], [1.0, 2.0]) == 0.0
    row = {"train step 1 loss": nan, "train later loss": 0.0, "train steps": 10}
    assert verdict(row, 1e-5, 1e-5, 1e-3).startswith("differs")


def test_the_differential_check_refuses_a_replay_that_did_not_run_the_recorded_code(monkeypatch, tmp_path):
    """The subprocess reports the fingerprint of what it imported; one file that is not the recorded
    version (the rebuilt tree shadowed, a search that picked another blob) fails the check."""
    from bench.experiments import recorded_code, replay
    monkeypatch.setattr(recorded_code, "rebuild", lambda recorded, current, dest, commit=None: dest)
    monkeypatch.setattr(recorded_code, "replay_there", lambda tree, job: {"code": {"bench/x.py": "today"}})
    monkeypatch.setattr(replay.runs, "code_fingerprint", lambda modules: {"bench/x.py": "today"})
    with pytest.raises(UserError, match="not the recorded one: bench/x.py"):
        replay.check_against_recorded_code(None, {"bench/x.py": "recorded"}, ["bench.x"], 3, None, None)


def test_the_differential_check_rebuilds_what_its_harness_imports_beside_an_untrained_rows_evaluator(monkeypatch):
    """An untrained row's evaluation names no trainer, but the replay's harness imports it: the rebuild
    is handed today's trainer too, so that it is taken at the run's commit beside the recorded files
    (recorded_code.rebuild; today's trainer beside an older exposure.py did not import)."""
    from bench.experiments import recorded_code, replay
    handed = {}

    def rebuild(recorded, current, dest, commit=None):
        handed.update(current)
        raise RuntimeError("stop here")
    monkeypatch.setattr(recorded_code, "rebuild", rebuild)
    with pytest.raises(RuntimeError, match="stop here"):
        replay.check_against_recorded_code(None, {}, ["bench.evaluate"], 0, None, None)
    assert {"bench/train.py", "bench/evaluate.py"} <= set(handed)


def test_the_rebuilt_code_takes_a_core_file_neither_fingerprint_names_at_the_runs_commit(tmp_path):
    """An EDSR run's fingerprint does not name models/srd.py, nor a training's the evaluator (today's
    does), but the replay's harness imports both: rebuilt beside an older hdr.py, today's would import
    what that hdr.py lacks. So they are taken at the run's recorded commit; the files the fingerprint
    names at their recorded hashes."""
    import subprocess

    from bench import runs
    from bench.experiments import recorded_code
    repo = tmp_path / "repo"
    (repo / "bench" / "models").mkdir(parents=True)
    (repo / "baselines").mkdir()

    def commit(hdr: str, srd: str) -> str:
        (repo / "bench" / "hdr.py").write_text(hdr)
        (repo / "bench" / "models" / "srd.py").write_text(srd)
        (repo / "bench" / "evaluate.py").write_text(srd)
        (repo / "bench" / "models" / "factory.py").write_text(srd)  # the harness's: always today's
        git = ["git", "-C", str(repo), "-c", "user.name=t", "-c", "user.email=t@t"]
        subprocess.run([*git, "add", "-A"], check=True, capture_output=True)
        subprocess.run([*git, "commit", "-qm", "v"], check=True, capture_output=True)
        return subprocess.run([*git, "rev-parse", "HEAD"], capture_output=True, text=True).stdout.strip()

    subprocess.run(["git", "init", "-q", str(repo)], check=True)
    then = commit("def to_network(x):\n    return x\n", "from bench.hdr import to_network\n")
    commit("def transforms(mode):\n    return mode\n", "from bench.hdr import transforms\n")
    old_hdr = tmp_path / "hdr_then.py"
    old_hdr.write_text("def to_network(x):\n    return x\n")
    recorded = {"bench/hdr.py": runs.source_hash.__wrapped__(old_hdr)}
    current = {path: runs.source_hash.__wrapped__(repo / path) for path in ("bench/hdr.py", "bench/evaluate.py")}
    for at, srd in ((then, "from bench.hdr import to_network\n"), (None, "from bench.hdr import transforms\n")):
        dest = recorded_code.rebuild(recorded, current, tmp_path / f"tree-{at}", at, repo=repo)
        assert (dest / "bench" / "hdr.py").read_text() == old_hdr.read_text()
        assert (dest / "bench" / "models" / "srd.py").read_text() == srd  # without the commit: today's
        assert (dest / "bench" / "evaluate.py").read_text() == srd
        assert (dest / "bench" / "models" / "factory.py").read_text() == "from bench.hdr import transforms\n"


def test_the_recorded_code_loads_weights_renamed_since_by_order_and_only_where_every_shape_matches(
        tmp_path, monkeypatch):
    """The archive's weights carry today's parameter names; the recorded code may predate a rename. Its
    replay loads them by order where every shape matches, and refuses weights of another architecture;
    today's code loads by name only, as the tables do."""
    from bench import archived
    from bench.experiments import replay
    from bench.experiments.replay import _load_recorded

    class Then(torch.nn.Module):  # today's model under the names it had before a rename
        def __init__(self, width=4):
            super().__init__()
            self.old_head, self.old_tail = torch.nn.Conv2d(3, width, 3), torch.nn.Conv2d(width, 3, 1)

    class Now(torch.nn.Module):
        def __init__(self):
            super().__init__()
            self.head, self.tail = torch.nn.Conv2d(3, 4, 3), torch.nn.Conv2d(4, 3, 1)

    archived.write_weights(Now().state_dict(), tmp_path / archived.WEIGHTS)
    saved = archived.state_dict(tmp_path)
    with pytest.raises(RuntimeError, match="Missing key|Unexpected key"):
        _load_recorded(Then(), tmp_path)
    monkeypatch.setattr(replay, "BY_ORDER", True)  # as replay.main sets it in the recorded code's subprocess
    loaded = _load_recorded(Then(), tmp_path).state_dict()
    assert all(torch.equal(a, b) for a, b in zip(loaded.values(), saved.values()))
    with pytest.raises(RuntimeError, match="Missing key"):    # by order too, shapes differ: the names' error
        _load_recorded(Then(width=5), tmp_path)


def test_adopt_restamps_the_evaluations_of_trainings_it_adopted_only_once_all_their_trainings_are_current(tmp_path):
    """An evaluation is re-stamped by the call that adopted one of its trainings (whose check scored the
    witness with today's evaluator), once every training it scored runs today's code (a Cascade's stages
    may be adopted in different calls); never one whose trainings were current before: nothing checked
    its evaluator."""
    import types
    from bench import runs
    from bench.experiments.adopt import evaluation_code, evaluations_to_restamp
    from bench.experiments.context import TRAINING_CODE, code_of
    cfg = {"_target_": "baselines.edsr.EDSR", "channels": 8, "blocks": 2}
    ctx = types.SimpleNamespace(runs_dir=tmp_path)

    def record(kind, h, **fields):
        (tmp_path / kind / h).mkdir(parents=True)
        (tmp_path / kind / h / runs.RECORD).write_text(json.dumps({"kind": kind, "hash": h, "status": "complete", **fields}))
    today = code_of(cfg, *TRAINING_CODE)
    record("train", "a" * 16, identity={"model": cfg}, code=today)
    record("train", "b" * 16, identity={"model": cfg}, code={**today, "bench/train.py": "old"})
    default = {"version": runs.IDENTITY_VERSION, "fast_path": "fp32", "tile": None}
    record("eval", "e" * 16, identity=default, metrics={"train_run": "a" * 16}, code={"bench/evaluate.py": "old"})
    record("eval", "f" * 16, identity=default, metrics={"train_run": "a" * 16 + "+" + "b" * 16},
           code={"bench/evaluate.py": "old"})
    assert evaluations_to_restamp(ctx, set()) == []                          # nothing adopted by this call
    assert [e.hash for e in evaluations_to_restamp(ctx, {"a" * 16})] == ["e" * 16]  # "f": its other stage is stale
    assert evaluation_code(ctx, evaluations_to_restamp(ctx, {"a" * 16})[0])["bench/train.py"] == today["bench/train.py"]


def test_adopt_after_a_call_with_nothing_stale_reads_its_empty_table(tmp_path):
    """A call with nothing stale writes an empty table.csv; the next call read it as pandas' EmptyDataError."""
    from bench.experiments.adopt import with_earlier_verdicts
    empty = tmp_path / "table.csv"
    pd.DataFrame().to_csv(empty, index=False)
    table = pd.DataFrame({"witness": ["t1"], "verdict": ["adopted"]})
    assert with_earlier_verdicts(table, empty).equals(table)


def test_the_recorded_code_of_an_adopted_run_is_taken_at_its_adoption_not_at_its_training():
    """A run adopted since it trained holds the fingerprint of the adopting commit: the rebuilt tree's
    other model definitions come from there (a training's own commit can predate names today's
    harness imports, e.g. bench.nn.load_old_names, removed before the cpu archive's last adoption)."""
    from bench.experiments.adopt import fingerprinted_at
    trained = {"git_commit": "a" * 40}
    assert fingerprinted_at(trained) == "a" * 40
    assert fingerprinted_at({**trained, "code_adopted": {"git_commit": "b" * 40}}) == "b" * 40
