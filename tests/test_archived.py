"""The run archive's compact form of a training (bench.archived): what an archived run holds, the round
trip against the full form, the converter, and the readers on a converted copy of one real archived run."""
import json
import shutil
import types
from pathlib import Path

import pandas as pd
import pytest
import torch

from bench import archived, runs
from bench.experiments.row import last_fifth_gain
from bench.experiments.training import archive_training
from bench.train import CHECKPOINT
from bench.weights import export, from_run, load_exported

ROOT = Path(__file__).resolve().parent.parent
ARCHIVE = ROOT / "results" / "cpu" / "runs"


def _curve_text(steps: int) -> str:
    return "step,loss,lr\n" + "".join(f"{s},{1 / s!r},{s * 1e-6!r}\n" for s in range(1, steps + 1))


def _state() -> dict:
    gen = torch.Generator().manual_seed(0)
    return {"conv.weight": torch.randn(4, 3, 3, 3, generator=gen), "conv.bias": torch.randn(4, generator=gen) * 1e-3,
            "norm.num_batches_tracked": torch.tensor(7), "scale": torch.tensor([1e6, -2.0])}  # beyond float16


def _trained_run(store: Path, schedule: str = "cosine", steps: int = 1003, seed: int = 0) -> runs.Run:
    """A complete training in the run store as the trainer leaves it: full checkpoint, both curves."""
    run = runs.begin(store, "train", {"model": {"_target_": "x"}, "train": {"schedule": schedule}, "seed": seed})
    ema, raw = _state(), {k: v + 1 for k, v in _state().items()}
    torch.save({"model": raw, "ema": ema, "optimizer": {"state": {}}, "step": steps, "curve": [], "val_curve": []},
               run.dir / CHECKPOINT)
    (run.dir / archived.CURVE).write_text(_curve_text(steps))
    (run.dir / archived.VAL_CURVE).write_text("step,PSNR\n0,20.0\n800,29.0\n1000,30.0\n")
    return runs.complete(run, {"steps": steps})


def test_weights_round_trip_to_float16_keeping_what_it_cannot_hold():
    state = _state()
    back = archived.decode(archived.encode(state))
    assert list(back) == list(state) and all(back[k].dtype == v.dtype for k, v in state.items())
    assert torch.equal(back["conv.weight"], state["conv.weight"].half().float())
    assert torch.equal(back["conv.bias"], state["conv.bias"].half().float())
    assert torch.equal(back["norm.num_batches_tracked"], torch.tensor(7))
    assert torch.equal(back["scale"], state["scale"])                 # 1e6 overflows float16: kept exact
    one = {"w": torch.tensor([0.5])}                                  # a single float16 value
    assert torch.equal(archived.decode(archived.encode(one))["w"], one["w"])
    with pytest.raises(ValueError, match="not archived weights"):
        archived.decode({"ema": state})


def test_the_curve_keeps_the_first_steps_whole_then_every_tenth_and_the_last():
    kept = pd.read_csv(pd.io.common.StringIO(archived.compact_curve(_curve_text(1003))))
    assert list(kept["step"]) == [*range(1, 101), *range(110, 1001, 10), 1003]
    full = pd.read_csv(pd.io.common.StringIO(_curve_text(1003))).set_index("step")
    pd.testing.assert_frame_equal(kept.set_index("step"), full.loc[kept["step"]])  # rows as written
    assert archived.compact_curve(_curve_text(1003), whole=True) == _curve_text(1003)


def test_an_archived_training_holds_its_record_float16_ema_weights_and_thinned_curves(tmp_path):
    run = _trained_run(tmp_path / "runs")
    archive_training(types.SimpleNamespace(runs_archive=tmp_path / "archive"), run)
    kept = tmp_path / "archive" / "train" / run.hash
    assert sorted(p.name for p in kept.iterdir()) == sorted(archived.FILES)
    saved = torch.load(kept / archived.WEIGHTS, weights_only=True)
    assert saved["format"] == archived.FORMAT and "optimizer" not in saved and "model" not in saved
    weights = archived.state_dict(kept)
    assert torch.equal(weights["conv.weight"], _state()["conv.weight"].half().float())   # the EMA, not the raw
    assert archived.rounded(kept) and not archived.rounded(run.dir)
    assert len(archived.read_curve(kept)) == 100 + 90 + 1
    assert archived.read_curve(run.dir)["step"].tolist() == list(range(1, 1004))     # the store keeps it whole


def test_a_range_tests_curve_is_archived_whole(tmp_path):
    run = _trained_run(tmp_path / "runs", schedule="range", steps=177)
    archive_training(types.SimpleNamespace(runs_archive=tmp_path / "archive"), run)
    assert archived.read_curve(tmp_path / "archive" / "train" / run.hash)["step"].tolist() == list(range(1, 178))


def test_the_converter_is_idempotent_and_gives_what_archiving_gives(tmp_path):
    run = _trained_run(tmp_path / "runs")
    archive_training(types.SimpleNamespace(runs_archive=tmp_path / "new"), run)
    old = tmp_path / "old" / "train" / run.hash                        # as archives were written before
    shutil.copytree(run.dir, old)
    assert archived.main([str(tmp_path / "old")]) == 0
    files = lambda d: {p.name: p.read_bytes() for p in d.iterdir()}
    assert files(old) == files(tmp_path / "new" / "train" / run.hash)
    assert archived.convert_archive(tmp_path / "old") == 0 and files(old) == files(tmp_path / "new" / "train" / run.hash)
    assert archived.main([str(tmp_path / "nothing")]) == 2


@pytest.mark.parametrize("flags,message", [
    (["--dry-run"], "--dry-run goes with --drop-unlisted or --first-seed-weights"),
    (["--list-unlisted"], "--list-unlisted goes with --verify"),
    (["--first-seed-weights", "--drop-unlisted", "results"], "not allowed with argument"),
    (["--verify", "--first-seed-weights"], "not allowed with argument"),
])
def test_a_flag_without_its_action_is_refused_and_the_archive_is_not_converted(tmp_path, capsys, flags, message):
    """--dry-run alone once fell through to the conversion, which rewrites weights as float16 and deletes
    checkpoints in place; two actions at once ran one of them."""
    run = _trained_run(tmp_path / "runs")
    archive = tmp_path / "archive"
    shutil.copytree(run.dir, archive / "train" / run.hash)
    before = {p.relative_to(archive): p.read_bytes() for p in archive.rglob("*") if p.is_file()}
    with pytest.raises(SystemExit) as end:
        archived.main([str(archive), *flags])
    assert end.value.code == 2 and message in capsys.readouterr().err
    assert {p.relative_to(archive): p.read_bytes() for p in archive.rglob("*") if p.is_file()} == before


def test_a_damaged_compact_curve_reads_as_missing(tmp_path, caplog):
    (tmp_path / archived.COMPACT_CURVE).write_bytes(b"\x1f\x8b not a whole gzip")
    assert archived.read_curve(tmp_path) is None and "is damaged" in caplog.text


def _one_real_training() -> Path:
    """The smallest archived training of the cpu archive that has weights (either form)."""
    found = [p.parent for p in ARCHIVE.glob(f"train/*/{runs.RECORD}") if archived.has_weights(p.parent)
             and (p.parent / archived.VAL_CURVE).exists()
             and not json.loads(p.read_text())["identity"].get("stage")]
    if not found:
        pytest.skip("no archived training with weights in results/cpu/runs")
    return min(found, key=lambda d: archived.weights_file(d).stat().st_size)


def test_the_readers_work_on_a_converted_copy_of_a_real_archived_run(tmp_path, monkeypatch):
    """Restore, the table's curve column, export and predict's weights, adopt's curve: on one real run."""
    original = _one_real_training()
    archive = tmp_path / "results" / "cpu" / "runs"
    copy = archive / "train" / original.name
    shutil.copytree(original, copy)
    archived.convert_archive(archive)
    assert sorted(p.name for p in copy.iterdir()) == sorted(archived.FILES)
    # the weights: float16-rounded float32 of the original's EMA
    expected = {k: v.half().to(v.dtype) if v.is_floating_point() else v for k, v in archived.state_dict(original).items()}
    monkeypatch.setattr(runs, "COMMITTED_RESULTS", tmp_path / "results")  # a fresh clone: no run store,
    monkeypatch.chdir(tmp_path)                                              # the copy its only archive
    model, meta = from_run(original.name, tmp_path / "no_store")
    assert all(torch.equal(v, expected[k]) for k, v in model.state_dict().items())
    exported, exported_meta = load_exported(export(original.name, tmp_path / "w.pt", tmp_path / "no_store"))
    assert exported_meta["weights_rounded_to_float16"]
    assert all(torch.equal(v, expected[k]) for k, v in exported.state_dict().items())
    # a table restores the run into its store and reuses it, weights included (trained_model's needs)
    record = runs.read_record(copy / runs.RECORD)
    store = tmp_path / "store"
    reused = runs.begin(store, "train", record["identity"], archive=archive, needs=((CHECKPOINT, archived.WEIGHTS),))
    assert reused.reused and archived.has_weights(reused.dir)
    assert last_fifth_gain(reused.dir) == last_fifth_gain(original)
    # adopt's replay reads the first steps and the learning rate of the kept ones
    full, thinned = archived.read_curve(original), archived.read_curve(reused.dir)
    pd.testing.assert_frame_equal(thinned.head(10), full.head(10))
    pd.testing.assert_frame_equal(thinned.reset_index(drop=True),
                                  full[full["step"].isin(thinned["step"])].reset_index(drop=True))


def _evaluated_run(store: Path) -> runs.Run:
    """A complete evaluation in the run store as the evaluator leaves it: its per-frame scores."""
    run = runs.begin(store, "eval", {"trained": "abc", "split": "val"})
    pd.DataFrame({"sequence": ["0001", "0001", "s2"], "frame": [0, 1, 0], "relMSE": [0.1, 0.2, 1 / 3]}).to_csv(
        run.dir / archived.PER_IMAGE, index=False)
    return runs.complete(run, {"relMSE": 0.2})


def test_an_archived_evaluation_holds_its_record_and_gzipped_scores_that_read_as_the_stores(tmp_path):
    from bench.experiments.evaluation import archive_evaluation
    run = _evaluated_run(tmp_path / "runs")
    ctx = types.SimpleNamespace(runs_archive=tmp_path / "archive", eval=types.SimpleNamespace(data_dir=None))
    archive_evaluation(ctx, run)
    kept = tmp_path / "archive" / "eval" / run.hash
    assert {p.name for p in kept.iterdir()} == set(archived.EVALUATION_FILES)
    stored, compact = archived.read_per_image(run.dir), archived.read_per_image(kept)
    pd.testing.assert_frame_equal(compact, stored)           # the same frames, bit for bit
    assert list(compact["sequence"]) == ["0001", "0001", "s2"]  # names stay strings
    old = tmp_path / "old" / "eval" / run.hash                # as archives were written before: the plain csv
    shutil.copytree(run.dir, old)
    assert archived.convert_archive(tmp_path / "old") == 1 and archived.convert_archive(tmp_path / "old") == 0
    assert {p.name: p.read_bytes() for p in old.iterdir()} == {p.name: p.read_bytes() for p in kept.iterdir()}
    (kept / archived.COMPACT_PER_IMAGE).write_bytes(b"\x1f\x8b not a whole gzip")
    assert archived.read_per_image(kept) is None             # damaged reads as missing


def test_drop_unlisted_deletes_the_evaluations_no_table_lists(tmp_path, capsys):
    archive, results = tmp_path / "results" / "cpu" / "runs", tmp_path / "results" / "cpu"
    for kind, h in (("eval", "listed"), ("eval", "deterministic"), ("eval", "superseded"), ("train", "t")):
        (archive / kind / h).mkdir(parents=True)
        (archive / kind / h / runs.RECORD).write_text(json.dumps({"hash": h, "label": h}))
    (results / "sota").mkdir()
    pd.DataFrame([{"method": "A", "runs": "listed"}, {"method": "B", "runs": "deterministic deterministic"}]).to_csv(
        results / "sota" / "table.csv", index=False)
    assert archived.main([str(archive), "--drop-unlisted", str(results), "--dry-run"]) == 0
    assert "would delete" in capsys.readouterr().out and (archive / "eval" / "superseded").exists()
    assert archived.main([str(archive), "--drop-unlisted", str(results)]) == 0
    assert sorted(p.name for p in (archive / "eval").iterdir()) == ["deterministic", "listed"]
    assert (archive / "train" / "t").exists()                            # trainings are not its business
    for elsewhere in (results / "sota", tmp_path / "results" / "smoke"):  # some tables, or another preset's
        assert archived.main([str(archive), "--drop-unlisted", str(elsewhere)]) == 2
        assert "another folder lists only some of them" in capsys.readouterr().err
    assert sorted(p.name for p in (archive / "eval").iterdir()) == ["deterministic", "listed"]
    (results / "sota" / "table.csv").write_bytes(b"\xff\xfe\x00 not a table")
    assert archived.main([str(archive), "--drop-unlisted", str(results)]) == 2
    assert f"{results / 'sota' / 'table.csv'} does not read" in capsys.readouterr().err
    (results / "sota" / "table.csv").unlink()
    assert archived.main([str(archive), "--drop-unlisted", str(results)]) == 2  # no table: no
    assert "every evaluation would go" in capsys.readouterr().err


def test_first_seed_weights_drops_the_other_seeds_weights_and_leaves_records_that_verify(tmp_path, capsys):
    """Per row (identity but the seed), the lowest seed archived keeps its weights; the others keep their
    record and curves, listed so that a verify finds nothing damaged, and archiving one again keeps it
    weightless."""
    ctx = types.SimpleNamespace(runs_archive=tmp_path / "archive")
    trained = {(schedule, seed): _trained_run(tmp_path / "runs", schedule, 150, seed)
               for schedule, seeds in (("cosine", (0, 1, 2)), ("step", (1, 2))) for seed in seeds}
    for run in trained.values():
        archive_training(ctx, run)
    kept = {key: tmp_path / "archive" / "train" / run.hash for key, run in trained.items()}
    assert archived.main([str(ctx.runs_archive), "--first-seed-weights", "--dry-run"]) == 0
    assert "3 trainings beyond their row's first seed" in capsys.readouterr().out
    assert all(archived.has_weights(d) for d in kept.values())
    assert archived.main([str(ctx.runs_archive), "--first-seed-weights"]) == 0
    assert {key for key, d in kept.items() if archived.has_weights(d)} == {("cosine", 0), ("step", 1)}
    assert archived.read_curve(kept[("cosine", 2)]) is not None
    assert archived.verify(ctx.runs_archive)[1]["damaged"] == 0
    archive_training(ctx, trained[("cosine", 1)])
    assert not archived.has_weights(kept[("cosine", 1)]) and archived.verify(ctx.runs_archive)[1]["damaged"] == 0
    assert archived.main([str(ctx.runs_archive), "--first-seed-weights"]) == 0  # nothing left to drop
    assert "0 trainings beyond" in capsys.readouterr().out


def test_conversion_leaves_a_run_store_and_unfinished_trainings_alone_and_names_a_damaged_run(tmp_path, capsys):
    store = tmp_path / "runs"
    run = _trained_run(store)
    (store / "data").mkdir()
    assert archived.main([str(store)]) == 2 and "is a run store" in capsys.readouterr().err
    assert (run.dir / CHECKPOINT).exists()
    archive = tmp_path / "results" / "runs"
    shutil.copytree(run.dir, archive / "train" / run.hash)
    record = json.loads((archive / "train" / run.hash / runs.RECORD).read_text())
    (archive / "train" / run.hash / runs.RECORD).write_text(json.dumps({**record, "status": "interrupted"}))
    assert archived.convert_archive(archive) == 0                    # its checkpoint is what it resumes from
    assert (archive / "train" / run.hash / CHECKPOINT).exists()
    (archive / "train" / run.hash / runs.RECORD).write_text(json.dumps(record))
    (archive / "train" / run.hash / CHECKPOINT).write_bytes(b"cut short")
    assert archived.main([str(archive)]) == 2
    assert f"{archive / 'train' / run.hash}: not converted" in capsys.readouterr().err
